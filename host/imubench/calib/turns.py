"""Known-angle turns (Ferraris et al. 1995): gyro scale and misalignment without a turntable.

A person turns the board by hand through a known angle (one full turn, 360°, on a table, about
the axis that points up) between two rests. Over the turn the board rotates about the vertical,
so the body rate stays along the board's "up" direction a and the integrated, bias-corrected
rate equals the angle times that direction:

    s = ∫ (u − b) dt = M · (θ · a)                       (u = M·x + b, docs/conventions.md)

Three turns about three independent axes give the 9 entries of M by (generalised) linear least
squares; more turns over-determine it. The gravity direction never has to change during a turn,
which the rotation method (calib.gyro.rotation_method) needs, and no fixture is needed.

    detect_turns(gyro, fs_hz, intervals, up_dirs)  the turns in a recording, with their integrals
    known_angle_turns(turns)                       TriadFit "turns": M, the rest bias, covariance
    combine_fits(a, b)                             two fits of M (turns and rotation) in one

Everything is numpy; nothing touches a file or a port. docs/calibration.md ("Known-angle turns")
states the error budget: the hand's angle error, a turn axis off the measured vertical (a table
that is not level, a board lifted), the bias during the turn and the integration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import integrate, special   # χ² survival function: scipy.stats costs far more to import

from imubench.calib import CalibrationError, NotObservable, TriadFit

__all__ = ["Turn", "detect_turns", "split_by_rotation", "turn_in_window", "known_angle_turns", "combine_fits",
           "TURN_DEG",           "ANGLE_SIGMA_DEG", "AXIS_SIGMA_DEG"]

TURN_DEG = 360.0            # one full turn
ANGLE_SIGMA_DEG = 1.0       # 1-sigma of where a hand puts the board back (against an edge or mark)
AXIS_SIGMA_DEG = 0.5        # 1-sigma of the turn axis off the measured vertical (table tilt, wobble)
SAME_ATTITUDE_DEG = 10.0    # rests before and after a turn must have "up" this close
TURN_TOL = 0.25             # |measured| must be within this fraction of a whole number of turns
MAX_OFF_AXIS = 0.2          # perpendicular part of the integral over its norm (11.5°)
_AXES = "XYZ"


@dataclass
class Turn:
    """One motion between two rests of the same attitude (samples start..stop inclusive)."""
    start: int                        # last sample of the rest before
    stop: int                         # first sample of the rest after
    rest_before: int                  # index of the interval before / after (in the list given)
    rest_after: int
    up: np.ndarray                    # (3,) unit: the board's up direction (specific force) at rest
    integral_rad: np.ndarray          # (3,) ∫(u − b) dt, trapezoid, in rad (u in rad/s)
    integration_err_rad: np.ndarray   # (3,) |trapezoid − Simpson|: the integration's error estimate
    bias_rad_s: np.ndarray            # (3,) the bias during the turn: mean of the two rests' rates
    bias_sigma_rad_s: np.ndarray      # (3,) its 1-sigma: rests' sigma and half their difference
    duration_s: float
    angle_rad: float = 0.0            # the known angle, signed by the data (0: not a whole turn)
    usable: bool = True
    reason: str = ""                  # why not usable
    label: str = ""                   # "turn about +Z" etc.

    @property
    def measured_rad(self) -> float:
        """The integral along the up direction (what the known angle is compared with)."""
        return float(self.integral_rad @ self.up)

    @property
    def off_axis_deg(self) -> float:
        n = float(np.linalg.norm(self.integral_rad))
        perp = self.integral_rad - self.measured_rad * self.up
        return math.degrees(math.atan2(float(np.linalg.norm(perp)), abs(self.measured_rad))) if n else 0.0


def _axis_label(up: np.ndarray) -> str:
    k = int(np.argmax(np.abs(up)))
    return ("+" if up[k] > 0 else "-") + _AXES[k]


def detect_turns(gyro, fs_hz: float, intervals, up_dirs, *, turn_deg: float = TURN_DEG,
                 breaks=(), clip_rad_s: float | None = None, noise_sigma_rad_s=None,
                 scale_known: bool = True, same_attitude_deg: float = SAME_ATTITUDE_DEG) -> list[Turn]:
    """The known-angle turns in a recording.

    gyro (n, 3) rad/s (nominally scaled); intervals: the still intervals in time order (objects
    with start, stop, or (start, stop) pairs); up_dirs (k, 3): the specific-force direction of
    each (from the accelerometer). A motion between two consecutive rests whose up directions
    agree within same_attitude_deg is a candidate; it is a turn when its integral along "up" is
    a whole number of turn_deg turns (within 25 %) and mostly about "up" (MAX_OFF_AXIS). With
    scale_known False (raw counts, no nominal scale) the magnitude cannot be judged: a candidate
    mostly about "up" counts as one turn. breaks: sample indices where the recording is not
    continuous (gaps, cut points); clip_rad_s: the gyro's range. A turn over a break or clipped
    samples is returned with usable False and the reason. Returns the turns (usable or not),
    in time order; other motions are not returned."""
    u = np.asarray(gyro, dtype=np.float64)
    iv = [(int(i.start), int(i.stop)) if hasattr(i, "start") else (int(i[0]), int(i[1])) for i in intervals]
    d = np.asarray(up_dirs, dtype=np.float64).reshape(-1, 3)
    if len(d) != len(iv):
        raise CalibrationError(f"detect_turns: {len(iv)} intervals but {len(d)} up directions")
    d = d / np.linalg.norm(d, axis=1)[:, None]
    h = 1.0 / fs_hz
    turn = math.radians(turn_deg)
    brk = np.asarray(sorted(int(b) for b in breaks), dtype=np.int64)
    out: list[Turn] = []
    rest_stats = []
    for a, z in iv:
        x = u[a:z]
        m = x.mean(axis=0)
        if noise_sigma_rad_s is not None:
            s = np.asarray(noise_sigma_rad_s, float) / math.sqrt(max(len(x), 1))
        else:
            s = x.std(axis=0, ddof=1) / math.sqrt(max(len(x), 1)) if len(x) > 1 else np.zeros(3)
        rest_stats.append((m, s))
    for j in range(len(iv) - 1):
        cosang = float(np.clip(d[j] @ d[j + 1], -1.0, 1.0))
        if math.degrees(math.acos(cosang)) > same_attitude_deg:
            continue
        s0, s1 = iv[j][1] - 1, iv[j + 1][0]
        if s1 - s0 < 2:
            continue
        up = d[j] + d[j + 1]
        up /= np.linalg.norm(up)
        (m0, e0), (m1, e1) = rest_stats[j], rest_stats[j + 1]
        b = 0.5 * (m0 + m1)
        bsig = np.sqrt(0.25 * (e0 ** 2 + e1 ** 2) + (0.5 * (m1 - m0)) ** 2)
        x = u[s0:s1 + 1] - b
        integ = integrate.trapezoid(x, dx=h, axis=0)
        simp = integrate.simpson(x, dx=h, axis=0)
        meas = float(integ @ up)
        norm = float(np.linalg.norm(integ))
        perp = float(np.linalg.norm(integ - meas * up))
        mostly_up = norm > 0 and perp <= MAX_OFF_AXIS * abs(meas)
        if scale_known:
            n_turns = int(round(abs(meas) / turn))
            if n_turns < 1 or abs(abs(meas) - n_turns * turn) > TURN_TOL * turn:
                continue
        else:
            if not mostly_up:
                continue
            n_turns = 1
        t = Turn(start=s0, stop=s1, rest_before=j, rest_after=j + 1, up=up, integral_rad=integ,
                 integration_err_rad=np.abs(integ - simp), bias_rad_s=b, bias_sigma_rad_s=bsig,
                 duration_s=(s1 - s0) * h, angle_rad=math.copysign(n_turns * turn, meas),
                 label=f"turn about {_axis_label(up)}")
        inside = brk[(brk > s0) & (brk <= s1)]
        if inside.size:
            t.usable = False
            t.reason = (f"the recording is not continuous inside the turn (break at sample {int(inside[0])}, "
                        f"t = {inside[0] * h:.2f} s): the integral would miss part of the rotation")
        elif clip_rad_s is not None and np.any(np.abs(u[s0:s1 + 1]) >= clip_rad_s):
            k = int(np.flatnonzero(np.any(np.abs(u[s0:s1 + 1]) >= clip_rad_s, axis=1))[0]) + s0
            t.usable = False
            t.reason = (f"the gyro reached its range ±{math.degrees(clip_rad_s):.0f} °/s at sample {k} "
                        "(clipped): turn slower")
        elif not mostly_up:
            t.usable = False
            t.reason = (f"the turn's axis was {t.off_axis_deg:.1f}° off the vertical (limit "
                        f"{math.degrees(math.atan(MAX_OFF_AXIS)):.0f}°): keep the board flat on the table")
        out.append(t)
    return out


def turn_in_window(gyro, fs_hz: float, start: int, stop: int, up, bias_rad_s, bias_sigma_rad_s, *,
                   turn_deg: float = TURN_DEG, label: str = "") -> Turn:
    """A turn over a given window of samples [start, stop) (e.g. a file cut into named parts
    around each turn, with no rest on both sides to find it by): integral of (u − bias) over the
    window; the known angle is the whole number of turn_deg nearest to it (at least one)."""
    u = np.asarray(gyro, dtype=np.float64)[start:stop]
    h = 1.0 / fs_hz
    up = np.asarray(up, float) / np.linalg.norm(up)
    b = np.asarray(bias_rad_s, float)
    x = u - b
    integ = integrate.trapezoid(x, dx=h, axis=0)
    simp = integrate.simpson(x, dx=h, axis=0)
    meas = float(integ @ up)
    n_turns = max(1, int(round(abs(meas) / math.radians(turn_deg))))
    t = Turn(start=start, stop=stop - 1, rest_before=-1, rest_after=-1, up=up, integral_rad=integ,
             integration_err_rad=np.abs(integ - simp), bias_rad_s=b,
             bias_sigma_rad_s=np.asarray(bias_sigma_rad_s, float),
             duration_s=(stop - 1 - start) * h, angle_rad=math.copysign(n_turns * math.radians(turn_deg), meas),
             label=label or f"turn about {_axis_label(up)}")
    if t.off_axis_deg > math.degrees(math.atan(MAX_OFF_AXIS)):
        t.usable = False
        t.reason = f"the turn's axis was {t.off_axis_deg:.1f}° off the vertical"
    return t


def split_by_rotation(acc, gyro, fs_hz: float, intervals, *, moving_dps: float = 5.0,
                      min_duration_s: float = 1.0, guard_s: float = 0.25, threshold: float | None = None) -> list:
    """Still intervals that are also still for the gyro: each interval of calib.static
    (found on the accelerometer alone) is cut where the rate departs from the interval's median
    by more than moving_dps (or `threshold`, in the gyro's own unit, e.g. raw counts) (± guard_s);
    pieces shorter than min_duration_s are dropped. A turn
    about the vertical without any acceleration (a smooth hand, a simulated bench) leaves the
    accelerometer still: only the gyro shows it."""
    from imubench.calib.static import StaticInterval, interval_stats
    a = np.asarray(acc, dtype=np.float64)
    u = np.asarray(gyro, dtype=np.float64)
    thr = math.radians(moving_dps) if threshold is None else float(threshold)
    guard = int(round(guard_s * fs_hz))
    min_n = max(2, int(math.ceil(min_duration_s * fs_hz)))
    out = []
    for iv in intervals:
        seg = u[iv.start:iv.stop]
        moving = np.max(np.abs(seg - np.median(seg, axis=0)), axis=1) > thr
        if not moving.any():
            out.append(iv)
            continue
        if guard:
            moving = np.convolve(moving.astype(float), np.ones(2 * guard + 1), mode="same") > 0
        edges = np.flatnonzero(np.diff(np.concatenate([[1], moving.astype(np.int8), [1]])))
        for s0, s1 in zip(edges[::2], edges[1::2]):
            if s1 - s0 >= min_n:
                mean, std, sig = interval_stats(a[iv.start + s0:iv.start + s1])
                out.append(StaticInterval(start=iv.start + s0, stop=iv.start + s1, n=s1 - s0, mean=mean, std=std,
                                          sigma_mean=sig, fs_hz=fs_hz))
    return out


def _turn_cov(t: Turn, noise_density, angle_sigma: float, axis_sigma: float) -> np.ndarray:
    """3x3 covariance of a turn's integral: bias over the turn, white noise integrated, the
    integration's error, the hand's angle error along up and the axis error across it."""
    T = t.duration_s
    nd = np.broadcast_to(np.asarray(noise_density, float), (3,))
    diag = (t.bias_sigma_rad_s * T) ** 2 + nd ** 2 * T + t.integration_err_rad ** 2
    a = t.up[:, None]
    return np.diag(diag) + angle_sigma ** 2 * (a @ a.T) + (t.angle_rad * axis_sigma) ** 2 * (np.eye(3) - a @ a.T)


def known_angle_turns(turns, bias: TriadFit | None = None, *, noise_density_rad_s_rthz=0.0,
                      angle_sigma_deg: float = ANGLE_SIGMA_DEG, axis_sigma_deg: float = AXIS_SIGMA_DEG,
                      refused=(), max_sigma: float = 0.01) -> TriadFit:
    """Gyro M from known-angle turns (Turn objects of detect_turns; unusable ones are left out).

    Generalised least squares on s_k = M·(θ_k·a_k): each turn's integral has the covariance of
    _turn_cov (bias during the turn × its duration, white noise N²·T, |trapezoid − Simpson|, the
    hand's angle sigma along a_k, θ·axis sigma across it). Cov(M) = (Σ AᵀC⁻¹A)⁻¹, scaled by
    max(1, χ²/dof) when there are more than three turns (with three, dof = 0: the sigmas are
    the error budget's alone, and the turns cannot check the fit). bias: the rest bias (its b
    and covariance are carried into the result; M does not depend on it except through the
    turns' own bias, which is the rests' around each turn). Raises NotObservable when the
    turns' axes do not span three dimensions, naming the axis missing, or when an entry of M's
    1σ exceeds max_sigma, naming the entry, its σ and the limit."""
    use = [t for t in turns if t.usable and t.angle_rad != 0.0]
    why_not = [f"{t.label} at {t.start}: {t.reason}" for t in turns if not t.usable] + list(refused)
    if len(use) < 3:
        have = ", ".join(t.label for t in use) or "none"
        raise NotObservable(
            f"known-angle turns: {len(use)} usable turn(s) ({have}); three about three different axes are "
            "needed (one full turn on a table with X, then Y, then Z pointing up, still before and after each)"
            + (". Not usable: " + "; ".join(why_not) if why_not else ""))
    V = np.array([t.angle_rad * t.up for t in use])
    sv = np.linalg.svd(V / np.linalg.norm(V, axis=1)[:, None], compute_uv=True)
    svals, vt = sv[1], sv[2]
    if svals[-1] < 0.3 * svals[0]:
        k = int(np.argmax(np.abs(vt[-1])))
        raise NotObservable(
            f"known-angle turns: the turns' axes ({', '.join(t.label for t in use)}) leave the direction "
            f"near board {_AXES[k]} without a turn: M's column {_AXES[k]} is not observable; turn the board "
            f"once with {_AXES[k]} pointing up")
    ang_s = math.radians(angle_sigma_deg)
    ax_s = math.radians(axis_sigma_deg)
    N = np.zeros((9, 9))
    r = np.zeros(9)
    covs = []
    for t in use:
        C = _turn_cov(t, noise_density_rad_s_rthz, ang_s, ax_s)
        Ci = np.linalg.inv(C)
        A = np.zeros((3, 9))
        v = t.angle_rad * t.up
        for i in range(3):
            A[i, 3 * i:3 * i + 3] = v
        N += A.T @ Ci @ A
        r += A.T @ Ci @ t.integral_rad
        covs.append((A, Ci, C))
    cov_m = np.linalg.inv(N)
    mvec = cov_m @ r
    M = mvec.reshape(3, 3)
    chi2 = float(sum((t.integral_rad - A @ mvec) @ Ci @ (t.integral_rad - A @ mvec)
                     for t, (A, Ci, _) in zip(use, covs)))
    dof = 3 * len(use) - 9
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    cov_m = cov_m * scale
    sm = np.sqrt(np.maximum(np.diag(cov_m), 0.0))
    over = np.flatnonzero(~(sm <= max_sigma))
    if over.size:
        raise NotObservable("known-angle turns: " + ", ".join(f"m{i // 3}{i % 3} σ {sm[i]:.3g}" for i in over)
                            + f" above the limit {max_sigma:g}: turns that place the board back more exactly "
                            "(a stop, a marked edge), more turns, or the rotation method with them")
    cov = np.full((12, 12), np.nan)
    cov[:9, :9] = cov_m
    b = np.zeros(3)
    est_b = False
    if bias is not None:
        b = np.asarray(bias.b, float)
        cb = np.asarray(bias.cov, float)[9:, 9:]
        cov[9:, 9:] = cb
        cov[:9, 9:] = 0.0
        cov[9:, :9] = 0.0
        est_b = bool(np.all(np.isfinite(cb)))
    Minv = np.linalg.inv(M)
    table = []
    resid = []
    for t, (A, _, C) in zip(use, covs):
        after = Minv @ t.integral_rad
        e = t.integral_rad - A @ mvec
        resid.append(float(np.linalg.norm(e)))
        sig_along = math.sqrt(float(t.up @ C @ t.up))
        table.append({"label": t.label, "start": t.start, "stop": t.stop, "duration_s": t.duration_s,
                      "known_deg": math.degrees(t.angle_rad),
                      "before_deg": math.degrees(t.measured_rad),
                      "after_deg": math.degrees(float(after @ t.up)),
                      "off_axis_before_deg": t.off_axis_deg,
                      "sigma_deg": math.degrees(sig_along),
                      "budget_deg": {
                          "bias": math.degrees(float(np.linalg.norm(t.bias_sigma_rad_s * t.duration_s))),
                          "noise": math.degrees(float(np.linalg.norm(np.broadcast_to(
                              noise_density_rad_s_rthz, (3,))) * math.sqrt(t.duration_s))),
                          "integration": math.degrees(float(np.linalg.norm(t.integration_err_rad))),
                          "hand_angle": angle_sigma_deg,
                          "axis_tilt": axis_sigma_deg * abs(t.angle_rad)}})
    warnings = []
    if dof == 0:
        warnings.append("three turns determine M exactly: after calibration each turn integrates to its known "
                        "angle by construction, so the turns cannot check the fit; its sigmas come from the "
                        "error budget alone (a fourth turn, or the rotation method, is the check)")
    return TriadFit(method="turns", m=M, b=b, cov=cov,
                    residual_rms=float(np.sqrt(np.mean(np.square(resid)))), residuals=np.array(resid),
                    dof=dof, estimated=np.array([True] * 9 + [est_b] * 3),
                    extra={"turns": table, "chi2": chi2, "chi2_red": chi2 / dof if dof > 0 else float("nan"),
                           "n_turns": len(use), "not_used": why_not,
                           "angle_sigma_deg": angle_sigma_deg, "axis_sigma_deg": axis_sigma_deg,
                           "warnings": warnings})


@dataclass
class Combined:
    fit: TriadFit
    chi2: float
    dof: int
    p_value: float
    consistent: bool
    notes: list = field(default_factory=list)


def combine_fits(a: TriadFit, b: TriadFit, p_min: float = 1e-3) -> Combined:
    """Two independent estimates of the same M (e.g. known-angle turns and the rotation method,
    both in the accelerometer's frame) in one: inverse-covariance weighting of the 9 entries.
    The bias and its covariance are a's. Their agreement is tested: χ² of the difference over
    the sum of the covariances (9 dof); below p_min they disagree, and the combined fit's
    covariance is inflated by χ²/dof (the fits are then not both right: say so)."""
    ca, cb = np.asarray(a.cov, float)[:9, :9], np.asarray(b.cov, float)[:9, :9]
    if not (np.all(np.isfinite(ca)) and np.all(np.isfinite(cb))):
        raise CalibrationError("combine_fits: both fits need a finite covariance of M")
    ia, ib = np.linalg.inv(ca), np.linalg.inv(cb)
    C = np.linalg.inv(ia + ib)
    m = C @ (ia @ a.m.ravel() + ib @ b.m.ravel())
    dlt = a.m.ravel() - b.m.ravel()
    chi2 = float(dlt @ np.linalg.solve(ca + cb, dlt))
    p = float(special.chdtrc(9, chi2))
    consistent = p >= p_min
    notes = []
    if not consistent:
        C = C * (chi2 / 9.0)
        notes.append(f"the {a.method} and {b.method} fits disagree (χ² = {chi2:.1f} for 9 dof, p = {p:.1e}); "
                     "the combined covariance is inflated by χ²/9; look at both fits separately")
    cov = np.array(a.cov, float, copy=True)
    cov[:9, :9] = C
    cov[:9, 9:] = np.nan if not np.all(np.isfinite(a.cov[9:, 9:])) else 0.0
    cov[9:, :9] = cov[:9, 9:].T
    fit = TriadFit(method=f"{a.method}+{b.method}", m=m.reshape(3, 3), b=a.b.copy(), cov=cov,
                   residual_rms=float("nan"), dof=a.dof + b.dof, estimated=a.estimated.copy(),
                   extra={"parts": [a.method, b.method], "chi2_between": chi2, "p_between": p,
                          "consistent": consistent, "warnings": notes,
                          "sigma_m_parts": [a.sigma_m.tolist(), b.sigma_m.tolist()],
                          "m_parts": [a.m.tolist(), b.m.tolist()]})
    return Combined(fit, chi2, 9, p, consistent, notes)
