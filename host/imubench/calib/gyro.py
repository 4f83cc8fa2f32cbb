"""Gyro triad calibration: bias at rest, turntable, and the rotation method (no fixture).

Model (docs/conventions.md): u = M·x + b, x = M⁻¹·(u − b); u the nominally scaled gyro
reading in rad/s, x the true angular rate of the board in rad/s, both in the board frame
(X forward, Y left, Z up; positive rate by the right-hand rule).

Three fits, each returning a :class:`~imubench.calib.TriadFit`:

* :func:`gyro_bias` — b from a recording at rest (M not estimated). Its sigma accounts for
  correlated samples (sensor filter, oversampling) and, when given, the bias's random walk.
* :func:`turntable` — M and b by weighted linear least squares from segments at known
  constant rates about known axes, each axis turned both ways.
* :func:`rotation_method` — M without a fixture (imu_tk's idea): between consecutive static
  poses the corrected gyro is integrated, the previous pose's gravity direction is carried
  through that rotation and compared with the next pose's; M is fitted by nonlinear least
  squares with the bias fixed from a rest recording.

Frame convention of :func:`integrate_rotation` (used by the rotation method): R is the
attitude of the board at the end of the interval expressed in the board frame at its start;
its columns are the end frame's axes in start-frame coordinates, so for a vector v given in
end-frame coordinates ``R @ v`` is the same vector in start-frame coordinates. Body rates
compose on the right (R = R₁·R₂ for two successive intervals). A world-fixed vector, such as
the direction of gravity, seen from the board: ``v_end = R.T @ v_start``. Example: +90° about
+Z gives R = Rz(90°), R @ e_x = e_y (the board's +X now points where +Y pointed).

Everything here is numpy/scipy; nothing touches a serial port.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
from scipy import special   # χ² survival function (chdtrc): lighter to import than scipy.stats

from imubench.calib import CalibrationError, NotObservable, TriadFit
from imubench.calib.rotint import (  # noqa: F401 - the integration kernels, used here and by rotation_model
    _qmul,
    _quat_chain,
    _quat_matrix,
    _quat_matrix_cf,
    _quat_prefix,
    _rotate,
    _rotvec_quat,
    _skew_rows,
    _step_vectors,
    _tangent_basis,
)

__all__ = [
    "TurntableSegment",
    "gyro_bias",
    "integrate_rotation",
    "rotation_method",
    "turntable",
]

_AXES = "XYZ"
_ADXRS450_RANGE_RAD_S = math.radians(300.0)
_CHECK_JACOBIAN = False      # tests set this to compare the analytic Jacobian with differences


# ---------------------------------------------------------------------------- helpers
def _as_rates(rates, what: str = "rates") -> np.ndarray:
    a = np.asarray(rates, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise CalibrationError(f"{what}: expected an (n, 3) array of rad/s, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{what}: contains NaN or infinite values")
    return a


def _avar_octaves(y: np.ndarray, ms: Sequence[int]) -> np.ndarray:
    """Overlapping Allan variance of the columns of y (n, c) at cluster sizes ms (samples)."""
    y = y - y.mean(axis=0)
    c = np.concatenate([np.zeros((1, y.shape[1])), np.cumsum(y, axis=0)])
    out = np.empty((len(ms), y.shape[1]))
    for i, m in enumerate(ms):
        a = (c[m:] - c[:-m]) / m              # means of m consecutive samples
        d = a[m:] - a[:-m]                     # differences of adjacent means
        out[i] = 0.5 * np.mean(d * d, axis=0)
    return out


def _mean_uncertainty(y: np.ndarray, min_cluster: int = 1, rrw2: np.ndarray | None = None) -> dict:
    """1-sigma uncertainty of the column means of y (n, c), in sample units.

    White level N² (variance per sample period, as if the samples were independent) from the
    overlapping Allan variance at cluster sizes m from max(n/128, min_cluster) to n/4, where a
    sensor's filter or oversampling no longer correlates the clusters: the per-cluster
    estimates m·AVAR(m) averaged with weights = their degrees of freedom (≈ 1.5 n/m).
    rrw2: a known bias random walk, variance per sample; adds K²·n/3 (the mean as an estimate
    of the bias at either end of the recording). Returned sigma = √(N²/n + K²·n/3), never less
    than std/√n. drift_z: (mean of the second half − mean of the first half) / its sigma from
    N² (≈ N(0, 1) for white noise; |drift_z| ≳ 4 when the bias wandered during the recording).
    """
    n, ncol = y.shape
    std = y.std(axis=0, ddof=1) if n > 1 else np.full(ncol, np.nan)
    white = std / math.sqrt(n)
    k2 = np.zeros(ncol) if rrw2 is None else np.broadcast_to(np.asarray(rrw2, float), (ncol,)).copy()
    out = {"sigma": np.sqrt(white**2 + k2 * n / 3.0), "sigma_white": white, "n2": std**2,
           "k2": k2, "drift_z": np.full(ncol, np.nan), "method": "std/sqrt(n)"}
    m_lo = max(1, int(min_cluster), n // 128)
    ms = []
    m = 1
    while m <= n // 4:
        if m >= m_lo:
            ms.append(m)
        m *= 2
    half = n // 2
    if len(ms) < 2:
        if half >= 1 and n > 2:
            out["drift_z"] = (y[half:].mean(0) - y[:half].mean(0)) / np.maximum(2.0 * white, 1e-300)
        return out
    ms_a = np.asarray(ms, dtype=np.float64)
    yk = _avar_octaves(y, ms) * ms_a[:, None]                    # per-cluster estimates of N²
    edf = np.maximum(1.0, 1.5 * n / ms_a - 2.0)
    n2 = edf @ yk / edf.sum()
    var = n2 / n + k2 * n / 3.0
    dz = (y[half:].mean(0) - y[:half].mean(0)) / np.maximum(
        np.sqrt(n2 / half + n2 / (n - half)), 1e-300)
    out.update(sigma=np.maximum(np.sqrt(var), white), n2=n2, drift_z=dz, method="allan")
    return out


def integrate_rotation(rates, fs_hz: float) -> np.ndarray:
    """Rotation of the board over a run of gyro samples.

    rates: (n, 3) true body rates in rad/s (board frame), sampled at fs_hz; the samples are
    instantaneous values at t_k = k/fs, and the interval runs from the first sample to the
    last ((n − 1)/fs long). Between samples the rate is interpolated by cubics through the
    four nearest samples, and each step's rotation vector carries the coning (second Magnus)
    term; constant rates are exact, smooth motions at 100 Hz and 300 °/s are within ~1e-5°.

    Returns R (3, 3): the board's attitude at the end expressed in the board frame at the
    start (columns: end-frame axes in start-frame coordinates). A world-fixed vector seen
    from the board transforms as v_end = R.T @ v_start. Successive intervals compose as
    R = R₁ @ R₂. Example: 1 s at +π/2 rad/s about +Z gives Rz(90°), R @ e_x = e_y.
    """
    x = _as_rates(rates)
    if not fs_hz > 0:
        raise CalibrationError("fs_hz must be positive")
    if len(x) < 2:
        return np.eye(3)
    return _rotate(_step_vectors(np.ascontiguousarray(x.T), 1.0 / fs_hz))


def _cov12(m_cov: np.ndarray | None = None, b_cov: np.ndarray | None = None,
           mb_cov: np.ndarray | None = None) -> np.ndarray:
    cov = np.full((12, 12), np.nan)
    if m_cov is not None:
        cov[:9, :9] = m_cov
    if b_cov is not None:
        cov[9:, 9:] = b_cov
    if mb_cov is not None:
        cov[:9, 9:] = mb_cov
        cov[9:, :9] = mb_cov.T
    return cov


def _bias_input(bias) -> tuple[np.ndarray, np.ndarray | None]:
    """(b, cov_b or None) from a TriadFit or a (3,) array."""
    if isinstance(bias, TriadFit):
        b = np.asarray(bias.b, dtype=np.float64).reshape(3)
        cb = np.asarray(bias.cov, dtype=np.float64)[9:, 9:]
        return b, (cb if np.all(np.isfinite(cb)) else None)
    b = np.asarray(bias, dtype=np.float64).reshape(-1)
    if b.shape != (3,) or not np.all(np.isfinite(b)):
        raise CalibrationError("bias: expected a TriadFit or three finite values in rad/s")
    return b, None


# ---------------------------------------------------------------------------- bias
def gyro_bias(rates, fs_hz: float, *, rate_random_walk=None) -> TriadFit:
    """Gyro bias from a recording at rest.

    rates: (n, 3) rad/s at rest; fs_hz: sample rate. rate_random_walk: optional bias random
    walk K per axis (rad/s·√Hz, ADEV(τ) = K·√(τ/3), from an Allan deviation run).

    b is the mean rate (it includes the Earth's rotation as seen by the board, ≤ 0.0042 °/s).
    Its sigma is the uncertainty of the mean: the white level comes from the Allan variance at
    cluster times long enough to ignore the sensor's filter, so oversampled, correlated samples
    are not over-trusted (std/√n would be too small by √(fs / 2·noise bandwidth)); never less
    than std/√n. With K given, K²·T/3 is added: sigma is then that of b as the bias at either
    end of the recording (the moment it is used), and extra["best_duration_s"] = √3·N/K is
    the rest length that minimises it. A random walk is not estimated from the recording
    itself (the recording cannot show it at its own length); extra["drift_z"] (second-half
    mean − first-half mean, in sigmas of white noise) beyond about ±4 flags a bias that
    visibly wandered (temperature settling, a bump): record again or pass K.
    M is not estimated (identity, NaN covariance). Raises CalibrationError when the data are
    too short or show motion.
    """
    u = _as_rates(rates)
    n = len(u)
    if not fs_hz > 0:
        raise CalibrationError("fs_hz must be positive")
    if n < 16:
        raise CalibrationError(f"gyro_bias: {n} samples at rest is too short; record at least "
                               "a few seconds (10-60 s recommended)")
    med = np.median(u, axis=0)
    mad = 1.4826 * np.median(np.abs(u - med), axis=0)
    excursion = np.max(np.abs(u - med), axis=0)
    limit = 10.0 * mad + math.radians(1.0)
    moved = excursion > limit
    if np.any(moved):
        axes = ", ".join(f"{_AXES[k]} ({math.degrees(excursion[k]):.2f} °/s)"
                         for k in np.flatnonzero(moved))
        raise CalibrationError(f"gyro_bias: the board was not at rest: rate excursions on {axes} "
                               "well beyond the noise; record again without touching the board")
    rrw2 = None
    kk = None
    if rate_random_walk is not None:
        kk = np.broadcast_to(np.asarray(rate_random_walk, float), (3,)).copy()
        if not (np.all(np.isfinite(kk)) and np.all(kk >= 0)):
            raise CalibrationError("rate_random_walk must be finite and >= 0")
        rrw2 = kk**2 / fs_hz
    mu = _mean_uncertainty(u, min_cluster=max(1, int(round(0.02 * fs_hz))), rrw2=rrw2)
    b = u.mean(axis=0)
    sig = mu["sigma"]
    res = u - b
    nd = np.sqrt(mu["n2"] / fs_hz)
    extra = {
        "n": n,
        "duration_s": n / fs_hz,
        "std_rad_s": res.std(axis=0, ddof=1),
        "sigma_white_rad_s": mu["sigma_white"],
        "noise_density_rad_s_rthz": nd,
        "drift_z": mu["drift_z"],
        "sigma_method": mu["method"],
    }
    if kk is not None:
        extra["rate_random_walk_rad_s_rthz"] = kk
        with np.errstate(divide="ignore"):
            extra["best_duration_s"] = np.where(kk > 0, math.sqrt(3.0) * nd / np.maximum(kk, 1e-300),
                                                np.inf)
    return TriadFit(
        method="bias",
        m=np.eye(3),
        b=b,
        cov=_cov12(b_cov=np.diag(sig**2)),
        residual_rms=float(np.sqrt(np.mean(res**2))),
        residuals=None,
        dof=3 * (n - 1),
        estimated=np.array([False] * 9 + [True] * 3),
        extra=extra,
    )


# ---------------------------------------------------------------------------- turntable
class TurntableSegment(NamedTuple):
    """One turntable segment: the board turning at a constant rate about a fixed axis.

    rates: (n, 3) gyro readings u in rad/s while the table turns at constant rate;
    axis: the table's rotation axis in the board frame (normalised here);
    table_rate_rad_s: the table's rate about that axis (right-hand rule; negative = other way);
    sigma: optional 1-sigma uncertainty of this segment's MEAN reading, rad/s (scalar or per
    axis); estimated from the data when None. specific_force_g: optional, see below.
    """

    rates: np.ndarray
    axis: np.ndarray
    table_rate_rad_s: float
    sigma: float | np.ndarray | None = None
    specific_force_g: np.ndarray | None = None   # (3,) the board's mean specific force in g during the
                                                 # segment (calibrated accelerometer): with gsens=, the
                                                 # bias predicted for it, G·f, is taken off the reading


def _segments(segments) -> list[TurntableSegment]:
    out = []
    for i, s in enumerate(segments):
        if isinstance(s, dict):
            s = TurntableSegment(**s)
        s = tuple(s)
        if len(s) not in (3, 4, 5):
            raise CalibrationError(f"segment {i}: expected (rates, axis, table_rate_rad_s[, sigma[, "
                                   "specific_force_g]])")
        rates = _as_rates(s[0], f"segment {i} rates")
        if len(rates) < 2:
            raise CalibrationError(f"segment {i}: needs at least 2 samples")
        ax = np.asarray(s[1], dtype=np.float64).reshape(-1)
        if ax.shape != (3,) or not np.all(np.isfinite(ax)) or np.linalg.norm(ax) < 1e-6:
            raise CalibrationError(f"segment {i}: axis must be a non-zero 3-vector in the board frame")
        ax = ax / np.linalg.norm(ax)
        w = float(s[2])
        if not math.isfinite(w):
            raise CalibrationError(f"segment {i}: table rate is not finite")
        sig = None if len(s) < 4 or s[3] is None else np.broadcast_to(
            np.asarray(s[3], float), (3,)).copy()
        if sig is not None and not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
            raise CalibrationError(f"segment {i}: sigma must be positive")
        f = None if len(s) < 5 or s[4] is None else np.asarray(s[4], float).reshape(3)
        if f is not None and not np.all(np.isfinite(f)):
            raise CalibrationError(f"segment {i}: specific_force_g must be finite")
        out.append(TurntableSegment(rates, ax, w, sig, f))
    return out


def _direction_coverage(vecs: np.ndarray, threshold: float) -> list[tuple[int, bool, bool]]:
    """For each board axis k: (k, has +, has −) where a vector counts for ±k when its
    k-component is at least `threshold` in that sign (threshold in the vectors' units)."""
    return [(k, bool(np.any(vecs[:, k] >= threshold)), bool(np.any(vecs[:, k] <= -threshold)))
            for k in range(3)]


def _check_turntable_design(design: np.ndarray, fix_b: bool) -> None:
    """Refuse when the segments leave a parameter with no information (σ unbounded), naming it:
    with b fitted, one rate per axis cannot separate scale from bias (two rates, or both ways, can)."""
    dn = design / np.maximum(np.linalg.norm(design, axis=0), 1e-300)
    _, sv, sv_vt = np.linalg.svd(dn, full_matrices=True)
    if sv.size == design.shape[1] and sv[-1] >= 1e-6 * sv[0]:
        return
    v = sv_vt[-1]
    if not fix_b and abs(v[3]) > 0.1:
        ax = [_AXES[i] for i in range(3) if abs(v[i]) > 0.1]
        raise NotObservable(
            "turntable: the bias and the response to rotation about board " + ", ".join(ax) + " cannot be "
            "separated (σ unbounded): every segment about that axis has the same rate. Add a segment the "
            "other way (or at another rate), or pass bias= from a rest recording (gyro_bias)")
    v = v[:3] / max(np.linalg.norm(v[:3]), 1e-300)
    raise NotObservable(
        "turntable: the segments' rate vectors do not span 3-D; nothing constrains the response to "
        f"rotation along {np.round(v, 3).tolist()} (board frame; σ unbounded). Turn the board about three "
        "independent axes")


def _check_sigma_limit_m(method: str, m_cov: np.ndarray, max_sigma: float) -> None:
    sig = np.sqrt(np.maximum(np.diag(m_cov), 0.0))
    over = np.flatnonzero(~(sig <= max_sigma))
    if over.size:
        raise NotObservable(f"{method}: " + ", ".join(f"m{i // 3}{i % 3} σ {sig[i]:.3g}" for i in over)
                            + f" above the limit {max_sigma:g}: add segments (longer, or at higher rates)")


def turntable(segments, bias: TriadFit | np.ndarray | None = None, *, max_sigma: float = 0.01,
              gsens=None) -> TriadFit:
    """M and b from turntable segments at known constant rates.

    segments: iterable of TurntableSegment or tuples (rates (n,3) rad/s, axis (3,) unit vector
    in the board frame, table_rate_rad_s, optional sigma of the segment mean). Each segment's
    mean reading ū = M·(ω·axis) + b; every row of M with its b is a weighted linear least
    squares problem (weights 1/σ² of the segment means, estimated from the data like
    gyro_bias unless given).

    bias: None → b is fitted with M; every board axis must then be turned both ways (the
    sum/difference of the two directions separates bias from scale). A TriadFit (e.g. from
    gyro_bias on a rest recording) → b is fixed to it and its uncertainty propagated into M;
    a plain (3,) array → b fixed and taken as exact (its covariance NaN). gsens: a g-sensitivity
    (calib.gsens.GSensFit, or G (3, 3) in rad/s per g): each segment's reading is taken less G·f
    (its specific_force_g), so b is then the bias at zero specific force.

    The covariance comes from the segment sigmas; it is scaled by the reduced chi-square when
    that is significantly above 1 (p < 0.01: unmodelled errors such as table-rate error or
    wobble), see extra["cov_scaled"]. residuals: per segment (S, 3), ū − (M·w + b), rad/s.
    Observability by the numbers: NotObservable when a parameter has no information (b fitted
    and every segment about an axis at the same rate; rate vectors not spanning 3-D) or an
    entry of M's 1σ exceeds max_sigma, naming it; CalibrationError when a segment's reading is far from its
    table rate (wrong axis or sign).
    """
    segs = _segments(segments)
    if not segs:
        raise NotObservable("turntable: no segments")
    S = len(segs)
    w = np.array([s.table_rate_rad_s * s.axis for s in segs])            # (S, 3) true rates
    ubar = np.array([s.rates.mean(axis=0) for s in segs])                 # (S, 3)
    if gsens is not None:               # the g-sensitivity's share of each segment's bias, G·f
        gm = np.asarray(gsens.g if hasattr(gsens, "g") else gsens, float).reshape(3, 3)
        missing = [i for i, s in enumerate(segs) if s.specific_force_g is None]
        if missing:
            raise CalibrationError(f"turntable: gsens given but segment {missing[0]} has no specific_force_g")
        ubar = ubar - np.array([gm @ s.specific_force_g for s in segs])
    sig = np.empty((S, 3))
    for i, s in enumerate(segs):
        sig[i] = s.sigma if s.sigma is not None else _mean_uncertainty(s.rates)["sigma"]
    sig = np.maximum(sig, 1e-12)

    fix_b = bias is not None
    if fix_b:
        b_fixed, cov_b = _bias_input(bias)
    # gross errors: the reading must be near the table rate (|M − I| ≲ 0.1, |b| ≲ 10 °/s)
    b_guess = b_fixed if fix_b else np.zeros(3)
    dev = np.linalg.norm(ubar - b_guess - w, axis=1)
    bad = np.flatnonzero(dev > 0.2 * np.linalg.norm(w, axis=1) + math.radians(10.0))
    if bad.size:
        i = int(bad[0])
        raise CalibrationError(
            f"turntable: segment {i} reads {np.round(np.degrees(ubar[i]), 2).tolist()} °/s but the "
            f"table turns {math.degrees(segs[i].table_rate_rad_s):.2f} °/s about board axis "
            f"{np.round(segs[i].axis, 3).tolist()}; check the axis and the sign (right-hand rule, "
            "board X forward, Y left, Z up)")

    design = np.column_stack([w, np.ones(S)]) if not fix_b else w.copy()
    _check_turntable_design(design, fix_b)
    p = design.shape[1]
    m = np.empty((3, 3))
    b = b_fixed.copy() if fix_b else np.empty(3)
    m_cov = np.zeros((9, 9))                  # from the segments' noise
    mb_cov = np.zeros((9, 3))
    b_cov = np.zeros((3, 3))
    G = np.zeros((9, 3))                      # dM/db when b is fixed
    resid = np.empty((S, 3))
    for i in range(3):
        wt = 1.0 / sig[:, i]
        A = design * wt[:, None]
        y = ubar[:, i] - (b_fixed[i] if fix_b else 0.0)
        sol = np.linalg.lstsq(A, y * wt, rcond=None)[0]
        C = np.linalg.inv(A.T @ A)
        m[i] = sol[:3]
        sl = slice(3 * i, 3 * i + 3)
        resid[:, i] = y - design @ sol
        m_cov[sl, sl] = C[:3, :3]
        if fix_b:
            G[sl, i] = -C @ (A.T @ wt)
        else:
            b[i] = sol[3]
            mb_cov[sl, i] = C[:3, 3]
            b_cov[i, i] = C[3, 3]

    # chi-square; with b fixed from a rest its error is common to every segment of a row, so
    # the residuals' covariance is diag(σ²) + σ_b²·11ᵀ (Sherman–Morrison)
    chi2 = float(np.sum((resid / sig) ** 2))
    if fix_b and cov_b is not None:
        for i in range(3):
            d = 1.0 / sig[:, i] ** 2
            sb2 = cov_b[i, i]
            chi2 -= sb2 * float(np.dot(d, resid[:, i])) ** 2 / (1.0 + sb2 * float(d.sum()))
    dof = 3 * S - 3 * p
    pval = float(special.chdtrc(dof, chi2)) if dof > 0 else float("nan")
    scaled = bool(dof > 0 and pval < 0.01)
    if scaled:
        f = chi2 / dof
        m_cov *= f
        mb_cov *= f
        b_cov *= f
    if fix_b:
        if cov_b is not None:                 # the rest bias's uncertainty, through the fit
            m_cov += G @ cov_b @ G.T
            mb_cov = G @ cov_b
            b_cov = cov_b.copy()
        else:
            b_cov = None
    have_b_cov = b_cov is not None
    cov = _cov12(m_cov, b_cov, mb_cov if have_b_cov else None)
    estimated = np.array([True] * 9 + [have_b_cov] * 3)
    fit = TriadFit(
        method="turntable",
        m=m,
        b=b,
        cov=cov,
        residual_rms=float(np.sqrt(np.mean(resid**2))),
        residuals=resid,
        dof=dof,
        estimated=estimated,
        extra={
            "segment_rates_rad_s": w,
            "segment_mean_rad_s": ubar,
            "segment_sigma_rad_s": sig,
            "normalized_residuals": resid / sig,
            "chi2": chi2,
            "reduced_chi2": chi2 / dof if dof > 0 else float("nan"),
            "chi2_p": pval,
            "cov_scaled": scaled,
            "bias_source": ("rest" if b_cov is not None else "given") if fix_b else "segments",
            "gsens_taken_off": gsens is not None,     # each segment's G·f taken off its reading
        },
    )
    if np.max(np.abs(m - np.eye(3))) > 0.2:
        raise CalibrationError(f"turntable: fitted M is far from identity ({np.round(m, 3).tolist()}); "
                               "check the segments' axes and signs")
    _check_sigma_limit_m("turntable", m_cov, max_sigma)
    return fit


# ---------------------------------------------------------------------------- rotation method


_COLUMN_NAMES = {0: "first column (m00, m10, m20: the response to rotation about X)",
                 1: "second column (m01, m11, m21: the response to rotation about Y)",
                 2: "third column (m02, m12, m22: the response to rotation about Z)"}
MAX_SIGMA_M = 0.01          # default limit of any entry's 1σ in the rotation method (1 % of scale, 0.57°)
MIN_MOTIONS = 6


# the rotation method's front end: small named checks, then calib.rotation_model's solver
def _check_rotation_inputs(gyro, fs_hz, static_intervals, gravity_dirs):
    """(u, intervals (k, 2), unit gravity directions (k, 3)), or CalibrationError naming the input."""
    u = _as_rates(gyro, "gyro")
    n = len(u)
    if not fs_hz > 0:
        raise CalibrationError("fs_hz must be positive")
    iv = np.asarray(static_intervals, dtype=np.int64).reshape(-1, 2) if len(static_intervals) else \
        np.zeros((0, 2), np.int64)
    k = len(iv)
    g = np.asarray(gravity_dirs, dtype=np.float64)
    if g.ndim != 2 or g.shape != (k, 3):
        raise CalibrationError(f"gravity_dirs: expected ({k}, 3), one per static interval, got {g.shape}")
    gn = np.linalg.norm(g, axis=1)
    if not np.all(np.isfinite(g)) or np.any(gn < 1e-9):
        raise CalibrationError("gravity_dirs: every direction must be a finite non-zero vector")
    for i, (a, z) in enumerate(iv):
        if not (0 <= a < z <= n):
            raise CalibrationError(f"static interval {i} = ({a}, {z}) is empty or outside 0..{n}")
        if i and a < iv[i - 1, 1]:
            raise CalibrationError(f"static intervals {i - 1} and {i} overlap or are out of order")
    return u, iv, g / gn[:, None]


def _kept_motions(k: int, exclude_motions) -> np.ndarray:
    keep = np.ones(max(k - 1, 0), dtype=bool)
    for j in exclude_motions:
        if 0 <= int(j) < len(keep):
            keep[int(j)] = False
    return keep


def _check_motion_count(J: int, k: int) -> None:
    if J < MIN_MOTIONS:
        raise NotObservable(
            f"rotation_method: {max(J, 0)} motion(s) between {k} static poses; at least {MIN_MOTIONS} are "
            "needed (2 constraints per motion for the 9 entries of M, and spare ones to estimate the noise) "
            "and 12–24 are recommended (e.g. ±90° and ±180° about X, Y and Z from different poses)")


def _check_clipping(u: np.ndarray, max_rate_rad_s: float | None, iv: np.ndarray, keep: np.ndarray) -> None:
    """Refuse when a motion the fit uses reaches the gyro's range (motions left out are not looked at)."""
    if max_rate_rad_s is None:
        return
    for j in np.flatnonzero(keep):
        s0 = int(iv[j, 1]) - 1
        over = np.flatnonzero(np.max(np.abs(u[s0:int(iv[j + 1, 0]) + 1]), axis=1) >= max_rate_rad_s)
        if over.size:
            raise CalibrationError(
                f"rotation_method: motion {j} has {over.size} samples at or beyond ±"
                f"{math.degrees(max_rate_rad_s):.0f} °/s (first at sample {s0 + over[0]}): the gyro may have "
                "clipped; leave the motion out (exclude_motions) or turn slower")


def _excitation(mo, m0: np.ndarray, b_motion: np.ndarray) -> np.ndarray:
    """(J, 3) rad: each motion's integrated rotation perpendicular to gravity (for the report:
    a turn about the vertical does not move gravity and informs nothing)."""
    P0 = np.linalg.inv(m0)
    U = np.moveaxis(mo.Uc, 0, -1)
    X0 = (U - b_motion[:, None, :]) @ P0.T
    X0[~mo.valid] = 0.0
    J = mo.J
    eps = mo.h * (X0.sum(axis=1) - 0.5 * X0[:, 0] - 0.5 * X0[np.arange(J), mo.lens - 1])
    gm = mo.g_prev + mo.g_next
    gmn = np.linalg.norm(gm, axis=1)
    gbar = np.where((gmn > 0.5)[:, None], gm / np.maximum(gmn, 1e-300)[:, None], mo.g_prev)
    return eps - np.sum(eps * gbar, axis=1)[:, None] * gbar


def _param_names(idx) -> str:
    return ", ".join(f"m{i // 3}{i % 3}" for i in idx)


def _null_hint(idx, eps_perp: np.ndarray, min_turn_rad: float) -> str:
    """What to record for the entries idx that the motions leave undetermined."""
    cols = sorted({int(i) % 3 for i in idx})
    out = []
    for c in cols:
        pos = bool(np.any(eps_perp[:, c] >= min_turn_rad))
        neg = bool(np.any(eps_perp[:, c] <= -min_turn_rad))
        what = ("no turn about board {a} with {a} off the vertical" if not (pos or neg) else
                "turns about board {a} only in the " + ("+" if pos else "−") + " direction")
        out.append(what.format(a=_AXES[c]) + f" (M's {_COLUMN_NAMES[c]})")
    return "; ".join(out)


def _refusal(message: str, entries) -> NotObservable:
    e = NotObservable(message)
    e.entries = [int(i) for i in entries]       # flat indices of M's unresolved entries
    return e


def _check_observable(model, m0: np.ndarray, cov_b, eps_perp: np.ndarray, min_turn_rad: float,
                      free=None) -> None:
    """Before the fit: refuse when the motions leave some combination of M's entries with no
    information at all (its σ is unbounded), naming the entries and what to record."""
    from imubench.calib.rotation_model import parameter_sigmas
    sig, null = parameter_sigmas(model, m0.ravel(), 1.0, cov_b, free)
    if np.any(np.isinf(sig)):
        idx = np.flatnonzero(np.isinf(sig))
        raise _refusal(
            f"rotation_method: the motions leave {_param_names(idx)} undetermined (σ unbounded): "
            f"{_null_hint(idx, eps_perp, min_turn_rad)}. Turn the board about that axis while it is off the "
            "vertical (a turn about the vertical does not move gravity), both ways and from several attitudes", idx)


def _check_sigma_limit(m_cov: np.ndarray, max_sigma: float, eps_perp, min_turn_rad: float,
                       bias_known: bool) -> None:
    """After the fit: refuse when an entry of M is known no better than max_sigma, naming it."""
    sig = np.sqrt(np.maximum(np.diag(m_cov), 0.0))
    over = np.flatnonzero(~(sig <= max_sigma))
    if over.size:
        worst = int(over[np.argmax(np.where(np.isfinite(sig[over]), sig[over], np.inf))])
        raise _refusal(
            f"rotation_method: {_param_names(over)} known only to "
            + ", ".join(f"σ {sig[i]:.3g}" for i in over)
            + f" (limit {max_sigma:g}; worst m{worst // 3}{worst % 3}): "
            + _null_hint(over, eps_perp, min_turn_rad)
            + (". The rest bias's uncertainty is propagated: a longer rest, or turns both ways, shrink it"
               if bias_known else ""), over)


def _axis_flip_hint(model, m0: np.ndarray, ang0: np.ndarray) -> str:
    """A reversed gyro axis: the gravity prediction with that axis negated fits far better."""
    best = None
    for flips in ((1, 1, -1), (1, -1, 1), (-1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1), (-1, -1, -1)):
        af = model.angles((m0 * np.asarray(flips, float)[:, None]).ravel())
        rms = float(np.sqrt(np.mean(af**2)))
        if best is None or rms < best[0]:
            best = (rms, flips)
    if best is not None and best[0] < math.radians(10.0) and best[0] < 0.2 * float(np.sqrt(np.mean(ang0**2))):
        return (" The data fit far better with gyro axis " + ", ".join(_AXES[i] for i in range(3) if best[1][i] < 0)
                + " reversed: check that axis's sign (right-hand rule).")
    return ""


def _check_fit_quality(fit: TriadFit, model, m0, ang, ang0, max_residual_deg: float) -> None:
    if fit.residual_rms > math.radians(max_residual_deg):
        worst = np.argsort(ang)[::-1][:3]
        raise CalibrationError(
            f"rotation_method: the gyro does not explain the gravity directions (RMS angle residual "
            f"{math.degrees(fit.residual_rms):.2f}° after the fit, limit {max_residual_deg:g}°; worst motions "
            + ", ".join(f"{int(i)} ({math.degrees(ang[i]):.1f}°)" for i in worst)
            + "). Check the static intervals (a pose moved, an interval spans a motion), the "
            "gravity directions (one per interval, board frame) and gyro clipping."
            + _axis_flip_hint(model, m0, ang0))
    if np.max(np.abs(fit.m - np.eye(3))) > 0.2:
        raise CalibrationError(
            f"rotation_method: fitted M is far from identity ({np.round(fit.m, 3).tolist()}); check "
            "the static intervals, the gravity directions (board frame, +Z up when level) and the "
            "gyro axes' signs")


def rotation_method(gyro, fs_hz: float, static_intervals, gravity_dirs, bias, init_m=None, *,
                    gravity_sigma=0.0, max_rate_rad_s: float | None = _ADXRS450_RANGE_RAD_S,
                    min_turn_deg: float = 30.0, max_residual_deg: float = 1.0,
                    max_sigma: float = MAX_SIGMA_M, exclude_motions=(), motion_bias=None, hold=()) -> TriadFit:
    """Gyro M without a turntable, from rotations between static poses (imu_tk's method).

    gyro: (n, 3) readings u in rad/s at fs_hz. static_intervals: k half-open sample ranges
    (start, stop), in time order, where the board was still. gravity_dirs: (k, 3) the
    calibrated accelerometer's specific-force direction (i.e. "up", +Z when level) in the board
    frame for each interval; normalised here. bias: (3,) rad/s or a TriadFit (gyro_bias of the
    rest recording; its uncertainty is propagated into M). init_m: starting M (identity).
    motion_bias: optional (k − 1, 3) rad/s, the bias during each motion (e.g. the bias the
    g-sensitivity predicts, calib.gsens), used instead of bias's b in the integration; bias's
    covariance still stands for its uncertainty.

    Motion j runs from the last sample of interval j to the first sample of interval j+1; the
    model and solver are calib.rotation_model's (residuals: the angle between the predicted and
    the measured gravity after each motion, two components weighted by the motion's expected
    noise: gyro white noise from the rests × √duration, and gravity_sigma, rad per direction,
    scalar or (k,)). The covariance is the Jacobian's, scaled by the reduced chi-square, plus
    the bias uncertainty propagated through the fit. M is relative to the accelerometer's frame.

    Observability is decided by the numbers: the fit is refused (NotObservable) only when an
    entry of M has no information (σ unbounded: no turn about that axis off the vertical; or a
    turn in one direction while the bias is unknown) or its 1σ after the fit exceeds max_sigma,
    and the message names the entries, their σ and the limit. A turn in one direction does
    constrain the scale when the bias is known: its uncertainty decides. At least 6 motions;
    12–24 are recommended.

    exclude_motions: indices j of motions (from interval j to j+1) to leave out, e.g. those
    with a gap in the recording (the integral would miss part of the rotation).

    hold: flat indices (row-major, 0–8) of M's entries held at init_m's (nominal) value, a
    nested model for motions that do not resolve them: the held entries' possible size
    (max_sigma) is carried into the others' covariance (rotation_model.solve) and is their σ;
    estimated marks them False and extra["held"] names them. A refusal for unresolved entries
    carries their indices in the exception's .entries.
    """
    from imubench.calib import rotation_model as RM
    u, iv, g = _check_rotation_inputs(gyro, fs_hz, static_intervals, gravity_dirs)
    k = len(iv)
    keep = _kept_motions(k, exclude_motions)
    J = int(keep.sum())
    _check_motion_count(J, k)
    b, cov_b = _bias_input(bias)
    m0 = np.eye(3) if init_m is None else np.asarray(init_m, dtype=np.float64).reshape(3, 3)
    if abs(np.linalg.det(m0)) < 1e-12:
        raise CalibrationError("init_m is singular")
    _check_clipping(u, max_rate_rad_s, iv, keep)
    gsig = np.broadcast_to(np.asarray(gravity_sigma, float), (k,)).astype(float)
    mo = RM.motions(u, fs_hz, iv, g, gsig, keep)
    if motion_bias is None:
        b_motion = np.broadcast_to(b, (J, 3))
    else:
        mb = np.asarray(motion_bias, float)
        if mb.shape != (k - 1, 3) or not np.all(np.isfinite(mb)):
            raise CalibrationError(f"motion_bias: expected ({k - 1}, 3) finite rad/s, one per motion")
        b_motion = mb[keep]
    model = RM.GravityModel(mo, b_motion)
    eps_perp = _excitation(mo, m0, model.b)
    min_turn = math.radians(min_turn_deg)
    free = np.ones(9, bool)
    free[list(hold)] = False
    if not free.any():
        raise CalibrationError("rotation_method: every entry of M held; nothing to fit")
    _check_observable(model, m0, cov_b, eps_perp, min_turn, free)

    sol = RM.solve(model, m0, cov_b, free, max_sigma if not free.all() else 0.0)
    if not sol.converged:
        raise CalibrationError(f"rotation_method: the fit did not converge ({sol.message})")
    jac_check = None
    if _CHECK_JACOBIAN:
        jm, jb = model.jacobian(sol.m.ravel(), with_bias=True)
        jmf, jbf = model.jacobian_fd(sol.m.ravel())
        jac_check = (float(np.max(np.abs(jm - jmf)) / np.max(np.abs(jmf))),
                     float(np.max(np.abs(jb - jbf)) / np.max(np.abs(jbf))))
    cov = _cov12(sol.m_cov, cov_b, sol.mb_cov)
    ang = model.angles(sol.m.ravel())
    ang0 = model.angles(m0.ravel())
    R = model.rotations(sol.m.ravel())
    turn = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1, 1)))
    warnings = []
    if J < 12:
        warnings.append(f"only {J} motions: the reduced chi-square (dof {sol.dof}) that scales the "
                        f"covariance is itself uncertain by ±{100 / math.sqrt(2 * sol.dof):.0f} %; "
                        "12-24 motions are recommended")
    fit = TriadFit(
        method="rotation",
        m=sol.m,
        b=b.copy(),
        cov=cov,
        residual_rms=float(np.sqrt(np.mean(ang**2))),
        residuals=ang,
        dof=sol.dof,
        estimated=np.array(free.tolist() + [cov_b is not None] * 3),
        extra={
            "angle_residuals_deg": np.degrees(ang),
            "angle_residuals_initial_deg": np.degrees(ang0),
            "motion_angles_deg": turn,
            "motion_duration_s": mo.dur,
            "excitation_deg": np.degrees(eps_perp),
            "motion_sigma_rad": mo.sigma,
            "noise_density_rad_s_rthz": mo.noise_density,
            "chi2": sol.chi2,
            "reduced_chi2": sol.reduced_chi2,
            "nfev": sol.nfev,
            "converged": sol.converged,
            "message": sol.message,
            "bias_source": "rest" if cov_b is not None else "given",
            "motion_bias": "given per motion" if motion_bias is not None else "one bias",
            "n_motions": J,
            "excluded_motions": [int(j) for j in np.flatnonzero(~keep)],
            "max_sigma": max_sigma,
            "held": [f"m{i // 3}{i % 3}" for i in np.flatnonzero(~free)],
            "warnings": warnings,
            **({"jacobian_check": jac_check} if jac_check is not None else {}),
        },
    )
    try:
        _check_fit_quality(fit, model, m0, ang, ang0, max_residual_deg)
    except CalibrationError as e:      # the entries the motions could not resolve, predicted at m0
        sig0, _ = RM.parameter_sigmas(model, m0.ravel(), 1.0, cov_b, free)
        over = np.flatnonzero(free & ~(sig0 <= max_sigma))
        if over.size:
            e.entries = [int(i) for i in over]
        raise
    _check_sigma_limit(np.where(np.outer(free, free), sol.m_cov, 0.0), max_sigma, eps_perp, min_turn,
                       cov_b is not None)
    return fit


def rotation_residuals(gyro, fs_hz: float, static_intervals, gravity_dirs, m, motion_bias) -> np.ndarray:
    """(k − 1,) degrees: for a given M and the bias during each motion ((k − 1, 3) or (3,) rad/s),
    the angle between the gravity direction the gyro predicts after each motion and the one
    measured at the next rest — the rotation method's residual, for motions a fit did not use
    (held out) as well as those it did."""
    from imubench.calib import rotation_model as RM
    u, iv, g = _check_rotation_inputs(gyro, fs_hz, static_intervals, gravity_dirs)
    k = len(iv)
    if k < 2:
        raise CalibrationError("rotation_residuals: at least two static intervals")
    mo = RM.motions(u, fs_hz, iv, g, np.zeros(k), np.ones(k - 1, bool))
    model = RM.GravityModel(mo, np.broadcast_to(np.asarray(motion_bias, float), (k - 1, 3)))
    return np.degrees(model.angles(np.asarray(m, float).reshape(9)))
