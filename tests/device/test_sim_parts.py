"""Issue 35: the sensor parts as data (protocol/parts.toml). The virtual board's parts are chosen
on the command line; the firmware identifies each from its ID registers and reports it; the host
takes every part constant from the generated table. Host build only (a few seconds each)."""
from __future__ import annotations

import numpy as np
import pytest

from imubench import units as U
from imubench.cli import main as imubench
from imubench.device.link import Device, DeviceError
from imubench.device.sim import VirtualBench, sim_parts_spec
from imubench.parts_gen import PART_BY_ID, PARTS
from imubench.wire.ids import part_names
from imubench.wire.protocol_gen import Error, Part


def test_the_table_is_the_one_source_of_the_host_constants():
    assert {p.name for p in PARTS.values()} == {"ADXL355", "ADXL359", "ADXRS450", "ADXRS453"}
    assert {p.id: p.name for p in PARTS.values()} == {int(v): v.name for v in Part if v != Part.NONE}
    assert U.ACCEL_LSB_PER_G == {2: 256000.0, 4: 128000.0, 8: 64000.0, 10: 51200.0, 20: 25600.0, 40: 12800.0}
    assert U.GYRO_LSB_PER_DPS == PARTS["adxrs453"].lsb_per_unit() == 80.0
    assert np.allclose(U.accel_counts_to_mps2([[51200, 0, 0]], 10), [[U.G0_MPS2, 0, 0]])
    # the ADXL359's temperature intercept is 1852 LSB (the ADXL355's 1885): the block's range says which
    assert U.accel_temp_counts_to_c(1852, range_g=10) == pytest.approx(25.0)
    assert U.accel_temp_counts_to_c([1885, 1852], range_g=[2, 20]) == pytest.approx([25.0, 25.0])
    assert PARTS["adxrs453"].bias_instability * 3600 == pytest.approx(16.0, rel=1e-6)
    with pytest.raises(KeyError, match="ADXL359 has no ±8 g range"):
        PARTS["adxl359"].range(8)
    assert all(p.source for p in PARTS.values())          # every part cites where its figures come from
    assert PART_BY_ID[4].name == "ADXRS453"


def test_a_mixed_board_is_identified_and_read_at_each_parts_scale():
    """Two ADXRS450 and one ADXRS453 beside an ADXL359: each found from its ID register, reported
    in info.parts, and its counts scaled by its own part (1 g reads 51200 counts at ±10 g)."""
    with VirtualBench(speed=0, seed=2, parts="accel=adxl359,gyro_z=adxrs453") as vb:
        with Device.open(vb.port_url, timeout=5.0) as dev:
            info = dev.info()
            assert part_names(info) == ["ADXL359", "ADXRS450", "ADXRS450", "ADXRS453"]
            assert list(info.parts) == [Part.ADXL359, Part.ADXRS450, Part.ADXRS450, Part.ADXRS453]
            assert (info.accel_ids[2], tuple(info.gyro_pid)) == (0xE9, (0x5201, 0x5201, 0x5202))
            assert info.accel_range_g == 10 and info.sensors_present == 0b1111
            with pytest.raises(DeviceError) as e:                 # an ADXL355 range: not this part's
                dev.start_stream(100, accel_range_g=2)
            assert e.value.code == Error.BAD_ARGUMENT
            dev.start_stream(100, accel_range_g=20)
            b = dev.read(n_samples=50, timeout=30)
            dev.stop_stream()
    assert np.all(b.accel_range_g == 20) and not np.any(b.status)
    assert np.median(np.abs(b.accel_counts[:, 2])) == pytest.approx(25600, rel=0.02)   # 1 g at ±20 g
    assert np.linalg.norm(b.si()[0].mean(axis=0)) == pytest.approx(U.G0_MPS2, rel=2e-3)


def test_the_default_board_is_unchanged():
    with VirtualBench(speed=0, seed=2) as vb:
        with Device.open(vb.port_url, timeout=5.0) as dev:
            info = dev.info()
    assert part_names(info) == ["ADXL355", "ADXRS450", "ADXRS450", "ADXRS450"]
    assert info.accel_range_g == 2 and info.accel_ids[2] == 0xED


@pytest.mark.parametrize("spec,msg", [
    ("accel=adxrs453", "the accelerometer parts are adxl355, adxl359"),
    ("gyro_w=adxrs453", "'gyro_w' is no slot"),
    ("gyro=adxl359", "the gyro parts are"),
    ("accel", "accel=?"),
])
def test_a_wrong_parts_spec_is_one_line(spec, msg, capsys):
    with pytest.raises(ValueError, match=msg.replace("?", r"\?")):
        sim_parts_spec(spec)
    for argv in (["calibrate", "--sim", "--sim-parts", spec], ["sim", "--parts", spec]):
        try:
            rc = imubench(argv)
        except SystemExit as e:
            rc = e.code
        assert rc == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err
        assert len([ln for ln in err.splitlines() if "error:" in ln]) == 1


def test_the_simulator_refuses_a_wrong_part_itself():
    """imubench-sim checks --parts too (a wrong name from another caller): one line, exit 2."""
    import subprocess

    from imubench.device.sim import build_sim
    r = subprocess.run([str(build_sim()), "--parts", "gyro_z=adxrs999"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2
    assert r.stderr.strip() == ("imubench-sim: --parts 'adxrs999': no such gyro part (known: ADXRS453, ADXRS450)")
