"""The device applies layout 3's temperature model (docs/conventions.md, "Temperature model"):
a cubic bias polynomial per axis, evaluated at the sensor's temperature clamped into the
triad's calibrated span, and the linear scale term at the same clamped ΔT. On the host build and
the exact F103 and F4 images, a block with a cubic bias and a narrow span is set, the virtual
bench's temperature moved below, into and above the span, and the calibrated stream compared with
the host mirror (`imubench.wire.params.correct`) applied to the raw stream of the same moment."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench import units as U
from imubench.device.link import Device
from imubench.device.sim import VirtualBench
from imubench.wire import params as PR

SPAN_A, SPAN_G = (10, 40), (15, 35)
T_REF_A, T_REF_G = 22.0, 25.0


def _cubic_params():
    p = PR.identity()
    p = replace(p, accel_m=(1.01, 0.002, -0.001, 0.0015, 0.992, 0.0, -0.002, 0.001, 1.004),
                accel_b_mps2=(0.05, -0.08, 0.12), gyro_m=(1.02, 0.01, 0.0, -0.005, 0.98, 0.002, 0.0, 0.003, 1.01),
                gyro_b_rad_s=(0.004, -0.002, 0.001),
                accel_bias_tc_mps2_per_c=(1e-3, -2e-3, 5e-4), accel_bias_tc2_mps2_per_c2=(2e-4, -1e-4, 3e-4),
                accel_bias_tc3_mps2_per_c3=(1e-5, 2e-5, -1e-5), accel_scale_tc_per_c=(1e-4, 0.0, -2e-4),
                gyro_bias_tc_rad_s_per_c=(2e-4, -1e-4, 1e-4), gyro_bias_tc2_rad_s_per_c2=(-2e-5, 1e-5, 3e-5),
                gyro_bias_tc3_rad_s_per_c3=(3e-6, -2e-6, 1e-6), gyro_scale_tc_per_c=(1e-4, -1e-4, 0.0),
                gyro_g_rad_s_per_mps2=(1e-4, 0.0, 0.0, 0.0, -5e-5, 0.0, 0.0, 0.0, 2e-5),
                accel_t_ref_c=T_REF_A, gyro_t_ref_c=T_REF_G, accel_t_min_c=SPAN_A[0], accel_t_max_c=SPAN_A[1],
                gyro_t_min_c=SPAN_G[0], gyro_t_max_c=SPAN_G[1])
    PR.validate(p)
    return PR.from_json(PR.to_json(p))


def _one(batch, name):
    """The one value every sample of a noise-free read holds (the test needs it constant)."""
    v = np.asarray(getattr(batch, name))
    assert len(np.unique(v, axis=0)) == 1, f"{name} varies within the read"
    return v[:1]


@pytest.mark.parametrize("target", ["host", "f103", "f4"])
def test_calibrated_stream_applies_the_clamped_cubic_like_the_host(target):
    p = _cubic_params()
    with VirtualBench(speed=0, seed=8, target=target) as vb, Device.open(vb.port_url, timeout=10.0) as dev:
        vb.set_truth(accel={"noise_n": 0.0, "rw_k": 0.0},
                     gyro=[{"noise_n": 0.0, **GYRO_NO_DRIFT, "bias_rad_s": 0.01 * (k + 1)} for k in range(3)])
        g = np.array([0.3, -0.5, 0.81])
        vb.set_orientation(gravity=list(g))
        vb.set_rate(list(25.0 * g / np.linalg.norm(g)))       # turning about the vertical: gravity stays put
        vb.wait(0.1)            # turning for a while: no sample averages the start of the turn
        # a small command first, as every imubench procedure starts (info): on the F103 a
        # 263-byte set_params frame sent while the image still starts its sensors overflows the
        # 255 bytes its RX ring holds and waits for the host's retry (docs/firmware.md, RX ring)
        assert dev.info().param_block_version == 3
        dev.set_params(p)
        n = 40
        seen = []
        for temp in (0.0, 28.0, 60.0):                        # below both spans, inside, above both
            vb.set_temperature(temp)

            def read(calibrated):
                dev.start_stream(200, calibrated=calibrated)
                dev.discard_buffered()
                b = dev.read(n_samples=n, calibrated=calibrated, timeout=60.0)
                dev.stop_stream()
                return b
            raw, cal, raw2 = read(False), read(True), read(False)
            for f in ("accel_counts", "gyro_counts", "accel_temp_counts", "gyro_temp_counts"):
                assert np.array_equal(_one(raw, f), _one(raw2, f)), f     # the same moment before and after
            t_acc = U.accel_temp_counts_to_c(_one(raw, "accel_temp_counts"))
            t_gyr = U.gyro_temp_counts_to_c(_one(raw, "gyro_temp_counts"))
            u_acc = U.accel_counts_to_mps2(_one(raw, "accel_counts"), raw.accel_range_g[:1])
            u_gyr = U.gyro_counts_to_rad_s(_one(raw, "gyro_counts"))
            want_a = PR.correct(PR.accel(p), u_acc, t_acc)
            want_g = PR.correct(PR.gyro(p), u_gyr, t_gyr, accel_mps2=want_a)
            got_a, got_g = _one(cal, "accel_mps2"), _one(cal, "rate_rad_s")
            np.testing.assert_allclose(got_a, want_a, rtol=3e-6, atol=3e-6)
            np.testing.assert_allclose(got_g, want_g, rtol=3e-6, atol=1e-7)
            # the clamp did something outside the span: unclamped, the cubic gives another output
            free_a = PR.correct(replace(PR.accel(p), t_min_c=-np.inf, t_max_c=np.inf), u_acc, t_acc)
            inside = SPAN_A[0] <= float(t_acc[0]) <= SPAN_A[1]
            assert np.allclose(free_a, got_a, rtol=3e-6, atol=3e-6) == inside, (t_acc, free_a, got_a)
            seen.append((float(t_acc[0]), *map(float, t_gyr[0])))
        seen = np.array(seen)
        assert seen[0].max() < min(SPAN_A[0], SPAN_G[0]) and seen[2].min() > max(SPAN_A[1], SPAN_G[1])
        assert np.all((seen[1, 1:] > SPAN_G[0]) & (seen[1, 1:] < SPAN_G[1])) and SPAN_A[0] < seen[1, 0] < SPAN_A[1]
