"""`imubench history`: the devices a history database knows, one device's runs and drift, and
the production queries: yield per station and day, the boards that failed and why, the
station sessions, and the export of one session as JSON or JUnit XML."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from imubench.cli.common import UsageError
from imubench.text import one_line, printable


def _db_target(s: str):
    """A database file (SQLite) or a postgresql:// URL."""
    if "://" in s:
        if not s.split("://", 1)[0] in ("postgresql", "postgres", "postgresql+psycopg"):
            raise argparse.ArgumentTypeError(f"{s.split('://', 1)[0]}:// is not a database this imubench speaks: "
                                             "give a file path (SQLite) or postgresql://USER@HOST[:PORT]/DBNAME")
        return s
    p = Path(s)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a directory: give the database file (e.g. {p / 'history.sqlite'})")
    return p


def _since(s: str) -> str:
    """A day (YYYY-MM-DD, UTC) or an ISO 8601 time."""
    import datetime as dt
    try:
        dt.datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a date: give YYYY-MM-DD (UTC) or an ISO 8601 time") from None
    return s


def register(sub) -> None:
    from imubench.results.where import ENV_DB, default_path
    p = sub.add_parser("history", help="calibration history: devices, drift, yield, failures, export",
                       description="Calibration history: the known devices, or one device's runs and how its "
                                   "bias and scale drifted between calibrations; for a production line the "
                                   "yield per station and day, the boards that failed and why, the station "
                                   "sessions and the export of one as JSON or JUnit XML. Identifiers are hex, "
                                   "as `imubench info` prints them.")
    p.add_argument("device", nargs="?", metavar="DEVICE",
                   help="MCU UID, a unique prefix of it (at least 4 hex digits) or a gyro serial number (hex)")
    p.add_argument("--db", type=_db_target, metavar="PATH|URL",
                   help=f"history database: an SQLite file or a postgresql://USER@HOST[:PORT]/DBNAME URL "
                        f"(default: ${ENV_DB}, else {default_path()})")
    p.add_argument("--json", action="store_true", help="print the same data as JSON")
    q = p.add_mutually_exclusive_group()
    q.add_argument("--yield", dest="yield_by", nargs="?", const="station_day", choices=("station", "day", "station_day"),
                   metavar="BY", help="first-pass yield per station, per day or per station and day (the default)")
    q.add_argument("--failed", action="store_true", help="the boards that failed and why, newest first")
    q.add_argument("--sessions", action="store_true", help="the latest station sessions (one per fixture run)")
    q.add_argument("--export", metavar="SESSION", help="one station session (a unique prefix of its id) as a test "
                                                       "record: --format json or junit")
    q.add_argument("--upgrade", action="store_true", help="upgrade the database's tables to this imubench's schema "
                                                          "(versioned migrations; a newer database is refused)")
    from imubench.results import exports as X
    X.add_option(p, "session", flag="--format", dest="format", what="with --export: the session as")
    p.add_argument("--out", metavar="FILE|DIR", type=Path, help="with --export: write to FILE instead of printing; "
                                                               "with several --format, the directory they go to")
    p.add_argument("--since", metavar="DATE", type=_since, help="with --yield, --failed, --sessions: runs started from DATE "
                                                   "(YYYY-MM-DD, UTC)")
    p.add_argument("--station", metavar="ID", help="with --yield, --failed, --sessions: one station only")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.results import history as H
    from imubench.cli import history_text as T
    from imubench.cli.history_text import strict_json
    from imubench.results.history import History, default_path, default_target

    production = a.yield_by or a.failed or a.sessions or a.export or a.upgrade
    if a.device and production:
        raise UsageError("DEVICE goes alone: --yield, --failed, --sessions, --export and --upgrade are about "
                         "the whole database", "drop DEVICE, or the option")
    if (a.since or a.station) and not (a.yield_by or a.failed or a.sessions):
        raise UsageError("--since and --station go with --yield, --failed or --sessions")
    if (a.out or a.format) and not a.export:
        raise UsageError("--format and --out go with --export SESSION")
    if a.out is not None and a.out.is_dir() and len(a.format or ()) < 2:
        raise UsageError(f"--out {a.out} is a directory", "give a file name, e.g. session.xml")
    target = a.db if a.db is not None else default_target()
    shown = H.DB.describe(target)
    if not H.DB.is_url(target) and not Path(target).exists() and a.db is None and a.device is None \
            and not a.upgrade and target == default_path():
        # the default database does not exist until the first session records into it
        print(json.dumps({"database": str(target), "devices": []}) if a.json
              else f"no calibrations recorded yet ({target} does not exist)")
        return 0
    if a.upgrade:
        if not H.DB.is_url(target) and not Path(target).is_file():
            raise UsageError(f"no history database at {target}", "give --db PATH of an existing file")
        from imubench.results import db as DB
        eng, conn = DB.make_engine(target), None
        try:
            conn = eng.connect()
            before = DB.prepare(conn, shown)
        finally:
            DB.close(eng, conn)
        print(f"{shown}: already at schema {DB.SCHEMA_VERSION}" if before == DB.SCHEMA_VERSION
              else f"{shown}: upgraded from schema {before} to {DB.SCHEMA_VERSION}")
        return 0
    with History(target, readonly=True) as h:
        if a.yield_by:
            rows = h.yield_table(a.yield_by, since=a.since, station=a.station)
            print(json.dumps(strict_json({"database": shown, "by": a.yield_by, "yield": rows}), indent=1)
                  if a.json else printable(T.format_yield(rows, a.yield_by, shown)))
            return 0
        if a.failed:
            runs = h.failures(since=a.since, station=a.station)
            print(json.dumps(strict_json({"database": shown, "failed": [_brief(r) for r in runs]}), indent=1)
                  if a.json else printable(T.format_failures(runs, shown)))
            return 0
        if a.sessions:
            rows = h.sessions(since=a.since, station=a.station)
            print(json.dumps({"database": shown, "sessions": rows}, indent=1) if a.json
                  else printable(T.format_sessions(rows, shown)))
            return 0
        if a.export:
            from imubench.results.export import junit_xml, session_json
            from imubench.results import exports as X
            from imubench.results.atomic import write_text_atomic
            formats = a.format or ("json",)
            if len(formats) > 1 and (a.out is None or (a.out.exists() and not a.out.is_dir())):
                raise UsageError(f"--format {','.join(formats)}: several files need --out DIR",
                                 "give the directory they go to, or one format")
            runs = h.session_runs(a.export)
            sid = str(runs[0]["session_id"])
            for fmt in formats:
                text = junit_xml(runs) if fmt == "junit" else session_json(runs) + "\n"
                if len(formats) > 1:
                    target = a.out / X.file_names("session", fmt, "".join(c if c.isalnum() or c in "-_" else "_"
                                                                          for c in sid))[0]
                    a.out.mkdir(parents=True, exist_ok=True)
                else:
                    target = a.out
                if target is not None:
                    write_text_atomic(target, text)
                    print(f"session {one_line(sid)} ({len(runs)} boards) written to {one_line(target)} as {fmt}")
                else:
                    print(text, end="")
            return 0
        if a.device is None:
            devs = h.devices()
            if a.json:
                print(json.dumps(strict_json({"database": shown, "devices": devs}), indent=1))
            else:
                print(printable(T.format_devices(devs, shown)))
            return 0
        rep = H.device_report(h, a.device)
    if a.json:
        print(json.dumps(strict_json({"database": shown, **rep}), indent=1, allow_nan=False))
    else:
        print(printable(T.format_device_report(rep)))
    return 0


def _brief(r: dict) -> dict:
    return {k: r.get(k) for k in ("run_id", "mcu_uid", "started", "station_id", "slot", "port", "operator",
                                  "session_id", "failed_stage", "failure", "measurements", "note")}
