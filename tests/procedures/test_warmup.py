"""The warm-up temperature calibration (issue 23): the polynomial fit on synthetic arrays (order
choice, the span's limit, honest sigmas, faces separating bias and scale), the PX4 and ArduPilot
files read back as those firmwares evaluate them, and `imubench thermal --warmup --sim` end to end
on the lagging, curved virtual part: the recovered curves against the truth within their sigma,
the files on disk, and Ctrl-C keeping the fit."""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from scipy.signal import lfilter
from imubench import units as U
from imubench.analysis import thermal_poly as TP
from imubench.device import sim_thermal as ST
from imubench.device.sim import VirtualBench
from imubench.procedures import warmup as W
from imubench.results import thermal_export as TX
from imubench.results.thermal_warmup import polyfit_from_json
from imubench.wire.decoder import decode_bytes

from procio import finish, wait_for_line

T_REF = 25.0
LINE = np.array([2e-3, 3e-4, 0.0, 0.0])
CUBIC = np.array([2e-3, 3e-4, -2e-5, 3e-6])


def _warmup_temps(rng, n=200, lo=5.0, hi=45.0, res=0.2):
    """Bin temperatures of a warm-up: fast at first, then slowing (first-order lag), quantised."""
    t = lo + (hi - lo) * (1 - np.exp(-np.linspace(0, 4, n)))
    return np.round((t + rng.normal(0, 0.02, n)) / res) * res


@pytest.mark.parametrize("truth,want", [(LINE, 1), (CUBIC, 3)])
def test_order_chosen_by_heldout_error(truth, want):
    rng = np.random.default_rng(7)
    got = []
    for _ in range(30):
        t = _warmup_temps(rng)
        sig = np.full(len(t), 2e-4)
        y = TP.poly_eval(truth, t, T_REF) + sig * rng.normal(size=len(t))
        f = TP.fit_bias_poly(t, y, sig, T_REF)
        got.append(f.order)
        assert set(f.heldout_by_order) == {0, 1, 2, 3}
        assert f.heldout_rms == f.heldout_by_order[f.order]
    assert np.mean(np.array(got) == want) >= 0.9, got


def test_order_never_beyond_span_and_distinct_temperatures():
    rng = np.random.default_rng(1)
    t = np.round(np.linspace(24.0, 25.0, 60) / 0.2) * 0.2          # 1 °C: six distinct readings
    sig = np.full(len(t), 1e-5)
    f = TP.fit_bias_poly(t, TP.poly_eval(CUBIC, t, T_REF) + sig * rng.normal(size=len(t)), sig, T_REF)
    assert f.max_supported_order == 1 and f.order <= 1 and f.n_distinct == 6
    assert any("order limited to 1" in n for n in f.notes)
    t = np.linspace(20.0, 30.0, 60)                                 # 10 °C: not a cubic's span
    f = TP.fit_bias_poly(t, TP.poly_eval(CUBIC, t, T_REF), sig, T_REF, order=3)
    assert f.max_supported_order == 2 and f.order == 2 and any("order 3 asked" in n for n in f.notes)
    assert TP.supported_order(40.0, 200) == 3 and TP.supported_order(0.5, 200) == 0
    with pytest.raises(ValueError):
        TP.fit_bias_poly([25.0, 25.0], [0.0, 1.0], [1.0, 1.0], T_REF)


def test_sigma_is_honest_with_drift_inside_the_bins():
    """Samples with a wander (AR(1), 0.5 s correlation at 100 Hz, as large as the white noise) binned:
    the batch-means sigma of a bin matches the real spread of bin means (white σ/√n alone is ~3x
    short); the fitted curve then holds the truth within 3 sigma over the span in at least 90 % of
    30 runs (and the z-scores are not absurdly small either)."""
    rng = np.random.default_rng(11)
    fs, n, bin_s = 100.0, 60_000, 10.0
    phi = np.exp(-1 / (0.5 * fs))
    zs, ratio = [], []
    for _ in range(30):
        e = rng.normal(0, 1e-3, n)
        wander = lfilter([1.0], [1.0, -phi], rng.normal(0, 1e-3 * np.sqrt(1 - phi ** 2), n))
        ts = np.arange(n) / fs
        temp = 5 + 40 * (1 - np.exp(-ts / 200.0))
        y = TP.poly_eval(CUBIC, temp, T_REF) + e + wander
        b = TP.bin_stream(ts, temp, y, bin_s)
        resid = b.mean[:, 0] - TP.poly_eval(CUBIC, b.temp_c[:, 0], T_REF)
        ratio.append(np.std(resid) / np.median(b.sigma[:, 0]))
        f = TP.fit_bias_poly(b.temp_c[:, 0], b.mean[:, 0], b.sigma[:, 0], T_REF, resolution_c=0.01)
        tt = np.linspace(f.span_c[0] + 1, f.span_c[1] - 1, 7)
        zs.append(np.max(np.abs(f(tt) - TP.poly_eval(CUBIC, tt, T_REF)) / f.curve_sigma(tt)))
    assert 0.7 < np.median(ratio) < 1.4, np.median(ratio)
    zs = np.array(zs)
    assert np.mean(zs < 3) >= 0.9 and np.median(zs) > 0.3, np.round(zs, 2)


def _face(direction, rng, temps, c, s_tc, m_kk=1.0, sig=2e-4):
    g = U.G0_MPS2 * m_kk * np.asarray(direction, float)
    y = np.array([[TP.poly_eval(c[k], t, T_REF) + (1 + s_tc[k] * (t - T_REF)) * g[k] for k in range(3)] for t in temps])
    return TP.FaceSegment(np.asarray(direction, float), temps, y + sig * rng.normal(size=y.shape),
                          np.full(y.shape, sig))


def test_faces_separate_bias_and_scale_terms():
    rng = np.random.default_rng(5)
    c = np.array([[0.01, 2e-4, 1e-6, 0], [-0.02, -1e-4, 0, 0], [0.03, 3e-4, -2e-6, 0]])
    s_tc = np.array([0.0, 0.0, 2e-4])
    temps = _warmup_temps(rng, n=150, res=1 / 9.05)
    one = TP.fit_triad_faces([_face([0, 0, 1], rng, temps, c, s_tc)], T_REF, U.G0_MPS2)
    assert one[2].scale_tc_per_c is None and "not separated" in one[2].undetermined[0]
    assert abs(one[2].bias.coef[1] - (c[2, 1] + s_tc[2] * U.G0_MPS2)) < 5 * one[2].bias.sigma[1]   # combined slope
    assert "never saw gravity" in one[0].undetermined[0] and abs(one[0].bias.coef[1] - c[0, 1]) < 5 * one[0].bias.sigma[1]
    two = TP.fit_triad_faces([_face([0, 0, 1], rng, temps, c, s_tc), _face([0, 0, -1], rng, temps, c, s_tc)],
                             T_REF, U.G0_MPS2)
    z = two[2]
    assert z.scale_tc_per_c is not None and not any("not separated" in u for u in z.undetermined)
    assert abs(z.scale_tc_per_c - s_tc[2]) < 4 * z.scale_tc_sigma_per_c
    assert abs(z.bias.coef[1] - c[2, 1]) < 4 * z.bias.sigma[1] and abs(z.bias.coef[0] - c[2, 0]) < 4 * z.bias.sigma[0]


def _fits_for_export(rng):
    temps = _warmup_temps(rng, n=200, res=1 / 9.05)
    c = np.array([[0.0, 2e-4, 3e-6, -1e-7], [0.0, -1e-4, 0, 0], [0.0, 3e-5, 2e-6, 0]])
    acc = TP.fit_triad_faces([_face([0, 0, 0], rng, temps, c, np.zeros(3), sig=1e-6)], T_REF, U.G0_MPS2)
    gyr = TP.fit_triad_faces([_face([0, 0, 0], rng, temps, c * 0.1, np.zeros(3), sig=1e-7)], T_REF, None)
    return {"accel": acc, "gyro": gyr}


def test_exports_read_back_as_the_firmware_evaluates_them(tmp_path):
    fits = _fits_for_export(np.random.default_rng(2))
    t_ref = {"accel": T_REF, "gyro": T_REF}
    files = TX.write_exports(tmp_path, {"px4": (fits, "words"), "ardupilot": (fits, "words")}, t_ref, TX.KINDS)
    px4 = TX.read_px4(files["px4"][0].read_text())
    ap = TX.read_ardupilot(files["ardupilot"][0].read_text())
    assert px4["TC_A_ENABLE"] == 1 and px4["TC_A0_TREF"] == T_REF and ap["INS_TCAL1_ENABLE"] == 1
    for triad, pre, name in (("accel", "TC_A0", "ACC"), ("gyro", "TC_G0", "GYR")):
        lo = max(a.bias.span_c[0] for a in fits[triad])
        hi = min(a.bias.span_c[1] for a in fits[triad])
        assert lo <= px4[f"{pre}_TMIN"] <= lo + 0.1 and hi - 0.1 <= px4[f"{pre}_TMAX"] <= hi   # rounded inwards
        assert ap["INS_TCAL1_TMIN"] >= lo and ap["INS_TCAL1_TMAX"] <= hi
        scale = np.max(np.abs([a.bias(hi) - a.bias.coef[0] for a in fits[triad]]))
        for T in (-10.0, 8.0, 20.0, 25.0, 33.3, 44.0, 70.0):       # inside the span and clamped beyond it
            def ours(t_min, t_max):
                return np.array([TP.poly_eval(np.r_[0.0, a.bias.coef[1:]], T, T_REF, t_min, t_max) for a in fits[triad]])
            got = TX.px4_offset(px4, pre, T)
            assert np.allclose(got, ours(px4[f"{pre}_TMIN"], px4[f"{pre}_TMAX"]), atol=1e-6 * scale), (triad, T)
            got = TX.ardupilot_correction(ap, name, T)
            want = ours(ap["INS_TCAL1_TMIN"], ap["INS_TCAL1_TMAX"])
            assert np.allclose(got, want, atol=1e-5 * scale), (triad, T, got, want)
    text = files["px4"][0].read_text() + files["ardupilot"][0].read_text()
    assert "cannot hold" in text and "scale temperature terms" in text


# ------------------------------------------------------------------ on the virtual device
SEED = 3


def _cli(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "imubench", "thermal", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _listening_socket_with_no_device():
    import socket
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    return s


@pytest.mark.parametrize("args,words", [
    (["--warmup", "--sim", "--tau", "30", "--span", "5,80"], "this bench brings the sensors from 5 to about"),
    (["--warmup", "--sim", "--face", "+q"], "one of +x, -x, +y, -y, +z, -z"),
    (["--warmup", "--sim", "--temps", "5,25"], "--temps is an option of the step method"),
    (["--span", "5,45"], "--span goes with --warmup"),
    (["--warmup", "--port", "socket://127.0.0.1:{port}"], "no answer to get_info"),
    (["--fit-warmups", "."], "no readable thermal.json of a warm-up"),
])
def test_warmup_mistakes_give_one_line(tmp_path, args, words):
    srv = _listening_socket_with_no_device()
    try:
        argv = [a.format(port=srv.getsockname()[1]) for a in args] + ["--out", str(tmp_path / "w")]
        r = subprocess.run([sys.executable, "-m", "imubench", "thermal", *argv], capture_output=True, text=True,
                           timeout=120, cwd=tmp_path, stdin=subprocess.DEVNULL)
    finally:
        srv.close()
    assert r.returncode != 0 and words in r.stderr, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "w" / "thermal.json").exists()        # nothing half-recorded


def test_warmup_cli_on_the_virtual_part_recovers_the_truth(tmp_path):
    out = tmp_path / "w"
    p = _cli("--warmup", "--sim", "--sim-seed", str(SEED), "--tau", "30",
             "--export", "px4,ardupilot", "--write", "--out", str(out))
    stdout, stderr = finish(p, 240)
    assert p.returncode == 0, stdout + stderr
    assert "temperatures stopped rising" in stdout and "note: bias and scale temperature terms of accelerometer z" in stdout
    d = json.loads((out / "thermal.json").read_text())
    assert d["kind"] == "imubench thermal warmup" and d["status"] == "done" and d["config"]["face"] == "+z"
    _, raw, _, _ = decode_bytes((out / "capture.bin").read_bytes())
    assert raw is not None and len(raw) >= sum(d["bins"]["n"])        # every binned sample is on disk
    assert set(d["exports"]) == {"px4", "ardupilot"} and all(os.path.exists(f[0]) for f in d["exports"].values())
    # written (layout 3), read back after a reboot, and the device's calibrated output matches the host's model
    w = d["write"]
    assert w["verified"] and w["check"]["ok"] and "rebooted" in w["steps"]
    for triad in ("accel", "gyro"):
        spans = np.array([a["span_c"] for a in d["fit"][triad]["axes"]])
        assert w["params"][f"{triad}_t_min_c"] == int(np.ceil(spans[:, 0].max()))      # rounded inwards
        assert w["params"][f"{triad}_t_max_c"] == int(np.floor(spans[:, 1].min()))
    c2 = [a["coef"][2] if a["order"] >= 2 else 0.0 for a in d["fit"]["gyro"]["axes"]]
    assert np.allclose(w["params"]["gyro_bias_tc2_rad_s_per_c2"], c2, rtol=1e-6, atol=1e-12)
    assert w["params"]["accel_scale_tc_per_c"][2] == 0.0                 # the one face: its slope is in c1
    with VirtualBench(speed=0, seed=SEED, truth="random") as vb:    # the same part: its truth from the seed
        truth = vb.get_truth()
    worst = 0.0
    for triad in ("accel", "gyro"):
        ref = d["t_ref_c"][triad]
        for k, a in enumerate(d["fit"][triad]["axes"]):
            if triad == "accel" and k == 2:
                assert "not separated" in a["undetermined"][0]     # bias and g·scale on the one face
                continue
            f = polyfit_from_json(a, ref)
            lo, hi = a["span_c"]
            tt = np.linspace(lo + 0.15 * (hi - lo), hi, 8)     # the first degrees: the hysteresis changes branch
            temps = np.repeat(tt[:, None], 4, axis=1)
            tb = ST.truth_bias(truth, temps)[0 if triad == "accel" else 1][:, k]
            t0 = ST.truth_bias(truth, np.full((1, 4), ref))[0 if triad == "accel" else 1][0, k]
            err = (f(tt) - f.coef[0]) - (tb - t0)
            sig = f.curve_sigma(tt, relative=True)
            worst = max(worst, float(np.max(np.abs(err) / sig)))
    assert worst < 4.0, worst


def test_ctrl_c_keeps_the_fit_of_what_came(tmp_path):
    out = tmp_path / "w"
    p = _cli("--warmup", "--sim", "--sim-seed", "4", "--tau", "60", "--out", str(out))
    lines: list[str] = []
    wait_for_line(p, r"orders accel \d/\d/\d", lines, timeout_s=120)        # a fit exists
    p.send_signal(signal.SIGINT)
    stdout, stderr = finish(p, 60)
    assert p.returncode == 130, "".join(lines) + stdout + stderr
    assert "Traceback" not in stderr
    d = json.loads((out / "thermal.json").read_text())
    assert d["status"] == "interrupted" and d["fit"] is not None and d["bins"] is not None
    assert "interrupted" in d["stop_reason"] and len(d["fit"]["gyro"]["axes"]) == 3


def test_two_faces_of_a_cube_separate_the_accel_scale_term(tmp_path):
    """Two warm-ups of the same virtual part, +Z up and −Z up, fitted together with
    `thermal --fit-warmups`: the accelerometer Z scale temperature term comes out (near the truth)
    and is no longer reported as undetermined; the bias curve of Z is the truth's within its σ;
    written with --port --write, the device holds the scale term."""
    cfg = W.WarmupConfig(rate_hz=100, bin_s=2.0, stop_window_s=20.0, stop_rate_c_per_min=0.5, fit_every_s=1e9)
    dirs = []
    with VirtualBench(speed=0, seed=6, truth="random") as vb, vb.device() as dev:
        # no bias random walk here: the coefficients' σ do not hold it (the curve's σ does), and this
        # test is about what the faces separate
        vb.set_truth(accel={"scale_tc": [0.0, 0.0, 1.5e-4], "rw_k": [0.0] * 3})
        for face in ("+z", "-z"):
            hooks = W.sim_warmup_hooks(vb, 5.0, 40.0, tau_s=20.0, self_heat_c=1.0)
            d = W.run_warmup(dev, tmp_path / face, W.WarmupConfig(**{**cfg.to_json(), "face": face}), hooks)
            assert d["status"] == "done" and d["fit"]["accel"]["axes"][2]["scale_tc_per_c"] is None
            dirs.append(str(tmp_path / face))
        truth = vb.get_truth()
        out = tmp_path / "both"
        p = _cli("--fit-warmups", *dirs, "--export", "px4", "--port", vb.port_url, "--write", "--out", str(out))
        stdout, stderr = finish(p, 120)
        assert p.returncode == 0, stdout + stderr
        with vb.device() as dev:
            from imubench.wire.protocol_gen import ParamsWhich
            active = dev.get_params(ParamsWhich.ACTIVE).params
    d = json.loads((out / "thermal.json").read_text())
    assert d["write"]["verified"] and "rebooted" in d["write"]["steps"]
    assert active.accel_scale_tc_per_c[2] == pytest.approx(d["fit"]["accel"]["axes"][2]["scale_tc_per_c"], rel=1e-6)
    z = d["fit"]["accel"]["axes"][2]
    assert d["faces"] == ["+z", "-z"] and not any("not separated" in u for u in z["undetermined"])
    # the scale term: within 5σ and 30 % (seeds 6-9 of this run gave |z| up to 3.4: its σ is from the
    # joint fit alone, the two runs' lags and hysteresis differ a little)
    s_fit, s_sig = z["scale_tc_per_c"], z["scale_tc_sigma_per_c"]
    assert abs(s_fit - 1.5e-4) < min(5 * s_sig, 0.3 * 1.5e-4), (s_fit, s_sig)
    # the bias curve of Z (no longer holding g·scale) against the truth's, within its σ over the span
    f = polyfit_from_json(z, d["t_ref_c"]["accel"])
    lo, hi = z["span_c"]
    tt = np.linspace(lo + 0.15 * (hi - lo), hi, 8)
    tb = ST.truth_bias(truth, np.repeat(tt[:, None], 4, axis=1))[0][:, 2]
    t0 = ST.truth_bias(truth, np.full((1, 4), d["t_ref_c"]["accel"]))[0][0, 2]
    err = (f(tt) - f.coef[0]) - (tb - t0)
    assert np.all(np.abs(err) < 4 * f.curve_sigma(tt, relative=True)), np.round(err / f.curve_sigma(tt, relative=True), 1)
    assert "scale temperature term" in (out / "warmup.px4-thermal.params").read_text()


def test_lost_link_and_stop_event_keep_the_fit(tmp_path):
    """The virtual device dies mid-run (its process stopped once a fit exists): status "failed",
    the link's error, and the fit of what came; a stop event ends a run as "interrupted" with its fit."""
    cfg = W.WarmupConfig(rate_hz=100, bin_s=2.0, stop_window_s=20.0, stop_rate_c_per_min=0.5, fit_every_s=10.0,
                         stall_s=3.0)
    import threading
    with VirtualBench(speed=0, seed=8, truth="random") as vb, vb.device() as dev:
        stop = threading.Event()
        d = W.run_warmup(dev, tmp_path / "stop", cfg, W.sim_warmup_hooks(vb, 5.0, 45.0, tau_s=60.0),
                         on_progress=lambda p: p["fit"] is not None and p["elapsed_s"] > 30 and stop.set(), stop=stop)
        assert d["status"] == "interrupted" and d["fit"] is not None and d["stop_reason"].startswith("stopped")
        got = []

        def kill(p):
            got.append(p)
            if p["fit"] is not None and vb.running:
                vb.stop()
        d = W.run_warmup(dev, tmp_path / "lost", cfg, W.sim_warmup_hooks(vb, 5.0, 45.0, tau_s=60.0), on_progress=kill)
    assert d["status"] == "failed" and d["stop_reason"] == "link lost" and d["error"], d["error"]
    assert d["fit"] is not None and len(d["fit"]["accel"]["axes"]) == 3
    on_disk = json.loads((tmp_path / "lost" / "thermal.json").read_text())
    assert on_disk["status"] == "failed" and on_disk["fit"] == d["fit"]
    assert set(got[-1]) >= {"elapsed_s", "temp_c", "rate_c_per_min", "span_c", "fit"}


def test_stops_when_the_span_is_covered_by_every_sensor(tmp_path):
    """--span 5,30 on a part soaked at 5 °C and warming towards 45 °C: the run ends as soon as every
    sensor's samples have reached 30 °C (judged by the samples, not by bin means that lag a fast
    rise), long before the temperatures would stop rising; the written span is inside the data."""
    cfg = W.WarmupConfig(span_c=(5.0, 30.0), rate_hz=100, bin_s=2.0, stop_window_s=20.0, fit_every_s=10.0)
    with VirtualBench(speed=0, seed=9, truth="random") as vb, vb.device() as dev:
        d = W.run_warmup(dev, tmp_path / "s", cfg, W.sim_warmup_hooks(vb, 5.0, 45.0, tau_s=40.0))
    assert d["status"] == "done" and "covered by every sensor" in d["stop_reason"], d["stop_reason"]
    lo = [s[0] for s in d["progress"]["span_c"]]
    hi = [s[1] for s in d["progress"]["span_c"]]
    assert max(lo) <= 5.5 and min(hi) >= 29.5 and max(hi) < 36.0, d["progress"]["span_c"]


def test_a_board_not_cooled_is_refused_for_a_span_from_cold(tmp_path):
    """The real-bench path (a prompt, no virtual fridge): the board is at room temperature but the
    span starts at 5 °C: one line says where the sensors are and what to do; thermal.json says so."""
    with VirtualBench(speed=0, seed=2) as vb:
        r = subprocess.run([sys.executable, "-m", "imubench", "thermal", "--warmup", "--span", "5,45", "--port",
                            vb.port_url, "--out", str(tmp_path / "w")], capture_output=True, text=True, input="\n",
                           timeout=120)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert "already, above the span's lower end 5 °C: cool the board first" in r.stderr
    d = json.loads((tmp_path / "w" / "thermal.json").read_text())
    assert d["status"] == "failed" and "cool the board first" in d["error"] and d["fit"] is None


def test_bias_random_walk_is_seen_and_enters_the_curve_sigma():
    """Bins of a warm-up whose bias also walks (K = 2e-5 per √s, bins of 10 s with white 5e-5): the
    walk is estimated from bins at one temperature far apart in time (on average within a factor
    2 of K²; one path gives a noisy estimate), and with it in the curve's σ the truth is within 3σ
    in at least 3/4 of 30 runs, far more often than without it (the fit takes the walk for a
    thermal slope). Honest on average, low in some runs: what one warm-up can tell of a walk."""
    rng = np.random.default_rng(21)
    K, white, n = 2e-5, 5e-5, 150
    ks, zs, z0 = [], [], []
    for _ in range(30):
        t = np.arange(n) * 10.0
        temp = np.round((5 + 40 * (1 - np.exp(-t / 300.0))) / 0.2) * 0.2
        walk = np.cumsum(rng.normal(0, K * np.sqrt(10.0), n))
        y = TP.poly_eval(LINE, temp, T_REF) + walk + rng.normal(0, white, n)
        seg = TP.FaceSegment(np.zeros(3), temp, np.tile(y[:, None], 3), np.full((n, 3), white), t)
        f = TP.fit_triad_faces([seg], T_REF, None)[0].bias
        ks.append(f.rw_var_per_s)
        tt = np.linspace(f.span_c[0] + 2, f.span_c[1], 7)
        err = np.abs((f(tt) - f.coef[0]) - (TP.poly_eval(LINE, tt, T_REF) - LINE[0]))
        zs.append(np.max(err / f.curve_sigma(tt, relative=True)))
        f.rw_var_per_s = 0.0
        z0.append(np.max(err / f.curve_sigma(tt, relative=True)))
    assert 0.5 < np.mean(ks) / K ** 2 < 2.0, np.mean(ks) / K ** 2
    within, within0 = np.mean(np.array(zs) < 3), np.mean(np.array(z0) < 3)
    assert within >= 0.75 and within >= within0 + 0.3, (within, within0, np.round(zs, 1))


def test_warmup_on_the_f103_image_writes_terms_the_image_applies(tmp_path):
    """The exact STM32F103 image under the emulator (short: τ 5 s, 1 s bins, stopped at 2 °C/min over
    5 s: about 30 s of device time from 5 to 45 °C, then the write's 2 x 1000-sample check): the
    warm-up runs, writes layout-3 terms, and the image's own calibrated output matches the host's
    model after the reboot (the device check of the write)."""
    out = tmp_path / "w"
    p = _cli("--warmup", "--sim", "--target", "f103", "--tau", "5", "--stop-window", "5", "--stop-rate", "2.0",
             "--bin", "1", "--write", "--out", str(out))
    stdout, stderr = finish(p, 300)
    assert p.returncode == 0, stdout + stderr
    d = json.loads((out / "thermal.json").read_text())
    assert d["status"] == "done" and d["config"]["target"] == "f103" and d["device"]["board"] != "SIM"
    assert d["write"]["verified"] and d["write"]["check"]["ok"]
    assert any(a["order"] >= 1 for a in d["fit"]["gyro"]["axes"])      # a temperature dependence was written


def test_the_progress_line_comes_every_fit_every_s_of_device_time(tmp_path, monkeypatch):
    """'every 20 s' means every 20 s of device time, within a read: the line came only when a
    10 s bin completed, 26 to 51 s apart (issue 38)."""
    import threading
    said = []
    real = W.format_progress
    monkeypatch.setattr(W, "format_progress", lambda p: said.append(p["elapsed_s"]) or real(p))
    cfg = W.WarmupConfig(rate_hz=50, bin_s=10.0, stop_window_s=60.0, stop_rate_c_per_min=0.01, fit_every_s=20.0)
    stop = threading.Event()
    with VirtualBench(speed=0, seed=8, truth="random") as vb, vb.device() as dev:
        W.run_warmup(dev, tmp_path / "w", cfg, W.sim_warmup_hooks(vb, 5.0, 45.0, tau_s=200.0),
                     on_progress=lambda p: p["elapsed_s"] > 125 and stop.set(), stop=stop)
    assert len(said) >= 5, said
    later = np.array(said[1:])          # the first with the first bin, then on every 20 s of device time
    assert np.all(np.abs(later - 20.0 * np.round(later / 20.0)) <= 0.5), np.round(said, 2)
    assert np.all(np.abs(np.diff(later) - 20.0) <= 0.5), np.round(said, 2)


def test_a_board_with_sibling_parts_is_named_by_them_in_every_line_and_file(tmp_path):
    """A virtual board with an ADXL359 and an ADXRS453 on Z (issue 35): the warm-up says which parts
    it has, names them with the temperatures in its lines, in thermal.json's fit and in the PX4 file;
    a span beyond a part's operating range is refused naming that part, before anything streams."""
    cfg = W.WarmupConfig(span_c=(5.0, 30.0), rate_hz=100, bin_s=2.0, stop_window_s=20.0, fit_every_s=10.0,
                         exports=("px4",))
    said = []
    with VirtualBench(speed=0, seed=9, truth="random", parts="accel=adxl359,gyro_z=adxrs453") as vb, \
            vb.device() as dev:
        hooks = W.sim_warmup_hooks(vb, 5.0, 45.0, tau_s=40.0, say=said.append)
        oven = dataclasses.replace(hooks, reachable_c=None)     # a real oven: it could reach 110 °C
        with pytest.raises(W.WarmupError, match=r"span 5\.\.110 °C: this board's ADXRS450 works from -40 to 105 °C"):
            W.run_warmup(dev, tmp_path / "hot", W.WarmupConfig(span_c=(5.0, 110.0)), oven)
        assert not (tmp_path / "hot").exists()
        d = W.run_warmup(dev, tmp_path / "s", cfg, hooks)
    assert d["status"] == "done", d.get("error")
    assert "parts: accel ADXL359, gyro_x ADXRS450, gyro_y ADXRS450, gyro_z ADXRS453" in said
    assert any("temperatures ADXL359/gyro X/Y/Z (ADXRS450/ADXRS450/ADXRS453)" in s for s in said), said
    assert d["device"]["parts"] == ["ADXL359", "ADXRS450", "ADXRS450", "ADXRS453"]
    assert d["fit"]["accel"]["temperature"] == "the ADXL359 temperature (all three axes)"
    assert "ADXRS450/ADXRS450/ADXRS453" in d["fit"]["gyro"]["temperature"]
    px4 = (tmp_path / "s" / "warmup.px4-thermal.params").read_text()
    assert "against the ADXL359 temperature" in px4 and "ADXRS453" in px4 and "ADXL355" not in px4
