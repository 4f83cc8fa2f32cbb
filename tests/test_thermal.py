"""Temperature calibration (imubench.thermal): the weighted fit, and the whole sweep on the
virtual device: fitted coefficients written to the device cut the drift of its calibrated
output over the sweep at least 10x (the device applies them itself)."""
from __future__ import annotations

import numpy as np
import pytest
from imubench import params as PR
from imubench import thermal as TH
from imubench import units as U
from imubench.protocol_gen import ParamsWhich
from imubench.sim import VirtualBench

TEMPS = [5.0, 25.0, 45.0]
ACC_BTC = np.array([2e-3, -1.5e-3, 1e-3])          # m/s²/°C
ACC_STC = np.array([1e-4, -8e-5, 2e-4])            # 1/°C
GYR_BTC = np.array([0.01, -0.008, 0.006]) * U.DEG  # rad/s/°C
GYR_STC = np.array([1e-4, -5e-5, 0.0])


def test_fit_tempco_recovers_known_coefficients():
    rng = np.random.default_rng(3)
    t = np.linspace(-10, 60, 8)
    coef, icpt = np.array([1e-3, -2e-3, 5e-4]), np.array([0.1, -0.05, 9.8])
    sig = np.tile([2e-4, 1e-4, 3e-4], (len(t), 1)) * rng.uniform(0.5, 2, (len(t), 3))
    z = []
    for _ in range(50):
        y = icpt + np.outer(t - 20.0, coef) + sig * rng.normal(size=sig.shape)
        c, _i, cov = TH.fit_tempco(t, y, sig, t_ref_c=20.0)
        assert cov.shape == (3, 2, 2)
        z.append((c - coef) / np.sqrt(cov[:, 0, 0]))
    z = np.array(z)
    assert np.all(np.abs(z[0]) < 3)                 # one fit: within 3 sigma
    assert np.all(np.abs(z) < 4.5)                  # 150 draws: none absurd
    assert 0.6 < z.std() < 1.4                      # the sigmas are honest
    # unweighted, per-axis temperatures
    tt = np.column_stack([t, t + 0.3, t - 0.2])
    y = icpt + (tt - 25.0) * coef + 1e-4 * rng.normal(size=tt.shape)
    c, _, cov = TH.fit_tempco(tt, y, None, 25.0)
    assert np.all(np.abs(c - coef) < 3 * np.sqrt(cov[:, 0, 0]))
    with pytest.raises(ValueError):
        TH.fit_tempco([25.0, 25.0], np.zeros((2, 3)), None, 25.0)


def test_apply_tempcos_validates():
    f = TH.ThermalFit(30.0, ACC_BTC, 0 * ACC_BTC, ACC_STC, 0 * ACC_STC, GYR_BTC, 0 * GYR_BTC, GYR_STC, 0 * GYR_STC)
    p = TH.apply_tempcos(PR.identity(), f)
    assert p.accel_t_ref_c == p.gyro_t_ref_c == 30.0
    assert np.allclose(p.gyro_bias_tc_rad_s_per_c, GYR_BTC)
    f.accel_scale_tc = np.array([0.0, 0.0, 5e-3])   # above the device's limit
    with pytest.raises(PR.InvalidParams):
        TH.apply_tempcos(PR.identity(), f, 25.0)


def test_sweep_on_virtual_device_cuts_drift_10x():
    with VirtualBench(speed=20, seed=4) as vb, vb.device() as dev:
        vb.set_truth(accel={"bias_tc": ACC_BTC.tolist(), "scale_tc": ACC_STC.tolist(), "rw_k": [0.0] * 3},
                     gyro=[{"bias_tempco_rad_s_per_c": float(b), "scale_tempco_per_c": float(s), "bias_rw_k": 0.0}
                           for b, s in zip(GYR_BTC, GYR_STC)])
        dev.set_params(PR.identity())
        hooks = TH.sim_hooks(vb)
        points = TH.sweep(dev, TEMPS, hooks, n=1500, poses=tuple(TH.POSES), turntable=True)
        # the models' temperature outputs follow the set point at once (no ramp)
        for p, c in zip(points, TEMPS):
            assert abs(p.accel_temp_c - c) < 0.2 and np.all(np.abs(p.gyro_temp_c - c) < 0.2)
        fit = TH.fit_sweep(points, 25.0)
        for got, sig, want in ((fit.accel_bias_tc, fit.accel_bias_tc_sigma, ACC_BTC),
                               (fit.accel_scale_tc, fit.accel_scale_tc_sigma, ACC_STC),
                               (fit.gyro_bias_tc, fit.gyro_bias_tc_sigma, GYR_BTC),
                               (fit.gyro_scale_tc, fit.gyro_scale_tc_sigma, GYR_STC)):
            assert np.all(np.abs(got - want) < 5 * sig + 1e-3 * np.abs(want)), (got, sig, want)

        before = TH.measure_drift(dev, TEMPS, hooks, n=2000)
        new = TH.apply_tempcos(PR.identity(), fit, 25.0)
        TH.write_params(dev, new)
        back = dev.get_params(ParamsWhich.ACTIVE).params
        assert np.allclose(back.accel_bias_tc_mps2_per_c, fit.accel_bias_tc, rtol=1e-6)
        after = TH.measure_drift(dev, TEMPS, hooks, n=2000)
        print(TH.format_drift(before, after))
        ga, gb = after["gyro_drift_rad_s"], before["gyro_drift_rad_s"]
        aa, ab = after["accel_drift_mps2"], before["accel_drift_mps2"]
        assert np.all(gb >= 10 * ga), (gb, ga)           # gyro bias, every axis
        assert np.all(ab[:3] >= 10 * aa[:3]), (ab, aa)   # accel x, y (bias) and z (bias + scale)
        assert ab[3] >= 10 * aa[3]                       # |a|


def test_main_thermal_sim(capsys):
    assert TH.main_thermal(["--sim", "--temps", "10,40", "--samples", "800", "--write"]) == 0
    out = capsys.readouterr().out
    assert "temperature coefficients" in out and "after" in out and "generation" in out
