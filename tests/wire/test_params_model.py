"""The host mirror of the device's correction (imubench.wire.params.correct) is the equation of
docs/conventions.md, "Temperature model", written out here term by term: the clamp into the
span, the cubic bias about t_ref, the linear scale term at the same clamped ΔT, M⁻¹ last."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from imubench.wire import params as PR


def _block():
    return replace(PR.identity(), accel_m=(1.01, 0.02, 0.0, -0.01, 0.99, 0.0, 0.0, 0.005, 1.02),
                   accel_b_mps2=(0.1, -0.2, 0.05), accel_bias_tc_mps2_per_c=(1e-3, 0.0, -2e-3),
                   accel_bias_tc2_mps2_per_c2=(1e-4, -2e-4, 0.0), accel_bias_tc3_mps2_per_c3=(0.0, 3e-6, -1e-6),
                   accel_scale_tc_per_c=(2e-4, 0.0, -1e-4), accel_t_ref_c=20.0, accel_t_min_c=5, accel_t_max_c=45,
                   gyro_bias_tc2_rad_s_per_c2=(1e-6, 0.0, 0.0), gyro_t_ref_c=30.0, gyro_t_min_c=10, gyro_t_max_c=50)


def test_correct_is_the_clamped_cubic_of_the_conventions():
    p = _block()
    PR.validate(p)
    rng = np.random.default_rng(3)
    u = rng.normal(0, 5, (7, 3))
    temps = np.array([-10.0, 5.0, 12.5, 20.0, 44.0, 45.0, 80.0])
    m = np.array(p.accel_m).reshape(3, 3)
    b, c1, c2, c3, s = (np.array(getattr(p, f)) for f in (
        "accel_b_mps2", "accel_bias_tc_mps2_per_c", "accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3",
        "accel_scale_tc_per_c"))
    want = []
    for ui, t in zip(u, temps):
        dt = min(max(t, 5.0), 45.0) - 20.0
        v = (ui - b - (c1 * dt + c2 * dt**2 + c3 * dt**3)) / (1 + s * dt)
        want.append(np.linalg.solve(m, v))
    got = PR.correct(PR.accel(p), u, temps)
    np.testing.assert_allclose(got, np.array(want), rtol=1e-12, atol=1e-12)
    # per-axis temperatures (n, 3) give the same as one temperature repeated
    np.testing.assert_allclose(PR.correct(PR.accel(p), u, np.repeat(temps[:, None], 3, axis=1)), got, rtol=1e-12)
    # at and beyond the span's ends the output is the same: the clamp
    np.testing.assert_allclose(got[0], PR.correct(PR.accel(p), u[:1], [5.0])[0], rtol=1e-12)
    np.testing.assert_allclose(got[6], PR.correct(PR.accel(p), u[6:], [45.0])[0], rtol=1e-12)
    assert not np.allclose(got[6], PR.correct(replace(PR.accel(p), t_max_c=np.inf), u[6:], [80.0])[0])


def test_factory_and_the_gyro_triad():
    ident = PR.identity()
    assert PR.is_factory(ident) and (ident.accel_t_min_c, ident.accel_t_max_c) == PR.DEFAULT_SPAN_C
    p = _block()
    assert not PR.is_factory(p)
    assert not PR.is_factory(replace(ident, gyro_bias_tc2_rad_s_per_c2=(1e-6, 0.0, 0.0)))
    g = PR.gyro(p)
    assert (g.t_min_c, g.t_max_c, g.t_ref_c) == (10.0, 50.0, 30.0)
    # ΔT 20 at 50 °C and above: 1e-6·20² = 4e-4 rad/s on x
    np.testing.assert_allclose(PR.correct(g, np.zeros((2, 3)), [50.0, 90.0])[:, 0], [-4e-4, -4e-4], rtol=1e-12)
