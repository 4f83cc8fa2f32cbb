"""The calibration record: what one calibration run produced, as stored in session.json,
record.json, the history and the exports.

One schema number, one validation, one verdict rule, one JSON conversion and one clock, for
every builder (the one-board session, the fixture's boards, a calibration from a file, the
command line's station fields, the history's check before storing).
"""
from __future__ import annotations

import datetime as _dt
import re
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from imubench.calib import TriadFit
from imubench.wire.ids import device_identity

RECORD_SCHEMA = 2           # of the result record a calibration session produces (1: before the production line)
RECORD_SCHEMAS = (1, 2)     # records this imubench stores


def now_utc() -> str:
    """The one clock of records and sessions: UTC, ISO 8601 with microseconds (two boards of a
    fixture that start in the same second still get distinct run starts)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")


def jsonable(x):
    """x with numpy arrays and scalars, tuples and paths turned into JSON's types (the one
    conversion of a record, a session's state and a station file; NaN stays NaN: the history
    keeps it, strict output turns it into null at the edge)."""
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def fit_dict(fit: TriadFit | None, unit: str) -> dict | None:
    """A fit as the record keeps it: M, b and their sigmas in SI (`unit`: mps2 or rad_s)."""
    if fit is None:
        return None
    return {"method": fit.method, "m": fit.m.tolist(), f"b_{unit}": fit.b.tolist(),
            "sigma_m": fit.sigma_m.tolist(), f"sigma_b_{unit}": fit.sigma_b.tolist(),
            "residual_rms": fit.residual_rms, "extra": jsonable(fit.extra)}


def device_ident(info) -> dict:
    """The record's device section from a device's info (wire.protocol_gen.DeviceInfo): the
    identity wire.ids.device_identity gives everywhere, the parts of each slot included."""
    return device_identity(info)


# ------------------------------------------------------------------ the record
@dataclass
class CalibrationRecord:
    """One calibration run. `passed` is the fit's own verdict (RMS of |a| − g within
    tolerances.accel_rms_mg); verdict() is the run's. `sections` carries what one builder
    adds (a station's fields, a recording's segmentation, a closure check), kept as given."""
    device: dict
    started: str                                     # this run's start (now_utc)
    method: str | None
    gyro_method: str | None
    accel: dict | None = None                        # fit_dict(accel, "mps2") + residual_rms_mps2
    gyro: dict | None = None                         # fit_dict(gyro, "rad_s")
    poses: list = field(default_factory=list)        # [{name, n, before_g, after_g, sigma_g, temp_c}]
    tolerances: dict = field(default_factory=dict)
    accel_rms_after_mg: float | None = None
    passed: bool = False
    written: bool = False
    verified: bool = False
    verification: list = field(default_factory=list)
    temperature_c: dict = field(default_factory=dict)
    note: str = ""
    capture_dir: str | None = None
    session_started: str | None = None               # the session's start (a resumed session: earlier)
    finished: str = field(default_factory=now_utc)
    failure: dict | None = None                      # {stage, reason}: failed before or during the run
    sections: dict = field(default_factory=dict)
    schema: int = RECORD_SCHEMA

    @classmethod
    def from_fit(cls, *, device: dict, started: str, method: str, gyro_method: str | None, accel: TriadFit,
                 gyro: TriadFit | None, poses: list, tolerances: dict, accel_rms_after_mg: float, **kw):
        """A fitted run: the fit's verdict from its tolerance (the one rule of `passed`)."""
        return cls(device=device, started=started, method=method, gyro_method=gyro_method,
                   accel=fit_dict(accel, "mps2") | {"residual_rms_mps2": accel.residual_rms},
                   gyro=fit_dict(gyro, "rad_s"), poses=poses, tolerances=tolerances,
                   accel_rms_after_mg=float(accel_rms_after_mg),
                   passed=fit_passed(accel_rms_after_mg, tolerances), **kw)

    def to_json(self) -> dict:
        """The record as JSON's types (the form session.json, record.json and the history keep)."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "sections"}
        if d["failure"] is None:
            del d["failure"]
        return jsonable(d | self.sections)

    @classmethod
    def from_json(cls, d: dict) -> "CalibrationRecord":
        """A stored record, validated (ValueError naming every problem)."""
        validate_result(d)
        known = {f.name for f in fields(cls)} - {"sections"}
        return cls(**{k: v for k, v in d.items() if k in known},
                   sections={k: v for k, v in d.items() if k not in known})


def fit_passed(accel_rms_after_mg: float, tolerances: dict) -> bool:
    """The fit's verdict: the RMS of |a| − g over the poses after calibration within tolerance."""
    return bool(accel_rms_after_mg <= tolerances["accel_rms_mg"])


def verdict(record: dict, write_requested: bool) -> tuple[bool, list[str]]:
    """The run's verdict, the one rule for a session, a fixture's board and the history: the
    fit passed, what was to be written was written and verified, no failure, and every
    measurement within its limit. Returns (passed, the reasons it did not)."""
    why = []
    if record.get("failure"):
        f = record["failure"]
        why.append(f"failed at {f.get('stage')}: {f.get('reason')}")
    elif not record.get("passed"):
        rms, tol = record.get("accel_rms_after_mg"), (record.get("tolerances") or {}).get("accel_rms_mg")
        why.append("fit out of tolerance" + (f": |a| − g RMS {rms:.3f} mg > {tol:g} mg"
                                             if rms is not None and tol is not None else ""))
    elif record.get("gyro_refused"):
        why.append(f"accelerometer calibrated; gyro not: {record['gyro_refused']}")
    elif write_requested and not record.get("verified"):
        why.append("written parameters not verified")
    why += [f"{m['name']} = {m['value']:.4g} {m['unit']} outside its limit" for m in record.get("measurements") or []
            if not m.get("passed") and m.get("value") is not None]
    return not why, why


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
