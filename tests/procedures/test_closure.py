"""Closure check (imubench.procedures.closure, imubench.analysis.strapdown): the strapdown integration against analytic cases, the
motion detection, the white-noise floor against a Monte Carlo, refusals; the simulator's
path motion; and the whole check on the virtual device, calibrated by a real session."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench.analysis import closure as ACL
from imubench.analysis import strapdown as SD
from imubench.cli import main as imubench
from imubench.device.sim import VirtualBench
from imubench.procedures import closure as CL
from imubench.results import closure as RCL
from imubench.wire import params as PR
from imubench.wire.decoder import SampleBlock
from imubench.wire.protocol_gen import Params

G = CL.G0
FS = 1000.0


# ------------------------------------------------------------------ synthetic trajectories
def _mj(s):
    return s ** 3 * (10 - 15 * s + 6 * s ** 2), 30 * s ** 2 * (1 - s) ** 2, 60 * s * (1 - 3 * s + 2 * s ** 2)


def _rot(axis, th):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx


def synthetic(legs, rest_s=2.0, end_s=2.0, fs=FS):
    """Exact specific force and body rates (board frame) for legs like the simulator's, at
    fs, with rest before and after. Returns t, f, w, true positions."""
    n_rest, n_end = int(rest_s * fs), int(end_s * fs)
    t_list, f_list, w_list, p_list = [], [], [], []
    r = np.eye(3)
    p = np.zeros(3)
    t0 = 0.0

    def still(n):
        nonlocal t0
        for _ in range(n):
            t_list.append(t0)
            f_list.append(r.T @ [0, 0, G])
            w_list.append(np.zeros(3))
            p_list.append(p.copy())
            t0 += 1 / fs
    still(n_rest)
    for leg in legs:
        T = leg["duration_s"]
        d = np.asarray(leg.get("move_m", [0, 0, 0]), float)
        axis = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}.get(leg.get("axis", "z"))
        ang = math.radians(leg.get("turn_deg", 0.0))
        r0, p0 = r.copy(), p.copy()
        for k in range(int(round(T * fs))):
            s = k / (T * fs)
            h, h1, h2 = _mj(s)
            rk = r0 @ _rot(axis, ang * h)
            acc = d * h2 / T ** 2
            t_list.append(t0)
            f_list.append(rk.T @ (acc + [0, 0, G]))
            w_list.append(np.asarray(axis) * ang * h1 / T)
            p_list.append(p0 + d * h)
            t0 += 1 / fs
        r = r0 @ _rot(axis, ang)
        p = p0 + d
    still(n_end)
    return np.array(t_list), np.array(f_list), np.array(w_list), np.array(p_list)


def test_strapdown_closes_exact_data_of_both_paths():
    for name, legs in CL.PATHS.items():
        t, f, w, p = synthetic(legs)
        i0, i1 = SD.motion_window(t, f, w, rest_s=2.0)
        res = SD.strapdown(t, f, w, i0, i1, align_n=1000)
        assert np.allclose(p[-1], p[0], atol=1e-12)                      # the paths are closed
        assert res.distance_m < 2e-3, (name, res.closure_m)
        # the integrated path follows the true one (not only its end)
        assert np.abs(res.pos_m - (p[i0:i1 + 1] - p[i0])).max() < 2e-3, name
        assert abs(res.path_length_m - np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) < 0.01


def test_strapdown_signs_gyro_bias_tilts_gravity_into_the_horizontal():
    """Board still and level for T s, gyro X reads a bias b: the integration believes the board
    rolls by b·t (right wing down), so gravity leaks into −Y... position error y = −g·b·T³/6."""
    n = int(10 * FS)
    t = np.arange(n) / FS
    f = np.tile([0, 0, G], (n, 1))
    b = np.radians(0.05)
    for k, (ax, sign) in enumerate((("x", -1.0), ("y", +1.0))):
        w = np.zeros((n, 3))
        w[:, k] = b
        res = SD.strapdown(t, f, w, 0, n - 1, align_n=1)
        T = t[-1]
        expect = G * b * T ** 3 / 6
        other = 1 - k                                   # roll (about X) moves Y, pitch moves X
        assert res.closure_m[other] == pytest.approx(sign * expect, rel=0.01), (ax, res.closure_m)
    # accelerometer bias: half of a·T² on that axis (no tilt since nothing turns... but the
    # levelling at the start absorbs a horizontal bias: the known limit of a level platform)
    w = np.zeros((n, 3))
    fb = f + [0.01, 0, 0.02]
    res = SD.strapdown(t, fb, w, 0, n - 1, align_n=100)
    assert abs(res.closure_m[0]) < 1e-6                     # levelled away
    zexp = (math.hypot(0.01, G + 0.02) - G) * t[-1] ** 2 / 2  # |f| − g stays vertical
    assert res.closure_m[2] == pytest.approx(zexp, rel=1e-3)


def test_turns_reveal_a_horizontal_accelerometer_bias():
    """The square path: an X bias is levelled away at the start, but the cart turns, so it
    points elsewhere and the loop no longer closes; calibration (removing it) closes it."""
    t, f, w, _ = synthetic(CL.PATHS["square"])
    i0, i1 = SD.motion_window(t, f, w, rest_s=2.0)
    biased = SD.strapdown(t, f + [0.05, 0, 0], w, i0, i1, align_n=1000)
    clean = SD.strapdown(t, f, w, i0, i1, align_n=1000)
    assert biased.horizontal_m > 0.3 and clean.horizontal_m < 2e-3


def test_motion_window_brackets_the_motion_and_refuses_bad_recordings():
    legs = CL.PATHS["box"]
    t, f, w, _ = synthetic(legs)
    rng = np.random.default_rng(3)
    fn = f + rng.normal(0, 0.007, f.shape)
    wn = w + rng.normal(0, 0.008, w.shape)
    i0, i1 = SD.motion_window(t, fn, wn, rest_s=2.0)
    t_start, t_end = 2.0, 2.0 + sum(leg["duration_s"] for leg in legs)
    assert t_start - 0.35 <= t[i0] <= t_start            # pad 0.25 s, detection within ~0.1 s
    assert t_end <= t[i1] <= t_end + 0.35
    with pytest.raises(SD.ClosureError, match="no motion"):
        SD.motion_window(t[:1500], fn[:1500], wn[:1500], rest_s=1.0)
    n_end = len(t) - 1000                                 # cut in the middle of the path
    with pytest.raises(SD.ClosureError, match="still moving"):
        SD.motion_window(t[:n_end - 2000], fn[:n_end - 2000], wn[:n_end - 2000], rest_s=2.0)
    with pytest.raises(SD.ClosureError, match="before its rest"):
        SD.motion_window(t[1500:], fn[1500:], wn[1500:], rest_s=1.0)
    # a board left still in another attitude than at the start is not moving
    still_tilted = np.vstack([np.tile([0, 0, G], (3000, 1)), np.tile(_rot([1, 0, 0], 0.3).T @ [0, 0, G], (3000, 1))])
    still_tilted += rng.normal(0, 0.007, still_tilted.shape)
    i0, i1 = SD.motion_window(np.arange(6000) / FS, still_tilted, rng.normal(0, 0.008, (6000, 3)), rest_s=2.0)
    assert 2700 <= i0 <= 3000 <= i1 <= 3300


def test_noise_floor_matches_a_monte_carlo():
    """White noise only, board still: the spread of the closure over many runs agrees with
    noise_floor's 1-sigma (within 20 %)."""
    rng = np.random.default_rng(11)
    n_rest, n_mov = 2000, 6000
    n = n_rest + n_mov
    t = np.arange(n) / FS
    sa, sg = 0.007, 0.0095
    ends = []
    for _ in range(150):
        f = np.tile([0, 0, G], (n, 1)) + rng.normal(0, sa, (n, 3))
        w = rng.normal(0, sg, (n, 3))
        ends.append(SD.strapdown(t, f, w, n_rest, n - 1, align_n=1600).closure_m)
    ends = np.array(ends)
    floor = SD.noise_floor(f[:n_rest], w[:n_rest], FS, t[-1] - t[n_rest], align_n=1600)
    sx, sz = np.std(ends[:, 0]), np.std(ends[:, 2])
    print(f"Monte Carlo sigma x {sx:.4f} m (floor {floor['sigma_x_m']:.4f}), z {sz:.5f} (floor {floor['sigma_z_m']:.5f})")
    assert sx == pytest.approx(floor["sigma_x_m"], rel=0.2)
    assert np.std(ends[:, 1]) == pytest.approx(floor["sigma_y_m"], rel=0.2)
    assert sz == pytest.approx(floor["sigma_z_m"], rel=0.2)


def _block(n=5000, gap_at=None, calibrated=False):
    idx = np.arange(n, dtype=np.int64)
    if gap_at is not None:
        idx[gap_at:] += 3
    z = np.zeros(n, dtype=np.uint8)
    return SampleBlock(calibrated=calibrated, t_us=idx * 1000, sample_index=idx, status=z, sensor_flags=z,
                       accel_temp_counts=np.full(n, 1885, dtype=np.uint16),
                       gyro_temp_counts=np.zeros((n, 3), dtype=np.int16), gyro_faults=np.zeros((n, 3), np.uint8),
                       accel_status=z, accel_range_g=np.full(n, 2, dtype=np.uint8),
                       accel_counts=np.tile([0, 0, 256000], (n, 1)).astype(np.int32),
                       gyro_counts=np.zeros((n, 3), dtype=np.int16))


def test_closure_refuses_lost_samples_calibrated_data_and_still_recordings():
    p = PR.identity()
    with pytest.raises(SD.ClosureError, match="3 samples were lost"):
        ACL.closure_from_block(_block(gap_at=2500), p)
    with pytest.raises(SD.ClosureError, match="RAW"):
        ACL.closure_from_block(_block(calibrated=True), p)
    with pytest.raises(SD.ClosureError, match="no motion"):
        ACL.closure_from_block(_block(), p)
    assert PR.is_factory(p) and not PR.is_factory(dataclasses.replace(p, gyro_b_rad_s=(0.001, 0.0, 0.0)))


# ------------------------------------------------------------------ the simulator's paths
def test_sim_path_moves_the_board_and_comes_back():
    with VirtualBench(speed=0, seed=5) as vb:
        legs = [{"duration_s": 1.0, "move_m": [0.4, 0, 0]}, {"duration_s": 1.0, "axis": "z", "turn_deg": 90},
                {"duration_s": 1.0, "move_m": [-0.4, 0, 0.1]}, {"duration_s": 0.5, "move_m": [0, 0, -0.1]}]
        r = vb.path(legs, wait=False)
        assert r["duration_s"] == pytest.approx(3.5)
        vb.wait(0.5)
        st = vb.status()                                   # mid first leg: peak speed 1.875·d/T
        assert st["moving"] and st["move"]["kind"] == "path" and st["move"]["leg"] == 0
        assert st["position_m"][0] == pytest.approx(0.2, abs=0.02)
        assert st["velocity_mps"][0] == pytest.approx(1.875 * 0.4, rel=0.02)
        # accelerating forward: the accelerometer feels it along board X, gravity on Z
        assert st["specific_force_mps2"][2] == pytest.approx(G, abs=1e-9)
        vb.wait_idle()
        st = vb.status()
        assert not st["moving"] and st["move"] is None
        assert np.allclose(st["position_m"], [0, 0, 0], atol=1e-12)
        assert st["yaw_deg"] == pytest.approx(90.0, abs=1e-9)
        assert np.allclose(st["specific_force_mps2"], [0, 0, G], atol=1e-9)
        for bad, msg in (([], "1 .. 32"), ([{"duration_s": 1, "turn_deg": 5}], "needs an axis"),
                         ([{"duration_s": 0.001}], "duration_s"), ([{"duration_s": 1, "move_m": [1, 2]}], "move_m"),
                         ([{"duration_s": 1, "speed": 3}], "unknown field")):
            with pytest.raises(Exception, match=msg):
                vb.control("path", legs=bad)


# ------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def calibrated_run(tmp_path_factory):
    """A virtual device with random truth (bias random walk off, so the truth holds still),
    calibrated by a real session (multi-position + turntable, frames aligned), then the
    closure check on the box path."""
    out = tmp_path_factory.mktemp("closure")
    with VirtualBench(speed=0, seed=31, truth="random") as vb:
        vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
        with vb.device(timeout=5.0) as dev:
            params = CL.calibrate_virtual(vb, dev, out / "session", seed=31, say=lambda s: None)
            truth = vb.get_truth()
            replies = []
            orig = vb.path

            def recording_path(lg, wait=True):
                replies.append(orig(lg, wait=wait))
                return replies[-1]
            vb.path = recording_path
            pos0 = vb.status()["position_m"]
            res = CL.run_closure(dev, out / "closure", params, vb, "box", say=lambda s: None)
            pos1 = vb.status()["position_m"]
    return {"out": out, "params": params, "truth": truth, "res": res, "reply": replies[0], "pos": (pos0, pos1)}


def test_closure_on_the_virtual_device_before_and_after_calibration(calibrated_run):
    res = calibrated_run["res"]
    print("\n" + RCL.summarize(res))
    floor = res["noise_floor"]["sigma_distance_m"]
    assert np.allclose(calibrated_run["pos"][0], calibrated_run["pos"][1], atol=1e-9)   # the path closes
    assert res["before"].distance_m > 1.0                      # random truth: metres off uncalibrated
    assert res["after"].distance_m < 4 * floor                 # calibrated: at the noise
    assert res["after_rest_bias"].distance_m < 4 * floor
    assert res["improvement"] > 10
    # the window found in the data brackets the path the bench drove
    # (pad 0.25 s; the 50 ms statistics may see the motion up to one window early or late)
    rep, w = calibrated_run["reply"], res["window"]
    assert w["t0_s"] <= rep["t_start_us"] * 1e-6 <= w["t0_s"] + 0.35
    assert w["t1_s"] - 0.35 <= rep["t_end_us"] * 1e-6 <= w["t1_s"]
    # the integrated path length is the driven one's, give or take the drift of the integration
    # (its end error is itself up to ~4 floors, and the drift lengthens the path by about that)
    true_len = float(np.linalg.norm(np.diff(CL.sim_truth_path(CL.PATHS["box"], 400), axis=0), axis=1).sum())
    assert abs(res["after_rest_bias"].path_length_m - true_len) < 0.1 + 4 * floor


def test_session_aligns_the_accelerometer_to_the_gyro_frame(calibrated_run):
    """Multi-position + turntable: the accelerometer's M is in the board frame, rotation
    included (the multi-position fit alone gives its lower-triangular form)."""
    t = calibrated_run["truth"]["accel"]
    m = np.array(calibrated_run["params"].accel_m).reshape(3, 3)
    m_true = np.array(t["m"])
    assert np.abs(m - m_true).max() < 1.5e-3
    from imubench.calib.accel import lower_triangular_form
    lower, _ = lower_triangular_form(m_true)
    assert np.abs(m - lower).max() > 3 * np.abs(m - m_true).max()   # the rotation is really there


def test_closure_files_and_reanalysis(calibrated_run, capsys):
    d = calibrated_run["out"] / "closure"
    meta = json.loads((d / "closure.json").read_text())
    assert meta["path"] == "box" and meta["params"]["accel_m"] == list(calibrated_run["params"].accel_m)
    assert meta["after"]["distance_m"] == pytest.approx(calibrated_run["res"]["after"].distance_m)
    assert (d / "closure.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert meta["decoder"]["samples_missing"] == 0
    assert max(abs(v) for v in meta["truth_closure_m"]) < 1e-9          # the bench's own path closed
    # the raw capture alone (with the parameters recorded first) gives the same figures
    assert imubench(["closure", "--analyse", str(d)]) == 0
    again = json.loads((d / "closure.json").read_text())
    assert again["before"]["distance_m"] == pytest.approx(meta["before"]["distance_m"], rel=1e-9)
    assert again["after"]["distance_m"] == pytest.approx(meta["after"]["distance_m"], rel=1e-9)
    assert "after calibration" in capsys.readouterr().out


def test_closure_refuses_factory_parameters(tmp_path, capsys):
    with VirtualBench(speed=0, seed=6) as vb:
        rc = imubench(["closure", "--port", vb.port_url, "--out", str(tmp_path / "c")])
    assert rc == 1
    assert "factory default" in capsys.readouterr().err


def test_params_file_is_read(tmp_path):
    p = dataclasses.replace(PR.identity(), gyro_b_rad_s=(0.01, 0.0, 0.0))
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"params": PR.to_json(p)}))
    q = CL.load_params(str(f))
    assert isinstance(q, Params) and q.gyro_b_rad_s == (0.01, 0.0, 0.0)


def test_truth_is_drawn_in_the_navigation_frame(tmp_path):
    """The board need not start level at yaw 0 (after `calibrate --closure` it starts in the
    last verification attitude): the driven path must be drawn in the integration's frame,
    where the measured track lies on it, not in the simulator's world frame."""
    with VirtualBench(speed=0, seed=8) as vb:       # ideal parts: nominal scaling is the truth
        vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
        vb.set_orientation(roll_deg=15, pitch_deg=-60, yaw_deg=130)
        with vb.device(timeout=5.0) as dev:
            said = []
            res = CL.run_closure(dev, tmp_path / "c", PR.identity(), vb, "square", say=said.append)
    meta = json.loads((tmp_path / "c" / "closure.json").read_text())
    assert meta["start_attitude_deg"]["yaw"] == pytest.approx(130, abs=1e-6)
    track = res["after_rest_bias"].pos_m[:, :2]

    def worst_gap(path):             # the largest distance from the track to the path drawn
        p = np.asarray(path)[:, :2]
        return float(np.sqrt(((track[:, None, :] - p[None, :, :]) ** 2).sum(-1)).min(axis=1).max())
    aligned = worst_gap(CL.truth_in_navigation_frame(meta, res))
    world = worst_gap(meta["truth_path_m"])
    assert aligned < 0.1 and world > 0.3, (aligned, world)
    # the person (or the log) is told once to hold still at the start, once at the end
    assert sum("hold the board still" in s for s in said) == 2
    assert sum("start mark" in s for s in said) == 2 and any("back at the start mark" in s for s in said)


def test_summary_table_is_aligned_and_ends_with_a_verdict(calibrated_run):
    text = RCL.summarize(calibrated_run["res"])
    lines = text.splitlines()
    rows = [ln for ln in lines if ln.startswith(("before calibration", "after calibration", "after, gyro",
                                                  "white-noise"))]
    assert len(rows) == 4

    def end_of_first_number(ln):
        import re
        m = re.search(r"\s(-?\d+\.\d{4})\b", ln)
        return m.end(1)
    assert len({end_of_first_number(r) for r in rows}) == 1, text      # the distance column lines up
    passed, words = RCL.verdict(calibrated_run["res"])
    assert lines[-1] == words and words.startswith("PASS" if passed else "ABOVE THE NOISE")
    assert "white-noise floor" in words
