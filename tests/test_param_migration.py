"""A parameter block stored by the previous firmware (layout 1: today's block without the gyro
g-sensitivity) is still read and used after the layout moved to 2 (issue 26): by the C core on
the host build and by the exact F103 and F4 images under the ARM emulator, each booted on a flash
file holding a layout-1 record as `imubench.wire.paramstore.params_record(p, layout=1)` writes it
(byte for byte what the previous firmware's ib_ps_save wrote: tests/test_qemu.py checks the
builder against the C store). Then a save writes layout 2, and G survives a reboot."""
from __future__ import annotations

import math

import numpy as np
import pytest

from imubench.device.link import Device
from imubench.device.sim import VirtualBench
from imubench.wire import params as PR
from imubench.wire import paramstore as PS
from imubench.wire.protocol_gen import PARAM_BLOCK_VERSION, ParamSource, ParamsWhich

# the flash file of each target: (slot layout, whole file size, slot 0's offset in it)
FLASH = {"sim": (PS.Layout((0, 0x800), 0x800, 4), 0x1000), "f103": (PS.LAYOUTS["f103"], 2 * 1024),
         "f4": (PS.LAYOUTS["f4"], 256 * 1024)}


def _layout1_params() -> object:
    p = PR.identity()
    p.accel_m = (1.004, 0.001, 0.0, -0.002, 0.997, 0.0, 0.003, 0.0, 1.01)
    p.accel_b_mps2 = (0.05, -0.08, 0.12)
    p.gyro_m = (1.002, 0.0, 0.001, 0.0, 0.998, 0.0, -0.001, 0.0, 1.003)
    p.gyro_b_rad_s = (0.004, -0.002, 0.001)
    p.cal_id = 1234
    return p


def layout1_flash_file(path, target: str, generation: int = 17):
    """A flash file whose slot 0 holds the previous firmware's layout-1 record, slot 1 erased."""
    lay, size = FLASH[target]
    rec = PS.params_record(_layout1_params(), generation=generation, program_unit=lay.program_unit, layout=1)
    img = bytearray(b"\xff" * size)
    img[:len(rec)] = rec
    path.write_bytes(bytes(img))
    return path


def _pack(p) -> bytes:
    return p.STRUCT.pack(*p.values())


def test_layout1_record_is_todays_prefix_and_reads_with_zero_g():
    p = _layout1_params()
    rec = PS.params_record(p, generation=3, layout=1)
    r = PS.parse_record(PS.slot_image(rec, 1024))
    assert r.payload_version == 1 and len(r.payload) == PS.PARAMS_SIZE_V1 == 160
    assert r.payload == PS.params_payload(p)[:160]
    assert _pack(r.params()) == _pack(p) and not any(r.params().gyro_g_rad_s_per_mps2)
    assert PARAM_BLOCK_VERSION == 2 and PS.parse_record(PS.slot_image(PS.params_record(p), 1024)).payload_version == 2
    q = PR.identity()
    q.gyro_g_rad_s_per_mps2 = (1e-4,) + (0.0,) * 8
    with pytest.raises(ValueError, match="layout-1 block has no gyro g-sensitivity"):
        PS.params_payload(q, layout=1)


@pytest.mark.parametrize("target", ["sim", "f103", "f4"])
def test_a_layout1_block_is_used_and_the_next_save_writes_layout2(tmp_path, target):
    flash = layout1_flash_file(tmp_path / "flash.bin", target)
    p = _layout1_params()
    with VirtualBench(speed=0, seed=3, flash=flash, target="host" if target == "sim" else target) as vb:
        with Device.open(vb.port_url, timeout=5.0) as d:
            info = d.info()
            assert info.param_source == ParamSource.FLASH and info.param_generation == 17
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FLASH and _pack(act.params) == _pack(p)
            assert _pack(d.get_params(ParamsWhich.STORED).params) == _pack(p)
            # a g-sensitivity set and saved: layout 2 in flash, kept over a reboot
            q = _layout1_params()
            q.gyro_g_rad_s_per_mps2 = tuple(float(np.float32(v)) for v in
                                             np.radians([0.03, -0.01, 0.0, 0.0, 0.02, 0.0, 0.01, 0.0, -0.03]) / 9.80665)
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
        assert newest.generation == 18 and newest.payload_version == 2 and len(newest.payload) == 196
        vb.restart()
        with Device.open(vb.port_url, timeout=5.0) as d:
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FLASH and _pack(act.params) == _pack(q)
            assert math.isclose(act.params.gyro_g_rad_s_per_mps2[0], q.gyro_g_rad_s_per_mps2[0])
