"""Calibration parameters: conversion between the wire block (protocol_gen.Params) and
numpy, the correction the device applies, and the validation the device performs.

Model (docs/conventions.md, "Temperature model"), per triad, u = nominally scaled measurement,
x = truth:
    u = M·x + b                      x = M⁻¹·(u − b)
with temperature terms, per axis k with its sensor's temperature T_k:
    ΔT = clamp(T_k, t_min, t_max) − t_ref
    x = M⁻¹·((u − b − (c1·ΔT + c2·ΔT² + c3·ΔT³)) / (1 + scale_tc·ΔT))
c1 = bias_tc; outside the calibrated span [t_min, t_max] the span's end is used (layout 3). The
gyro's g-sensitivity G (layout 2) is taken off first: u ← u − G·a, a the calibrated specific
force in m/s² (the device's calibrated accelerometer output of the same sample).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from imubench.wire.protocol_gen import LIMITS, LIMITS_F32, Error, Params


# The span a block without one (factory defaults, a migrated layout-1 or -2 block) gets, °C.
DEFAULT_SPAN_C = (-40, 85)


def identity() -> Params:
    """Factory defaults: identity matrices, zero biases and temperature terms, span −40..85 °C."""
    eye = tuple(float(v) for v in np.eye(3).ravel())
    lo, hi = DEFAULT_SPAN_C
    return Params(accel_m=eye, gyro_m=eye, accel_t_ref_c=25.0, gyro_t_ref_c=25.0,
                  accel_t_min_c=lo, accel_t_max_c=hi, gyro_t_min_c=lo, gyro_t_max_c=hi)


def migrated_span(t_ref_c: float) -> tuple[int, int]:
    """The span a layout-1 or -2 block is given on migration (core.c migrated_t_max): −40..85 °C,
    its upper end raised to hold t_ref when t_ref lies above 85 °C (so that a block valid
    before stays valid; t_ref's own limit keeps it at or above −40)."""
    lo, hi = DEFAULT_SPAN_C
    t = np.float32(t_ref_c)
    if t > hi:
        hi = int(np.ceil(t)) if t <= 127 else 127
    return lo, hi


def is_factory(p: Params) -> bool:
    """True for parameters that change nothing (identity matrices, zero biases and tempcos):
    a device with these streams its raw data, scaled, as "calibrated"."""
    ident = identity()
    return all(np.allclose(getattr(p, f), getattr(ident, f)) for f in
               ("accel_m", "accel_b_mps2", "gyro_m", "gyro_b_rad_s", "accel_bias_tc_mps2_per_c",
                "accel_scale_tc_per_c", "gyro_bias_tc_rad_s_per_c", "gyro_scale_tc_per_c", "gyro_g_rad_s_per_mps2",
                "accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3", "gyro_bias_tc2_rad_s_per_c2",
                "gyro_bias_tc3_rad_s_per_c3"))


def to_json(p: Params) -> dict:
    """The block as a JSON-able dict: field names of the protocol definition, vectors as lists."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(p).items()}


def from_json(d: dict, partial: bool = False) -> Params:
    """The inverse of to_json. Unknown keys are an error (InvalidParams naming them); with
    partial=True, fields not given keep their factory value (identity()). A block written
    before layout 3 (without c2, c3 and the spans; or also without gyro_g, layout 1) is read
    as the device reads such a stored block: c2 = c3 = 0, G = 0, span migrated_span(t_ref)."""
    if not isinstance(d, dict):
        raise InvalidParams(Error.BAD_ARGUMENT, f"parameters must be a JSON object of Params fields, not {type(d).__name__}")
    base = asdict(identity()) if partial else {}
    unknown = set(d) - set(Params.__dataclass_fields__)
    if unknown:
        raise InvalidParams(Error.BAD_ARGUMENT, f"unknown parameter fields: {', '.join(sorted(unknown))}")
    missing = set(Params.__dataclass_fields__) - set(d) - set(base)
    if missing and missing not in (set(_LAYOUT3_FIELDS), set(_LAYOUT3_FIELDS) | {"gyro_g_rad_s_per_mps2"}):
        raise InvalidParams(Error.BAD_ARGUMENT, f"missing parameter fields: {', '.join(sorted(missing))}")
    kw = {**base, **{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}}
    if missing:          # a block written before layout 3 (or 2): migrated as the device migrates it
        kw.update({f: (0.0,) * (9 if f.startswith("gyro_g") else 3) for f in missing if not f.endswith(("min_c", "max_c"))})
        try:
            (kw["accel_t_min_c"], kw["accel_t_max_c"]), (kw["gyro_t_min_c"], kw["gyro_t_max_c"]) = (
                migrated_span(float(kw["accel_t_ref_c"])), migrated_span(float(kw["gyro_t_ref_c"])))
        except (TypeError, ValueError):
            raise InvalidParams(Error.BAD_ARGUMENT, "accel_t_ref_c and gyro_t_ref_c must be numbers") from None
    return Params(**kw)


# the fields layout 3 added (a JSON block of an earlier layout lacks them: from_json migrates it)
_LAYOUT3_FIELDS = ("accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3", "gyro_bias_tc2_rad_s_per_c2",
                   "gyro_bias_tc3_rad_s_per_c3", "accel_t_min_c", "accel_t_max_c", "gyro_t_min_c", "gyro_t_max_c")


@dataclass
class Triad:
    m: np.ndarray          # (3, 3)
    b: np.ndarray          # (3,)
    bias_tc: np.ndarray    # (3,) c1, per °C
    scale_tc: np.ndarray   # (3,) per °C
    t_ref_c: float
    g: np.ndarray | None = None   # (3, 3) gyro g-sensitivity, rad/s per m/s² (None for the accelerometer)
    bias_tc2: np.ndarray | None = None   # (3,) c2, per °C² (None = 0)
    bias_tc3: np.ndarray | None = None   # (3,) c3, per °C³ (None = 0)
    t_min_c: float = -np.inf     # calibrated span: ΔT is clamped into it
    t_max_c: float = np.inf

    def delta_t(self, temp_c) -> np.ndarray:
        """ΔT = clamp(T, t_min, t_max) − t_ref, °C."""
        return np.clip(np.asarray(temp_c, dtype=np.float64), self.t_min_c, self.t_max_c) - self.t_ref_c

    def bias_poly(self, dt) -> np.ndarray:
        """c1·ΔT + c2·ΔT² + c3·ΔT³ (Horner), ΔT broadcast against the 3 axes ((n, 1) or (n, 3)),
        in the bias's unit."""
        dt = np.asarray(dt, dtype=np.float64)
        c2 = np.zeros(3) if self.bias_tc2 is None else self.bias_tc2
        c3 = np.zeros(3) if self.bias_tc3 is None else self.bias_tc3
        return dt * (self.bias_tc + dt * (c2 + dt * c3))


def _triad(p: Params, kind: str, g: np.ndarray | None) -> Triad:
    f64 = lambda name: np.array(getattr(p, name), dtype=np.float64)   # noqa: E731
    if kind == "accel":
        return Triad(f64("accel_m").reshape(3, 3), f64("accel_b_mps2"), f64("accel_bias_tc_mps2_per_c"),
                     f64("accel_scale_tc_per_c"), float(p.accel_t_ref_c), g, f64("accel_bias_tc2_mps2_per_c2"),
                     f64("accel_bias_tc3_mps2_per_c3"), float(p.accel_t_min_c), float(p.accel_t_max_c))
    return Triad(f64("gyro_m").reshape(3, 3), f64("gyro_b_rad_s"), f64("gyro_bias_tc_rad_s_per_c"),
                 f64("gyro_scale_tc_per_c"), float(p.gyro_t_ref_c), g, f64("gyro_bias_tc2_rad_s_per_c2"),
                 f64("gyro_bias_tc3_rad_s_per_c3"), float(p.gyro_t_min_c), float(p.gyro_t_max_c))


def accel(p: Params) -> Triad:
    return _triad(p, "accel", None)


def gyro(p: Params) -> Triad:
    return _triad(p, "gyro", np.array(p.gyro_g_rad_s_per_mps2, dtype=np.float64).reshape(3, 3))


def correct(t: Triad, u: np.ndarray, temp_c=None, accel_mps2=None) -> np.ndarray:
    """Apply the correction to measurements u (n, 3) in SI. temp_c: None (= t_ref), (n,) one
    temperature for all axes, or (n, 3) per axis, clamped into the triad's span
    (docs/conventions.md). accel_mps2: the calibrated specific force (n, 3) of the same samples,
    for a gyro triad with a g-sensitivity (taken off first, as the device does); required when
    t.g is non-zero."""
    u = np.asarray(u, dtype=np.float64)
    if t.g is not None and np.any(t.g != 0.0):
        if accel_mps2 is None:
            raise ValueError("correct: this gyro triad has a g-sensitivity: give accel_mps2 (calibrated, m/s²)")
        u = u - np.asarray(accel_mps2, dtype=np.float64) @ t.g.T
    if temp_c is None:
        v = u - t.b
    else:
        dt = t.delta_t(temp_c)
        if dt.ndim == u.ndim - 1:
            dt = dt[..., None]
        v = (u - t.b - t.bias_poly(dt)) / (1.0 + t.scale_tc * dt)
    return v @ np.linalg.inv(t.m).T


class InvalidParams(ValueError):
    def __init__(self, code: Error, reason: str):
        super().__init__(f"{code.name}: {reason}")
        self.code = code


_F32 = np.float32


def _invert3_f32(m) -> tuple | None:
    """M⁻¹ of a row-major 3×3 matrix exactly as the device computes it (core.c invert3): the
    same float32 operations in the same order, so the same roundings, overflows and NaNs.
    None when the device calls M singular (|det| ≤ m_det_min, or det not finite)."""
    a, b, cc, d, e, f, g, h, i = m
    A = e * i - f * h
    B = -(d * i - f * g)
    C = d * h - e * g
    det = a * A + b * B + cc * C
    if not (abs(det) > _F32(LIMITS_F32["m_det_min"])) or not np.isfinite(det):
        return None
    r = _F32(1.0) / det
    return (A * r, -(b * i - cc * h) * r, (b * f - cc * e) * r,
            B * r, (a * i - cc * g) * r, -(a * f - cc * d) * r,
            C * r, -(a * h - b * g) * r, (a * e - b * d) * r)


def _check_triad(name: str, m, b, btc, stc, t_ref, bias_max: float, bias_tc_max: float,
                 poly: tuple | None = None) -> None:
    """The device's checks of one triad (core.c check_triad), in its order and in float32 with
    the float32 limits of the definition (LIMITS_F32): conditioning, then each limit."""
    L = LIMITS_F32
    inv = _invert3_f32(m)
    if inv is None:
        raise InvalidParams(Error.PARAM_ILL_CONDITIONED, f"{name} M is singular (|det M| ≤ {LIMITS['m_det_min']})")
    fm = fi = _F32(0.0)
    for k in range(9):
        fm = fm + m[k] * m[k]
        fi = fi + inv[k] * inv[k]
    cond_max = _F32(L["m_cond_max"])
    if fm * fi > cond_max * cond_max:
        raise InvalidParams(Error.PARAM_ILL_CONDITIONED,
                            f"{name} M condition ||M||·||M⁻¹|| = {float(np.sqrt(fm * fi)):.3g} > {LIMITS['m_cond_max']}")
    for r in range(3):
        for k in range(3):
            v = m[r * 3 + k]
            if r == k and (v < _F32(L["m_diag_min"]) or v > _F32(L["m_diag_max"])):
                raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} scale M[{r}][{k}] = {float(v)!r} outside "
                                    f"[{LIMITS['m_diag_min']}, {LIMITS['m_diag_max']}]")
            if r != k and abs(v) > _F32(L["m_offdiag_max"]):
                raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} cross-axis term M[{r}][{k}] = {float(v)!r} "
                                    f"above {LIMITS['m_offdiag_max']} in magnitude")
    for k in range(3):
        if abs(b[k]) > _F32(bias_max):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} bias[{k}] = {float(b[k])!r} above {bias_max} in magnitude")
        if abs(btc[k]) > _F32(bias_tc_max):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE,
                                f"{name} bias temperature coefficient[{k}] = {float(btc[k])!r} above {bias_tc_max}")
        if abs(stc[k]) > _F32(L["scale_tc_max_per_c"]):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} scale temperature coefficient[{k}] = "
                                f"{float(stc[k])!r} above {LIMITS['scale_tc_max_per_c']}")
    if t_ref < _F32(L["t_ref_min_c"]) or t_ref > _F32(L["t_ref_max_c"]):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} reference temperature {float(t_ref)!r} °C outside "
                            f"[{LIMITS['t_ref_min_c']}, {LIMITS['t_ref_max_c']}]")
    if poly is not None:
        _check_poly(name, b, btc, t_ref, bias_max, *poly)


def _check_poly(name: str, b, btc, t_ref, bias_max: float, c2, c3, t_min: int, t_max: int,
                c2_max: float, c3_max: float, span_max: float) -> None:
    """Layout 3's checks of one triad (core.c check_poly), after t_ref, in float32: the span in
    the part's rated range, t_min < t_max, t_ref inside it; per axis c2, c3 and the bound
    D·(|c1| + D·(|c2| + D·|c3|)) of the polynomial's excursion over the span (D the larger
    distance from t_ref to an end) within the bias limit."""
    lo, hi = _F32(t_min), _F32(t_max)
    if lo < _F32(LIMITS_F32["t_span_min_c"]) or hi > _F32(span_max):
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} calibrated span {t_min}..{t_max} °C outside the "
                            f"part's rated {LIMITS['t_span_min_c']:g}..{float(span_max):g} °C")
    if not lo < hi:
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} calibrated span {t_min}..{t_max} °C is empty "
                            "(t_min must be below t_max)")
    if t_ref < lo or t_ref > hi:
        raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} reference temperature {float(t_ref)!r} °C outside "
                            f"its calibrated span {t_min}..{t_max} °C")
    d = max(t_ref - lo, hi - t_ref)
    for k in range(3):
        if abs(c2[k]) > _F32(c2_max):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} second-order bias coefficient[{k}] = "
                                f"{float(c2[k])!r} above {float(c2_max):g} in magnitude")
        if abs(c3[k]) > _F32(c3_max):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} third-order bias coefficient[{k}] = "
                                f"{float(c3[k])!r} above {float(c3_max):g} in magnitude")
        e = d * (abs(btc[k]) + d * (abs(c2[k]) + d * abs(c3[k])))
        if not e <= _F32(bias_max):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"{name} bias polynomial[{k}] may move the bias by up to "
                                f"{float(e):.4g} over its span {t_min}..{t_max} °C, more than the bias limit "
                                f"{float(bias_max):g}")


def validate(p: Params) -> None:
    """Raise InvalidParams (with the error code the device would nack with) unless the
    block is acceptable: the device's checks (core.c ib_core_check_params), in its order, on the
    values as the device holds them (float32) and in float32 arithmetic, so that host and device
    give the same verdict and the same code for every block, also at the limits."""
    with np.errstate(all="ignore"):           # a double beyond float32 becomes ±inf, as on the wire
        f32 = [_F32(v) for v in p.values()[:38]]
        gg = [_F32(v) for v in p.gyro_g_rad_s_per_mps2]
        a2, a3, g2, g3 = ([_F32(v) for v in getattr(p, f)] for f in (
            "accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3", "gyro_bias_tc2_rad_s_per_c2",
            "gyro_bias_tc3_rad_s_per_c3"))
    if not all(np.isfinite(v) for v in f32 + gg + a2 + a3 + g2 + g3):
        raise InvalidParams(Error.PARAM_NOT_FINITE, "a parameter is NaN or infinite")
    am, ab, gm, gb = f32[0:9], f32[9:12], f32[12:21], f32[21:24]
    abtc, astc, gbtc, gstc = f32[24:27], f32[27:30], f32[30:33], f32[33:36]
    L = LIMITS_F32
    with np.errstate(all="ignore"):           # overflow to inf / NaN is part of the device's arithmetic
        _check_triad("accel", am, ab, abtc, astc, f32[36], L["accel_bias_max_mps2"], L["accel_bias_tc_max_mps2_per_c"],
                     (a2, a3, int(p.accel_t_min_c), int(p.accel_t_max_c), L["accel_bias_tc2_max_mps2_per_c2"],
                      L["accel_bias_tc3_max_mps2_per_c3"], L["accel_t_span_max_c"]))
        _check_triad("gyro", gm, gb, gbtc, gstc, f32[37], L["gyro_bias_max_rad_s"], L["gyro_bias_tc_max_rad_s_per_c"],
                     (g2, g3, int(p.gyro_t_min_c), int(p.gyro_t_max_c), L["gyro_bias_tc2_max_rad_s_per_c2"],
                      L["gyro_bias_tc3_max_rad_s_per_c3"], L["gyro_t_span_max_c"]))
    for k, v in enumerate(gg):                # the g-sensitivity last, as core.c
        if abs(v) > _F32(LIMITS_F32["gyro_g_max_rad_s_per_mps2"]):
            raise InvalidParams(Error.PARAM_OUT_OF_RANGE, f"gyro g-sensitivity[{k}] = {float(v)!r} above "
                                f"{LIMITS['gyro_g_max_rad_s_per_mps2']} rad/s per m/s² in magnitude")
