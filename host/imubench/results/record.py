"""The calibration record: what one calibration run produced, as stored in session.json,
record.json, the history and the exports.

One schema number, one validation, one verdict rule, one JSON conversion and one clock, for
every builder (the one-board session, the fixture's boards, a calibration from a file, the
command line's station fields, the history's check before storing).
"""
from __future__ import annotations

import datetime as _dt
import re
from pathlib import Path

import numpy as np

from imubench.calib import TriadFit

RECORD_SCHEMA = 2           # of the result record a calibration session produces (1: before the production line)
RECORD_SCHEMAS = (1, 2)     # records this imubench stores


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def fit_dict(fit: TriadFit | None, unit: str) -> dict | None:
    if fit is None:
        return None
    return {"method": fit.method, "m": fit.m.tolist(), f"b_{unit}": fit.b.tolist(),
            "sigma_m": fit.sigma_m.tolist(), f"sigma_b_{unit}": fit.sigma_b.tolist(),
            "residual_rms": fit.residual_rms, "extra": _jsonable(fit.extra)}


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
