"""Gyro calibration (imubench.calib.gyro) against synthetic data from known truths.

Truth: M = I + scale errors up to ±3 % + cross-axis up to ±1 %, biases up to ±0.5 °/s,
white noise 0.015 °/s/√Hz (ADXRS450, docs sensors.md 2.10). Every random draw has a fixed
seed. The attitude trajectories of the rotation-method tests are built in closed form here
(own Rodrigues formula, body rates by exact differentiation), independently of the module.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from imubench.calib import CalibrationError, NotObservable, TriadFit
from imubench.calib import gyro as G
from imubench.calib.gyro import (
    TurntableSegment,
    gyro_bias,
    integrate_rotation,
    rotation_method,
    turntable,
)
from scipy import signal

D2R = math.pi / 180.0
ND = 0.015 * D2R                      # white noise density, rad/s/√Hz
EX, EY, EZ = np.eye(3)

M_TRUE = np.array([[1.030, 0.010, -0.008],
                   [-0.006, 0.980, 0.009],
                   [0.010, -0.010, 1.025]])
B_TRUE = np.array([0.5, -0.3, 0.2]) * D2R


# ---------------------------------------------------------------------------- helpers
def rot(axis, angle: float) -> np.ndarray:
    """Closed-form rotation matrix (Rodrigues) about a unit axis by angle (rad)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def rot_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) of the rotation a⁻¹·b, precise for small angles."""
    c = a.T @ b
    v = np.array([c[2, 1] - c[1, 2], c[0, 2] - c[2, 0], c[1, 0] - c[0, 1]])
    return math.atan2(np.linalg.norm(v) / 2.0, (np.trace(c) - 1.0) / 2.0)


def smooth_motion(parts, duration_s: float, fs: float):
    """Body rates of R(s) = Π_i exp([a_i]× θ_i p(s)), all parts at once, p(s) = s − sin(2πs)/2π
    (rate and its derivative zero at both ends). Returns (rates (n, 3) at t_k = k/fs including
    both ends, exact final rotation). ω = Σ_i (Π_{j>i} R_j)ᵀ a_i θ_i p'."""
    n = int(round(duration_s * fs)) + 1
    T = (n - 1) / fs
    s = np.arange(n) / (n - 1)
    p = s - np.sin(2 * np.pi * s) / (2 * np.pi)
    dp = (1 - np.cos(2 * np.pi * s)) / T
    axes = [np.asarray(a, float) / np.linalg.norm(a) for a, _ in parts]
    angs = [th for _, th in parts]
    w = np.zeros((n, 3))
    for k in range(n):
        after = np.eye(3)
        for i in range(len(parts) - 1, -1, -1):
            w[k] += after.T @ axes[i] * angs[i] * dp[k]
            after = rot(axes[i], angs[i] * p[k]) @ after
    total = np.eye(3)
    for a, th in zip(axes, angs):
        total = total @ rot(a, th)
    return w, total


X, Y, Z = EX, EY, EZ
# 24 motions: every axis both ways from several poses, 90° and 180° turns, compound turns
MOTIONS = [
    [(X, 90)], [(Z, 90)], [(Y, 90)], [(X, -90)], [(Z, -90)], [(Y, -90)],
    [(Y, 90)], [(X, 90)], [(Z, -90)], [(Y, -90)], [(X, -90)], [(Z, 90)],
    [(X, 180)], [(Y, -180)], [(Z, 90)], [(X, -180)], [(Y, 180)], [(Z, -90)],
    [(X, 60), (Y, 45)], [(Y, -60), (Z, 45)], [(Z, 60), (X, -45)], [(X, -45), (Y, -30), (Z, -40)],
    [(Y, 120)], [(Z, -120), (X, 30)],
]


def trajectory(fs: float, motions=MOTIONS, rest_s: float = 10.0, static_s: float = 1.0,
               peak_dps: float = 180.0):
    """A rest, then static poses joined by smooth motions (peak rate ≤ peak_dps).

    Returns true body rates (n, 3), static intervals [(start, stop)], the true specific-force
    direction ("up") in the board frame for each, and the rest slice. The board's attitude C
    (board → world) updates as C ← C·R_motion; up in the board frame is Cᵀ·e_z.
    """
    chunks, iv, up = [np.zeros((int(rest_s * fs), 3))], [], []
    pos = len(chunks[0])
    ns = int(static_s * fs)
    C = np.eye(3)

    def static():
        nonlocal pos
        chunks.append(np.zeros((ns, 3)))
        iv.append((pos, pos + ns))
        up.append(C.T @ EZ)
        pos += ns

    static()
    for parts in motions:
        parts = [(a, ang * D2R) for a, ang in parts]
        total = math.sqrt(sum(t * t for _, t in parts))
        w, R = smooth_motion(parts, max(0.5, 2 * total / (peak_dps * D2R)), fs)
        w = w[1:-1]                   # the end samples (zero rate) belong to the static poses
        chunks.append(w)
        pos += len(w)
        C = C @ R
        static()
    return np.concatenate(chunks), iv, np.array(up), slice(0, int(rest_s * fs))


@pytest.fixture(scope="module")
def traj200():
    return trajectory(200.0)


def sigma_ratio(err: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """Monte Carlo spread / RMS of the reported sigma, per parameter."""
    return err.std(axis=0, ddof=1) / np.sqrt(np.mean(sig**2, axis=0))


# ---------------------------------------------------------------------------- integrate_rotation
def test_integrate_rotation_signs():
    """Positive rate about +Z turns the board's +X toward +Y (right-hand rule), and the
    world-fixed "up" seen from the board turns the other way."""
    fs = 200.0
    n = 201                                                   # 1 s
    for axis, frm, to in ((EZ, EX, EY), (EX, EY, EZ), (EY, EZ, EX)):
        R = integrate_rotation(np.tile(axis * (math.pi / 2), (n, 1)), fs)
        np.testing.assert_allclose(R @ frm, to, atol=1e-12)   # end-frame axis in start frame
        np.testing.assert_allclose(R, rot(axis, math.pi / 2), atol=1e-12)
    # worked example of the rotation method's prediction: level board (up = +Z), +90° roll
    # about X (left side goes up) → up is along the board's +Y
    R = integrate_rotation(np.tile(EX * (math.pi / 2), (n, 1)), fs)
    np.testing.assert_allclose(R.T @ EZ, EY, atol=1e-12)
    # the test trajectory agrees with that (built from world-frame reasoning)
    _, _, up, _ = trajectory(200.0, motions=[[(X, 90)]], rest_s=0.1, static_s=0.1)
    np.testing.assert_allclose(up[1], EY, atol=1e-12)


@pytest.mark.parametrize("fs", [100.0, 1000.0, 4000.0])
def test_integrate_rotation_constant_rate_any_axis(fs):
    rng = np.random.default_rng(11)
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rate = rng.uniform(-300, 300) * D2R
        n = int(rng.integers(2, int(2 * fs)))
        R = integrate_rotation(np.tile(axis * rate, (n, 1)), fs)
        assert rot_angle(R, rot(axis, rate * (n - 1) / fs)) < 1e-11


@pytest.mark.parametrize("fs", [100.0, 200.0, 1000.0, 4000.0])
def test_integrate_rotation_two_stage_and_compound(fs):
    """Successive turns compose in the body frame (R = R₁·R₂, order matters); compound smooth
    turns at up to ~300 °/s are integrated to within 2e-6 rad (1e-4 °)."""
    w1, R1 = smooth_motion([(EX, math.pi / 2)], 0.5, fs)
    w2, R2 = smooth_motion([(EY, math.pi / 2)], 0.5, fs)
    both = np.concatenate([w1, w2[1:]])                       # shared zero-rate sample
    R = integrate_rotation(both, fs)
    assert rot_angle(R, rot(EX, math.pi / 2) @ rot(EY, math.pi / 2)) < 2e-6
    assert rot_angle(R, rot(EY, math.pi / 2) @ rot(EX, math.pi / 2)) > 1.0
    np.testing.assert_allclose(R @ EX, EY, atol=1e-5)         # X → −Z (Ry) → +Y (Rx)
    assert rot_angle(integrate_rotation(w1, fs) @ integrate_rotation(w2, fs), R) < 2e-6
    w, Rt = smooth_motion([(EZ, math.pi), ([1, 1, 0], -math.pi / 2), ([0, 1, 1], math.pi / 3)],
                          1.2, fs)
    assert np.max(np.linalg.norm(w, axis=1)) > 250 * D2R
    assert rot_angle(integrate_rotation(w, fs), Rt) < 2e-6


def test_integrate_rotation_short_and_bad_input():
    np.testing.assert_array_equal(integrate_rotation(np.zeros((1, 3)), 100.0), np.eye(3))
    with pytest.raises(CalibrationError):
        integrate_rotation(np.zeros((5, 2)), 100.0)
    with pytest.raises(CalibrationError):
        integrate_rotation(np.full((5, 3), np.nan), 100.0)


# ---------------------------------------------------------------------------- gyro_bias
def _bias_mc(runs, fs, dur, seed, filt=None, rrw=0.0, pass_rrw=False):
    rng = np.random.default_rng(seed)
    n = int(fs * dur)
    err, sig, naive = [], [], []
    for _ in range(runs):
        w = rng.normal(0.0, ND * math.sqrt(fs), (n, 3))
        if filt is not None:
            w = signal.lfilter(*filt, w, axis=0)
        b = np.broadcast_to(B_TRUE, (n, 3))
        truth = B_TRUE
        if rrw:
            b = b + np.cumsum(rng.normal(0.0, rrw / math.sqrt(fs), (n, 3)), axis=0)
            truth = b[-1]                                     # the bias when the rest ends
        f = gyro_bias(b + w, fs, rate_random_walk=rrw if pass_rrw else None)
        err.append(f.b - truth)
        sig.append(f.sigma_b)
        naive.append(f.extra["sigma_white_rad_s"])
    return np.array(err), np.array(sig), np.array(naive)


def test_gyro_bias_white_noise_monte_carlo():
    err, sig, _ = _bias_mc(400, 200.0, 20.0, seed=1)
    assert np.mean(np.abs(err / sig) < 3) >= 0.99
    r = sigma_ratio(err, sig)
    assert np.all((r > 0.8) & (r < 1.2)), r
    # and the sigma is the white-noise one: N/√T
    np.testing.assert_allclose(np.sqrt(np.mean(sig**2, axis=0)), ND / math.sqrt(20.0), rtol=0.05)


def test_gyro_bias_oversampled_filtered_noise():
    """At 2 kHz behind a 77.5 Hz filter, consecutive samples are correlated: std/√n is ~3x
    too small; the Allan-based sigma matches the spread."""
    filt = signal.butter(1, 77.5, fs=2000.0)
    err, sig, naive = _bias_mc(200, 2000.0, 8.0, seed=2, filt=filt)
    r = sigma_ratio(err, sig)
    assert np.all((r > 0.8) & (r < 1.2)), r
    assert np.mean(np.abs(err / sig) < 3) >= 0.99
    assert np.all(sigma_ratio(err, naive) > 2.0)


def test_gyro_bias_known_random_walk():
    """With K given, sigma covers the bias at the end of the rest: N²/T + K²T/3."""
    K = 3 * ND / 20.0                                         # RW term 3x the white one at 20 s
    err, sig, _ = _bias_mc(300, 200.0, 20.0, seed=3, rrw=K, pass_rrw=True)
    r = sigma_ratio(err, sig)
    assert np.all((r > 0.8) & (r < 1.2)), r
    assert np.mean(np.abs(err / sig) < 3) >= 0.99
    f = gyro_bias(np.random.default_rng(0).normal(0, ND * math.sqrt(200), (4000, 3)), 200.0,
                  rate_random_walk=K)
    np.testing.assert_allclose(f.extra["best_duration_s"], math.sqrt(3) * ND / K, rtol=0.1)


def test_gyro_bias_result_shape_and_checks():
    rng = np.random.default_rng(4)
    u = B_TRUE + rng.normal(0, ND * math.sqrt(200), (2000, 3))
    f = gyro_bias(u, 200.0)
    assert isinstance(f, TriadFit) and f.method == "bias"
    np.testing.assert_array_equal(f.m, np.eye(3))
    assert np.all(np.isnan(f.cov[:9])) and np.all(np.isnan(f.cov[:, :9]))
    assert np.all(np.isfinite(f.cov[9:, 9:]))
    np.testing.assert_array_equal(f.estimated, [False] * 9 + [True] * 3)
    assert np.all(np.abs(f.extra["drift_z"]) < 4)
    np.testing.assert_allclose(f.extra["noise_density_rad_s_rthz"], ND, rtol=0.15)
    bumped = u.copy()
    bumped[1000:1020, 1] += 20 * D2R
    with pytest.raises(CalibrationError, match="not at rest.*Y"):
        gyro_bias(bumped, 200.0)
    with pytest.raises(CalibrationError, match="too short"):
        gyro_bias(u[:10], 200.0)


# ---------------------------------------------------------------------------- turntable
TT_PLAN = [(axis, r * D2R) for axis in (EX, EY, EZ) for r in (30, -30, 90, -90)]


def _tt_segments(rng, plan=TT_PLAN, fs=200.0, dur=3.0):
    n = int(fs * dur)
    return [TurntableSegment(w * a @ M_TRUE.T + B_TRUE + rng.normal(0, ND * math.sqrt(fs), (n, 3)),
                             a, w) for a, w in plan]


@pytest.mark.parametrize("with_rest", [False, True])
def test_turntable_monte_carlo(with_rest):
    rng = np.random.default_rng(20 + with_rest)
    err, sig = [], []
    for _ in range(200):
        bias = None
        if with_rest:
            bias = gyro_bias(B_TRUE + rng.normal(0, ND * math.sqrt(200), (2000, 3)), 200.0)
        f = turntable(_tt_segments(rng), bias=bias)
        err.append(np.concatenate([(f.m - M_TRUE).ravel(), f.b - B_TRUE]))
        sig.append(np.concatenate([f.sigma_m.ravel(), f.sigma_b]))
    err, sig = np.array(err), np.array(sig)
    assert np.mean(np.abs(err / sig) < 3) >= 0.99
    r = sigma_ratio(err, sig)
    assert np.all((r > 0.8) & (r < 1.2)), r
    assert f.method == "turntable" and f.estimated.all()
    assert f.residuals.shape == (len(TT_PLAN), 3)
    assert f.dof == 3 * len(TT_PLAN) - (9 if with_rest else 12)
    assert f.extra["bias_source"] == ("rest" if with_rest else "segments")


def test_turntable_single_direction_not_observable():
    """Decided by the numbers: one rate per axis with b fitted leaves scale and bias inseparable
    (named); two different rates in the same direction separate them."""
    rng = np.random.default_rng(30)
    plan = [(a, w) for a, w in TT_PLAN if w > 0]
    same_rate = [(a, w) for a, w in plan if abs(w) == max(abs(w) for _, w in plan)]
    with pytest.raises(NotObservable, match=r"bias and the response to rotation about board X, Y, Z cannot be "
                                            r"separated \(σ unbounded\)"):
        turntable(_tt_segments(rng, same_rate))
    if len({abs(w) for _, w in plan}) > 1:
        f = turntable(_tt_segments(rng, plan))
        assert np.all(np.abs(f.m - M_TRUE) < 5 * f.sigma_m)
    # with the bias from a rest recording one direction suffices
    bias = gyro_bias(B_TRUE + rng.normal(0, ND * math.sqrt(200), (2000, 3)), 200.0)
    f = turntable(_tt_segments(rng, [(a, w) for a, w in TT_PLAN if w > 0]), bias=bias)
    assert np.all(np.abs(f.m - M_TRUE) < 5 * f.sigma_m)


def test_turntable_not_spanning_and_wrong_sign():
    rng = np.random.default_rng(31)
    bias = gyro_bias(B_TRUE + rng.normal(0, ND * math.sqrt(200), (2000, 3)), 200.0)
    plan = [(a, w) for a, w in TT_PLAN if not a[2]]
    with pytest.raises(NotObservable, match="span 3-D"):
        turntable(_tt_segments(rng, plan), bias=bias)
    segs = _tt_segments(rng)
    segs[5] = segs[5]._replace(table_rate_rad_s=-segs[5].table_rate_rad_s)   # sign mix-up
    with pytest.raises(CalibrationError, match="segment 5.*sign"):
        turntable(segs)


def test_turntable_given_sigma_and_tuples():
    rng = np.random.default_rng(32)
    segs = [(s.rates, s.axis, s.table_rate_rad_s, ND * math.sqrt(1 / 3.0))
            for s in _tt_segments(rng)]
    f = turntable(segs)
    np.testing.assert_allclose(f.extra["segment_sigma_rad_s"], ND / math.sqrt(3.0))
    assert np.all(np.abs(f.m - M_TRUE) < 4 * f.sigma_m)


# ---------------------------------------------------------------------------- rotation method
GRAV_SIGMA = 2.5e-5                    # rad: ADXL355 direction noise after ~1 s of averaging


def test_rotation_method_monte_carlo(traj200):
    x, iv, up, rest = traj200
    fs = 200.0
    clean = x @ M_TRUE.T + B_TRUE
    rng = np.random.default_rng(40)
    err, sig, chi2 = [], [], []
    for _ in range(100):
        u = clean + rng.normal(0, ND * math.sqrt(fs), x.shape)
        g = up + rng.normal(0, GRAV_SIGMA, up.shape)
        bias = gyro_bias(u[rest], fs)
        f = rotation_method(u, fs, iv, g, bias, gravity_sigma=GRAV_SIGMA)
        err.append((f.m - M_TRUE).ravel())
        sig.append(f.sigma_m.ravel())
        chi2.append(f.extra["reduced_chi2"])
    err, sig = np.array(err), np.array(sig)
    assert np.mean(np.abs(err / sig) < 3) >= 0.99
    r = sigma_ratio(err, sig)
    assert np.all((r > 0.8) & (r < 1.2)), r
    assert 0.85 < np.mean(chi2) < 1.15
    assert f.method == "rotation" and f.dof == 2 * len(MOTIONS) - 9
    assert f.residuals.shape == (len(MOTIONS),)
    assert np.all(f.extra["angle_residuals_deg"] < 0.1)
    assert np.max(f.extra["angle_residuals_initial_deg"]) > 1.0   # the fit did something
    np.testing.assert_array_equal(f.estimated, [True] * 12)      # b carried from the rest fit
    np.testing.assert_array_equal(f.b, bias.b)


def test_rotation_method_fast_motions_high_rate(monkeypatch):
    """1 kHz, turns at up to 280 °/s; analytic Jacobians agree with finite differences."""
    monkeypatch.setattr(G, "_CHECK_JACOBIAN", True)
    fs = 1000.0
    x, iv, up, rest = trajectory(fs, peak_dps=280.0, static_s=0.5)
    assert np.max(np.abs(x)) > 250 * D2R
    rng = np.random.default_rng(41)
    u = x @ M_TRUE.T + B_TRUE + rng.normal(0, ND * math.sqrt(fs), x.shape)
    f = rotation_method(u, fs, iv, up, gyro_bias(u[rest], fs))
    assert np.all(np.abs(f.m - M_TRUE) < 4 * f.sigma_m)
    assert max(f.extra["jacobian_check"]) < 1e-3


def test_rotation_method_noise_free_exact(traj200):
    x, iv, up, _ = traj200
    f = rotation_method(x @ M_TRUE.T + B_TRUE, 200.0, iv, up, B_TRUE)
    np.testing.assert_allclose(f.m, M_TRUE, atol=1e-8)
    assert f.extra["bias_source"] == "given" and not f.estimated[9:].any()
    assert np.all(np.isnan(f.cov[9:, 9:]))


def test_rotation_method_no_z_turns_not_observable():
    xy = [[(X, 90)], [(Y, 90)], [(X, -90)], [(Y, -90)], [(X, 180)], [(Y, -180)],
          [(X, 90)], [(Y, 90)], [(X, -90)], [(Y, -90)], [(X, 45), (Y, 45)], [(X, -60)]]
    x, iv, up, _ = trajectory(200.0, xy, rest_s=1.0)
    with pytest.raises(NotObservable, match=r"m02, m12, m22 undetermined \(σ unbounded\): no turn about board Z"
                                            r".*third column"):
        rotation_method(x, 200.0, iv, up, np.zeros(3))


def test_rotation_method_z_turns_only_about_vertical():
    """Turning about Z while Z is vertical does not move gravity: still not observable."""
    mv = [[(Z, 90)], [(Z, -90)], [(Z, 90)], [(Z, -90)], [(X, 90)], [(X, -90)], [(Y, 90)],
          [(Y, -90)]]
    x, iv, up, _ = trajectory(200.0, mv, rest_s=1.0)
    with pytest.raises(NotObservable, match="m22 undetermined .σ unbounded.: no turn about board Z with Z off the vertical"):
        rotation_method(x, 200.0, iv, up, np.zeros(3))


def test_rotation_method_one_way_turns_fit_when_the_bias_is_known():
    """Every axis turned one way only (as by hand on a real recording): with the rest bias and its
    σ the scale is constrained; the fit is within its σ, which grows with the bias's σ."""
    one = [[(X, 90)], [(Y, 90)], [(Z, 90)], [(X, 90)], [(Y, 90)], [(Z, 90)], [(X, 90), (Y, 45)],
           [(Y, 90)], [(Z, 90)], [(X, 90)], [(Y, 90), (Z, 30)], [(Z, 90)], [(X, 90)], [(Y, 90)]]
    fs = 200.0
    x, iv, up, rest = trajectory(fs, one, rest_s=1.0)
    rng = np.random.default_rng(42)
    u = x @ M_TRUE.T + B_TRUE + rng.normal(0, ND * math.sqrt(fs), x.shape)
    bias = gyro_bias(u[rest], fs)
    f = rotation_method(u, fs, iv, up, bias, max_sigma=0.05)
    assert np.all(np.abs(f.m - M_TRUE) < 4 * f.sigma_m)
    assert np.all(f.sigma_m < 0.05)
    with pytest.raises(NotObservable, match=r"known only to σ .*\(limit 1e-05; worst m\d\d\)"):
        rotation_method(u, fs, iv, up, bias, max_sigma=1e-5)


def test_rotation_method_too_few():
    x, iv, up, _ = trajectory(200.0, MOTIONS[:4], rest_s=1.0)
    with pytest.raises(NotObservable, match="4 motion.*at least 6"):
        rotation_method(x, 200.0, iv, up, np.zeros(3))


def test_rotation_method_reversed_axis_and_clipping(traj200):
    x, iv, up, _ = traj200
    flipped = x.copy()
    flipped[:, 2] *= -1
    with pytest.raises(CalibrationError, match="gyro axis Z reversed"):
        rotation_method(flipped, 200.0, iv, up, np.zeros(3))
    with pytest.raises(CalibrationError, match="clipped"):
        rotation_method(x * 2.0, 200.0, iv, up, np.zeros(3))


def test_rotation_method_input_checks(traj200):
    x, iv, up, _ = traj200
    with pytest.raises(CalibrationError, match="gravity_dirs"):
        rotation_method(x, 200.0, iv, up[:-1], np.zeros(3))
    bad = list(iv)
    bad[3], bad[4] = bad[4], bad[3]
    with pytest.raises(CalibrationError, match="overlap or are out of order"):
        rotation_method(x, 200.0, bad, up, np.zeros(3))


# ---------------------------------------------------------------------------- g-sensitivity
def test_gsens_recovered_within_sigma_and_refused_when_attitudes_cannot_separate_it():
    from imubench.calib.gsens import DPS, fit_gsens
    rng = np.random.default_rng(50)
    G_true = rng.normal(0, 0.03, (3, 3)) / DPS                     # rad/s per g, ADXRS450-like
    b_true = np.radians([0.5, -0.3, 0.2])
    faces = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    corners = rng.normal(size=(8, 3))
    f = np.vstack([faces, corners / np.linalg.norm(corners, axis=1)[:, None]])
    sig = np.full((len(f), 3), np.radians(0.002))
    z = []
    for _ in range(200):
        u = b_true + f @ G_true.T + rng.normal(0, 1, f.shape) * sig
        fit = fit_gsens(u, sig, f)
        z.append(((fit.g - G_true) / fit.sigma_g).ravel())
    z = np.array(z)
    assert np.mean(np.abs(z) < 3) > 0.98 and 0.8 < np.std(z) < 1.25
    assert fit.significant and "resolved" in fit.summary()
    np.testing.assert_allclose(fit.bias(f[:2]), b_true + f[:2] @ G_true.T, atol=np.radians(0.01))
    # no g-sensitivity: not resolved (jointly), most of the time
    ps = [fit_gsens(b_true + rng.normal(0, 1, f.shape) * sig, sig, f).p_zero for _ in range(100)]
    assert np.mean(np.array(ps) < 0.01) < 0.05
    # rests only with Z up or down (turned about Z): G's X and Y columns cannot be told from b
    flat = np.array([[0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1]], float)
    with pytest.raises(NotObservable, match=r"cannot separate .*σ unbounded"):
        fit_gsens(np.zeros((6, 3)), np.full((6, 3), 1e-4), flat)
    with pytest.raises(NotObservable, match="4 rests"):
        fit_gsens(np.zeros((4, 3)), np.full((4, 3), 1e-4), faces[:4])


def test_rotation_residuals_of_a_given_m_match_the_fit(traj200):
    x, iv, up, rest = traj200
    fs = 200.0
    rng = np.random.default_rng(51)
    u = x @ M_TRUE.T + B_TRUE + rng.normal(0, ND * math.sqrt(fs), x.shape)
    bias = gyro_bias(u[rest], fs)
    f = rotation_method(u, fs, iv, up, bias, exclude_motions=[3, 7])
    ang = G.rotation_residuals(u, fs, iv, up, f.m, bias.b)
    keep = [j for j in range(len(iv) - 1) if j not in (3, 7)]
    np.testing.assert_allclose(ang[keep], f.extra["angle_residuals_deg"], atol=1e-9)
    assert np.all(ang[[3, 7]] < 0.1)                # held out: the truth-like M predicts them too
    # a per-motion bias: the bias g-sensitivity predicts, here the true one: same fit
    f2 = rotation_method(u, fs, iv, up, bias, motion_bias=np.broadcast_to(B_TRUE, (len(iv) - 1, 3)))
    assert np.all(np.abs(f2.m - M_TRUE) < 4 * f2.sigma_m) and f2.extra["motion_bias"] == "given per motion"


def test_turntable_with_g_sensitivity_takes_g_f_off_each_segment():
    """Segments in several attitudes with a g-sensitive gyro: without G the fit is biased by
    G·f; with G (and each segment's specific force) it is within its σ of the truth."""
    from imubench.calib.gsens import DPS
    rng = np.random.default_rng(52)
    G_true = np.full((3, 3), 0.05) / DPS + np.diag([0.1, -0.1, 0.08]) / DPS
    segs = []
    for k, (a, w) in enumerate(TT_PLAN):
        f = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, -1]][k % 4], float)
        n = 600
        u = w * a @ M_TRUE.T + B_TRUE + G_true @ f + rng.normal(0, ND * math.sqrt(200), (n, 3))
        segs.append(TurntableSegment(u, a, w, None, f))
    fit = turntable(segs, gsens=G_true)
    assert np.all(np.abs(fit.m - M_TRUE) < 4 * fit.sigma_m) and np.all(np.abs(fit.b - B_TRUE) < 4 * fit.sigma_b)
    plain = turntable([s._replace(specific_force_g=None) for s in segs])
    assert np.abs((plain.b - B_TRUE) / plain.sigma_b).max() > 4 or plain.extra["cov_scaled"]
    with pytest.raises(CalibrationError, match="segment 0 has no specific_force_g"):
        turntable([s._replace(specific_force_g=None) for s in segs], gsens=G_true)
