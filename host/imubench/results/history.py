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
import math
import re
from pathlib import Path

import numpy as np
from sqlalchemy import bindparam, text

from imubench import units as U
from imubench.results import db as DB
from imubench.results.export import measurement_text, measurements_of
from imubench.results.numbers import pm
from imubench.text import one_line
from imubench.wire.ids import parse_id, sn_text

SCHEMA_VERSION = DB.SCHEMA_VERSION   # of the database (results.db: the tables and their migrations)
RECORD_SCHEMA = 2           # of the result record a calibration session produces (1: before the production line)
RECORD_SCHEMAS = (1, 2)     # records this imubench stores
DRIFT_SIGMAS = 3.0          # a change is flagged when |change| > DRIFT_SIGMAS * combined sigma
MIN_PREFIX = 4              # hex digits of an MCU UID prefix
_AXES = ("x", "y", "z")

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


def default_path() -> Path:
    import platformdirs
    return Path(platformdirs.user_data_dir("imubench")) / "history.sqlite"


def default_target() -> str | Path:
    """The database to use when none is given: $IMUBENCH_DB (a path or a postgresql:// URL),
    else default_path()."""
    import os
    env = os.environ.get(DB.ENV_DB, "").strip()
    return env if DB.is_url(env) else Path(env) if env else default_path()


# ------------------------------------------------------------------ validation
def _num_array(x, shape) -> np.ndarray | None:
    """x as a float array of `shape` (None → NaN), or None when it is not that."""
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a if a.shape == shape else None


def _parse_time(s) -> _dt.datetime | None:
    if not isinstance(s, str):
        return None
    try:
        t = _dt.datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        return None
    if t.tzinfo is None:            # no offset: taken as UTC (what sessions write)
        t = t.replace(tzinfo=_dt.timezone.utc)
    return t.astimezone(_dt.timezone.utc)


def _utc_text(t: _dt.datetime) -> str:
    return t.isoformat(timespec="microseconds")


def _triad_problems(d, prefix: str, b_key: str, rms_keys: tuple[str, ...]) -> tuple[list, list]:
    missing, bad = [], []
    if not isinstance(d, dict):
        return [], [f"{prefix} must be an object"]
    for k in ("m", b_key, "sigma_m", f"sigma_{b_key}"):
        if k not in d:
            missing.append(f"{prefix}.{k}")
    if not any(k in d for k in rms_keys):
        missing.append(f"{prefix}.{rms_keys[0]}")
    if "m" in d:
        m = _num_array(d["m"], (3, 3))
        if m is None or not np.isfinite(m).all():
            bad.append(f"{prefix}.m must be 3x3 finite numbers")
    if b_key in d:
        b = _num_array(d[b_key], (3,))
        if b is None or not np.isfinite(b).all():
            bad.append(f"{prefix}.{b_key} must be 3 finite numbers")
    if "sigma_m" in d and _num_array(d["sigma_m"], (3, 3)) is None:
        bad.append(f"{prefix}.sigma_m must be 3x3 numbers (null/NaN where not estimated)")
    if f"sigma_{b_key}" in d and _num_array(d[f"sigma_{b_key}"], (3,)) is None:
        bad.append(f"{prefix}.sigma_{b_key} must be 3 numbers (null/NaN where not estimated)")
    return missing, bad


def validate_result(result) -> None:
    """Raise ValueError naming every missing or malformed key of a result record."""
    if not isinstance(result, dict):
        raise ValueError(f"a result record is a dict, got {type(result).__name__}")
    missing, bad = [], []
    # a board that failed before it was fitted (schema 2: "failure" says where and why) has
    # no fit, maybe no poses and, when its link never answered, no identity
    failed = result.get("schema") == 2 and result.get("failure") is not None
    required = (("schema", "device", "started", "finished", "passed", "failure") if failed else
                ("schema", "device", "started", "finished", "method", "gyro_method", "accel", "gyro",
                 "poses", "passed", "written", "verified"))
    for k in required:
        if k not in result:
            missing.append(k)
    if "schema" in result and result["schema"] not in RECORD_SCHEMAS:
        bad.append(f"schema is {result['schema']!r}, this imubench records schema "
                   + " and ".join(map(str, RECORD_SCHEMAS)))
    if failed:
        f = result["failure"]
        if not (isinstance(f, dict) and isinstance(f.get("stage"), str) and isinstance(f.get("reason"), str)):
            bad.append("failure must be an object with stage and reason (text)")
        if result.get("passed"):
            bad.append("a record with a failure cannot have passed")
    meas = result.get("measurements")
    if meas is not None and not (isinstance(meas, list) and all(isinstance(m, dict) and "name" in m for m in meas)):
        bad.append("measurements must be a list of objects with a name")
    dev = result.get("device")
    if "device" in result:
        if not isinstance(dev, dict):
            bad.append("device must be an object")
        else:
            missing += [f"device.{k}" for k in ("mcu_uid", "board", "fw_version", "fw_build")
                        if k not in dev and not failed]
            uid = dev.get("mcu_uid")
            if (uid is not None or not failed) and "mcu_uid" in dev and \
                    not (isinstance(uid, str) and re.fullmatch(r"[0-9a-fA-F]{24}", uid)):
                bad.append(f"device.mcu_uid must be 24 hex digits, got {uid!r}")
            sn = dev.get("gyro_sn")
            if sn is not None and not (isinstance(sn, list) and all(isinstance(v, int) for v in sn)):
                bad.append("device.gyro_sn must be a list of integers")
    for k in ("started", "finished"):
        if k in result and _parse_time(result[k]) is None:
            bad.append(f"{k} must be an ISO 8601 time, got {result[k]!r}")
    if "method" in result and not (isinstance(result["method"], str) and result["method"]) \
            and not (failed and result["method"] is None):
        bad.append("method must be a non-empty string")
    if "gyro_method" in result and not (result["gyro_method"] is None or isinstance(result["gyro_method"], str)):
        bad.append("gyro_method must be a string or null")
    if "accel" in result and not (failed and result["accel"] is None):
        mi, ba = _triad_problems(result["accel"], "accel", "b_mps2", ("residual_rms_mps2", "residual_rms"))
        missing += mi
        bad += ba
    if result.get("gyro") is not None:
        mi, ba = _triad_problems(result["gyro"], "gyro", "b_rad_s", ("residual_rms",))
        missing += mi
        bad += ba
    if "poses" in result and not (failed and not result["poses"]):
        poses = result["poses"]
        if not isinstance(poses, list) or not poses:
            bad.append("poses must be a non-empty list")
        else:
            for i, p in enumerate(poses):
                if not isinstance(p, dict):
                    bad.append(f"poses[{i}] must be an object")
                    continue
                missing += [f"poses[{i}].{k}" for k in ("name", "before_g", "after_g") if k not in p]
    for k in ("passed", "written", "verified"):
        if k in result and not isinstance(result[k], (bool, np.bool_)):
            bad.append(f"{k} must be true or false")
    problems = []
    if missing:
        problems.append("missing " + ", ".join(missing))
    if bad:
        problems += bad
    if problems:
        raise ValueError("result record not stored: " + "; ".join(problems))


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON-serialisable")


def _dumps(x) -> str | None:
    if x is None:
        return None
    return json.dumps(x, sort_keys=True, default=_json_default)


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
        device_row = {"board": dev.get("board"), "accel_ids": _dumps(dev.get("accel_ids")),
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
                    db.execute(text("UPDATE devices SET board = :board, accel_ids = :accel_ids, gyro_pid = :gyro_pid, "
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
            rows = db.execute(text("SELECT id, mcu_uid, board, accel_ids, gyro_pid, gyro_sn, first_seen, last_seen "
                                   "FROM devices ORDER BY last_seen DESC, mcu_uid")).all()
            out = []
            for (dev_id, uid, board, ids, pid, sn, first, last) in rows:
                n = db.execute(text("SELECT COUNT(*) FROM runs WHERE device_id = :d"), {"d": dev_id}).scalar()
                latest = db.execute(text("SELECT started, method, gyro_method, passed, written, verified FROM runs "
                                         "WHERE device_id = :d ORDER BY started DESC, id DESC LIMIT 1"),
                                    {"d": dev_id}).first()
                d = {"mcu_uid": uid.upper(), "board": board, "accel_ids": _loads(ids), "gyro_pid": _loads(pid),
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


# ------------------------------------------------------------------ derived values
def _fin(x) -> float | None:
    """A float for JSON: None for NaN/inf/None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _sigma_ok(s) -> bool:
    return s is not None and math.isfinite(s) and s > 0


def _triad_summary(t: dict | None, b_key: str, to_user, bias_unit: str) -> dict | None:
    """Bias in user units, scale error diag(M) − 1 in ppm, the largest off-diagonal of M in
    ppm; sigmas None where the fit did not estimate the parameter."""
    if t is None:
        return None
    m = np.array(t["m"], dtype=np.float64)
    sm = np.array(t["sigma_m"], dtype=np.float64)
    b = np.array(t[b_key], dtype=np.float64)
    sb = np.array(t[f"sigma_{b_key}"], dtype=np.float64)
    off = np.abs(m)
    np.fill_diagonal(off, -1.0)             # only the off-diagonal (cross-axis) terms compete
    i, j = np.unravel_index(int(np.argmax(off)), (3, 3))
    return {
        f"bias_{bias_unit}": [_fin(v) for v in to_user(b)],
        f"bias_sigma_{bias_unit}": [_fin(v) for v in to_user(sb)],
        "scale_error_ppm": [_fin(v) for v in (np.diag(m) - 1.0) * 1e6],
        "scale_error_sigma_ppm": [_fin(v) for v in np.diag(sm) * 1e6],
        "cross_axis": {"term": f"M[{_AXES[i]},{_AXES[j]}]", "row": int(i), "col": int(j),
                       "ppm": _fin(m[i, j] * 1e6), "sigma_ppm": _fin(sm[i, j] * 1e6)},
    }


def run_summary(run: dict, index: int) -> dict:
    """One run in user units (mg, °/s, ppm), as `imubench history DEVICE` shows it."""
    acc = _triad_summary(run["accel"], "b_mps2", U.mps2_to_mg, "mg")
    if acc is not None:
        rr = run["accel"].get("residual_rms_mps2")
        acc["residual_rms_mg"] = _fin(U.mps2_to_mg(rr)) if rr is not None else None
    gyr = _triad_summary(run["gyro"], "b_rad_s", U.rad_s_to_dps, "dps")
    if gyr is not None:
        gyr["residual_rms"] = _fin(run["gyro"].get("residual_rms"))
    return {
        "index": index, "run_id": run["run_id"], "started": run["started"], "finished": run["finished"],
        "method": run["method"], "gyro_method": run["gyro_method"],
        "fw_version": run["fw_version"], "fw_build": run["fw_build"],
        "accel": acc, "gyro": gyr,
        "temperature_c": {"accel": _fin(run["temperature_c"]["accel"]),
                          "gyro": None if run["temperature_c"]["gyro"] is None
                          else [_fin(v) for v in run["temperature_c"]["gyro"]]},
        "passed": run["passed"], "written": run["written"], "verified": run["verified"],
        "note": run["note"] or "", "capture_dir": run["capture_dir"],
        **{k: run.get(k) for k in ("station_id", "operator", "fixture", "slot", "port", "host_version",
                                   "session_id", "capture_sha256", "capture_uri", "failed_stage", "failure")},
        "measurements": run.get("measurements") or [],
    }


# (key, sensor, value key, sigma key, unit)
DRIFT_QUANTITIES = (
    ("accel_bias_mg", "accel", "bias_mg", "bias_sigma_mg", "mg"),
    ("accel_scale_ppm", "accel", "scale_error_ppm", "scale_error_sigma_ppm", "ppm"),
    ("gyro_bias_dps", "gyro", "bias_dps", "bias_sigma_dps", "°/s"),
    ("gyro_scale_ppm", "gyro", "scale_error_ppm", "scale_error_sigma_ppm", "ppm"),
)


def _change(a: dict, b: dict) -> dict:
    d = b["value"] - a["value"]
    s = math.hypot(a["sigma"], b["sigma"])
    return {"from": a["index"], "to": b["index"], "from_run_id": a["run_id"], "to_run_id": b["run_id"],
            "change": d, "sigma": s, "n_sigma": abs(d) / s, "flagged": abs(d) > DRIFT_SIGMAS * s}


def drift(summaries: list[dict]) -> dict:
    """How each bias and scale error moved across runs: per axis, the change between
    consecutive runs that estimated it, and first → last; each with the combined 1-sigma
    sqrt(σ1² + σ2²) and flagged when |change| > DRIFT_SIGMAS × that. A run where a quantity
    was not estimated (no sigma, e.g. the gyro scale of a bias-only run) is left out of it."""
    out = {"threshold_sigmas": DRIFT_SIGMAS, "quantities": {}, "flagged": []}
    for key, sensor, vkey, skey, unit in DRIFT_QUANTITIES:
        axes = {}
        for k, ax in enumerate(_AXES):
            series = []
            for s in summaries:
                t = s[sensor]
                if t is None:
                    continue
                v, sg = t[vkey][k], t[skey][k]
                if v is None or not _sigma_ok(sg):
                    continue
                series.append({"index": s["index"], "run_id": s["run_id"], "value": v, "sigma": sg})
            steps = [_change(a, b) for a, b in zip(series, series[1:])]
            first_last = _change(series[0], series[-1]) if len(series) >= 2 else None
            axes[ax] = {"runs": [x["index"] for x in series], "steps": steps, "first_last": first_last}
            for st in steps + ([first_last] if first_last and len(series) > 2 else []):
                if st["flagged"]:
                    out["flagged"].append({"quantity": key, "axis": ax, "unit": unit, **st})
        out["quantities"][key] = {"unit": unit, "axes": axes}
    return out


def device_report(h: History, device: str) -> dict:
    """Everything `imubench history DEVICE` shows, as data."""
    uid = h.resolve(device)
    runs = h.runs(uid)
    dev = next(d for d in h.devices() if d["mcu_uid"] == uid)
    summaries = [run_summary(r, i + 1) for i, r in enumerate(runs)]
    return {"device": dev, "runs": summaries, "drift": drift(summaries)}


# ------------------------------------------------------------------ text
def _pm(v, s, dec: int, width: int = 0) -> str:
    """value ± sigma to sigma's precision (results.numbers; `dec` decimals where no sigma)."""
    if v is None:
        return "-".rjust(width)
    if s is not None and math.isfinite(s) and s > 0:
        txt = pm(v, s)
    else:
        txt = f"{v:+.{dec}f} (not estimated)"
    return txt.ljust(width)


def _when(iso: str) -> str:
    t = _parse_time(iso)
    return t.strftime("%Y-%m-%d %H:%M UTC") if t else str(iso)


def _yes(b: bool) -> str:
    return "yes" if b else "NO"


def format_devices(devs: list[dict], path) -> str:
    if not devs:
        return f"no calibrations recorded yet in {path}"
    lines = [f"{'MCU UID':<24}  {'board':<6} {'runs':>4}  {'last calibration':<20}  {'method':<16}  result"]
    for d in devs:
        lr = d["last_run"] or {}
        method = lr.get("method", "-") + (f"/{lr['gyro_method']}" if lr.get("gyro_method") else "")
        res = ("passed" if lr.get("passed") else "FAILED") + (", written" if lr.get("written") else ", not written") \
            + (", verified" if lr.get("verified") else ", not verified") if lr else "-"
        lines.append(f"{d['mcu_uid']:<24}  {d['board'] or '-':<6} {d['runs']:>4}  {_when(d['last_seen']):<20}  "
                     f"{method:<16}  {res}")
    lines.append(f"({len(devs)} device{'s' if len(devs) != 1 else ''} in {path}; "
                 "`imubench history DEVICE` for one device's runs and drift)")
    return "\n".join(lines)


_LABEL_W = 24       # label column of the per-run lines
_CELL_W = 20        # one axis: "+1.0197 ± 0.0020"


def _triad_lines(t: dict, name: str, bias_unit: str, bias_label: str, bias_dec: int) -> list[str]:
    def row(label, values, sigmas, dec):
        return (f"  {label}".ljust(_LABEL_W)
                + "  ".join(f"{ax.upper()} " + _pm(v, s, dec, _CELL_W) for ax, v, s in zip(_AXES, values, sigmas))).rstrip()
    lines = [row(f"{name} bias [{bias_label}]", t[f"bias_{bias_unit}"], t[f"bias_sigma_{bias_unit}"], bias_dec),
             row(f"{name} scale [ppm]", t["scale_error_ppm"], t["scale_error_sigma_ppm"], 1)]
    c = t["cross_axis"]
    lines.append(f"  {name} cross-axis".ljust(_LABEL_W) + f"largest {c['term']} = {_pm(c['ppm'], c['sigma_ppm'], 1)} ppm")
    return lines


def format_device_report(rep: dict) -> str:
    dev = rep["device"]
    runs = rep["runs"]
    sn = dev.get("gyro_sn")
    out = [f"device {dev['mcu_uid']}  board {dev['board'] or '-'}"
           + (f"  gyro SN {' '.join(sn_text(x) for x in sn)}" if sn else "")
           + f"  {len(runs)} run{'s' if len(runs) != 1 else ''}"]
    for s in runs:
        out.append("")
        gm = f", gyro {s['gyro_method']}" if s["gyro_method"] else ", no gyro calibration"
        out.append(f"run {s['index']} (id {s['run_id']})  {_when(s['started'])}  method {s['method']}{gm}  "
                   f"fw {s['fw_version']} ({s['fw_build']})")
        out += _station_lines(s)
        if s["accel"] is None:
            out.append("  accel".ljust(_LABEL_W) + "no fit (the board failed before it)")
        else:
            out += _triad_lines(s["accel"], "accel", "mg", "mg", 4)
        if s["accel"] is not None and s["accel"]["residual_rms_mg"] is not None:
            out.append("  accel fit residual".ljust(_LABEL_W) + f"{s['accel']['residual_rms_mg']:.4f} mg RMS")
        if s["gyro"] is not None:
            out += _triad_lines(s["gyro"], "gyro", "dps", "°/s", 5)
        t = s["temperature_c"]
        temp = []
        if t["accel"] is not None:
            temp.append(f"accel {t['accel']:.1f} °C")
        if t["gyro"]:
            temp.append("gyro X/Y/Z " + "/".join("-" if v is None else f"{v:.1f}" for v in t["gyro"]) + " °C")
        out.append("  temperature".ljust(_LABEL_W) + (", ".join(temp) or "-"))
        out.append("  status".ljust(_LABEL_W) + f"passed {_yes(s['passed'])}, written {_yes(s['written'])}, "
                   f"verified {_yes(s['verified'])}")
        if s.get("failure"):
            out.append("  failed".ljust(_LABEL_W) + one_line(f"at {s['failed_stage']}: {s['failure']}"))
        for m in s.get("measurements") or []:
            out.append("  measured".ljust(_LABEL_W) + f"{m['name']} = {measurement_text(m)}")
        if s["note"]:
            out.append("  note".ljust(_LABEL_W) + one_line(s["note"]))
    out.append("")
    out += _format_drift(rep["drift"], len(runs))
    return "\n".join(out)


def _station_lines(s: dict) -> list[str]:
    """Where and by whom a run was made, and where its raw capture is (schema-2 runs)."""
    out = []
    if s.get("station_id") or s.get("operator") or s.get("fixture"):
        parts = [f"station {s.get('station_id') or '-'}" + (f" slot {s['slot']}" if s.get("slot") is not None else "")]
        if s.get("operator"):
            parts.append(f"operator {s['operator']}")
        if s.get("fixture"):
            parts.append(f"fixture {s['fixture']}")
        if s.get("host_version"):
            parts.append(f"host {s['host_version']}")
        if s.get("session_id"):
            parts.append(f"session {s['session_id']}")
        out.append("  where".ljust(_LABEL_W) + ", ".join(parts))
    if s.get("capture_sha256"):
        out.append("  raw capture".ljust(_LABEL_W) + f"capture sha256 {s['capture_sha256']}"
                   + (f" at {s['capture_uri']}" if s.get("capture_uri") else ""))
    return out


# ------------------------------------------------------------------ production queries, as text
def _pct(x) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def format_yield(rows: list[dict], by: str, path) -> str:
    """First-pass yield per station and/or day (a percentage of counted runs: one decimal,
    the resolution of 1 in 1000 runs)."""
    if not rows:
        return f"no runs in {path} match"
    keys = {"station": ["station"], "day": ["day"], "station_day": ["station", "day"]}[by]
    w = {"station": max(8, *(len(str(r["station"])) for r in rows)) if "station" in keys else 0, "day": 10}
    head = "".join(f"{k:<{w[k]}}  " for k in keys) + f"{'runs':>5} {'passed':>6} {'failed':>6} {'yield':>8}  boards"
    lines = [head]
    for r in rows:
        lines.append("".join(f"{str(r[k]):<{w[k]}}  " for k in keys)
                     + f"{r['runs']:>5} {r['passed']:>6} {r['failed']:>6} {_pct(r['yield']):>8}  {r['devices']}")
    n = sum(r["runs"] for r in rows)
    p = sum(r["passed"] for r in rows)
    lines.append("".join(f"{('total' if i == 0 else ''):<{w[k]}}  " for i, k in enumerate(keys))
                 + f"{n:>5} {p:>6} {n - p:>6} {_pct(p / n if n else None):>8}")
    lines.append(f"(first-pass yield = passed runs / runs, from {path}; `--failed` lists why the others failed)")
    return "\n".join(lines)


def format_failures(runs: list[dict], path) -> str:
    """The boards that failed and why: the stage and reason, or the measurements out of limits."""
    if not runs:
        return f"no failed runs in {path}"
    lines = []
    for r in runs:
        who = r["mcu_uid"] or f"unidentified board (port {r.get('port') or '-'})"
        where = f"station {r.get('station_id') or '-'}" + (f" slot {r['slot']}" if r.get("slot") is not None else "")
        lines.append(f"{_when(r['started'])}  {who}  {where}  run {r['run_id']}"
                     + (f"  session {r['session_id']}" if r.get("session_id") else ""))
        reasons = []
        if r.get("failure"):
            reasons.append(f"failed at {r.get('failed_stage') or '?'}: {r['failure']}")
        for m in r.get("measurements") or []:
            if not m.get("passed"):
                reasons.append(f"{m['name']} = {measurement_text(m)}")
        if not reasons:
            reasons.append("did not pass" + (f" ({r['note']})" if r.get("note") else ""))
        lines += [f"    {x}" for x in reasons]
    lines.append(f"({len(runs)} failed run{'s' if len(runs) != 1 else ''} in {path}, newest first)")
    return "\n".join(lines)


def format_sessions(rows: list[dict], path) -> str:
    if not rows:
        return f"no station sessions in {path}"
    lines = [f"{'session':<36}  {'station':<10} {'operator':<10} {'started':<20} boards passed"]
    for r in rows:
        lines.append(f"{r['session_id']:<36}  {r['station_id'] or '-':<10} {r['operator'] or '-':<10} "
                     f"{_when(r['started']):<20} {r['boards']:>6} {r['passed']:>6}")
    lines.append("(`imubench history --export SESSION --format junit|json` writes one as a test record)")
    return "\n".join(lines)


_DRIFT_LABELS = {"accel_bias_mg": ("accel bias [mg]", 4), "accel_scale_ppm": ("accel scale [ppm]", 1),
                 "gyro_bias_dps": ("gyro bias [°/s]", 5), "gyro_scale_ppm": ("gyro scale [ppm]", 1)}


_DRIFT_LABEL_W = 28
_DRIFT_CELL_W = 28


def _format_drift(dr: dict, n_runs: int) -> list[str]:
    thr = dr["threshold_sigmas"]
    if n_runs < 2:
        return ["drift: only one run, nothing to compare yet"]
    out = [f"drift across runs: change ± combined 1σ; DRIFT where |change| > {thr:g}σ (a real change, not fit noise)"]
    for key, q in dr["quantities"].items():
        label, dec = _DRIFT_LABELS[key]
        # rows: each step, then first -> last, over the runs that estimated the quantity
        rows: dict[tuple, dict] = {}
        for ax in _AXES:
            a = q["axes"][ax]
            for st in a["steps"]:
                rows.setdefault(("step", st["from"], st["to"]), {})[ax] = st
            if a["first_last"] is not None and len(a["runs"]) > 2:
                fl = a["first_last"]
                rows.setdefault(("first_last", fl["from"], fl["to"]), {})[ax] = fl
        if not rows:
            out.append(f"  {label}: fewer than two runs estimated it")
            continue
        out.append(f"  {label}".ljust(_DRIFT_LABEL_W) + "".join(f"{ax.upper():<{_DRIFT_CELL_W}}" for ax in _AXES).rstrip())
        for k in sorted(rows, key=lambda k: (k[0] == "first_last", k[1], k[2])):
            name = (f"first -> last ({k[1]} -> {k[2]})" if k[0] == "first_last" else f"run {k[1]} -> {k[2]}")
            cells = []
            for ax in _AXES:
                st = rows[k].get(ax)
                cell = "-" if st is None else _pm(st["change"], st["sigma"], dec) + (" DRIFT" if st["flagged"] else "")
                cells.append(cell.ljust(_DRIFT_CELL_W))
            out.append(f"    {name}".ljust(_DRIFT_LABEL_W) + "".join(cells).rstrip())
    flagged = dr["flagged"]
    if flagged:
        out.append(f"{len(flagged)} change{'s' if len(flagged) != 1 else ''} larger than {thr:g}σ: "
                   + "; ".join(f"{f['quantity'].rsplit('_', 1)[0].replace('_', ' ')} {f['axis'].upper()} "
                               f"run {f['from']} -> {f['to']} {f['change']:+.{_DRIFT_LABELS[f['quantity']][1]}f} "
                               f"{f['unit']} ({f['n_sigma']:.1f}σ)" for f in flagged))
    else:
        out.append(f"no change larger than {thr:g}σ: bias and scale are stable within the fits' uncertainty")
    return out


# ------------------------------------------------------------------ CLI
def strict_json(x):
    """NaN/inf → null, so --json output is standard JSON."""
    if isinstance(x, dict):
        return {k: strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
