"""Temperature calibration (imubench.procedures.thermal): the weighted fit, and the whole sweep on the
virtual device: fitted coefficients written to the device cut the drift of its calibrated
output over the sweep at least 10x (the device applies them itself); thermal settling on a
ramping chamber; the write-back checked after a reboot; thermal.json written point by point."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench import units as U
from imubench.analysis import thermal as ATH
from imubench.cli import main as imubench
from imubench.device.sim import VirtualBench
from imubench.procedures import thermal as TH
from imubench.results import thermal as RTH
from imubench.wire import params as PR
from imubench.wire.protocol_gen import Params, ParamsWhich

TEMPS = [5.0, 25.0, 45.0]
ACC_BTC = np.array([2e-3, -1.5e-3, 1e-3])          # m/s²/°C
ACC_STC = np.array([1e-4, -8e-5, 2e-4])            # 1/°C
GYR_BTC = np.array([0.01, -0.008, 0.006]) * U.DEG  # rad/s/°C
GYR_STC = np.array([1e-4, -5e-5, 0.0])
FAST = TH.Settling(rate_c_per_min=0.1, window_s=1.0, timeout_s=120.0)   # short window: the sim has no lag


def _pack(p: Params) -> bytes:
    return Params.STRUCT.pack(*p.values())


def test_fit_tempco_recovers_known_coefficients():
    rng = np.random.default_rng(3)
    t = np.linspace(-10, 60, 8)
    coef, icpt = np.array([1e-3, -2e-3, 5e-4]), np.array([0.1, -0.05, 9.8])
    sig = np.tile([2e-4, 1e-4, 3e-4], (len(t), 1)) * rng.uniform(0.5, 2, (len(t), 3))
    z = []
    for _ in range(50):
        y = icpt + np.outer(t - 20.0, coef) + sig * rng.normal(size=sig.shape)
        c, _i, cov = ATH.fit_tempco(t, y, sig, t_ref_c=20.0)
        assert cov.shape == (3, 2, 2)
        z.append((c - coef) / np.sqrt(cov[:, 0, 0]))
    z = np.array(z)
    assert np.all(np.abs(z[0]) < 3)                 # one fit: within 3 sigma
    assert np.all(np.abs(z) < 4.5)                  # 150 draws: none absurd
    assert 0.6 < z.std() < 1.4                      # the sigmas are honest
    # unweighted, per-axis temperatures
    tt = np.column_stack([t, t + 0.3, t - 0.2])
    y = icpt + (tt - 25.0) * coef + 1e-4 * rng.normal(size=tt.shape)
    c, _, cov = ATH.fit_tempco(tt, y, None, 25.0)
    assert np.all(np.abs(c - coef) < 3 * np.sqrt(cov[:, 0, 0]))
    with pytest.raises(ValueError):
        ATH.fit_tempco([25.0, 25.0], np.zeros((2, 3)), None, 25.0)


def test_apply_tempcos_validates():
    f = ATH.ThermalFit(30.0, ACC_BTC, 0 * ACC_BTC, ACC_STC, 0 * ACC_STC, GYR_BTC, 0 * GYR_BTC, GYR_STC, 0 * GYR_STC)
    p = ATH.apply_tempcos(PR.identity(), f)
    assert p.accel_t_ref_c == p.gyro_t_ref_c == 30.0
    assert np.allclose(p.gyro_bias_tc_rad_s_per_c, GYR_BTC)
    # a block a warm-up wrote (curvature, a narrow span): the step method's line replaces it whole
    old = PR.identity()
    old.accel_bias_tc2_mps2_per_c2, old.gyro_bias_tc3_rad_s_per_c3 = (1e-5, 0.0, 0.0), (0.0, 2e-9, 0.0)
    old.accel_t_min_c, old.accel_t_max_c, old.gyro_t_min_c, old.gyro_t_max_c = 5, 45, 6, 44
    PR.validate(old)
    p = ATH.apply_tempcos(old, f)
    assert not any(p.accel_bias_tc2_mps2_per_c2 + p.gyro_bias_tc3_rad_s_per_c3)
    assert (p.accel_t_min_c, p.accel_t_max_c, p.gyro_t_min_c, p.gyro_t_max_c) == (-40, 85, -40, 85)
    f.accel_scale_tc = np.array([0.0, 0.0, 5e-3])   # above the device's limit
    with pytest.raises(PR.InvalidParams):
        ATH.apply_tempcos(PR.identity(), f, 25.0)


def test_sweep_on_virtual_device_cuts_drift_10x():
    with VirtualBench(speed=0, seed=4) as vb, vb.device() as dev:
        vb.set_truth(accel={"bias_tc": ACC_BTC.tolist(), "scale_tc": ACC_STC.tolist(), "rw_k": [0.0] * 3},
                     gyro=[{"bias_tempco_rad_s_per_c": float(b), "scale_tempco_per_c": float(s), **GYRO_NO_DRIFT}
                           for b, s in zip(GYR_BTC, GYR_STC)])
        dev.set_params(PR.identity())
        hooks = TH.sim_hooks(vb)
        points = TH.sweep(dev, TEMPS, hooks, n=1500, poses=tuple(ATH.POSES), turntable=True, settle=FAST)
        # the models' temperature outputs follow the set point at once (no ramp)
        for p, c in zip(points, TEMPS):
            assert abs(p.accel_temp_c - c) < 0.2 and np.all(np.abs(p.gyro_temp_c - c) < 0.2)
        fit = ATH.fit_sweep(points, 25.0)
        for got, sig, want in ((fit.accel_bias_tc, fit.accel_bias_tc_sigma, ACC_BTC),
                               (fit.accel_scale_tc, fit.accel_scale_tc_sigma, ACC_STC),
                               (fit.gyro_bias_tc, fit.gyro_bias_tc_sigma, GYR_BTC),
                               (fit.gyro_scale_tc, fit.gyro_scale_tc_sigma, GYR_STC)):
            assert np.all(np.abs(got - want) < 5 * sig + 1e-3 * np.abs(want)), (got, sig, want)

        before = TH.measure_drift(dev, TEMPS, hooks, n=2000, settle=FAST)
        new = ATH.apply_tempcos(PR.identity(), fit, 25.0)
        wb = TH.write_params(dev, new)
        assert wb["verified"] and "rebooted" in wb["steps"]
        back = dev.get_params(ParamsWhich.ACTIVE).params
        assert np.allclose(back.accel_bias_tc_mps2_per_c, fit.accel_bias_tc, rtol=1e-6)
        after = TH.measure_drift(dev, TEMPS, hooks, n=2000, settle=FAST)
        print(RTH.format_drift(before, after))
        ga, gb = after["gyro_drift_rad_s"], before["gyro_drift_rad_s"]
        aa, ab = after["accel_drift_mps2"], before["accel_drift_mps2"]
        assert np.all(gb >= 10 * ga), (gb, ga)           # gyro bias, every axis
        assert np.all(ab[:3] >= 10 * aa[:3]), (ab, aa)   # accel x, y (bias) and z (bias + scale)
        assert ab[3] >= 10 * aa[3]                       # |a|


def test_settling_waits_for_the_ramp():
    """With a ramping chamber the set_temperature hook returns at once; the sweep measures
    only after the sensors' temperatures stopped moving: each point at its set point, its
    first sample after the latest time the ramp can have ended. Without settling the same
    sweep measures mid-ramp (caught by the sensors-follow-the-set-point check), and a ramp
    slower than the timeout allows fails naming the temperature reached and the rate."""
    ramp = 2.0                                               # °C/s
    settle = TH.Settling(rate_c_per_min=0.1, window_s=2.0, timeout_s=120.0)
    with VirtualBench(speed=0, seed=6) as vb, vb.device() as dev:
        hooks = TH.sim_hooks(vb, ramp_c_per_s=ramp)
        set_t, ramp_end = hooks.set_temperature, {}

        def set_and_note(c):
            t_from = vb.status()["temperature_c"]
            set_t(c)
            st = vb.status()
            assert st["temperature_ramping"]                 # the hook does not wait for the ramp
            ramp_end[c] = st["time_us"] + abs(c - t_from) / ramp * 1e6   # latest end of the ramp

        hooks.set_temperature = set_and_note
        points = TH.sweep(dev, [15.0, 35.0], hooks, n=300, poses=("+z",), turntable=False, settle=settle)
        for p in points:
            c = p.target_c
            assert abs(p.accel_temp_c - c) < 0.2 and np.all(np.abs(p.gyro_temp_c - c) < 0.2), (c, p.accel_temp_c)
            assert p.t_first_us > ramp_end[c], (c, p.t_first_us, ramp_end[c])
            assert p.settle["waited_s"] >= settle.window_s and max(map(abs, p.settle["rate_c_per_min"])) < 0.1
        assert points[1].settle["waited_s"] >= 0.9 * 20.0 / ramp       # 15 -> 35 °C takes 10 s

        # the same without settling: measured while the chamber still ramps
        with pytest.raises(RuntimeError, match="sensors report"):
            TH.sweep(dev, [15.0], hooks, n=300, poses=("+z",), turntable=False, settle=None)

        # a ramp too slow for the timeout
        slow = TH.sim_hooks(vb, ramp_c_per_s=0.2)                    # 12 °C/min
        with pytest.raises(TH.SettleTimeout) as ei:
            TH.sweep(dev, [60.0], slow, n=300, poses=("+z",), turntable=False,
                     settle=TH.Settling(rate_c_per_min=0.1, window_s=2.0, timeout_s=4.0))
    e = ei.value
    msg = str(e)
    assert e.target_c == 60.0 and "set point 60 °C" in msg and "°C/min" in msg
    assert all(6.0 < r < 18.0 for r in e.rate_c_per_min), e.rate_c_per_min          # ~12 °C/min, heating
    assert all(c < 55.0 for c in e.temp_c)                                            # not there yet
    assert f"ADXL355 {e.temp_c[0]:.2f} °C" in msg and f"{e.rate_c_per_min[0]:+.3f}" in msg


def test_write_params_checks_after_reboot_and_restores_on_mismatch(monkeypatch):
    fit = ATH.ThermalFit(25.0, ACC_BTC, 0 * ACC_BTC, ACC_STC, 0 * ACC_STC, GYR_BTC, 0 * GYR_BTC, GYR_STC, 0 * GYR_STC)
    with VirtualBench(speed=0, seed=7) as vb, vb.device() as dev:
        old = PR.identity()
        old.accel_b_mps2 = (0.01, -0.02, 0.03)
        dev.set_params(old)
        dev.save_params()
        new = ATH.apply_tempcos(old, fit)
        reboots = vb.status()["reboots"]
        wb = TH.write_params(dev, new)
        assert wb["verified"] and wb["generation"] >= 2 and "rebooted" in wb["steps"]
        assert wb["steps"][-1].startswith("read back after reboot")
        assert vb.status()["reboots"] == reboots + 1                   # it really rebooted
        assert _pack(dev.get_params(ParamsWhich.ACTIVE).params) == _pack(new)
        assert _pack(dev.get_params(ParamsWhich.STORED).params) == _pack(new)

        # the active parameters after the reboot differ in one bit-ish: detected, `new` restored
        fit.gyro_scale_tc = GYR_STC * 2
        newer = ATH.apply_tempcos(old, fit)
        real_get, real_reboot, seen = dev.get_params, dev.reboot, []

        def reboot(*a, **k):
            seen.append("reboot")
            return real_reboot(*a, **k)

        def get_params(which=ParamsWhich.ACTIVE):
            rb = real_get(which)
            if seen == ["reboot"] and which == ParamsWhich.ACTIVE:
                seen.append("tampered")
                p = Params.from_values(rb.params.values())
                p.gyro_scale_tc_per_c = (p.gyro_scale_tc_per_c[0] * (1 + 1e-6),) + tuple(p.gyro_scale_tc_per_c[1:])
                return dataclasses.replace(rb, params=p)
            return rb

        monkeypatch.setattr(dev, "reboot", reboot)
        monkeypatch.setattr(dev, "get_params", get_params)
        with pytest.raises(RuntimeError, match="after reboot"):
            TH.write_params(dev, newer)
        assert seen == ["reboot", "tampered"]
        monkeypatch.undo()
        assert _pack(dev.get_params(ParamsWhich.ACTIVE).params) == _pack(new)
        assert _pack(dev.get_params(ParamsWhich.STORED).params) == _pack(new)
        dev.reboot(wait_s=10.0)
        assert _pack(dev.get_params(ParamsWhich.ACTIVE).params) == _pack(new)


def test_interrupted_sweep_keeps_the_points_measured(tmp_path):
    """thermal.json is rewritten as each point is measured: a chamber failing before the
    third temperature leaves the first two on disk, with the error."""
    out = tmp_path / "t"
    with VirtualBench(speed=0, seed=8) as vb, vb.device() as dev:
        hooks = TH.sim_hooks(vb, ramp_c_per_s=5.0)
        set_t, calls, on_disk = hooks.set_temperature, [], []

        def set_or_fail(c):
            calls.append(c)
            d = json.loads((out / "thermal.json").read_text())
            on_disk.append([p["set_c"] for p in d["points"]])
            if len(calls) == 3:
                raise RuntimeError("chamber failed")
            set_t(c)

        hooks.set_temperature = set_or_fail
        with pytest.raises(RuntimeError, match="chamber failed"):
            TH.run_thermal(dev, out, [10.0, 25.0, 40.0], hooks, n=200, settle=FAST, write=True)
    assert on_disk == [[], [10.0], [10.0, 25.0]]            # saved as they came, not at the end
    d = json.loads((out / "thermal.json").read_text())
    assert [p.name for p in out.iterdir()] == ["thermal.json"]  # no temp file left
    assert d["status"] == "failed" and d["stage"] == "sweep" and "chamber failed" in d["error"]
    assert [p["set_c"] for p in d["points"]] == [10.0, 25.0]
    for p in d["points"]:
        assert abs(p["accel_temp_c"] - p["set_c"]) < 0.2 and len(p["gyro_temp_c"]) == 3
        assert len(p["gyro_rest_rad_s"]) == 3 and len(p["accel_mps2"]["+z"]) == 3
        assert p["t_last_us"] > p["t_first_us"] and p["settle"]["window_s"] == FAST.window_s
    assert "accel_bias_tc_mps2_per_c" not in d and "write" not in d
    with pytest.raises(FileExistsError):                    # never overwrites a run
        RTH.ThermalRecord(out, {})


def test_main_thermal_sim_saves_thermal_json(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    args = ["--sim", "--temps", "10,40", "--samples", "400", "--write", "--ramp", "5", "--settle-s", "2"]
    assert imubench(["thermal", *args]) == 0
    out = capsys.readouterr().out
    assert "temperature coefficients" in out and "after" in out and "generation" in out
    dirs = list(tmp_path.glob("imubench-thermal-*"))               # the default: a new timestamped directory
    assert len(dirs) == 1 and [p.name for p in dirs[0].iterdir()] == ["thermal.json"]
    path = dirs[0] / "thermal.json"
    assert f"saved {dirs[0].name}/thermal.json" in out                # relative, as given
    d = json.loads(path.read_text())
    assert d["status"] == "done" and d["error"] is None and d["t_ref_c"] == 25.0 and d["notes"] == []
    assert d["config"]["ramp_c_per_s"] == 5.0 and d["config"]["settle_s"] == 2.0 and d["config"]["sim"]
    assert d["device"]["board"] == "SIM"
    # the points: sensors' temperatures, settled after the ramp, six poses, the turntable
    assert [p["set_c"] for p in d["points"]] == [10.0, 40.0]
    for p, ramp_s in zip(d["points"], (15 / 5, 30 / 5)):
        assert abs(p["accel_temp_c"] - p["set_c"]) < 0.2 and np.all(np.abs(np.array(p["gyro_temp_c"]) - p["set_c"]) < 0.2)
        assert p["settle"]["waited_s"] >= 0.9 * ramp_s + 2.0
        assert sorted(p["accel_mps2"]) == sorted(ATH.POSES) and len(p["gyro_turn_rad_s"]) == 3
        assert np.all(np.array(p["gyro_rest_sigma_rad_s"]) > 0)
    # the fit, with units in the keys, near the virtual device's truth
    truth = {"accel_bias_tc_mps2_per_c": TH.SIM_ACCEL_TRUTH["bias_tc"],
             "accel_scale_tc_per_c": TH.SIM_ACCEL_TRUTH["scale_tc"],
             "gyro_bias_tc_rad_s_per_c": [g["bias_tempco_rad_s_per_c"] for g in TH.SIM_GYRO_TRUTH],
             "gyro_scale_tc_per_c": [g["scale_tempco_per_c"] for g in TH.SIM_GYRO_TRUTH]}
    for key, want in truth.items():
        got = np.array(d[key])
        sig = np.array(d[key.replace("_tc_", "_tc_sigma_")])
        assert np.all(sig > 0) and np.all(np.abs(got - want) < 5 * sig + 1e-3 * np.abs(want)), (key, got, sig, want)
    # write-back verified after a reboot, and the drift measured before and after
    assert d["write"]["verified"] is True and d["write"]["generation"] >= 1 and "rebooted" in d["write"]["steps"]
    b, a = d["drift_before"], d["drift_after"]
    assert b["set_c"] == a["set_c"] == [10.0, 40.0] and len(b["accel_drift_mps2"]) == 4
    assert np.all(np.array(b["accel_drift_mps2"]) > 10 * np.array(a["accel_drift_mps2"]))
    assert np.all(np.array(b["gyro_drift_rad_s"]) > 3 * np.array(a["gyro_drift_rad_s"]))
    # an existing run is never overwritten
    assert imubench(["thermal", *args, "--out", str(dirs[0])]) == 1
    assert "exists" in capsys.readouterr().err
    assert json.loads(path.read_text()) == d


def test_thermal_says_each_thing_once(tmp_path, capsys):
    """A fast virtual chamber settles before the first wall-clock progress report: one
    'settled' line per temperature and stage, each stage named, no stream of repeated
    'settling' lines (on main: about twenty)."""
    assert imubench(["thermal", "--sim", "--temps", "10,40", "--samples", "300", "--write", "--ramp", "5",
                     "--out", str(tmp_path / "t")]) == 0
    out = capsys.readouterr().out
    assert out.count("settling:") == 0
    assert out.count("settled after") == 6                # 2 temperatures × sweep, drift before, drift after
    assert "before writing" in out and "after writing" in out
    fit = [ln for ln in out.splitlines() if " bias " in ln and " scale " in ln]
    assert len(fit) == 6 and all(" ± " in ln and ln.count(".") <= 4 for ln in fit)
