"""Calibration parameters: conversion between the wire block (protocol_gen.Params) and
numpy, the correction the device applies, and the validation the device performs.

Model (docs/conventions.md), per triad, u = nominally scaled measurement, x = truth:
    u = M·x + b                      x = M⁻¹·(u − b)
with temperature terms: x = M⁻¹·((u − b − bias_tc·ΔT) / (1 + scale_tc·ΔT)), ΔT = T − t_ref.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from imubench.wire.protocol_gen import LIMITS, Error, Params


def identity() -> Params:
    """Factory defaults: identity matrices, zero biases and temperature terms."""
    eye = tuple(float(v) for v in np.eye(3).ravel())
    return Params(accel_m=eye, gyro_m=eye, accel_t_ref_c=25.0, gyro_t_ref_c=25.0)


def is_factory(p: Params) -> bool:
    """True for parameters that change nothing (identity matrices, zero biases and tempcos):
    a device with these streams its raw data, scaled, as "calibrated"."""
    ident = identity()
    return all(np.allclose(getattr(p, f), getattr(ident, f)) for f in
               ("accel_m", "accel_b_mps2", "gyro_m", "gyro_b_rad_s", "accel_bias_tc_mps2_per_c",
                "accel_scale_tc_per_c", "gyro_bias_tc_rad_s_per_c", "gyro_scale_tc_per_c"))


def to_json(p: Params) -> dict:
    """The block as a JSON-able dict: field names of the protocol definition, vectors as lists."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(p).items()}


def from_json(d: dict, partial: bool = False) -> Params:
    """The inverse of to_json. Unknown keys are an error (InvalidParams naming them); with
    partial=True, fields not given keep their factory value (identity())."""
    if not isinstance(d, dict):
        raise InvalidParams(Error.BAD_ARGUMENT, f"parameters must be a JSON object of Params fields, not {type(d).__name__}")
    base = asdict(identity()) if partial else {}
    unknown = set(d) - set(Params.__dataclass_fields__)
    if unknown:
        raise InvalidParams(Error.BAD_ARGUMENT, f"unknown parameter fields: {', '.join(sorted(unknown))}")
    missing = set(Params.__dataclass_fields__) - set(d) - set(base)
    if missing:
        raise InvalidParams(Error.BAD_ARGUMENT, f"missing parameter fields: {', '.join(sorted(missing))}")
    kw = {**base, **{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}}
    return Params(**kw)


@dataclass
class Triad:
    m: np.ndarray          # (3, 3)
    b: np.ndarray          # (3,)
    bias_tc: np.ndarray    # (3,)
    scale_tc: np.ndarray   # (3,)
    t_ref_c: float


def accel(p: Params) -> Triad:
    return Triad(np.array(p.accel_m, dtype=np.float64).reshape(3, 3), np.array(p.accel_b_mps2, dtype=np.float64),
                 np.array(p.accel_bias_tc_mps2_per_c, dtype=np.float64),
                 np.array(p.accel_scale_tc_per_c, dtype=np.float64), float(p.accel_t_ref_c))


def gyro(p: Params) -> Triad:
    return Triad(np.array(p.gyro_m, dtype=np.float64).reshape(3, 3), np.array(p.gyro_b_rad_s, dtype=np.float64),
                 np.array(p.gyro_bias_tc_rad_s_per_c, dtype=np.float64),
                 np.array(p.gyro_scale_tc_per_c, dtype=np.float64), float(p.gyro_t_ref_c))


def correct(t: Triad, u: np.ndarray, temp_c=None) -> np.ndarray:
    """Apply the correction to measurements u (n, 3) in SI. temp_c: None (= t_ref), (n,) one
    temperature for all axes, or (n, 3) per axis (docs/conventions.md)."""
    u = np.asarray(u, dtype=np.float64)
    if temp_c is None:
        v = u - t.b
    else:
        dt = np.asarray(temp_c, dtype=np.float64) - t.t_ref_c
        if dt.ndim == u.ndim - 1:
            dt = dt[..., None]
        v = (u - t.b - t.bias_tc * dt) / (1.0 + t.scale_tc * dt)
    return v @ np.linalg.inv(t.m).T


class InvalidParams(ValueError):
    def __init__(self, code: Error, reason: str):
        super().__init__(f"{code.name}: {reason}")
        self.code = code


def _check_triad(name: str, t: Triad, bias_max: float, bias_tc_max: float) -> None:
    """The device's checks, in the device's order: conditioning, then each limit."""
    L = LIMITS
    det = np.linalg.det(t.m)
    if det == 0.0 or not np.isfinite(det):
        raise InvalidParams(Error.PARAM_ILL_CONDITIONED, f"{name} M is singular")
    cond = np.linalg.norm(t.m) * np.linalg.norm(np.linalg.inv(t.m))
    if cond > L["m_cond_max"]:
        raise InvalidParams(Error.PARAM_ILL_CONDITIONED,
                            f"{name} M condition ||M||·||M⁻¹|| = {cond:.3g} > {L['m_cond_max']}")
    d = np.diag(t.m)
    if np.any(d < L["m_diag_min"]) or np.any(d > L["m_diag_max"]):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} scale (diagonal of M) {d} outside "
                            f"[{L['m_diag_min']}, {L['m_diag_max']}]")
    off = t.m[~np.eye(3, dtype=bool)]
    if np.any(np.abs(off) > L["m_offdiag_max"]):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} cross-axis term above {L['m_offdiag_max']}")
    if np.any(np.abs(t.b) > bias_max):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} bias {t.b} above {bias_max} per axis")
    if np.any(np.abs(t.bias_tc) > bias_tc_max):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} bias temperature coefficient above {bias_tc_max}")
    if np.any(np.abs(t.scale_tc) > L["scale_tc_max_per_c"]):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} scale temperature coefficient above {L['scale_tc_max_per_c']}")
    if not L["t_ref_min_c"] <= t.t_ref_c <= L["t_ref_max_c"]:
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} reference temperature {t.t_ref_c} °C out of range")


def validate(p: Params) -> None:
    """Raise InvalidParams (with the error code the device would nack with) unless the
    block is acceptable. Checks in the device's order: finite, then each triad."""
    # values as the device sees them: float32
    vals = np.array([v for v in p.values() if isinstance(v, float)], dtype=np.float32)
    if not np.all(np.isfinite(vals)):
        raise InvalidParams(Error.PARAM_NOT_FINITE, "a parameter is NaN or infinite")
    p32 = Params.from_values(Params.STRUCT.unpack(Params.STRUCT.pack(*p.values())))
    _check_triad("accel", accel(p32), LIMITS["accel_bias_max_mps2"], LIMITS["accel_bias_tc_max_mps2_per_c"])
    _check_triad("gyro", gyro(p32), LIMITS["gyro_bias_max_rad_s"], LIMITS["gyro_bias_tc_max_rad_s_per_c"])
