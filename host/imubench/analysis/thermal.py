"""Temperature coefficients from a sweep: weighted straight lines of bias and scale against each
sensor's own temperature, and the parameter block with them. Pure numpy: measured points in,
coefficients with 1-sigma out (the sweep on a device is imubench.procedures.thermal).

Model (docs/conventions.md), per axis k, ΔT_k = T_k − t_ref:
    v_k = (u_k − b_k − bias_tc_k·ΔT_k) / (1 + scale_tc_k·ΔT_k)        x = M⁻¹·v
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from imubench.wire import params as PR
from imubench.wire.protocol_gen import Params

AXES = "xyz"


POSES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
         "+z": (0, 0, 1), "-z": (0, 0, -1)}


def fit_tempco(temps_c, values, sigmas=None, t_ref_c: float = 25.0):
    """Weighted straight line per axis: values[:, k] = intercept_k + coef_k·(T − t_ref).

    temps_c (k,) or (k, 3) (one temperature per axis), values (k, 3), sigmas (k, 3) 1-sigma
    of each value or None (unweighted; the scatter about the line sets the sigmas).
    Returns coef (3,), intercept (3,) (the value at t_ref) and cov (3, 2, 2) of
    (coef, intercept) per axis; 1-sigma of coef_k is sqrt(cov[k, 0, 0]).
    With sigmas the covariance is the absolute one, inflated by the reduced chi² when that
    exceeds 1 (points scattering more than their sigmas say)."""
    y = np.asarray(values, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 3:
        raise ValueError("values must be (k, 3)")
    t = np.asarray(temps_c, dtype=np.float64)
    if t.ndim == 1:
        t = np.repeat(t[:, None], 3, axis=1)
    if t.shape != y.shape:
        raise ValueError("temps_c must be (k,) or (k, 3) matching values")
    k = len(y)
    if k < 2:
        raise ValueError("need at least two temperatures")
    coef, icpt, cov = np.zeros(3), np.zeros(3), np.zeros((3, 2, 2))
    for a in range(3):
        x = t[:, a] - t_ref_c
        if np.ptp(x) == 0:
            raise ValueError(f"axis {AXES[a]}: all points at the same temperature")
        A = np.column_stack([x, np.ones(k)])
        w = np.ones(k) if sigmas is None else 1.0 / np.asarray(sigmas, dtype=np.float64)[:, a] ** 2
        N = A.T @ (A * w[:, None])
        C = np.linalg.inv(N)
        p = C @ (A.T @ (w * y[:, a]))
        r = y[:, a] - A @ p
        dof = k - 2
        chi2 = float(np.sum(w * r * r)) / dof if dof > 0 else 0.0
        if sigmas is None or chi2 > 1.0:
            C = C * chi2
        coef[a], icpt[a], cov[a] = p[0], p[1], C
    return coef, icpt, cov


@dataclass
class TempPoint:
    """What one temperature step measured (nominally scaled SI, means and their 1-sigma)."""
    target_c: float | None
    accel_temp_c: float
    gyro_temp_c: np.ndarray                       # (3,)
    gyro_rest: np.ndarray                         # (3,) rad/s
    gyro_rest_sigma: np.ndarray                   # (3,)
    accel: dict = field(default_factory=dict)     # pose name -> (mean (3,), sigma (3,)) m/s²
    turns: dict = field(default_factory=dict)     # axis index -> (scale (rad/s, at +rate), sigma)
    t_first_us: int | None = None                 # device time of the first / last sample measured
    t_last_us: int | None = None
    settle: dict | None = None                    # what wait_settled returned (None: not waited for)


@dataclass
class ThermalFit:
    t_ref_c: float
    accel_bias_tc: np.ndarray          # m/s²/°C
    accel_bias_tc_sigma: np.ndarray
    accel_scale_tc: np.ndarray         # 1/°C
    accel_scale_tc_sigma: np.ndarray
    gyro_bias_tc: np.ndarray           # rad/s/°C
    gyro_bias_tc_sigma: np.ndarray
    gyro_scale_tc: np.ndarray
    gyro_scale_tc_sigma: np.ndarray
    notes: list = field(default_factory=list)


def fit_sweep(points: Sequence[TempPoint], t_ref_c: float = 25.0) -> ThermalFit:
    notes = []
    ta = np.array([p.accel_temp_c for p in points])
    tg = np.array([p.gyro_temp_c for p in points])
    gb, _, gcov = fit_tempco(tg, np.array([p.gyro_rest for p in points]),
                             np.array([p.gyro_rest_sigma for p in points]), t_ref_c)
    a_btc, a_btc_s = np.zeros(3), np.zeros(3)
    a_stc, a_stc_s = np.zeros(3), np.zeros(3)
    have = set(points[0].accel)
    for k in range(3):
        plus, minus = f"+{AXES[k]}", f"-{AXES[k]}"
        if plus in have and minus in have:
            up = np.array([p.accel[plus][0][k] for p in points])
            dn = np.array([p.accel[minus][0][k] for p in points])
            su = np.array([p.accel[plus][1][k] for p in points])
            sd = np.array([p.accel[minus][1][k] for p in points])
            s = np.hypot(su, sd) / 2
            c, _, cov = fit_tempco(ta, np.tile(((up + dn) / 2)[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_btc[k], a_btc_s[k] = c[0], np.sqrt(cov[0, 0, 0])
            c, i, cov = fit_tempco(ta, np.tile(((up - dn) / 2)[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_stc[k] = c[0] / i[0]
            a_stc_s[k] = np.sqrt(cov[0, 0, 0]) / abs(i[0])
        else:
            m = np.array([p.accel["+z"][0][k] for p in points])
            s = np.array([p.accel["+z"][1][k] for p in points])
            c, _, cov = fit_tempco(ta, np.tile(m[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_btc[k], a_btc_s[k] = c[0], np.sqrt(cov[0, 0, 0])
            if k == 2:
                notes.append("accel Z: level only, bias and scale tempco not separated "
                             "(slope = bias_tc + scale_tc·g put into bias_tc; right at level only)")
            else:
                notes.append(f"accel {AXES[k].upper()}: scale tempco not measured (needs ±{AXES[k].upper()} poses)")
    g_stc, g_stc_s = np.zeros(3), np.zeros(3)
    if all(len(p.turns) == 3 for p in points):
        sc = np.array([[p.turns[a][0] for a in range(3)] for p in points])
        ss = np.array([[p.turns[a][1] for a in range(3)] for p in points])
        c, i, cov = fit_tempco(tg, sc, ss, t_ref_c)
        g_stc, g_stc_s = c / i, np.sqrt(cov[:, 0, 0]) / np.abs(i)
    else:
        notes.append("gyro scale tempco not measured (no turntable): left at 0")
    return ThermalFit(t_ref_c, a_btc, a_btc_s, a_stc, a_stc_s, gb, np.sqrt(gcov[:, 0, 0]),
                      g_stc, g_stc_s, notes)


def apply_tempcos(params: Params, fits: ThermalFit, t_ref_c: float | None = None) -> Params:
    """A copy of params with the temperature coefficients and reference temperatures of fits
    (t_ref_c overrides fits.t_ref_c), checked with params.validate (raises InvalidParams).

    The step method fits straight lines: the bias polynomial's c2 and c3 are cleared (a previous
    warm-up's curvature must not stay on top of a new line) and both triads get the default span
    −40..85 °C (params.migrated_span), not the measured one. A straight line extrapolates
    gently, and the data sheets give linear temperature coefficients over the parts' whole
    range; clamping it at the set points' ends would hold the bias constant beyond them while
    the part keeps drifting. Clamping to the measured span is for curved fits, whose
    extrapolation diverges (docs/conventions.md, Temperature model)."""
    t_ref = float(fits.t_ref_c if t_ref_c is None else t_ref_c)
    p = Params.from_values(params.values())
    p.accel_bias_tc2_mps2_per_c2 = p.accel_bias_tc3_mps2_per_c3 = (0.0, 0.0, 0.0)
    p.gyro_bias_tc2_rad_s_per_c2 = p.gyro_bias_tc3_rad_s_per_c3 = (0.0, 0.0, 0.0)
    p.accel_t_min_c, p.accel_t_max_c = PR.migrated_span(t_ref)
    p.gyro_t_min_c, p.gyro_t_max_c = PR.migrated_span(t_ref)
    p.accel_bias_tc_mps2_per_c = tuple(float(v) for v in fits.accel_bias_tc)
    p.accel_scale_tc_per_c = tuple(float(v) for v in fits.accel_scale_tc)
    p.gyro_bias_tc_rad_s_per_c = tuple(float(v) for v in fits.gyro_bias_tc)
    p.gyro_scale_tc_per_c = tuple(float(v) for v in fits.gyro_scale_tc)
    p.accel_t_ref_c = t_ref
    p.gyro_t_ref_c = t_ref
    PR.validate(p)
    return p
