"""The one database layer of the history: SQLite (a file, the default) or PostgreSQL (a
server several stations share), the same tables through SQLAlchemy Core.

    target = "history.sqlite"                          # a path: SQLite
    target = "postgresql://imubench@dbhost/imubench"    # a URL: PostgreSQL (psycopg 3)

`connect(target, readonly=...)` opens it, creates the tables in an empty database and
upgrades an older one in place (MIGRATIONS, one function per version step, each in one
transaction with every other writer locked out); a database written by a newer imubench is
refused with a message saying so, and nothing is changed.

Why SQLAlchemy Core (and not the ORM, nor hand-written SQL per dialect): the history is a
handful of tables and explicit transactions; Core gives one table definition and one query
text for both databases (types, ON CONFLICT, RETURNING, identifiers quoted per dialect)
while leaving the SQL visible. psycopg 3 is the maintained PostgreSQL driver SQLAlchemy
speaks natively (`postgresql+psycopg://`), with its own libpq in the binary wheel.

Transactions: `write(conn)` is BEGIN IMMEDIATE on SQLite (one writer at a time, other
writers wait up to the busy timeout; readers never block in WAL mode) and READ COMMITTED on
PostgreSQL where writers of the same device serialise on that device's row (history.py);
`read(conn)` is one snapshot (SQLite: a deferred transaction; PostgreSQL: REPEATABLE READ
READ ONLY) so a multi-statement query sees one state of the database.
"""
from __future__ import annotations

import shlex
import sqlite3
import time
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import (
    Column,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    Table,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    inspect,
    text,
)
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import DBAPIError, OperationalError, SQLAlchemyError
from sqlalchemy.pool import NullPool

from imubench.errors import ImubenchError
from imubench.files import make_dir
from imubench.results.where import ENV_DB  # noqa: F401 - re-exported: the variable naming the database

SCHEMA_VERSION = 3          # of the database (the tables below; MIGRATIONS reach it)
PG_LOCK_KEY = 0x494D5542    # "IMUB": the advisory lock a PostgreSQL migration holds

metadata = MetaData()

schema_version = Table(
    "schema_version", metadata,
    Column("version", Integer, nullable=False),
)

devices = Table(
    "devices", metadata,
    Column("id", Integer, primary_key=True),
    Column("mcu_uid", Text, nullable=False, unique=True),     # lower-case hex
    Column("board", Text),
    Column("parts", Text),                                    # JSON: the part in each slot (protocol/parts.toml)
    Column("accel_ids", Text),                                # JSON, as of the latest run
    Column("gyro_pid", Text),                                 # JSON
    Column("gyro_sn", Text),                                  # JSON
    Column("first_seen", Text, nullable=False),               # UTC ISO 8601 of the first run's start
    Column("last_seen", Text, nullable=False),                # ... of the latest run's start
)

runs = Table(
    "runs", metadata,
    Column("id", Integer, primary_key=True),
    Column("device_id", Integer, ForeignKey("devices.id")),   # NULL: a board that never told its identity
    Column("started", Text, nullable=False),                  # UTC, fixed width: sorts as text
    Column("finished", Text),
    Column("method", Text),
    Column("gyro_method", Text),
    Column("accel_m", Text),                                  # JSON 3x3; NULL when no fit (a failed board)
    Column("accel_b_mps2", Text),
    Column("accel_sigma_m", Text),
    Column("accel_sigma_b_mps2", Text),
    Column("accel_residual_rms_mps2", Float),
    Column("gyro_m", Text),
    Column("gyro_b_rad_s", Text),
    Column("gyro_sigma_m", Text),
    Column("gyro_sigma_b_rad_s", Text),
    Column("gyro_residual_rms", Float),
    Column("poses", Text),
    Column("verification", Text),
    Column("temp_accel_c", Float),
    Column("temp_gyro_c", Text),
    Column("tolerances", Text),
    Column("fw_version", Text),
    Column("fw_build", Text),
    Column("gyro_sn", Text),
    Column("passed", Integer, nullable=False),
    Column("written", Integer, nullable=False),
    Column("verified", Integer, nullable=False),
    Column("note", Text),
    Column("capture_dir", Text),
    Column("recorded_at", Text, nullable=False),
    Column("record", Text, nullable=False),                   # the whole result record, JSON (sorted keys)
    # schema 2: the production line
    Column("station_id", Text),
    Column("operator", Text),
    Column("fixture", Text),
    Column("slot", Integer),                                  # position on the fixture (1 = first port)
    Column("port", Text),
    Column("host_version", Text),
    Column("session_id", Text),                               # the station session that ran this board
    Column("params_before", Text),                            # JSON parameter block read before writing
    Column("params_after", Text),                             # ... read back after (NULL when nothing written)
    Column("capture_sha256", Text),
    Column("capture_uri", Text),
    Column("failed_stage", Text),                             # where a failed board stopped
    Column("failure", Text),                                  # why, in words
    UniqueConstraint("device_id", "started"),
)
Index("runs_device_started", runs.c.device_id, runs.c.started)
Index("runs_station_started", runs.c.station_id, runs.c.started)
Index("runs_session", runs.c.session_id)

measurements = Table(
    "measurements", metadata,
    Column("id", Integer, primary_key=True),
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("seq", Integer, nullable=False),                   # order within the run
    Column("name", Text, nullable=False),
    Column("value", Float),                                   # NULL: not measured (the board failed before)
    Column("unit", Text, nullable=False),
    Column("low", Float),                                     # limits; NULL = no limit on that side
    Column("high", Float),
    Column("passed", Integer, nullable=False),
)
Index("measurements_run", measurements.c.run_id)


class DatabaseError(ImubenchError):
    """The database cannot be used; the message says why."""


class SchemaError(DatabaseError):
    """The database was written by a newer imubench (or is not an imubench history)."""


def is_url(target) -> bool:
    return isinstance(target, str) and "://" in target


def _masked(target: str) -> str:
    """A URL with everything before the last '@' of its authority hidden: shown when the URL
    cannot be parsed, so that no part of a password ever reaches a message."""
    scheme, _, rest = target.partition("://")
    cut = min((i for i in (rest.find("/"), rest.find("?"), rest.find("#")) if i >= 0), default=len(rest))
    netloc, tail = rest[:cut], rest[cut:]
    if "@" in netloc:
        netloc = "***@" + netloc.rsplit("@", 1)[1]
    return f"{scheme}://{netloc}{tail}"


def describe(target) -> str:
    """The target for messages: a path as given, a URL without its password (SQLAlchemy's
    own rendering, hide_password)."""
    if not is_url(target):
        return str(target)
    from sqlalchemy.engine import make_url
    try:
        if _authority(target).count("@") > 1:
            return _masked(target)
        return make_url(target).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a malformed URL is shown without what could be secret
        return _masked(target)


def _authority(target: str) -> str:
    rest = target.partition("://")[2]
    cut = min((i for i in (rest.find("/"), rest.find("?"), rest.find("#")) if i >= 0), default=len(rest))
    return rest[:cut]


def check_url(target: str) -> None:
    """Refuse, with its own one-line message, a database URL SQLAlchemy would misread: an '@'
    in the password (it would take the rest for the host, and show half the password), a
    port that is not a number (a bare ValueError inside SQLAlchemy)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError
    auth = _authority(target)
    if auth.count("@") > 1:
        raise DatabaseError(f"the database URL {_masked(target)} has more than one '@' before its host; write an "
                            "'@' in the user name or password as %40 (percent-encoding, RFC 3986)")
    try:
        make_url(target)
    except ValueError:
        hostport = auth.rsplit("@", 1)[-1]
        port = hostport.rsplit("]", 1)[-1].partition(":")[2] if hostport.startswith("[") else hostport.partition(":")[2]
        raise DatabaseError(f"the database URL {_masked(target)} has a port that is not a number "
                            f"({port!r}); give postgresql://USER@HOST[:PORT]/DBNAME with PORT a number") from None
    except ArgumentError as e:
        raise DatabaseError(f"the database URL {_masked(target)} cannot be read ({e})") from None


def _pg_url(url: str) -> str:
    for scheme in ("postgresql://", "postgres://", "postgresql+psycopg://"):
        if url.startswith(scheme):
            return "postgresql+psycopg://" + url[len(scheme):]
    raise DatabaseError(f"unsupported database URL {describe(url)!r}: give a file path (SQLite) or a "
                        "postgresql://USER@HOST[:PORT]/DBNAME URL")


def _sqlite_wal(dbapi_conn, timeout_s: float) -> None:
    """Put a SQLite file in WAL mode. Changing the journal mode takes the file's exclusive lock,
    and SQLite answers "database is locked" at once, without its busy timeout, while another
    station's connection is changing it too (several stations opening a new file together):
    tried again until timeout_s."""
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            dbapi_conn.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as e:
            if "locked" not in str(e) or time.monotonic() > t_end:
                raise
            time.sleep(0.01)


def make_engine(target, *, readonly: bool = False, timeout_s: float = 10.0) -> Engine:
    """An engine for a path (SQLite) or a postgresql:// URL."""
    if is_url(target):
        check_url(target)
        try:
            eng = create_engine(_pg_url(target), poolclass=NullPool,
                                connect_args={"connect_timeout": max(1, int(timeout_s)),
                                              "application_name": "imubench"})
        except (ImportError, ModuleNotFoundError) as e:
            raise DatabaseError(f"PostgreSQL needs the psycopg driver ({e}): pip install 'imubench[postgres]'") from None
        except SQLAlchemyError as e:
            raise DatabaseError(f"bad database URL {describe(target)}: {e}") from None
        eng.imubench_readonly = readonly
        return eng
    path = Path(target)
    if readonly:
        if not path.is_file():
            raise DatabaseError(f"no history database at {path}")
        dsn, uri = path.resolve().as_uri() + "?mode=ro", True
    else:
        if path.exists() and not path.is_file():
            raise DatabaseError(f"{path} is not a file")
        make_dir(path.parent)
        dsn, uri = str(path), False

    def creator():
        return sqlite3.connect(dsn, uri=uri, timeout=timeout_s, isolation_level=None, check_same_thread=False)

    eng = create_engine("sqlite://", creator=creator, poolclass=NullPool)

    @event.listens_for(eng, "connect")
    def _on_connect(dbapi_conn, _rec):
        dbapi_conn.isolation_level = None           # transactions are ours (BEGIN below), not pysqlite's
        dbapi_conn.execute("PRAGMA foreign_keys = ON")
        if not readonly:
            _sqlite_wal(dbapi_conn, timeout_s)                  # readers never block a recording session
            dbapi_conn.execute("PRAGMA synchronous = FULL")     # a recorded run survives a power cut too

    @event.listens_for(eng, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.info.get("imubench_write") else "BEGIN DEFERRED")

    eng.imubench_readonly = readonly
    return eng


def is_pg(conn: Connection) -> bool:
    return conn.dialect.name == "postgresql"


@contextmanager
def write(conn: Connection):
    """One write transaction (see the module's doc)."""
    conn.info["imubench_write"] = True
    try:
        try:
            txn = conn.begin()
        except OperationalError as e:   # e.g. another writer held the lock past the timeout
            raise DatabaseError(f"history database busy or unavailable: {e.orig}") from None
        with txn:
            yield conn
    finally:
        conn.info["imubench_write"] = False


@contextmanager
def read(conn: Connection):
    """One read snapshot."""
    conn.info["imubench_write"] = False
    try:
        txn = conn.begin()
    except OperationalError as e:
        raise DatabaseError(f"history database busy or unavailable: {e.orig}") from None
    with txn:
        if is_pg(conn):
            conn.exec_driver_sql("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY")
        yield conn


def connect(target, *, readonly: bool = False, timeout_s: float = 10.0) -> tuple[Engine, Connection]:
    """Open the database, create or upgrade its tables (unless readonly) and check its
    version. Returns (engine, connection); close both (close())."""
    eng = make_engine(target, readonly=readonly, timeout_s=timeout_s)
    try:
        conn = eng.connect()
    except DBAPIError as e:
        eng.dispose()
        raise DatabaseError(f"cannot open {describe(target)}: {_first_line(e.orig)}") from None
    try:
        prepare(conn, describe(target), readonly=readonly)
    except DBAPIError as e:
        close(eng, conn)
        raise DatabaseError(f"cannot read {describe(target)} as an imubench history database: "
                            f"{_first_line(e.orig)}") from None
    except BaseException:
        close(eng, conn)
        raise
    return eng, conn


def close(eng: Engine | None, conn: Connection | None) -> None:
    if conn is not None:
        try:
            conn.close()
        except SQLAlchemyError:
            pass
    if eng is not None:
        eng.dispose()


def _first_line(e) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def _tables(conn: Connection) -> set[str]:
    return set(inspect(conn).get_table_names())


def _version(conn: Connection, tables: set[str]) -> int | None:
    if "schema_version" not in tables:
        return None
    return conn.execute(text("SELECT MAX(version) FROM schema_version")).scalar()


def _check(conn: Connection, name: str) -> int | None:
    tables = _tables(conn)
    version = _version(conn, tables)
    if version is not None and version > SCHEMA_VERSION:
        raise SchemaError(f"{name} was written by a newer imubench (history schema {version}; this one reads "
                          f"up to {SCHEMA_VERSION}): upgrade imubench to read it; nothing was changed")
    if version is None and tables - {"schema_version"}:
        raise SchemaError(f"{name} is {'an SQLite' if conn.dialect.name == 'sqlite' else 'a PostgreSQL'} "
                          f"database but not an imubench history (tables: {', '.join(sorted(tables))})")
    return version


def prepare(conn: Connection, name: str, readonly: bool = False) -> int:
    """Create the tables (empty database) or upgrade them to SCHEMA_VERSION; returns the
    version found before. Readonly: only check."""
    with read(conn):
        version = _check(conn, name)
    if readonly:
        if version is None:
            raise SchemaError(f"{name} is empty: not an imubench history database")
        if version < SCHEMA_VERSION:
            raise SchemaError(f"{name} has history schema {version}: record one run with this imubench "
                              f"(or run `imubench history --upgrade --db {shlex.quote(str(name))}`) to upgrade it to {SCHEMA_VERSION}")
        return version
    if version == SCHEMA_VERSION:
        return version
    with write(conn):
        if is_pg(conn):         # one migrator at a time; DDL is transactional there
            conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": PG_LOCK_KEY})
        version = _check(conn, name)        # again, under the lock: another station may have done it
        if version is None:
            metadata.create_all(conn)
            conn.execute(schema_version.insert().values(version=SCHEMA_VERSION))
        else:
            for v in range(version, SCHEMA_VERSION):
                MIGRATIONS[v](conn)
                conn.execute(schema_version.update().values(version=v + 1))
    return version if version is not None else 0


# ------------------------------------------------------------------ migrations
_V1_RUN_COLUMNS = (
    "id, device_id, started, finished, method, gyro_method, accel_m, accel_b_mps2, accel_sigma_m, "
    "accel_sigma_b_mps2, accel_residual_rms_mps2, gyro_m, gyro_b_rad_s, gyro_sigma_m, gyro_sigma_b_rad_s, "
    "gyro_residual_rms, poses, verification, temp_accel_c, temp_gyro_c, tolerances, fw_version, fw_build, "
    "gyro_sn, passed, written, verified, note, capture_dir, recorded_at, record")


def _migrate_1_to_2(conn: Connection) -> None:
    """Schema 1 (imubench before the production line: SQLite only) -> 2: runs gain the
    station, operator, fixture, slot, port, host version, session, parameters before and
    after, capture hash and location, and the failure; a failed board may have no fit and
    no identity (columns that were NOT NULL become nullable, which SQLite can only do by
    rebuilding the table); the measurements table holds each run's measurements and limits.
    Every v1 row is kept, its id unchanged."""
    conn.exec_driver_sql("DROP INDEX IF EXISTS runs_device_started")
    conn.exec_driver_sql("ALTER TABLE runs RENAME TO runs_v1")
    runs.create(conn)
    conn.exec_driver_sql(f"INSERT INTO runs ({_V1_RUN_COLUMNS}) SELECT {_V1_RUN_COLUMNS} FROM runs_v1")
    conn.exec_driver_sql("DROP TABLE runs_v1")
    measurements.create(conn)
    if is_pg(conn):             # keep the id sequence past the copied ids
        conn.exec_driver_sql("SELECT setval(pg_get_serial_sequence('runs', 'id'), COALESCE(MAX(id), 0) + 1, false) "
                             "FROM runs")


def _migrate_2_to_3(conn: Connection) -> None:
    """Schema 2 -> 3: a device row says which part sits in each slot (accelerometer, gyro
    X/Y/Z: info.parts, protocol/parts.toml); NULL for devices last seen before parts were
    reported (their boards carried ADXL355 and ADXRS450s)."""
    conn.exec_driver_sql("ALTER TABLE devices ADD COLUMN parts TEXT")


MIGRATIONS = {1: _migrate_1_to_2, 2: _migrate_2_to_3}       # from version k to k + 1
