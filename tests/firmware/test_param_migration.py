"""A parameter block stored by a previous firmware (layout 1: without the gyro g-sensitivity;
layout 2: without the bias polynomial's c2, c3 and the calibrated spans) is still read and used
after the layout moved to 3 (issues 26 and 23): by the C core on the host build and by the exact
F103 and F4 images under the ARM emulator, each booted on a flash file holding such a record as
`imubench.wire.paramstore.params_record(p, layout=1 or 2)` writes it (byte for byte what the
previous firmware's ib_ps_save wrote: tests/device/test_qemu.py checks the builder against the C
store). The migration gives G = 0 (layout 1), c2 = c3 = 0 and the span −40..85 °C, raised to
hold a t_ref above 85 °C. Then a save writes layout 3, and the new fields survive a reboot."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench.device.link import Device
from imubench.device.sim import VirtualBench
from imubench.wire import params as PR
from imubench.wire import paramstore as PS
from imubench.wire.protocol_gen import PARAM_BLOCK_VERSION, ParamSource, ParamsWhich

# the flash file of each target: (slot layout, whole file size, slot 0's offset in it)
FLASH = {"sim": (PS.Layout((0, 0x800), 0x800, 4), 0x1000), "f103": (PS.LAYOUTS["f103"], 2 * 1024),
         "f4": (PS.LAYOUTS["f4"], 256 * 1024)}


def _old_params(layout: int) -> object:
    """A block a layout-1 or -2 firmware could have stored (as today's Params, migrated)."""
    p = PR.identity()
    p.accel_m = (1.004, 0.001, 0.0, -0.002, 0.997, 0.0, 0.003, 0.0, 1.01)
    p.accel_b_mps2 = (0.05, -0.08, 0.12)
    p.gyro_m = (1.002, 0.0, 0.001, 0.0, 0.998, 0.0, -0.001, 0.0, 1.003)
    p.gyro_b_rad_s = (0.004, -0.002, 0.001)
    p.cal_id = 1234
    if layout == 2:                   # a g-sensitivity, and a gyro t_ref above 85 °C: span -40..91
        p.gyro_g_rad_s_per_mps2 = tuple(float(np.float32(v)) for v in np.radians([0.03, 0, 0, 0, -0.02, 0, 0, 0, 0.01]) / 9.80665)
        p.accel_bias_tc_mps2_per_c = (1e-4, -2e-4, 0.0)
        p.gyro_t_ref_c = 90.5
        p.gyro_t_min_c, p.gyro_t_max_c = -40, 91
    return p


def layout1_flash_file(path, target: str, generation: int = 17, layout: int = 1):
    """A flash file whose slot 0 holds a previous firmware's layout-1 (or -2) record, slot 1 erased."""
    lay, size = FLASH[target]
    rec = PS.params_record(_old_params(layout), generation=generation, program_unit=lay.program_unit, layout=layout)
    img = bytearray(b"\xff" * size)
    img[:len(rec)] = rec
    path.write_bytes(bytes(img))
    return path


def _pack(p) -> bytes:
    return p.STRUCT.pack(*p.values())


def test_previous_layouts_are_todays_prefixes_and_migrate():
    assert PARAM_BLOCK_VERSION == 3
    for layout, size in ((1, 160), (2, 196)):
        p = _old_params(layout)
        r = PS.parse_record(PS.slot_image(PS.params_record(p, generation=3, layout=layout), 1024))
        assert r.payload_version == layout and len(r.payload) == size
        assert r.payload == PS.params_payload(p)[:size]
        assert _pack(r.params()) == _pack(p)
        m = r.params()
        assert not any(m.accel_bias_tc2_mps2_per_c2 + m.accel_bias_tc3_mps2_per_c3 + m.gyro_bias_tc2_rad_s_per_c2
                       + m.gyro_bias_tc3_rad_s_per_c3)
        assert (m.accel_t_min_c, m.accel_t_max_c) == (-40, 85)
        PR.validate(m)
    assert (m.gyro_t_min_c, m.gyro_t_max_c) == (-40, 91)           # raised to hold t_ref 90.5
    assert PR.migrated_span(85.0) == (-40, 85) and PR.migrated_span(85.01) == (-40, 86)
    assert PS.parse_record(PS.slot_image(PS.params_record(p), 1024)).payload_version == 3
    q = PR.identity()
    q.gyro_g_rad_s_per_mps2 = (1e-4,) + (0.0,) * 8
    with pytest.raises(ValueError, match="layout-1 block has no gyro g-sensitivity"):
        PS.params_payload(q, layout=1)
    for change in ({"gyro_bias_tc2_rad_s_per_c2": (1e-7, 0.0, 0.0)}, {"accel_t_min_c": 0}):
        with pytest.raises(ValueError, match="layout-2 block has no bias c2, c3 or span"):
            PS.params_payload(replace(PR.identity(), **change), layout=2)


@pytest.mark.parametrize("target,layout", [("sim", 1), ("sim", 2), ("f103", 1), ("f103", 2), ("f4", 1), ("f4", 2)])
def test_a_previous_layout_block_is_used_and_the_next_save_writes_layout3(tmp_path, target, layout):
    flash = layout1_flash_file(tmp_path / "flash.bin", target, layout=layout)
    p = _old_params(layout)
    with VirtualBench(speed=0, seed=3, flash=flash, target="host" if target == "sim" else target) as vb:
        with Device.open(vb.port_url, timeout=5.0) as d:
            info = d.info()
            assert info.param_source == ParamSource.FLASH and info.param_generation == 17
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FLASH and _pack(act.params) == _pack(p)
            assert _pack(d.get_params(ParamsWhich.STORED).params) == _pack(p)
            # a cubic bias over a narrow span set and saved: layout 3 in flash, kept over a reboot
            q = replace(p, accel_bias_tc2_mps2_per_c2=(2e-5, 0.0, -1e-5), gyro_bias_tc3_rad_s_per_c3=(0.0, 0.0, 3e-9),
                        accel_t_min_c=5, accel_t_max_c=45, gyro_t_min_c=-10, gyro_t_max_c=95)
            q = PR.from_json(PR.to_json(q))
            d.set_params(q)
            d.save_params()
        lay, _ = FLASH[target]
        data = flash.read_bytes()
        recs = []
        for k in range(2):
            off = lay.slots[k] - lay.slots[0]
            try:
                recs.append(PS.parse_record(data[off:off + lay.slot_size], program_unit=lay.program_unit))
            except PS.InvalidRecord:
                pass
        newest = max(recs, key=lambda r: r.generation)
        assert newest.generation == 18 and newest.payload_version == 3 and len(newest.payload) == 248
        # a reboot of the device (its firmware loads the block from flash again, as at power-up:
        # the file-backed flash was read at start-up above); not a restart of the emulator's
        # process, which cost a second start-up of the ARM emulator per case
        with Device.open(vb.port_url, timeout=5.0) as d:
            reboots = vb.status()["reboots"]
            info = d.reboot()
            assert vb.status()["reboots"] == reboots + 1 and info.param_generation == 18
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FLASH
            got = act.params
            assert (got.accel_t_min_c, got.accel_t_max_c, got.gyro_t_min_c, got.gyro_t_max_c) == (5, 45, -10, 95)
            assert math.isclose(got.accel_bias_tc2_mps2_per_c2[0], 2e-5, rel_tol=1e-6)
            assert math.isclose(got.gyro_bias_tc3_rad_s_per_c3[2], 3e-9, rel_tol=1e-6)
            assert _pack(got) == _pack(q)


# ------------------------------------------------------------------ g-sensitivity through a whole session
def _gsens_session(tmp_path, target: str):
    """A whole session with random truth (every ADXRS450 with its g-sensitivity): multi-position on
    the host build; on the ARM images (slow: the emulator) six faces held 1 s and shorter reads,
    which resolve G less well (its σ ≈ 0.015 °/s/g) but exercise the same code in the image."""
    host = target == "host"
    from imubench.calib.geometry import rotation_to
    from imubench.procedures.session import Session, SessionConfig, SimPresenter, plan_for
    from imubench.wire.protocol_gen import ParamsWhich as W
    with VirtualBench(speed=0, seed=31, truth="random", target=target) as vb:
        vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
        with Device.open(vb.port_url, timeout=5.0) as dev:
            method = "multi" if host else "six"
            s = Session(dev, tmp_path / "s", SessionConfig(method=method, gyro="bias", write=True,
                                                           hold_s=2.0 if host else 1.0),
                        SimPresenter(vb, quiet=True))
            result = s.run(plan_for(method))
            s.write_back(s.accel_fit, s.gyro_fit, cal_id=9)
            truth = vb.get_truth()
            active = dev.get_params(W.ACTIVE).params
            # the calibrated stream, still, in two attitudes whose specific force differs by 2 g
            rates = []
            for up in ([0, 0, 1], [0, 0, -1], [1, 0, 0]):
                turn = rotation_to(vb.status()["gravity_board"], np.array(up, float))
                if turn is not None:
                    vb.rotate(turn[0], turn[1] / 1.0, duration_s=1.0)
                dev.start_stream(200, calibrated=True)
                dev.discard_buffered()
                w = dev.read(n_samples=2000 if host else 600, calibrated=True, timeout=120.0).rate_rad_s.astype(float)
                dev.stop_stream()
                rates.append((w.mean(axis=0), w.std(axis=0, ddof=1) / math.sqrt(len(w))))
    return result, truth, active, rates


@pytest.mark.parametrize("target", ["host"])     # the images: tests/device/test_arm_images.py's whole session
def test_session_recovers_g_sensitivity_and_the_device_applies_it(tmp_path, target):
    result, truth, active, rates = _gsens_session(tmp_path, target)
    g = result["gsens"]
    assert g["applied"], g
    g_true = np.array([t["gsens_rad_s_per_mps2"] for t in truth["gyro"]]) * 9.80665 * 180 / math.pi   # °/s per g
    z = (np.array(g["g_dps_per_g"]) - g_true) / np.array(g["sigma_dps_per_g"])
    assert np.all(np.abs(z) < 4.5), z
    assert np.abs(g_true).max() > 0.02                       # the random truth has a visible G
    np.testing.assert_allclose(np.array(active.gyro_g_rad_s_per_mps2).reshape(3, 3),
                               np.array(g["g_dps_per_g"]) * math.pi / 180 / 9.80665, rtol=1e-5, atol=1e-12)
    # no rate change between attitudes beyond noise: Z up vs Z down (2 g apart) and X up. The
    # tolerance: 4σ of the stream means' noise and of G's error over the change in f; without G
    # the change would be G_true·Δf, beyond it on some axis (checked, so the test can fail)
    (m0, s0), *others = rates
    sig_g = np.array(g["sigma_dps_per_g"])
    for (m1, s1), df in zip(others, (np.array([0, 0, -2.0]), np.array([1.0, 0, -1.0]))):
        d = np.degrees(m1 - m0)
        tol = 4.0 * np.sqrt(np.degrees(s0) ** 2 + np.degrees(s1) ** 2 + (sig_g**2) @ (df**2))
        assert np.all(np.abs(d) < tol), (d, tol)
        if df[2] == -2.0 and target == "host":   # the host's 26 poses resolve G well enough to show it
            assert np.any(np.abs(g_true @ df) > tol), (g_true @ df, tol)


def test_a_json_block_of_an_earlier_layout_reads_as_the_device_migrates_it():
    """A parameter file or closure.json written before layout 3 (no c2, c3, spans; layout 1 also
    no G) loads as the device loads such a stored block; a block missing anything else is refused."""
    full = PR.to_json(_old_params(2))
    tail = ("accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3", "gyro_bias_tc2_rad_s_per_c2",
            "gyro_bias_tc3_rad_s_per_c3", "accel_t_min_c", "accel_t_max_c", "gyro_t_min_c", "gyro_t_max_c")
    v2 = {k: v for k, v in full.items() if k not in tail}
    assert _pack(PR.from_json(v2)) == _pack(_old_params(2))            # gyro span raised to 91 for t_ref 90.5
    v1 = {k: v for k, v in PR.to_json(_old_params(1)).items() if k not in tail + ("gyro_g_rad_s_per_mps2",)}
    assert _pack(PR.from_json(v1)) == _pack(_old_params(1))
    for drop in (("accel_t_min_c",), tail[:4], ("gyro_g_rad_s_per_mps2",)):
        with pytest.raises(PR.InvalidParams, match="missing parameter fields"):
            PR.from_json({k: v for k, v in full.items() if k not in drop})
