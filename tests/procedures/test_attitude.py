"""Attitude (roll/pitch) from the calibrated accelerometer and gyros: sign convention against
the virtual device, the three filters, and the tilt-step requirement (static error after
settling <= 0.01 deg RMS; the seed paper reached 0.104 deg)."""
from __future__ import annotations

import csv
import math
import time

import numpy as np
import pytest
from imubench.analysis import tilt as T
from imubench.cli import main as imubench
from imubench.procedures import attitude as A
from imubench.results import attitude as RA
from imubench.units import G0_MPS2


# ------------------------------------------------------------------ pure functions
@pytest.mark.parametrize("roll,pitch", [(0, 0), (20, 0), (-20, 0), (0, 20), (0, -20), (15, -25),
                                        (-35, 40), (170, 10), (-120, -60)])
def test_accel_tilt_closed_form(roll, pitch):
    r, p = math.radians(roll), math.radians(pitch)
    f = G0_MPS2 * np.array([-math.sin(p), math.sin(r) * math.cos(p), math.cos(r) * math.cos(p)])
    got_r, got_p = T.accel_tilt(f)
    assert got_r == pytest.approx(roll, abs=1e-9)
    assert got_p == pytest.approx(pitch, abs=1e-9)
    # a block, and scale-free
    rr, pp = T.accel_tilt(np.stack([f, 0.5 * f]))
    assert np.allclose(rr, roll) and np.allclose(pp, pitch)


def test_accel_tilt_named_vectors():
    g = G0_MPS2
    assert T.accel_tilt([0, 0, g]) == pytest.approx((0, 0))
    assert T.accel_tilt([0, g, 0]) == pytest.approx((90, 0))        # left side (+Y) up
    assert T.accel_tilt([-g, 0, 0]) == pytest.approx((0, 90))       # nose (+X) down: +pitch
    assert T.accel_tilt([g, 0, 0]) == pytest.approx((0, -90))
    assert T.accel_tilt([0, 0, -g])[0] == pytest.approx(180)        # upside down


def test_euler_rates_single_axis():
    w = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])
    rr, pr = T.euler_rates(w, np.zeros(2), np.zeros(2))
    assert np.allclose(rr, [0.1, 0.0]) and np.allclose(pr, [0.0, 0.2])


def test_settling_time():
    t = np.arange(0, 5, 0.01)
    a = 10 * (1 - np.exp(-t / 0.5))
    st = T.settling_time(t, a, 10.0, 0.1)
    assert st == pytest.approx(0.5 * math.log(100), abs=0.011)
    assert T.settling_time(t, np.full_like(t, 10.0), 10.0, 0.1) == 0.0
    assert T.settling_time(t, a, 20.0, 0.1) == math.inf
    assert T.settling_time(t, a, 10.0, 0.1, t_step=1.0) == pytest.approx(st - 1.0, abs=0.011)


def _synthetic_step(fs=200.0, n=2000, step_at=400, deg=10.0, rate_dps=20.0, seed=0):
    """Roll from 0 to `deg` at rate_dps starting at sample step_at, with sensor noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    move = round(deg / rate_dps * fs)
    w = np.zeros(n)
    w[step_at:step_at + move] = math.radians(rate_dps)
    roll = np.concatenate([[0.0], np.cumsum(w[1:]) / fs])
    acc = G0_MPS2 * np.stack([np.zeros(n), np.sin(roll), np.cos(roll)], axis=1)
    acc += rng.normal(0, T.ACCEL_NOISE_N * math.sqrt(fs), acc.shape)
    gyr = np.stack([w, np.zeros(n), np.zeros(n)], axis=1) + rng.normal(0, T.GYRO_NOISE_N * math.sqrt(fs), (n, 3))
    return t, acc, gyr, np.degrees(roll)


def test_filters_stream_equals_batch_and_track():
    _t, acc, gyr, truth = _synthetic_step()
    for f in T.make_filters("all", num=20, tau_s=0.5):
        r_all, p_all = f.run(acc, gyr, 200)
        f.reset()
        parts = [f.update(acc[i:i + 37], gyr[i:i + 37], 1 / 200) for i in range(0, len(acc), 37)]
        r_st = np.concatenate([p[0] for p in parts])
        assert np.allclose(r_all, r_st, atol=1e-9), f.name
        # settled at the end: mean of the last second near the truth (the complementary
        # filter with tau 0.5 s integrates gyro noise over 0.5 s: looser)
        tol = 0.03 if isinstance(f, T.Complementary) else 0.01
        assert abs(np.mean(r_all[-200:]) - truth[-1]) < tol, f.name
        assert abs(np.mean(p_all[-200:])) < tol, f.name


def test_rc_settles_slower_with_larger_num():
    t, acc, gyr, _truth = _synthetic_step()
    times = [T.settling_time(t, T.RCLowPass(n).run(acc, gyr, 200)[0], 10.0, 0.05, t_step=2.0)
             for n in (5, 20, 80)]
    assert all(math.isfinite(x) for x in times)
    assert times[0] < times[1] < times[2]


def test_kalman_speed():
    n = 20000
    acc = np.tile([0.0, 0.0, G0_MPS2], (n, 1))
    gyr = np.zeros((n, 3))
    t0 = time.perf_counter()
    T.KalmanTilt().run(acc, gyr, 200)
    per_sample = (time.perf_counter() - t0) / n
    print(f"Kalman (roll + pitch): {per_sample * 1e6:.2f} us per sample")
    assert per_sample < 50e-6          # 200 Hz needs < 5000 us per sample


# ------------------------------------------------------------------ on the virtual device
@pytest.fixture(scope="module")
def bench():
    from imubench.device.sim import VirtualBench
    with VirtualBench(speed=0, seed=1) as b:   # default truth: ideal parts, datasheet noise
        yield b


@pytest.mark.parametrize("roll,pitch", [(20, 0), (-20, 0), (0, 20), (0, -20)])
def test_sign_convention_matches_simulator(bench, roll, pitch):
    bench.set_orientation(roll_deg=roll, pitch_deg=pitch, yaw_deg=0)
    st = bench.status()
    assert T.accel_tilt(st["specific_force_mps2"]) == pytest.approx((roll, pitch), abs=1e-9)
    with bench.device() as dev:
        dev.start_stream(rate_hz=200, calibrated=True)
        try:
            block = dev.read(n_samples=200)
        finally:
            dev.stop_stream()
    r, p = T.accel_tilt(block.accel_mps2.astype(np.float64).mean(axis=0))
    assert r == pytest.approx(roll, abs=0.02)
    assert p == pytest.approx(pitch, abs=0.02)
    bench.set_orientation(roll_deg=0, pitch_deg=0, yaw_deg=0)


def test_tilt_steps_static_error_and_settling(bench, tmp_path):
    t0 = time.perf_counter()
    with bench.device() as dev:
        res = A.tilt_step_experiment(bench, dev, angles=(-20, -10, 0, 10, 20), axes=("roll", "pitch"),
                                     rate_hz=200, rate_dps=20.0, dwell_s=6.0, avg_s=3.0, band_deg=0.05)
    print(f"\ntilt steps on the virtual turntable ({time.perf_counter() - t0:.1f} s wall); settling "
          f"time from the motion start to within +-{res['band_deg']} deg, static error = mean of the "
          f"last 3 s of each dwell minus the simulator's angle:")
    print(RA.summarize(res))
    steps = res["steps"]
    assert len(steps) == 10
    assert [s.target_deg for s in steps] == pytest.approx([-20, -10, 0, 10, 20] * 2, abs=1e-6)
    rms = {n: math.sqrt(np.mean([s.error_deg[n] ** 2 for s in steps])) for n in ["accel"] + res["filters"]}
    for name in ("rc10", "rc40", "kalman", "comp0.1s"):
        assert rms[name] <= 0.01, (name, rms[name])
    assert rms["comp0.5s"] <= 0.02          # gyro noise integrated over 0.5 s; reported
    for s in steps:
        move_s = (20.0 if s.target_deg == -20 else 10.0) / 20.0
        for name in res["filters"]:
            assert math.isfinite(s.settle_s[name]), (s, name)
            assert s.settle_s[name] >= move_s - 0.02         # cannot beat the turntable
        assert s.settle_s["rc10"] < s.settle_s["rc40"]       # larger num: slower
        # gyro-aided filters follow the move: settled (almost) as soon as it ends
        assert s.settle_s["kalman"] <= s.settle_s["rc10"]
        assert s.settle_s["kalman"] < move_s + 0.1
    png = tmp_path / "steps.png"
    RA.plot_steps(res, png)
    assert png.stat().st_size > 10000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_main_attitude_records(bench, tmp_path, capsys):
    rec = tmp_path / "att.bin"
    bench.set_orientation(roll_deg=10, pitch_deg=-5, yaw_deg=0)
    rc = imubench(["attitude", "--port", bench.port_url, "--rate", "200", "--duration", "5.0",
                          "--record", str(rec), "--filter", "all"])
    bench.set_orientation(roll_deg=0, pitch_deg=0, yaw_deg=0)
    assert rc == 0
    out = capsys.readouterr().out
    assert "kalman" in out and "rc20" in out and "comp0.5s" in out
    assert rec.stat().st_size > 1000
    with open(str(rec) + ".angles.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert 995 <= len(rows) <= 1001                          # 5 s of device time at 200 Hz, at any speed
    assert set(rows[0]) >= {"t_s", "accel_roll_deg", "kalman_roll_deg", "rc20_pitch_deg", "comp0.5s_roll_deg"}
    last = rows[-1]
    for name in ("rc20", "kalman", "comp0.5s"):
        assert float(last[f"{name}_roll_deg"]) == pytest.approx(10, abs=0.05)
        assert float(last[f"{name}_pitch_deg"]) == pytest.approx(-5, abs=0.05)
    # the capture decodes back to the same stream
    from imubench.wire.decoder import decode_bytes
    _, _, cal, _ = decode_bytes(rec.read_bytes())
    assert cal is not None and len(cal) >= len(rows)


def test_main_attitude_bad_port(capsys):
    assert imubench(["attitude", "--port", "socket://127.0.0.1:1", "--duration", "0.1"]) == 1
    assert "imubench attitude" in capsys.readouterr().err


def test_attitude_plot_and_numbers_for_the_report(tmp_path, capsys):
    """`attitude --plot FILE` writes the PNG the report embeds and its numbers beside it; a
    device with factory parameters is named as uncalibrated (stderr, the plot's title and
    the numbers)."""
    import json
    png = tmp_path / "att.png"
    assert imubench(["attitude", "--sim", "--duration", "2", "--plot", str(png), "--print-hz", "1"]) == 0
    err = capsys.readouterr().err
    assert "factory parameters" in err and "uncalibrated" not in err.splitlines()[-1]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    d = json.loads(png.with_suffix(".json").read_text())
    assert d["mode"] == "live" and d["device"]["factory_parameters"] is True
    assert 1.9 <= d["duration_s"] <= 2.01                       # device time, cut at --duration
    assert abs(d["roll_deg"]["kalman"]["mean"]) < 0.05 and d["roll_deg"]["accel"]["std"] > 0


def test_attitude_steps_need_the_virtual_bench():
    assert imubench(["attitude", "--steps", "--port", "socket://127.0.0.1:1"]) == 2
