"""A calibration session's state file, DIR/session.json: its schema version and the one reader
every part uses (the session resuming, the report), so a damaged or foreign file is named the
same way everywhere. The session rewrites it atomically (results.atomic) after every pose."""
from __future__ import annotations

import json
from pathlib import Path

from imubench.errors import ImubenchError
from imubench.files import MAX_JSON_BYTES, FileRefused, read_text

SESSION_SCHEMA = 1
NAME = "session.json"


class SessionFileError(ImubenchError):
    """session.json is missing, damaged, or of another schema; the message says which."""


def load_state(directory) -> dict:
    """The content of DIR/session.json, checked to be a session of this schema."""
    path = Path(directory) / NAME
    try:
        text = read_text(path, MAX_JSON_BYTES, "the session file", errors="replace")
    except FileNotFoundError:
        raise SessionFileError(f"{directory} holds no {NAME}: not a calibration session directory "
                               "(the --dir of imubench calibrate)") from None
    except FileRefused as e:
        raise SessionFileError(str(e)) from None
    try:
        state = json.loads(text)
    except ValueError as e:
        raise SessionFileError(f"{path} is damaged (not JSON: {e}); the raw captures beside it are intact: "
                               "start a new session, or restore the file") from None
    if not isinstance(state, dict):
        raise SessionFileError(f"{path} is damaged (a JSON {type(state).__name__}, not a session)")
    if state.get("schema") != SESSION_SCHEMA:
        raise SessionFileError(f"{path} has session schema {state.get('schema')!r}; this imubench reads "
                               f"{SESSION_SCHEMA}")
    for key, kind in (("started", str), ("config", dict), ("poses", list)):
        if not isinstance(state.get(key), kind):
            raise SessionFileError(f"{path} is damaged: {key!r} must be a {kind.__name__}, "
                                   f"got {type(state.get(key)).__name__}")
    problem = _check(state, _STATE, "")
    if problem:
        field, want, got = problem
        raise SessionFileError(f"{path} is damaged: {field!r} must be {want}, got {_kind(got)}; "
                               "the raw captures beside it are intact: restore the file or start a new session")
    return state


# ------------------------------------------------------------------ the fields read
# What the session (resuming) and the report read, and the type each must have. A spec is a
# type name, ("list", spec) (any length), ("list", spec, n), ("opt", spec) (or null), or a
# dict of field: spec (fields may be absent; present ones are checked).
def _kind(x) -> str:
    return "null" if x is None else type(x).__name__


def _is_num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


_PRIMS = {"str": (lambda x: isinstance(x, str), "a string"),
          "int": (lambda x: isinstance(x, int) and not isinstance(x, bool), "an integer"),
          "num": (_is_num, "a number"),
          "bool": (lambda x: isinstance(x, bool), "true or false"),
          "dict": (lambda x: isinstance(x, dict), "an object")}


def _describe(spec) -> str:
    if isinstance(spec, str):
        return _PRIMS[spec][1]
    if isinstance(spec, dict):
        return "an object"
    if spec[0] == "opt":
        return _describe(spec[1]) + " or null"
    if len(spec) == 3:
        return f"a list of {spec[2]}"
    return "a list"


def _check(x, spec, where: str):
    """None, or (field, what it must be, the value found) of the first value not of its spec."""
    if isinstance(spec, str):
        return None if _PRIMS[spec][0](x) else (where, _describe(spec), x)
    if isinstance(spec, dict):
        if not isinstance(x, dict):
            return (where, "an object", x)
        for k, sub in spec.items():
            if k in x:
                bad = _check(x[k], sub, f"{where}.{k}" if where else k)
                if bad:
                    return bad
        return None
    if spec[0] == "opt":
        return None if x is None else _check(x, spec[1], where)
    if not isinstance(x, list) or (len(spec) == 3 and len(x) != spec[2]):
        return (where, _describe(spec), x)
    for i, v in enumerate(x):
        bad = _check(v, spec[1], f"{where}[{i}]")
        if bad:
            return bad
    return None


_NUM_OR_NULL = ("opt", "num")                 # null/NaN where a sigma was not estimated
_VEC3 = ("list", _NUM_OR_NULL, 3)
_MAT3 = ("list", _VEC3, 3)
_FIT = {"method": "str", "m": _MAT3, "sigma_m": _MAT3, "b_mps2": _VEC3, "sigma_b_mps2": _VEC3,
        "b_rad_s": _VEC3, "sigma_b_rad_s": _VEC3, "residual_rms": _NUM_OR_NULL,
        "residual_rms_mps2": _NUM_OR_NULL, "extra": ("opt", "dict")}
_DEVICE = {"mcu_uid": "str", "board": "str", "fw_version": "str", "fw_build": "str",
           "accel_ids": ("list", "int"), "gyro_pid": ("list", "int"), "gyro_sn": ("list", "int")}
_STATE = {
    "device": _DEVICE,      # the device it was captured on (a session saved before issue 38 has none)
    "config": {"method": "str", "gyro": ("opt", "str"), "rate_hz": "num", "hold_s": "num", "rest_s": "num",
               "settle_s": "num", "note": "str", "write": "bool", "tolerances": "dict"},
    "rest": ("opt", {"noise_mps2": ("list", "num", 3), "gyro": ("opt", ("list", ("list", "num", 3))),
                     "start_index": "int", "stop_index": "int"}),
    "poses": ("list", {"name": "str", "direction": ("list", "num", 3), "mean_mps2": ("list", "num", 3),
                       "sigma_mean_mps2": ("list", "num", 3), "n": "int", "start_index": "int",
                       "stop_index": "int", "temp_c": "num", "gyro_mean_rad_s": ("list", "num", 3),
                       "stream": "int"}),
    "complete": "bool",
    "result": ("opt", {
        "device": {"mcu_uid": "str", "board": "str", "fw_version": "str", "fw_build": "str",
                   "parts": ("list", "str", 4), "accel_ids": ("list", "int"), "gyro_pid": ("list", "int"), "gyro_sn": ("list", "int")},
        "started": "str", "session_started": "str", "finished": "str", "method": "str",
        "gyro_method": ("opt", "str"), "note": "str", "passed": "bool", "written": "bool", "verified": "bool",
        "accel_rms_after_mg": _NUM_OR_NULL, "tolerances": {k: "num" for k in (
            "accel_rms_mg", "verify_mg", "gyro_turntable_rms_dps", "gyro_rotation_rms_deg")},
        "accel": _FIT, "gyro": ("opt", _FIT), "temperature_c": "dict",
        "poses": ("list", {"name": "str", "n": "int", "before_g": _NUM_OR_NULL, "after_g": _NUM_OR_NULL,
                           "sigma_g": _NUM_OR_NULL, "temp_c": _NUM_OR_NULL}),
        "verification": ("list", {"name": "str", "after_g": _NUM_OR_NULL, "sigma_g": _NUM_OR_NULL,
                                  "angle_from_plan_deg": _NUM_OR_NULL}),
    }),
}
