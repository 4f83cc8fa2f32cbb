"""The host link and device client over a real pseudo-terminal, against the Python fake
device (imubench.device.fake). The same tests run against the virtual device once it exists."""
from __future__ import annotations

import os

import numpy as np
import pytest
from imubench.device.fake import FakeDevice
from imubench.device.link import Device, DeviceError, LinkError, LinkTimeout
from imubench.wire import params as PR
from imubench.wire.protocol_gen import (
    Error,
    MsgType,
    ParamSource,
    ParamsWhich,
    StreamState,
)


@pytest.fixture
def fake():
    with FakeDevice(seed=3, speed=1.0) as f:
        yield f


@pytest.fixture
def dev(fake):
    with Device.open(fake.port_url, timeout=0.5, retries=2) as d:
        yield d


def test_port_from_environment(fake, monkeypatch):
    monkeypatch.setenv("IMUBENCH_PORT", fake.port_url)
    with Device.open() as d:
        assert d.ping() < 0.5


def test_no_port_is_a_clear_error(monkeypatch):
    monkeypatch.delenv("IMUBENCH_PORT", raising=False)
    with pytest.raises(LinkError, match="IMUBENCH_PORT"):
        Device.open()


def test_bad_port_is_a_clear_error():
    with pytest.raises(LinkError, match="cannot open"):
        Device.open("/dev/does-not-exist-imubench")


def test_ping_and_info(dev):
    assert dev.ping(nonce=0xCAFEF00D) < 0.5
    info = dev.info()
    assert info.accel_ids == (0xAD, 0x1D, 0xED, 0x01)
    assert info.sensors_present == 0b1111
    assert info.stream_state == StreamState.STOPPED
    assert info.fw_build == "python-fake"


def test_stream_raw_samples_as_numpy(dev):
    batch = dev.start_stream(rate_hz=1000)
    assert batch == 4
    block = dev.read(n_samples=500)
    dev.stop_stream()
    assert len(block) == 500
    assert block.accel_counts.shape == (500, 3)
    assert np.all(np.diff(block.sample_index) == 1)
    assert np.all(np.diff(block.t_us) == 1000)
    # gravity on +Z at 256000 counts/g, noise of a few hundred counts
    assert abs(np.mean(block.accel_counts[:, 2]) - 256000) < 200
    assert abs(np.mean(block.accel_counts[:, 0])) < 200
    assert dev.link.decoder.stats.frames_rejected == 0
    assert dev.link.decoder.stats.samples_missing == 0


def test_stream_iterator_and_calibrated_mode(dev):
    dev.start_stream(rate_hz=500, calibrated=True)
    got = 0
    for b in dev.stream():
        assert b.calibrated and b.accel_mps2.dtype == np.float32
        got += len(b)
        if got >= 200:
            break
    dev.stop_stream()
    assert got >= 200


def test_bad_arguments_are_nacked_with_a_code(dev):
    with pytest.raises(DeviceError) as e:
        dev.start_stream(rate_hz=3000)       # does not divide 4000
    assert e.value.code == Error.BAD_ARGUMENT
    assert e.value.command == MsgType.START_STREAM
    with pytest.raises(DeviceError) as e:
        dev.start_stream(rate_hz=1000, accel_range_g=3)
    assert e.value.code == Error.BAD_ARGUMENT


def test_params_set_get_save_clear(dev, fake):
    p = PR.identity()
    p.accel_b_mps2 = (0.125, -0.25, 0.0625)
    p.accel_m = (1.01, 0.002, 0.0, 0.0, 0.99, 0.0, 0.0, 0.0, 1.0)
    dev.set_params(p)
    rb = dev.get_params(ParamsWhich.ACTIVE)
    assert rb.source == ParamSource.UNSAVED
    assert rb.params.accel_b_mps2 == p.accel_b_mps2
    assert np.array_equal(np.float32(rb.params.accel_m), np.float32(p.accel_m))
    assert dev.save_params() == 1
    assert dev.get_params(ParamsWhich.STORED).generation == 1
    dev.clear_params()
    assert dev.get_params(ParamsWhich.ACTIVE).params.accel_b_mps2 == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("field,value,code", [
    ("accel_b_mps2", (float("nan"), 0.0, 0.0), Error.PARAM_NOT_FINITE),
    ("accel_m", (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0), Error.PARAM_ILL_CONDITIONED),
    ("accel_m", (1.6, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), Error.PARAM_OUT_OF_RANGE),
    ("gyro_b_rad_s", (1.0, 0.0, 0.0), Error.PARAM_OUT_OF_RANGE),
    ("gyro_m", (0.5, -0.19, -0.19, -0.19, 0.5, -0.19, -0.19, -0.19, 0.5), Error.PARAM_ILL_CONDITIONED),
])
def test_invalid_params_refused_and_previous_kept(dev, field, value, code):
    good = PR.identity()
    good.accel_b_mps2 = (0.5, 0.0, 0.0)
    dev.set_params(good)
    bad = PR.identity()
    setattr(bad, field, value)
    with pytest.raises(DeviceError) as e:
        dev.set_params(bad)
    assert e.value.code == code
    assert dev.get_params().params.accel_b_mps2 == (0.5, 0.0, 0.0)


def test_flash_failure_is_reported_and_nothing_changes(dev, fake):
    fake.flash_fails = True
    dev.set_params(PR.identity())
    with pytest.raises(DeviceError) as e:
        dev.save_params()
    assert e.value.code == Error.FLASH_ERROR


def test_lost_ack_is_retried_without_running_the_command_twice(dev, fake):
    fake.drop_acks = 1
    before = fake.commands_executed.count(MsgType.SAVE_PARAMS)
    assert dev.save_params() == 1
    assert fake.commands_executed.count(MsgType.SAVE_PARAMS) == before + 1


def test_an_ack_whose_data_frame_was_damaged_is_retried(dev, fake):
    fake.damage_data = 2               # the readback of the first two sends fails its CRC
    before = fake.commands_executed.count(MsgType.GET_PARAMS)
    assert dev.get_params().params.accel_m == PR.identity().accel_m
    assert fake.commands_executed.count(MsgType.GET_PARAMS) == before + 1   # retries, not re-runs
    assert dev.link.decoder.stats.frames_rejected == 2


def test_data_that_never_arrives_intact_fails_after_the_retries(dev, fake):
    fake.damage_data = 100
    with pytest.raises(LinkError, match="3 of 3 times"):
        dev.info()
    fake.damage_data = 0
    assert dev.info().fw_build == "python-fake"      # the link itself is fine


def test_no_answer_times_out_after_retries(dev, fake):
    fake.drop_acks = 100
    with pytest.raises(LinkTimeout, match="3 tries"):
        dev.ping()


def test_reboot_announces_itself_and_loses_unsaved_params(dev):
    p = PR.identity()
    p.gyro_b_rad_s = (0.01, 0.0, 0.0)
    dev.set_params(p)
    info = dev.reboot(wait_s=2.0)
    assert info.request_id == 0 and info.param_source == ParamSource.FACTORY
    assert dev.get_params().params.gyro_b_rad_s == (0.0, 0.0, 0.0)


def test_saved_params_are_active_after_reboot(dev):
    p = PR.identity()
    p.gyro_b_rad_s = (0.0625, 0.0, 0.0)
    dev.set_params(p)
    dev.save_params()
    info = dev.reboot(wait_s=2.0)
    assert info.param_source == ParamSource.FLASH
    assert dev.get_params().params.gyro_b_rad_s == (0.0625, 0.0, 0.0)


def test_stats_and_self_test(dev):
    s = dev.stats()
    assert s.frames_sent > 0
    r = dev.self_test()
    assert r.passed == r.tested == 0b1111


def test_capture_file_gets_every_byte(fake, tmp_path):
    path = tmp_path / "cap.bin"
    with open(path, "wb") as cap, Device.open(fake.port_url, capture=cap) as d:
        d.start_stream(rate_hz=1000)
        d.read(n_samples=400)
        d.stop_stream()
        received = d.link.decoder.stats.bytes_in
    assert os.path.getsize(path) == received > 400 * 16


def test_device_gone_mid_stream_raises_link_error(fake):
    d = Device.open(fake.port_url, timeout=0.3, retries=0)
    try:
        d.start_stream(rate_hz=1000)
        d.read(n_samples=100)
        fake.close()
        with pytest.raises((LinkError, LinkTimeout)):
            d.read(n_samples=100000, timeout=2.0)
    finally:
        d.close()
