"""Accelerometer calibration (imubench.calib.accel) and static detection (imubench.calib.static)
on synthetic data from known truths. Deterministic (seeded); the whole file runs in seconds.

Truth: M = I + U(−1 %, +1 %) in every entry (scale and cross-axis), b up to ±25 mg; white
noise of the ADXL355, 22.5 µg/√Hz, 2 s per pose at 1 kHz unless a test says otherwise (the
mean of a pose then has σ = 22.5/√2 = 15.9 µg, whatever the rate).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from imubench.calib import CalibrationError, NotObservable, TriadFit
from imubench.calib.accel import (
    FACES,
    MULTI_PARAM_NAMES,
    POSE_PLAN,
    check_observability,
    lower_triangular_form,
    match_plan,
    multi_params_to_mb,
    multi_position,
    pose_table,
    six_position,
)
from imubench.calib.static import (
    NotEnoughStatic,
    StaticIntervals,
    detect_static,
    interval_stats,
    moving_variance,
    require_static,
    rest_noise,
)
from imubench.calib.stillness import StillnessDetector
from imubench.units import G0_MPS2 as G0
from scipy.signal import lfilter

N_WHITE = 22.5e-6 * G0          # ADXL355 white noise, m/s²/√Hz
PLAN_DIRS = np.array([p.direction for p in POSE_PLAN])
I26 = list(range(26))
I18 = list(range(18))                                  # faces + edges
I12 = list(range(6)) + list(range(18, 24))             # faces + 6 corners
LSB_PER_G = 256000.0


# --------------------------------------------------------------------------------------------
# synthetic data
# --------------------------------------------------------------------------------------------

def rot(rng, max_deg):
    """A random rotation by an angle up to max_deg about a random axis."""
    ax = rng.standard_normal(3)
    ax /= np.linalg.norm(ax)
    ang = math.radians(max_deg) * rng.uniform(0, 1)
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def make_truth(rng, scale=0.01, bias_g=0.025):
    M = np.eye(3) + rng.uniform(-scale, scale, (3, 3))
    b = rng.uniform(-bias_g, bias_g, 3) * G0
    return M, b


def attitudes(rng, idx, tilt_deg=0.0):
    """True specific force (m/s²) at the planned attitudes idx, each tilted by up to tilt_deg."""
    d = PLAN_DIRS[idx]
    if tilt_deg > 0:
        d = np.array([rot(rng, tilt_deg) @ v for v in d])
    return d * G0


def measure(rng, M, b, x, T=2.0, fs=1000.0):
    """Pose means and their sigma as a static detector would report them (std/√n, with the std
    itself estimated from n samples), drawn directly (same distribution as averaging samples)."""
    n = int(T * fs)
    s = N_WHITE * math.sqrt(fs)
    u = x @ M.T + b
    means = u + rng.standard_normal(u.shape) * s / math.sqrt(n)
    std = s * np.sqrt(rng.chisquare(n - 1, u.shape) / (n - 1))
    return means, std / math.sqrt(n)


def recording(dirs, fs, hold_s=3.0, move_s=1.0, lead_s=3.0, noise=N_WHITE, seed=0, M=None, b=None):
    """Samples (n, 3) of holds at the given gravity directions joined by smooth moves (with a
    5 % dynamic acceleration), and the true [start, stop) of each hold."""
    rng = np.random.default_rng(seed)
    M = np.eye(3) if M is None else M
    b = np.zeros(3) if b is None else b
    parts, holds, pos = [], [], 0
    dirs = [np.asarray(d, float) / np.linalg.norm(d) for d in dirs]
    for i, d in enumerate(dirs):
        n = int(round((lead_s if i == 0 else hold_s) * fs))
        parts.append(np.tile(d * G0, (n, 1)))
        holds.append((pos, pos + n))
        pos += n
        if i + 1 < len(dirs):
            m = int(round(move_s * fs))
            t = np.linspace(0, 1, m + 2)[1:-1]
            s = 0.5 - 0.5 * np.cos(np.pi * t)
            v = (1 - s)[:, None] * d + s[:, None] * dirs[i + 1]
            v /= np.linalg.norm(v, axis=1)[:, None]
            parts.append(v * G0 * (1 + 0.05 * np.sin(np.pi * t))[:, None])
            pos += m
    x = np.vstack(parts)
    u = x @ M.T + b
    return u + rng.standard_normal(u.shape) * noise * math.sqrt(fs), holds


def params12(fit):
    return np.r_[fit.m.ravel(), fit.b]


# --------------------------------------------------------------------------------------------
# static detection
# --------------------------------------------------------------------------------------------

HOLD_DIRS = [[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, 1, 0], [1, 1, 1]]


def test_moving_variance_matches_a_direct_computation():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((200, 3)) + 1e4          # a large offset, as counts have
    for w in (3, 11, 51):
        h = w // 2
        got = moving_variance(a, w)
        want = np.array([a[max(0, i - h):i + h + 1].var(axis=0, ddof=1) for i in range(len(a))])
        assert np.allclose(got, want, rtol=1e-9)
        got = moving_variance(a, w, centred=False)
        want = np.array([a[i - w + 1:i + 1].var(axis=0, ddof=1) for i in range(w - 1, len(a))])
        assert np.allclose(got, want, rtol=1e-9)


@pytest.mark.parametrize("fs", [20, 100, 1000, 4000])
def test_rest_noise_matches_the_sensor_noise(fs):
    a, _ = recording(HOLD_DIRS, fs, seed=1)
    sigma = N_WHITE * math.sqrt(fs)
    est = rest_noise(a, fs)
    assert np.all(np.abs(est / sigma - 1) < 0.15), est / sigma


@pytest.mark.parametrize("fs", [20, 100, 1000, 4000])
@pytest.mark.parametrize("noisy", [True, False])
def test_detect_static_finds_every_hold(fs, noisy):
    noise = N_WHITE if noisy else 0.0
    a, holds = recording(HOLD_DIRS, fs, noise=noise, seed=2)
    iv = detect_static(a, fs)
    assert isinstance(iv, StaticIntervals) and len(iv) == len(holds), [(i.start, i.stop) for i in iv]
    w = 0.5 * fs
    for it, (s, e), d in zip(iv, holds, HOLD_DIRS):
        assert s <= it.start < it.stop <= e                       # no motion sample inside
        assert it.n == it.stop - it.start >= (e - s) - 2.5 * w - 2   # loses at most ~a window per edge
        truth = np.asarray(d, float) / np.linalg.norm(d) * G0
        if noisy:
            assert np.all(np.abs(it.mean - truth) < 5 * it.sigma_mean)
            assert np.all(it.sigma_mean >= it.std / math.sqrt(it.n) * 0.999)
            assert it.clean
        else:
            assert np.allclose(it.mean, truth, atol=1e-9)
    assert 2.0 <= iv.k <= 10.0


def test_detect_static_never_merges_across_a_gentle_move():
    """Two holds 3° apart, joined by a slow 1 s tilt: two intervals, none spanning the move."""
    fs = 100
    d1 = np.array([0, 0, 1.0])
    d2 = np.array([math.sin(math.radians(3)), 0, math.cos(math.radians(3))])
    a, holds = recording([d1, d2, d1], fs, move_s=1.0, seed=3)
    iv = detect_static(a, fs)
    assert len(iv) == 3
    for it, (s, e) in zip(iv, holds):
        assert s <= it.start and it.stop <= e


def test_detect_static_auto_k_follows_noisier_holds():
    """The holds are 3x noisier than the rest at the start (a hand on the board): k = 2 finds
    almost nothing, the automatic k finds every hold, clean."""
    fs = 200
    a, holds = recording(HOLD_DIRS, fs, hold_s=4, lead_s=10, seed=4)
    rng = np.random.default_rng(5)
    a[holds[0][1]:] += rng.standard_normal(a[holds[0][1]:].shape) * N_WHITE * math.sqrt(fs) * 2.8
    assert len(detect_static(a, fs, k=2)) < 3
    iv = detect_static(a, fs)
    assert len(iv) == len(holds) and iv.k_auto and iv.k > 2
    assert all(it.clean for it in iv)
    for it, (s, e) in zip(iv, holds):
        assert s <= it.start and it.stop <= e


def test_detect_static_quantised_counts_without_noise():
    fs = 200
    a, holds = recording(HOLD_DIRS, fs, noise=0.0, seed=6)
    counts = np.round(a / G0 * LSB_PER_G)
    iv = detect_static(counts, fs)
    assert len(iv) == len(holds)


def test_not_enough_static_explains_itself():
    fs = 100
    a, holds = recording(HOLD_DIRS, fs, hold_s=1.2, lead_s=3.0, seed=7)
    iv = detect_static(a, fs)
    assert len(iv) < 6
    with pytest.raises(NotEnoughStatic) as ei:
        require_static(iv, 6)
    e = ei.value
    msg = str(e)
    assert isinstance(e, CalibrationError)
    assert f"found {len(iv)} still interval" in msg and "6 needed" in msg
    assert "dropped as under 1.0 s" in msg                 # the short holds and how long they were
    assert f"k = {iv.k:.1f}" in msg and "rest noise" in msg
    assert "hold each pose at least" in msg
    assert e.found == len(iv) and e.needed == 6 and len(e.short_s) >= 1 and e.hold_s >= 2
    assert require_static(iv, len(iv)) is iv


def test_stillness_detector_states_and_mean():
    for fs, noise in ((100, N_WHITE), (1000, N_WHITE), (20, N_WHITE), (100, 0.0)):
        dirs = [[0, 0, 1], [1, 0, 0], [0, 1, 0]]
        a, holds = recording(dirs, fs, hold_s=3, move_s=1.5, noise=noise, seed=8)
        det = StillnessDetector(fs, rest_noise(a, fs))
        chunk = max(1, fs // 20)
        seen = {}
        for i in range(0, len(a), chunk):
            st = det.update(a[i:i + chunk])
            seen[i + chunk] = st
        # well inside each hold (after a window and the settle time): still
        for s, e in holds:
            t = (e // chunk) * chunk
            assert seen[t].state == "still", (fs, t, seen[t])
        # in the middle of each move: moving
        for (s0, e0), (s1, e1) in zip(holds, holds[1:]):
            mid = ((e0 + s1) // 2 // chunk) * chunk
            assert seen[mid].state == "moving", (fs, mid, seen[mid])
        last = seen[max(seen)]
        assert last.state == "still"
        truth = np.array([0, 1.0, 0]) * G0
        if noise:
            assert np.all(np.abs(last.mean - truth) < 5 * last.sigma_mean)
        else:
            assert np.allclose(last.mean, truth, atol=1e-9)
        assert last.still_s > 2.0


def test_interval_stats_sigma_of_the_mean_with_correlated_noise():
    """AR(1) noise, φ = 0.8 (τ = 9): sigma_mean follows the true spread of the mean."""
    rng = np.random.default_rng(9)
    phi, n = 0.8, 2000
    means, sig = [], []
    for _ in range(200):
        x = lfilter([1.0], [1.0, -phi], rng.standard_normal((n + 200, 3)), axis=0)
        m, s, sm = interval_stats(x[200:])
        means.append(m)
        sig.append(sm)
    ratio = np.std(means, axis=0) / np.mean(sig, axis=0)
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    white = [interval_stats(rng.standard_normal((n, 3))) for _ in range(20)]     # white: std/√n
    ratio = np.mean([sm / (s / math.sqrt(n)) for _, s, sm in white], axis=0)
    assert np.all((ratio >= 1) & (ratio < 1.1)), ratio


# --------------------------------------------------------------------------------------------
# pose plan
# --------------------------------------------------------------------------------------------

def test_pose_plan():
    names = [p.name for p in POSE_PLAN]
    assert len(POSE_PLAN) == 26 and len(set(names)) == 26
    for n in ("+Z up (level)", "-Z up (upside down)", "+X+Z edge", "+X+Y+Z corner", "-X-Y-Z corner"):
        assert n in names
    assert np.allclose(np.linalg.norm(PLAN_DIRS, axis=1), 1)
    ang = np.degrees(np.arccos(np.clip(PLAN_DIRS @ PLAN_DIRS.T, -1, 1)))
    np.fill_diagonal(ang, 180)
    assert 35 < ang.min() and np.all(ang.min(axis=1) <= 45.01)
    assert POSE_PLAN[0].direction == (0.0, 0.0, 1.0)        # level reads +g on Z


def test_match_plan():
    rng = np.random.default_rng(10)
    M, b = make_truth(rng)
    u, _ = measure(rng, M, b, attitudes(rng, I18, tilt_deg=5))
    off = np.array([[math.sin(math.radians(22.5)), 0, math.cos(math.radians(22.5))]]) * G0   # 22.5° from +Z and +X+Z
    covered, missing, unmatched = match_plan(np.vstack([u, off]))
    assert covered == [p.name for p in POSE_PLAN[:18]]
    assert missing == [p.name for p in POSE_PLAN[18:]]
    assert unmatched == [18]


# --------------------------------------------------------------------------------------------
# six-position
# --------------------------------------------------------------------------------------------

def test_six_position_recovers_truth():
    rng = np.random.default_rng(11)
    M, b = make_truth(rng)
    order = [4, 0, 3, 1, 5, 2]                               # any order of the faces
    u, s = measure(rng, M, b, attitudes(rng, order))
    f = six_position(u, s)
    assert f.method == "six_position" and f.dof == 6 and f.residuals.shape == (6, 3)
    assert f.cov.shape == (12, 12) and np.all(f.estimated)
    z = (params12(f) - np.r_[M.ravel(), b]) / np.sqrt(np.diag(f.cov))
    assert np.all(np.abs(z) < 3), z
    assert f.extra["faces"] == ["+Y", "+Z", "-X", "-Z", "-Y", "+X"]
    # same data as ±2 g counts, g in counts: same M, b in counts, same relative uncertainty
    c = LSB_PER_G / G0
    fc = six_position(u * c, s * c, g=LSB_PER_G)
    assert np.allclose(fc.m, f.m, rtol=0, atol=1e-10)
    assert np.allclose(fc.b / c, f.b, rtol=0, atol=1e-9)
    assert np.allclose(fc.sigma_m, f.sigma_m, rtol=1e-9)


def test_six_position_each_face_twice():
    rng = np.random.default_rng(12)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, list(range(6)) * 2))
    f = six_position(u, s)
    assert f.dof == 24
    z = (params12(f) - np.r_[M.ravel(), b]) / np.sqrt(np.diag(f.cov))
    assert np.all(np.abs(z) < 3.5), z


def test_six_position_monte_carlo():
    """1000 runs, one truth: estimates within 3σ in ≥ 99 % of (run, parameter) pairs; the
    reported σ (mean over runs) agrees with the runs' spread within 20 % for all 12."""
    rng = np.random.default_rng(13)
    M, b = make_truth(rng)
    x = attitudes(rng, list(range(6)))
    truth = np.r_[M.ravel(), b]
    est, sig = [], []
    for _ in range(1000):
        u, s = measure(rng, M, b, x)
        f = six_position(u, s)
        est.append(params12(f))
        sig.append(np.sqrt(np.diag(f.cov)))
    est, sig = np.array(est), np.array(sig)
    coverage = np.mean(np.abs(est - truth) <= 3 * sig)
    ratio = est.std(axis=0) / sig.mean(axis=0)
    assert coverage >= 0.99, coverage
    assert np.all(np.abs(ratio - 1) <= 0.2), ratio


def test_tilted_faces_bias_six_position_not_multi_position():
    """Faces tilted by up to 5°: six-position, which assumes ±g exactly on one axis, is biased
    (cross-axis terms by a few %, biases by ~10–25 mg: thousands of noise sigmas; its χ²
    flags it); multi-position on the same tilted poses is not (|a| = g needs no alignment)."""
    rng = np.random.default_rng(14)
    M, b = make_truth(rng)
    x = attitudes(rng, I26, tilt_deg=5.0)
    # noise-free: the bias itself
    f0 = six_position(x[:6] @ M.T + b, None)
    err = params12(f0) - np.r_[M.ravel(), b]
    off = [1, 2, 3, 5, 6, 7]
    assert np.max(np.abs(err[off])) > 0.01                  # > 1 % cross-axis error
    assert np.max(np.abs(err[9:])) > 0.001 * G0             # > 1 mg bias error
    u, s = measure(rng, M, b, x)
    f6 = six_position(u[:6], s[:6], chi2_scaling="never")   # σ from the noise alone
    z6 = (params12(f6) - np.r_[M.ravel(), b]) / np.sqrt(np.diag(f6.cov))
    assert np.max(np.abs(z6)) > 100
    assert f6.extra["chi2_red"] > 100
    fm = multi_position(u, s)
    L, _ = lower_triangular_form(M)
    k = fm.estimated
    zm = (params12(fm) - np.r_[L.ravel(), b])[k] / np.sqrt(np.diag(fm.cov))[k]
    assert np.all(np.abs(zm) < 3.5), zm


def test_missing_and_repeated_faces_are_named():
    rng = np.random.default_rng(15)
    M, b = make_truth(rng)
    # faces: +X, +X, -X, +Y, +X, -Z  → missing -Y, +Z; +X repeated (poses 1, 2 and 5)
    idx = [2, 2, 3, 4, 2, 1]
    u, s = measure(rng, M, b, attitudes(rng, idx))
    with pytest.raises(NotObservable) as ei:
        six_position(u, s)
    assert "missing faces: -Y, +Z; repeated: +X (poses 1, 2 and 5)" in str(ei.value)
    # five poses: -X, +X, +Y, -Z, +X
    u, s = measure(rng, M, b, attitudes(rng, [3, 2, 4, 1, 2]))
    with pytest.raises(CalibrationError) as ei:
        six_position(u, s)
    assert str(ei.value).startswith("missing faces: -Y, +Z; repeated: +X (poses 2 and 5).")


def test_six_position_rejects_a_non_face_pose():
    rng = np.random.default_rng(16)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, list(range(6)) + [18]))
    with pytest.raises(CalibrationError, match=r"pose 7 \(5\d°\)"):
        six_position(u, s)
    f = six_position(u, s, skip_non_faces=True)
    assert f.extra["skipped_poses"] == [6]


def test_unit_mismatch_is_explained():
    rng = np.random.default_rng(17)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, I26))
    c = LSB_PER_G / G0
    with pytest.raises(CalibrationError, match="same unit"):
        multi_position(u * c, s * c)                         # counts with g in m/s²
    with pytest.raises(CalibrationError, match="same unit"):
        six_position(u[:6] * c, s[:6] * c)


# --------------------------------------------------------------------------------------------
# multi-position
# --------------------------------------------------------------------------------------------

def test_multi_position_parametrisation():
    theta = np.array([0.1, -0.2, 0.3, 1.01, 0.99, 1.005, 0.002, -0.003, 0.004])
    M, b = multi_params_to_mb(theta)
    assert np.allclose(np.triu(M, 1), 0)
    assert np.allclose(np.diag(M), theta[3:6])
    assert np.isclose(M[1, 0], 0.99 * 0.002) and np.isclose(M[2, 0], 1.005 * -0.003)
    assert np.isclose(M[2, 1], 1.005 * 0.004) and np.allclose(b, theta[:3])
    rng = np.random.default_rng(18)
    Mt, _ = make_truth(rng)
    L, Q = lower_triangular_form(Mt)
    assert np.allclose(L @ Q, Mt) and np.allclose(Q @ Q.T, np.eye(3)) and np.allclose(np.triu(L, 1), 0)


@pytest.mark.parametrize("idx", [I26, I18, I12], ids=["26", "18", "12"])
def test_multi_position_recovers_truth(idx):
    rng = np.random.default_rng(19 + len(idx))
    M, b = make_truth(rng)
    L, _ = lower_triangular_form(M)
    u, s = measure(rng, M, b, attitudes(rng, idx, tilt_deg=5))
    f = multi_position(u, s)
    assert f.method == "multi_position" and f.dof == len(idx) - 9 and f.residuals.shape == (len(idx),)
    k = f.estimated
    assert k.sum() == 9 and not k[1] and not k[2] and not k[5]
    assert np.all(np.diag(f.cov)[~k] == 0)                  # fixed by the frame convention
    z = (params12(f) - np.r_[L.ravel(), b])[k] / np.sqrt(np.diag(f.cov))[k]
    assert np.all(np.abs(z) < 3), z
    # |a| residual after calibration: within 1.5x the noise of the averaged data
    floor = math.sqrt(np.mean(s ** 2))
    assert f.residual_rms <= 1.5 * floor, (f.residual_rms, floor)
    ex = f.extra
    assert set(ex["params"]) == set(MULTI_PARAM_NAMES)
    assert np.allclose(ex["scales"], np.diag(f.m))
    assert np.isclose(ex["angles_rad"]["a_yx"], f.m[1, 0] / f.m[1, 1])
    assert all(v > 0 for v in ex["sigma_angles_rad"].values()) and np.all(ex["sigma_scales"] > 0)


@pytest.mark.parametrize("idx,runs", [(I26, 600), (I18, 600), (I12, 1000)], ids=["26", "18", "12"])
def test_multi_position_monte_carlo(idx, runs):
    """One truth, fixed (5°-tilted) attitudes: coverage of 3σ ≥ 99 % over all parameters and
    runs; the reported σ (mean over runs) within 20 % of the spread, every parameter."""
    rng = np.random.default_rng(30 + len(idx))
    M, b = make_truth(rng)
    L, _ = lower_triangular_form(M)
    truth = np.r_[L.ravel(), b]
    x = attitudes(rng, idx, tilt_deg=5)
    est, sig = [], []
    for _ in range(runs):
        u, s = measure(rng, M, b, x)
        f = multi_position(u, s)
        est.append(params12(f))
        sig.append(np.sqrt(np.diag(f.cov)))
    k = f.estimated
    est, sig = np.array(est)[:, k], np.array(sig)[:, k]
    coverage = np.mean(np.abs(est - truth[k]) <= 3 * sig)
    ratio = est.std(axis=0) / sig.mean(axis=0)
    assert coverage >= 0.99, coverage
    assert np.all(np.abs(ratio - 1) <= 0.2), ratio


def test_multi_position_counts_and_si_alike():
    rng = np.random.default_rng(40)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, I26, tilt_deg=5))
    f = multi_position(u, s)
    c = LSB_PER_G / G0
    fc = multi_position(u * c, s * c, g=LSB_PER_G)
    assert np.allclose(fc.m, f.m, rtol=0, atol=1e-10)
    assert np.all(np.abs(fc.b / c - f.b) < 1e-6 * f.sigma_b)
    assert np.allclose(fc.sigma_m, f.sigma_m, rtol=1e-6)
    assert np.allclose(fc.sigma_b / c, f.sigma_b, rtol=1e-6)
    L, _ = lower_triangular_form(M)
    k = fc.estimated
    z = (params12(fc) - np.r_[L.ravel(), b * c])[k] / np.sqrt(np.diag(fc.cov))[k]
    assert np.all(np.abs(z) < 3.5)
    # the corrected output is in counts too: |a| = 256000 in every pose
    assert np.allclose(np.linalg.norm(fc.correct(u * c), axis=1), LSB_PER_G, rtol=1e-4)


def test_multi_position_converges_from_a_poor_start():
    rng = np.random.default_rng(41)
    M, b = make_truth(rng, scale=0.08, bias_g=0.2)          # 8 % errors, 200 mg biases
    L, _ = lower_triangular_form(M)
    u, s = measure(rng, M, b, attitudes(rng, I18, tilt_deg=5))
    ref = multi_position(u, s)                               # no init
    k = ref.estimated
    z = (params12(ref) - np.r_[L.ravel(), b])[k] / np.sqrt(np.diag(ref.cov))[k]
    assert np.all(np.abs(z) < 3)
    assert ref.extra["start"] in ("ellipsoid", "minmax")
    # a poor init (20 % scale, 300 mg biases) converges by itself
    poor = TriadFit("guess", m=1.2 * np.eye(3), b=np.array([0.3, -0.3, 0.3]) * G0, cov=np.full((12, 12), np.nan))
    f = multi_position(u, s, init=poor)
    assert f.extra["start"] == "init"
    assert np.allclose(f.m, ref.m, atol=1e-9) and np.allclose(f.b, ref.b, atol=1e-7)
    # an absurd one (40° rotation, 30 % scale, 500 mg) may not: the automatic starts take over
    absurd = TriadFit("guess", m=1.3 * rot(np.random.default_rng(0), 40), b=np.array([0.5, -0.5, 0.5]) * G0,
                      cov=np.full((12, 12), np.nan))
    f = multi_position(u, s, init=absurd)
    assert np.allclose(f.m, ref.m, atol=1e-9) and np.allclose(f.b, ref.b, atol=1e-7)


def test_multi_position_from_a_six_position_pre_calibration():
    rng = np.random.default_rng(42)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, I26, tilt_deg=3))
    pre = six_position(u[:6], s[:6])
    f = multi_position(u, s, init=pre)
    assert f.extra["start"] == "init"
    assert np.allclose(f.m, multi_position(u, s).m, atol=1e-9)
    table = pose_table(u, f)
    assert len(table) == 26 and table[0]["pose"] == "+Z up (level)" and table[0]["index"] == 0
    before = np.array([r["before_g"] for r in table])
    after = np.array([r["after_g"] for r in table])
    assert np.max(np.abs(after - 1)) < 1e-4 < np.max(np.abs(before - 1))


def test_axis_never_pointed_down_is_not_observable():
    rng = np.random.default_rng(43)
    M, b = make_truth(rng)
    idx = [i for i in I26 if PLAN_DIRS[i, 2] >= -0.01]     # Z never below the horizon
    u, s = measure(rng, M, b, attitudes(rng, idx))
    with pytest.raises(NotObservable, match="the Z axis was never pointed down"):
        multi_position(u, s)
    # corners count as pointing up/down (within 60°): faces ±X, ±Y, +Z, edges and corners pass
    idx = [i for i in I26 if i != 1]
    check_observability(measure(rng, M, b, attitudes(rng, idx))[0], "multi_position")


def test_too_few_poses():
    rng = np.random.default_rng(44)
    M, b = make_truth(rng)
    u, s = measure(rng, M, b, attitudes(rng, [0, 1, 2, 3, 4, 5, 6, 9]))
    with pytest.raises(NotObservable, match="too few poses: 8 given"):
        multi_position(u, s)
    # 12 poses but only 6 attitudes: repeats count once
    u, s = measure(rng, M, b, attitudes(rng, list(range(6)) * 2))
    with pytest.raises(NotObservable, match="6 distinct attitudes"):
        multi_position(u, s)


def test_check_observability_reports():
    rep = check_observability(PLAN_DIRS * G0, "multi_position")
    assert rep["n_distinct"] == 26 and rep["warnings"] == []
    assert all(abs(v - 1) < 0.05 for v in rep["dop"].values())
    rep = check_observability(PLAN_DIRS[list(range(6)) + [6, 9, 10, 14]] * G0, "multi_position")
    assert any("10 distinct attitudes" in w for w in rep["warnings"])
    # corners and ±Z only: a rank-deficient set; the unconstrained combination is named
    with pytest.raises(NotObservable, match=r"combination of .*s_x.* unconstrained"):
        check_observability(PLAN_DIRS[[0, 1] + list(range(18, 26))] * G0, "multi_position")
    with pytest.raises(NotObservable, match="missing faces: -Y"):
        check_observability(PLAN_DIRS[[0, 1, 2, 3, 4]] * G0, "six_position")
    assert FACES == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def test_end_to_end_recording_to_calibration():
    """A 26-pose recording at 200 Hz (3 s holds): detect the holds, calibrate from their means
    and sigma_mean, recover the truth within 3σ."""
    fs = 200
    rng = np.random.default_rng(45)
    M, b = make_truth(rng)
    dirs = [rot(rng, 5) @ d for d in PLAN_DIRS]
    a, holds = recording(dirs, fs, hold_s=3.0, lead_s=3.0, seed=46, M=M, b=b)
    iv = require_static(detect_static(a, fs), 26)
    assert len(iv) == 26
    means = np.array([it.mean for it in iv])
    sig = np.array([it.sigma_mean for it in iv])
    f = multi_position(means, sig)
    L, _ = lower_triangular_form(M)
    k = f.estimated
    z = (params12(f) - np.r_[L.ravel(), b])[k] / np.sqrt(np.diag(f.cov))[k]
    assert np.all(np.abs(z) < 3), z
    covered, missing, unmatched = match_plan(means)
    assert len(covered) == 26 and not missing and not unmatched
