"""Calibration history: every finished session's result record, per device, in SQLite or in
a PostgreSQL database several stations share (imubench.results.db).

    imubench history [DEVICE] [--db PATH|URL] [--json]
    imubench history --yield [station|day|station_day] | --failed | --sessions | --export SESSION

Without DEVICE: the devices the database knows (MCU UID, board, number of runs, last
calibration). With DEVICE (the full MCU UID, a unique prefix of it of at least 4 hex
digits, or one of its gyro serial numbers): every run in time order, then how bias and
scale moved from session to session, flagged where a change is larger than 3 combined
sigmas (a real drift, not the noise of the two fits). For a production line: first-pass
yield per station and day, the failed runs with their stage and reason or the measurements
out of their limits, the station sessions, and one session exported (results.export).

The database is $IMUBENCH_DB (a path or a postgresql:// URL) or, without it, a file in the
user's data directory (platformdirs: `user_data_dir("imubench")/history.sqlite`), unless one
is given (`History(path_or_url)`, `--db`). SQLite runs in WAL mode, so readers (another
`imubench history`) never block a session that is recording; every write is one
transaction on either database: a crash or an exception leaves either the whole run (with
its device row and measurements) or nothing, and concurrent stations never see half a run.

Records: schema 1 (a one-board session before the production line) and schema 2 (adds
station, operator, fixture, slot, port, host version, session id, parameters before and
after, measurements with limits, the raw capture's SHA-256 and location, and, for a board
that failed before it was fitted, "failure": {stage, reason} instead of the fit).

Units as docs/conventions.md: stored parameters are SI (m/s², rad/s); the report converts at
the edge (mg, °/s, ppm = 1e-6 of the dimensionless M).
"""
from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

from sqlalchemy import bindparam, text

from imubench.analysis.drift import drift, run_summary
from imubench.results import db as DB
from imubench.results.export import measurements_of
from imubench.results.record import _parse_time, jsonable, validate_result
from imubench.results.where import default_path  # noqa: F401 - re-exported
from imubench.wire.ids import parse_id

SCHEMA_VERSION = DB.SCHEMA_VERSION   # of the database (results.db: the tables and their migrations)
MIN_PREFIX = 4              # hex digits of an MCU UID prefix

HistoryError = DB.DatabaseError     # the history database cannot be used; the message says why
SchemaError = DB.SchemaError        # written by a newer imubench, or not an imubench history


class UnknownDevice(HistoryError, LookupError):
    """No device matches what was asked for."""


class AmbiguousDevice(HistoryError, LookupError):
    """A UID prefix or serial number matches more than one device."""

    def __init__(self, query: str, matches: list[str]):
        self.query = query
        self.matches = matches
        super().__init__(f"{query!r} matches {len(matches)} devices: {', '.join(matches)} — give more of the MCU UID")


def default_target() -> str | Path:
    """The database to use when none is given: $IMUBENCH_DB (a path or a postgresql:// URL),
    else default_path()."""
    import os
    env = os.environ.get(DB.ENV_DB, "").strip()
    return env if DB.is_url(env) else Path(env) if env else default_path()


# ------------------------------------------------------------------ times
def _utc_text(t: _dt.datetime) -> str:
    return t.isoformat(timespec="microseconds")



def _dumps(x) -> str | None:
    if x is None:
        return None
    return json.dumps(jsonable(x), sort_keys=True)


def _loads(s):
    return None if s is None else json.loads(s)


# ------------------------------------------------------------------ database
def _device_id_sql(conn):
    return text("SELECT id, first_seen, last_seen FROM devices WHERE mcu_uid = :uid"
                + (" FOR UPDATE" if DB.is_pg(conn) else ""))


class History:
    """The calibration history database. `History()` opens (creating) the one named by
    IMUBENCH_DB or, without it, the SQLite file in the user's data directory; `History(path)`
    another file, `History("postgresql://...")` a PostgreSQL database (results.db);
    `readonly=True` never creates or changes it."""

    def __init__(self, path: str | Path | None = None, *, readonly: bool = False, timeout_s: float = 10.0):
        target = default_target() if path is None else path
        self.url = target if DB.is_url(target) else None
        self.path = target if self.url else Path(target)       # what messages name (a URL has no password here)
        if self.url:
            self.path = DB.describe(target)
        self.readonly = readonly
        self._engine, self._db = DB.connect(target, readonly=readonly, timeout_s=timeout_s)

    @property
    def dialect(self) -> str:
        return self._db.dialect.name

    # ------------------------------------------------------------ transactions
    def _write(self):
        return DB.write(self._db)

    def _read(self):
        return DB.read(self._db)       # one snapshot for a multi-statement read

    # ------------------------------------------------------------ API
    def close(self) -> None:
        if self._db is not None:
            DB.close(self._engine, self._db)
            self._db = self._engine = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def record(self, result: dict) -> int:
        """Store one session's result record; returns its run id. Raises ValueError (and
        stores nothing) when a required key is missing or malformed. Recording the same
        record again returns the existing run's id; a different record for the same device
        and start time is refused."""
        return self.record_once(result)[0]

    def record_once(self, result: dict) -> tuple[int, bool]:
        """record(), and whether the run is new: (run id, True) when it was stored now,
        (run id, False) when this very run (the same device, session start and run start,
        the same record) was already in the history and nothing was stored. The run, its
        device row and its measurements are one transaction: another station writing at
        the same time never sees half of it, and a failure leaves nothing."""
        validate_result(result)
        dev = result.get("device") or {}
        uid = dev["mcu_uid"].lower() if dev.get("mcu_uid") else None
        started = _utc_text(_parse_time(result["started"]))
        finished = _utc_text(_parse_time(result["finished"]))
        meas = result.get("measurements")
        if meas is None:
            meas = measurements_of(result)
        record_json = _dumps(result)          # everything serialised before the transaction starts
        acc = result.get("accel")
        gyr = result.get("gyro")
        temps = result.get("temperature_c") or {}
        sn = dev.get("gyro_sn")
        station = result.get("station") or {}
        capture = result.get("capture") or {}
        failure = result.get("failure") or {}
        run = {
            "started": started, "finished": finished, "method": result.get("method"),
            "gyro_method": result.get("gyro_method"),
            "accel_m": _dumps(acc["m"]) if acc else None, "accel_b_mps2": _dumps(acc["b_mps2"]) if acc else None,
            "accel_sigma_m": _dumps(acc["sigma_m"]) if acc else None,
            "accel_sigma_b_mps2": _dumps(acc["sigma_b_mps2"]) if acc else None,
            "accel_residual_rms_mps2": _float_or_none(acc.get("residual_rms_mps2", acc.get("residual_rms")))
            if acc else None,
            "gyro_m": _dumps(gyr["m"]) if gyr else None,
            "gyro_b_rad_s": _dumps(gyr["b_rad_s"]) if gyr else None,
            "gyro_sigma_m": _dumps(gyr["sigma_m"]) if gyr else None,
            "gyro_sigma_b_rad_s": _dumps(gyr["sigma_b_rad_s"]) if gyr else None,
            "gyro_residual_rms": _float_or_none(gyr.get("residual_rms")) if gyr else None,
            "poses": _dumps(result.get("poses")), "verification": _dumps(result.get("verification")),
            "temp_accel_c": _float_or_none(temps.get("accel")), "temp_gyro_c": _dumps(temps.get("gyro")),
            "tolerances": _dumps(result.get("tolerances")),
            "fw_version": dev.get("fw_version"), "fw_build": dev.get("fw_build"), "gyro_sn": _dumps(sn),
            "passed": int(bool(result["passed"])), "written": int(bool(result.get("written"))),
            "verified": int(bool(result.get("verified"))), "note": result.get("note"),
            "capture_dir": None if result.get("capture_dir") is None else str(result["capture_dir"]),
            "recorded_at": _utc_text(_dt.datetime.now(_dt.timezone.utc)), "record": record_json,
            "station_id": station.get("id"), "operator": station.get("operator"),
            "fixture": station.get("fixture"), "slot": station.get("slot"), "port": station.get("port"),
            "host_version": station.get("host_version"), "session_id": result.get("session_id"),
            "params_before": _dumps(result.get("params_before")), "params_after": _dumps(result.get("params_after")),
            "capture_sha256": capture.get("sha256"), "capture_uri": capture.get("uri"),
            "failed_stage": failure.get("stage"), "failure": failure.get("reason"),
        }
        device_row = {"board": dev.get("board"), "parts": _dumps(dev.get("parts")), "accel_ids": _dumps(dev.get("accel_ids")),
                      "gyro_pid": _dumps(dev.get("gyro_pid")), "gyro_sn": _dumps(sn)}
        with self._write() as db:
            device_id = None
            if uid is not None:
                db.execute(_insert_ignore(db, DB.devices).values(
                    mcu_uid=uid, first_seen=started, last_seen=started, **device_row))
                device_id, first_seen, last_seen = db.execute(_device_id_sql(db), {"uid": uid}).one()
                existing = db.execute(text("SELECT id, record FROM runs WHERE device_id = :d AND started = :s"),
                                      {"d": device_id, "s": started}).first()
                if existing is not None:
                    if existing[1] == record_json:
                        return existing[0], False
                    same_session = json.loads(existing[1]).get("session_started") == result.get("session_started")
                    raise ValueError(f"device {uid} already has a different run started at {result['started']} "
                                     f"(run {existing[0]}"
                                     + (", of the same session: its session.json changed since" if same_session
                                        and result.get("session_started") else "") + "): not stored")
                if started >= last_seen:     # the newest run describes the device as it is now
                    db.execute(text("UPDATE devices SET board = :board, parts = :parts, accel_ids = :accel_ids, gyro_pid = :gyro_pid, "
                                    "gyro_sn = :gyro_sn, last_seen = :s WHERE id = :d"),
                               {**device_row, "s": started, "d": device_id})
                if started < first_seen:
                    db.execute(text("UPDATE devices SET first_seen = :s WHERE id = :d"), {"s": started, "d": device_id})
            else:                           # an unidentified board: the same record twice is one run
                existing = db.execute(text("SELECT id FROM runs WHERE device_id IS NULL AND started = :s "
                                           "AND record = :r"), {"s": started, "r": record_json}).first()
                if existing is not None:
                    return existing[0], False
            run_id = self._insert_run(db, device_id, run)
            if meas:
                db.execute(DB.measurements.insert(), [
                    {"run_id": run_id, "seq": i, "name": str(m["name"]), "value": _float_or_none(m.get("value")),
                     "unit": str(m.get("unit") or ""), "low": _float_or_none(m.get("low")),
                     "high": _float_or_none(m.get("high")), "passed": int(bool(m.get("passed")))}
                    for i, m in enumerate(meas)])
            return run_id, True

    def _insert_run(self, db, device_id: int | None, run: dict) -> int:
        res = db.execute(DB.runs.insert().values(device_id=device_id, **run))
        return int(res.inserted_primary_key[0])

    def devices(self) -> list[dict]:
        """Every known device, most recently calibrated first."""
        with self._read() as db:
            rows = db.execute(text("SELECT id, mcu_uid, board, parts, accel_ids, gyro_pid, gyro_sn, first_seen, "
                                   "last_seen FROM devices ORDER BY last_seen DESC, mcu_uid")).all()
            out = []
            for (dev_id, uid, board, parts, ids, pid, sn, first, last) in rows:
                n = db.execute(text("SELECT COUNT(*) FROM runs WHERE device_id = :d"), {"d": dev_id}).scalar()
                latest = db.execute(text("SELECT started, method, gyro_method, passed, written, verified FROM runs "
                                         "WHERE device_id = :d ORDER BY started DESC, id DESC LIMIT 1"),
                                    {"d": dev_id}).first()
                d = {"mcu_uid": uid.upper(), "board": board, "parts": _loads(parts), "accel_ids": _loads(ids),
                     "gyro_pid": _loads(pid),
                     "gyro_sn": _loads(sn), "first_seen": first, "last_seen": last, "runs": n, "last_run": None}
                if latest:
                    d["last_run"] = {"started": latest[0], "method": latest[1], "gyro_method": latest[2],
                                     "passed": bool(latest[3]), "written": bool(latest[4]), "verified": bool(latest[5])}
                out.append(d)
        return out

    def resolve(self, device: str) -> str:
        """The full MCU UID (upper-case hex) of `device`: a full UID, a unique UID prefix (at
        least MIN_PREFIX hex digits) or a gyro serial number, all in hex as `imubench info`
        prints them (imubench.wire.ids: case, 0x and separators do not matter)."""
        if not str(device).strip():
            raise UnknownDevice("no device given")
        try:
            q = parse_id(device)
        except ValueError as e:
            raise UnknownDevice(str(e)) from None
        with self._read() as db:
            devs = db.execute(text("SELECT id, mcu_uid, gyro_sn FROM devices")).all()
            run_sns = db.execute(text("SELECT DISTINCT device_id, gyro_sn FROM runs "
                                      "WHERE gyro_sn IS NOT NULL AND device_id IS NOT NULL")).all()
        by_id = {i: uid.upper() for i, uid, _ in devs}
        if q in by_id.values():
            return q
        matches: set[str] = set()
        if len(q) >= MIN_PREFIX:
            matches |= {uid for uid in by_id.values() if uid.startswith(q)}
        serial = int(q, 16) if len(q) <= 8 else None
        if serial is not None:
            for i, _uid, sn in devs:
                if serial in (_loads(sn) or []):
                    matches.add(by_id[i])
            for i, sn in run_sns:           # a gyro that was on the board in an earlier run
                if serial in (_loads(sn) or []):
                    matches.add(by_id[i])
        if len(matches) == 1:
            return matches.pop()
        if len(matches) > 1:
            raise AmbiguousDevice(str(device).strip(), sorted(matches))
        hint = ""
        if len(q) < MIN_PREFIX:
            hint = f" (no gyro has that serial number, and a UID prefix needs at least {MIN_PREFIX} hex digits)"
        raise UnknownDevice(f"no device {str(device).strip()!r} in {self.path}{hint}")

    def _select_runs(self, where: str, params: dict, order: str = "r.started, r.id") -> list[dict]:
        with self._read() as db:
            res = db.execute(text("SELECT r.*, d.mcu_uid, d.board FROM runs r LEFT JOIN devices d ON d.id = r.device_id "
                                  f"WHERE {where} ORDER BY {order}"), params)
            rows = [dict(r._mapping) for r in res]
            ids = [r["id"] for r in rows]
            meas: dict[int, list] = {}
            for k in range(0, len(ids), 500):
                chunk = ids[k:k + 500]
                q = text("SELECT run_id, name, value, unit, low, high, passed FROM measurements "
                         "WHERE run_id IN :ids ORDER BY run_id, seq").bindparams(bindparam("ids", expanding=True))
                for m in db.execute(q, {"ids": chunk}):
                    meas.setdefault(m[0], []).append({"name": m[1], "value": m[2], "unit": m[3], "low": m[4],
                                                      "high": m[5], "passed": bool(m[6])})
        return [_run_from_row(r, meas.get(r["id"], [])) for r in rows]

    def runs(self, device: str) -> list[dict]:
        """Every run of a device (see resolve()), oldest first."""
        uid = self.resolve(device)
        return self._select_runs("d.mcu_uid = :uid", {"uid": uid.lower()})

    def run(self, run_id: int) -> dict:
        """One run by its id."""
        got = self._select_runs("r.id = :i", {"i": int(run_id)})
        if not got:
            raise UnknownDevice(f"no run {run_id} in {self.path}")
        return got[0]

    def session_runs(self, session_id: str) -> list[dict]:
        """Every board's run of one station session (a unique prefix of its id is enough),
        in fixture-slot order."""
        sid = str(session_id).strip()
        with self._read() as db:
            like = sid.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
            ids = [r[0] for r in db.execute(text("SELECT DISTINCT session_id FROM runs WHERE session_id LIKE :p "
                                                 "ESCAPE '\\'"), {"p": like})
                   if r[0] is not None]
        if not ids:
            raise UnknownDevice(f"no session {sid!r} in {self.path} (`imubench history --sessions` lists them)")
        if len(ids) > 1 and sid not in ids:
            raise UnknownDevice(f"session {sid!r} is ambiguous: {', '.join(sorted(ids)[:5])}: give more of it")
        sid = sid if sid in ids else ids[0]
        return self._select_runs("r.session_id = :s", {"s": sid}, order="r.slot, r.id")

    def sessions(self, since: str | None = None, station: str | None = None, limit: int = 50) -> list[dict]:
        """The latest station sessions: id, station, operator, fixture, start, boards, passed."""
        where, params = _filters(since, station)
        with self._read() as db:
            rows = db.execute(text(
                "SELECT session_id, MIN(station_id), MIN(operator), MIN(fixture), MIN(started), COUNT(*), "
                "SUM(passed) FROM runs r WHERE session_id IS NOT NULL" + where
                + " GROUP BY session_id ORDER BY MIN(started) DESC LIMIT :lim"), {**params, "lim": int(limit)}).all()
        return [{"session_id": r[0], "station_id": r[1], "operator": r[2], "fixture": r[3], "started": r[4],
                 "boards": int(r[5]), "passed": int(r[6] or 0)} for r in rows]

    def yield_table(self, by: str = "station_day", since: str | None = None, station: str | None = None) -> list[dict]:
        """First-pass yield: runs and passed runs grouped by station, by UTC day or both."""
        keys = {"station": ["station"], "day": ["day"], "station_day": ["station", "day"]}[by]
        expr = {"station": "COALESCE(r.station_id, '-')", "day": "SUBSTR(r.started, 1, 10)"}
        where, params = _filters(since, station)
        cols = ", ".join(f"{expr[k]} AS {k}" for k in keys)
        with self._read() as db:
            rows = db.execute(text(
                f"SELECT {cols}, COUNT(*) AS runs, SUM(r.passed) AS passed, "
                "COUNT(DISTINCT r.device_id) AS devices FROM runs r WHERE 1 = 1" + where
                + f" GROUP BY {', '.join(keys)} ORDER BY {', '.join(keys)}"), params).all()
        out = []
        for r in rows:
            m = dict(r._mapping)
            m["runs"], m["passed"] = int(m["runs"]), int(m["passed"] or 0)
            m["devices"] = int(m["devices"])
            m["failed"] = m["runs"] - m["passed"]
            m["yield"] = m["passed"] / m["runs"] if m["runs"] else None
            out.append(m)
        return out

    def failures(self, since: str | None = None, station: str | None = None) -> list[dict]:
        """Every failed run: the board, where and why it failed, the measurements out of
        their limits; newest first."""
        where, params = _filters(since, station)
        return self._select_runs("r.passed = 0" + where, params, order="r.started DESC, r.id DESC")

    def count_runs(self) -> int:
        with self._read() as db:
            return db.execute(text("SELECT COUNT(*) FROM runs")).scalar()


def _filters(since: str | None, station: str | None) -> tuple[str, dict]:
    where, params = "", {}
    if since:
        t = _parse_time(since if "T" in since else since + "T00:00:00+00:00")
        if t is None:
            raise HistoryError(f"--since {since!r} is not a date: give YYYY-MM-DD or an ISO 8601 time")
        where += " AND r.started >= :since"
        params["since"] = _utc_text(t)
    if station:
        where += " AND r.station_id = :station"
        params["station"] = station
    return where, params


def _insert_ignore(conn, table):
    """INSERT ... ON CONFLICT DO NOTHING in the connection's dialect."""
    if DB.is_pg(conn):
        from sqlalchemy.dialects.postgresql import insert
    else:
        from sqlalchemy.dialects.sqlite import insert
    return insert(table).on_conflict_do_nothing()


def _float_or_none(x):
    if x is None:
        return None
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


def _run_from_row(r: dict, measurements: list | None = None) -> dict:
    record = json.loads(r["record"])
    gyro = None
    if r["gyro_m"] is not None:
        gyro = {"m": _loads(r["gyro_m"]), "b_rad_s": _loads(r["gyro_b_rad_s"]),
                "sigma_m": _loads(r["gyro_sigma_m"]), "sigma_b_rad_s": _loads(r["gyro_sigma_b_rad_s"]),
                "residual_rms": r["gyro_residual_rms"]}
    accel = None
    if r["accel_m"] is not None:
        accel = {"m": _loads(r["accel_m"]), "b_mps2": _loads(r["accel_b_mps2"]),
                 "sigma_m": _loads(r["accel_sigma_m"]), "sigma_b_mps2": _loads(r["accel_sigma_b_mps2"]),
                 "residual_rms_mps2": r["accel_residual_rms_mps2"]}
    return {
        "run_id": r["id"], "mcu_uid": r["mcu_uid"].upper() if r.get("mcu_uid") else None, "board": r.get("board"),
        "started": record["started"], "finished": record["finished"],
        "started_utc": r["started"], "finished_utc": r["finished"],
        "method": r["method"], "gyro_method": r["gyro_method"],
        "accel": accel,
        "gyro": gyro,
        "poses": _loads(r["poses"]), "verification": _loads(r["verification"]) or [],
        "temperature_c": {"accel": r["temp_accel_c"], "gyro": _loads(r["temp_gyro_c"])},
        "tolerances": _loads(r["tolerances"]),
        "fw_version": r["fw_version"], "fw_build": r["fw_build"], "gyro_sn": _loads(r["gyro_sn"]),
        "passed": bool(r["passed"]), "written": bool(r["written"]), "verified": bool(r["verified"]),
        "note": r["note"], "capture_dir": r["capture_dir"], "recorded_at": r["recorded_at"],
        "station_id": r.get("station_id"), "operator": r.get("operator"), "fixture": r.get("fixture"),
        "slot": r.get("slot"), "port": r.get("port"), "host_version": r.get("host_version"),
        "session_id": r.get("session_id"), "params_before": _loads(r.get("params_before")),
        "params_after": _loads(r.get("params_after")), "capture_sha256": r.get("capture_sha256"),
        "capture_uri": r.get("capture_uri"), "failed_stage": r.get("failed_stage"), "failure": r.get("failure"),
        "measurements": measurements if measurements is not None else [],
        "record": record,
    }


def device_report(h: History, device: str) -> dict:
    """Everything `imubench history DEVICE` shows, as data."""
    uid = h.resolve(device)
    runs = h.runs(uid)
    dev = next(d for d in h.devices() if d["mcu_uid"] == uid)
    summaries = [run_summary(r, i + 1) for i, r in enumerate(runs)]
    return {"device": dev, "runs": summaries, "drift": drift(summaries)}
