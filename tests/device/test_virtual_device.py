"""The virtual device end to end, through the real serial path: host link -> TCP -> the
firmware core on the simulated board -> drivers -> register-level sensor models."""
from __future__ import annotations


import numpy as np
import pytest
from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench import units as U
from imubench.device.link import Device, DeviceError, LinkError, LinkTimeout
from imubench.device.sim import VirtualBench
from imubench.wire import frame as P
from imubench.wire import params as PR
from imubench.wire.protocol_gen import (
    BatchFlags,
    Board,
    Error,
    FaultKind,
    MsgType,
    Params,
    ParamSource,
    ParamsWhich,
    SampleStatus,
    Sensor,
    StreamState,
)


def _connect(vb: VirtualBench, **kw) -> Device:
    d = Device.open(vb.port_url, timeout=kw.pop("timeout", 3.0), **kw)
    d.ping()   # the link is settled: what the device sent before we connected is behind us
    return d


@pytest.fixture
def vb():
    with VirtualBench(speed=0, seed=11) as b:
        yield b


@pytest.fixture
def dev(vb):
    d = _connect(vb)
    try:
        yield d
    finally:
        d.close()


def _pack(p: Params) -> bytes:
    return p.STRUCT.pack(*p.values())


def _params_example(scale=1.0) -> Params:
    p = PR.identity()
    p.accel_m = (1.0 + 0.01 * scale, 0.002, -0.001, 0.0015, 1.0 - 0.008 * scale, 0.0, -0.002, 0.001, 1.0 + 0.004 * scale)
    p.accel_b_mps2 = (0.05 * scale, -0.08 * scale, 0.12 * scale)
    p.gyro_m = (1.02, 0.01, 0.0, -0.005, 0.98, 0.002, 0.0, 0.003, 1.01)
    p.gyro_b_rad_s = (0.004 * scale, -0.002, 0.001)
    p.accel_bias_tc_mps2_per_c = (1e-4, -2e-4, 5e-5)
    p.gyro_scale_tc_per_c = (1e-4, 0.0, -1e-4)
    p.cal_id = 1234
    return p


# ------------------------------------------------------------------ identity
def test_info_reports_what_the_drivers_read(vb, dev):
    info = dev.info()
    truth = vb.get_truth()
    assert info.board == Board.SIM
    assert info.sensors_present == 0b1111
    assert info.accel_ids == (0xAD, 0x1D, 0xED, 0x01)
    assert info.gyro_pid == (0x5201,) * 3
    assert list(info.gyro_sn) == [g["serial"] for g in truth["gyro"]]
    assert info.param_source == ParamSource.FACTORY and info.param_generation == 0
    assert info.fw_build.startswith("sim") and info.baud == 2000000
    assert info.stream_state == StreamState.STOPPED
    assert bytes(info.mcu_uid) != bytes(12)


# ------------------------------------------------------------------ streaming
@pytest.mark.parametrize("rate", [1000, 4000])
def test_stream_60_s_of_device_time_without_loss(vb, dev, rate):
    batch = dev.start_stream(rate)
    assert batch == rate // 250
    block = dev.read(n_samples=60 * rate, timeout=60)
    dev.stop_stream()
    st = dev.link.decoder.stats
    assert len(block) == 60 * rate
    assert st.frames_rejected == 0 and st.frames_missing == 0 and st.samples_missing == 0
    assert np.array_equal(block.sample_index, np.arange(60 * rate))
    assert np.all(np.diff(block.t_us) == 1_000_000 // rate)
    assert not block.status.any()
    dstats = dev.stats()
    assert dstats.samples_dropped == 0 and dstats.frames_dropped == 0
    # a still, level board with ideal parts: +1 g on Z, noise N*sqrt(rate) (docs/conventions.md)
    truth = vb.get_truth()
    acc = U.accel_counts_to_mps2(block.accel_counts, block.accel_range_g)
    assert np.allclose(acc.mean(axis=0), [0, 0, U.G0_MPS2], atol=2e-3)
    want_a = np.array(truth["accel"]["noise_n"]) * np.sqrt(rate)
    assert np.allclose(acc.std(axis=0), want_a, rtol=0.1)
    rate_rs = U.gyro_counts_to_rad_s(block.gyro_counts)
    want_g = np.array([g["noise_n"] for g in truth["gyro"]]) * np.sqrt(rate)
    assert np.allclose(rate_rs.std(axis=0), want_g, rtol=0.1)


@pytest.mark.parametrize("rate", P.gen.STREAM_RATES_HZ)
def test_every_documented_rate_streams_with_datasheet_noise(vb, dev, rate):
    dev.start_stream(rate)
    n = max(400, rate // 2)
    block = dev.read(n_samples=n, timeout=60)
    dev.stop_stream()
    assert np.all(np.diff(block.t_us) == 1_000_000 // rate)
    acc = U.accel_counts_to_mps2(block.accel_counts, block.accel_range_g)
    want = vb.get_truth()["accel"]["noise_n"][2] * np.sqrt(rate)
    assert acc[:, 2].std() == pytest.approx(want, rel=0.25)


@pytest.mark.parametrize("rate", [0, 32, 16, 3000, 4001, 8000])
def test_unsupported_rates_are_refused(dev, rate):
    with pytest.raises(DeviceError) as e:
        dev.start_stream(rate)
    assert e.value.code == Error.BAD_ARGUMENT


def test_ranges_and_orientation_follow_the_world(vb, dev):
    vb.set_orientation(gravity=[1, 0, 0])      # nose up: +g on X
    for rng, lsb in ((2, 256000), (4, 128000), (8, 64000)):
        dev.start_stream(500, accel_range_g=rng)
        b = dev.read(n_samples=500)
        dev.stop_stream()
        assert set(np.unique(b.accel_range_g)) == {rng}
        assert np.mean(b.accel_counts[:, 0]) == pytest.approx(lsb, rel=2e-3)
        assert abs(np.mean(b.accel_counts[:, 2])) < lsb * 2e-3


def test_turntable_rotation_integrates_to_the_angle(vb, dev):
    dev.start_stream(1000)
    dev.read(n_samples=200)
    vb.rotate("z", rate_dps=90.0, duration_s=1.0, wait=False)
    b = dev.read(n_samples=2500)
    dev.stop_stream()
    rate_dps = U.rad_s_to_dps(U.gyro_counts_to_rad_s(b.gyro_counts))
    angle = rate_dps[:, 2].sum() / 1000.0
    assert angle == pytest.approx(90.0, abs=0.5)
    assert abs(rate_dps[:, 0].sum() / 1000.0) < 0.5


# ------------------------------------------------------------------ commands
def test_every_command(vb, dev):
    assert dev.ping(nonce=0xA5A55A5A) < 2.0
    assert dev.info().sensors_present == 0b1111
    r = dev.self_test()
    assert r.tested == r.passed == 0b1111
    assert all(f == 0xFE for f in r.gyro_chk_faults)
    for k in range(3):
        assert abs(r.accel_delta_counts[k]) > 0
    dev.set_params(_params_example())
    assert _pack(dev.get_params(ParamsWhich.ACTIVE).params) == _pack(_params_example())
    gen = dev.save_params()
    assert gen >= 1
    rb = dev.get_params(ParamsWhich.STORED)
    assert rb.source == ParamSource.FLASH and rb.generation == gen and _pack(rb.params) == _pack(_params_example())
    dev.start_stream(1000, calibrated=True)
    b = dev.read(n_samples=100)
    assert b.calibrated
    for cmd in (dev.save_params, dev.clear_params, dev.self_test):
        with pytest.raises(DeviceError) as e:
            cmd()
        assert e.value.code == Error.STREAMING
    dev.stop_stream()
    s = dev.stats(reset=True)
    assert s.frames_sent > 0 and s.samples_produced >= 100
    assert dev.stats().samples_produced == 0
    dev.clear_params()
    rb = dev.get_params(ParamsWhich.STORED)
    assert rb.source == ParamSource.FACTORY
    info = dev.reboot(wait_s=10)
    assert info.param_source == ParamSource.FACTORY and info.request_id == 0


def _raw_command(dev: Device, frame: bytes):
    """Send hand-made bytes and return the ack that answers them."""
    rid = P.HEADER.unpack_from(P.cobs.decode(frame[:-1]))[2]
    link = dev.link
    from imubench.device.link import _Pending
    with link._cond:
        pend = link._pending[rid] = _Pending(P.cobs.decode(frame[:-1])[1], None, [])
    link._write(frame)
    dev.clock.wait_for(lambda: pend.ack is not None, 3, link._cond)     # device time in lockstep
    with link._cond:
        link._pending.pop(rid, None)
    return pend.ack


def test_bad_frames_are_nacked_or_counted(dev):
    from cobs import cobs

    def frame(version, mtype, seq, payload):
        raw = P.HEADER.pack(version, mtype, seq, 0) + payload
        return cobs.encode(raw + P.crc32c(raw).to_bytes(4, "little")) + b"\0"

    v = P.PROTOCOL_VERSION
    assert _raw_command(dev, frame(v, 0x7E, 900, b"")).error == Error.UNKNOWN_COMMAND
    assert _raw_command(dev, frame(v, 0x01, 901, b"\x01\x02")).error == Error.BAD_LENGTH
    assert _raw_command(dev, frame(v + 1, 0x01, 902, b"\0\0\0\0")).error == Error.BAD_VERSION
    assert _raw_command(dev, frame(v - 1, 0x01, 905, b"\0\0\0\0")).error == Error.BAD_VERSION   # version 1
    assert _raw_command(dev, frame(v, MsgType.ACK, 903, bytes(8))).error == Error.UNKNOWN_COMMAND
    before = dev.stats().rx_frame_errors
    bad = bytearray(frame(v, 0x01, 904, b"\0\0\0\0"))
    bad[5] ^= 0x10                                    # CRC no longer matches: no answer, counted
    dev.link._write(bytes(bad) + b"\x55" * 10 + b"\0")
    dev.clock.sleep(0.2)
    assert dev.stats().rx_frame_errors == before + 2
    assert dev.ping() < 2.0                            # and it still serves commands


def test_a_retried_command_is_not_run_twice(vb, dev):
    dev.set_params(_params_example())
    frame = P.encode(P.gen.SaveParams(), seq=4242)
    first = _raw_command(dev, frame)
    again = _raw_command(dev, frame)                   # same id, same content: a retry
    assert first.error == again.error == Error.OK
    assert again.value == first.value                  # the same generation: not saved twice
    assert dev.get_params(ParamsWhich.STORED).generation == first.value


def _crc_twin(payload: bytes, free_bits: list[int]) -> bytes:
    """A different payload of the same length and the same CRC-32C, made by flipping a
    combination of free_bits (bit k = bit k % 8 of byte k // 8). For equal lengths the CRC is
    linear over GF(2): crc(a ^ d) = crc(a) ^ crc0(d); with more than 32 candidate bits some
    non-empty combination has crc0 = 0, found by Gaussian elimination."""
    base = P.crc32c(payload)

    def flipped(k):
        b = bytearray(payload)
        b[k // 8] ^= 1 << (k % 8)
        return bytes(b)

    rows = [(P.crc32c(flipped(k)) ^ base, 1 << i) for i, k in enumerate(free_bits)]
    pivots = []                                        # (bit, col, comb)
    for col, comb in rows:
        for bit, pcol, pcomb in pivots:
            if col >> bit & 1:
                col, comb = col ^ pcol, comb ^ pcomb
        if col == 0:
            out = bytearray(payload)
            for i, k in enumerate(free_bits):
                if comb >> i & 1:
                    out[k // 8] ^= 1 << (k % 8)
            return bytes(out)
        pivots.append((col.bit_length() - 1, col, comb))
    raise AssertionError("no combination found")


def test_a_reused_id_with_an_equal_crc_is_not_taken_for_a_retry(dev):
    """Two different set_params blocks with one CRC-32C, sent with one request id: the
    second is applied (or refused), never acked and ignored."""
    a = _params_example()
    raw_a = _pack(a)
    # the 8 low mantissa bits of each accel bias (bytes 36..47) and the bits of cal_id (156..159):
    # any combination leaves a valid block
    bits = [(36 + 4 * k) * 8 + j for k in range(3) for j in range(8)] + [156 * 8 + j for j in range(32)]
    raw_b = _crc_twin(raw_a, bits)
    assert raw_b != raw_a and P.crc32c(raw_b) == P.crc32c(raw_a)
    b = Params.from_values(Params.STRUCT.unpack(raw_b))
    PR.validate(b)
    assert raw_b[36:48] != raw_a[36:48]                # a float field differs, not only the id
    first = _raw_command(dev, P.encode(P.gen.SetParams(params=a), seq=4343))
    second = _raw_command(dev, P.encode(P.gen.SetParams(params=b), seq=4343))
    assert first.error == Error.OK and second is not None
    active = _pack(dev.get_params(ParamsWhich.ACTIVE).params)
    assert active == (raw_b if second.error == Error.OK else raw_a)


def test_a_nack_in_between_does_not_answer_a_retry(dev):
    """A frame nacked before it runs replaces the stored reply; a retry of the command before
    it gets that command's own reply, not the nack."""
    ping = P.encode(P.gen.Ping(nonce=0x12345678), seq=5151)
    assert _raw_command(dev, ping).value == 0x12345678
    raw = P.HEADER.pack(P.PROTOCOL_VERSION, MsgType.PING, 5152, 0) + b"\x01\x02"
    short = P.cobs.encode(raw + P.crc32c(raw).to_bytes(4, "little")) + b"\0"
    assert _raw_command(dev, short).error == Error.BAD_LENGTH
    again = _raw_command(dev, ping)
    assert again is not None and again.error == Error.OK and again.value == 0x12345678


# ---------------------------------------------------------------- parameters
def test_saved_parameters_survive_a_restart_bit_exactly(vb):
    p = _params_example(scale=2.0)
    with _connect(vb) as d:
        d.set_params(p)
        gen = d.save_params()
    vb.restart()
    with _connect(vb) as d:
        info = d.info()
        assert info.param_source == ParamSource.FLASH and info.param_generation == gen
        assert _pack(d.get_params(ParamsWhich.ACTIVE).params) == _pack(p)
        assert _pack(d.get_params(ParamsWhich.STORED).params) == _pack(p)


def test_saving_an_unchanged_block_touches_no_flash(vb, dev):
    """Flash wear: 1,000 saves of the block already stored perform no flash operation after the
    first and keep its generation; a changed block is still saved."""
    p = _params_example()
    dev.set_params(p)
    gen = dev.save_params()
    ops = vb.flash_ops()
    for _ in range(1000):
        assert dev.save_params() == gen
        assert dev.last_save_unchanged                       # the reply says so (protocol v2)
    assert vb.flash_ops() == ops
    assert _pack(dev.get_params(ParamsWhich.STORED).params) == _pack(p)
    dev.set_params(_params_example(scale=-1.0))
    assert dev.save_params() == gen + 1 and not dev.last_save_unchanged
    assert vb.flash_ops() > ops


def test_erases_per_slot_are_reported_and_survive_a_reboot(vb):
    """stats.param_slot_erases: every real save erases the slot not holding the current block,
    so the two counts grow alternately and add up to the generation; they are derived from
    the stored generation, so a reboot keeps them; an unchanged save adds nothing."""
    with _connect(vb) as d:
        g0 = d.info().param_generation
        e0 = list(d.stats().param_slot_erases)
        assert sum(e0) == g0
        for k in range(1, 6):
            d.set_params(_params_example(scale=1.0 + 0.01 * k))
            assert d.save_params() == g0 + k
            e = list(d.stats().param_slot_erases)
            assert sum(e) == g0 + k and abs(e[0] - e[1]) <= 1
        d.save_params()                                       # unchanged: nothing erased
        assert list(d.stats().param_slot_erases) == e
        d.reboot(wait_s=5.0)
        d.discard_buffered()
        assert list(d.stats().param_slot_erases) == e


def test_the_host_warns_before_a_save_that_wears_a_slot_out(vb):
    """write_verified warns (naming the counts, the rating and the fraction) once a save would
    take a slot past the warning fraction of its rated erase cycles."""
    from imubench.procedures.writeback import wear_warning, write_verified
    with _connect(vb) as d:
        rated = min(d.stats().param_slot_erases) + 1           # the next save reaches it
        assert wear_warning(d) is None                         # far below 10 000 cycles
        assert wear_warning(d, endurance=10 * rated) is None   # below 80 % of a small rating too
        w = wear_warning(d, endurance=rated)
        assert w is not None and "erase cycles the flash is rated for" in w and "%" in w
        said = []
        import imubench.procedures.writeback as S
        old = S.ERASE_ENDURANCE.copy()
        try:
            S.ERASE_ENDURANCE["SIM"] = rated
            write_verified(d, _params_example(scale=1.5), say=said.append)
        finally:
            S.ERASE_ENDURANCE.update(old)
        assert any(s.startswith("warning: flash wear") for s in said), said


def test_power_cut_at_every_step_of_a_save_leaves_a_valid_boot(vb):
    old, new = _params_example(1.0), _params_example(-1.0)
    with _connect(vb) as d:
        d.set_params(old)
        d.save_params()
        d.set_params(new)                          # a different block: a real save (an unchanged
        before = vb.flash_ops()                    # one touches no flash)
        d.save_params()
        ops_per_save = vb.flash_ops() - before
    assert ops_per_save >= 3
    seen = set()
    for k in range(1, ops_per_save + 1):
        with _connect(vb, retries=0, timeout=2.0) as d:
            d.set_params(old)
            d.save_params()
            d.set_params(new)
            vb.power_cut(after_flash_ops=k)
            with pytest.raises((LinkTimeout, LinkError, DeviceError)):
                d.save_params()
        with _connect(vb) as d:
            info = d.info()
            active = _pack(d.get_params(ParamsWhich.ACTIVE).params)
            assert info.param_source == ParamSource.FLASH, k
            assert active in (_pack(old), _pack(new)), k
            assert _pack(d.get_params(ParamsWhich.STORED).params) == active
            seen.add("new" if active == _pack(new) else "old")
            d.set_params(new)                        # and the store still works afterwards
            d.save_params()
            assert _pack(d.get_params(ParamsWhich.STORED).params) == _pack(new)
    assert vb.status()["power_cuts"] == ops_per_save
    assert "old" in seen          # a cut before the CRC is written keeps the old block


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("field,value,code", [
    ("accel_b_mps2", (NAN, 0.0, 0.0), Error.PARAM_NOT_FINITE),
    ("gyro_m", (INF, 0, 0, 0, 1, 0, 0, 0, 1), Error.PARAM_NOT_FINITE),
    ("gyro_t_ref_c", NAN, Error.PARAM_NOT_FINITE),
    ("accel_m", (1, 0, 0, 0, 1, 0, 0, 0, 0), Error.PARAM_ILL_CONDITIONED),
    ("accel_m", (1, 0, 0, 1, 0, 0, 0, 0, 1), Error.PARAM_ILL_CONDITIONED),
    ("gyro_m", (0.5, -0.19, -0.19, -0.19, 0.5, -0.19, -0.19, -0.19, 0.5), Error.PARAM_ILL_CONDITIONED),
    ("accel_m", (1.6, 0, 0, 0, 1, 0, 0, 0, 1), Error.PARAM_OUT_OF_RANGE),
    ("gyro_m", (1, 0.25, 0, 0, 1, 0, 0, 0, 1), Error.PARAM_OUT_OF_RANGE),
    ("accel_b_mps2", (0.0, 10.0, 0.0), Error.PARAM_OUT_OF_RANGE),
    ("gyro_b_rad_s", (0.0, 0.0, -0.6), Error.PARAM_OUT_OF_RANGE),
    ("accel_scale_tc_per_c", (0.0, 0.002, 0.0), Error.PARAM_OUT_OF_RANGE),
    ("accel_t_ref_c", 150.0, Error.PARAM_OUT_OF_RANGE),
])
def test_invalid_parameters_are_refused_and_never_reach_flash(vb, dev, field, value, code):
    good = _params_example()
    dev.set_params(good)
    gen = dev.save_params()
    bad = _params_example()
    setattr(bad, field, value)
    with pytest.raises(PR.InvalidParams) as host:
        PR.validate(bad)
    assert host.value.code == code                      # host and device agree
    with pytest.raises(DeviceError) as e:
        dev.set_params(bad)
    assert e.value.code == code
    assert _pack(dev.get_params(ParamsWhich.ACTIVE).params) == _pack(good)
    assert dev.save_params() == gen                    # the same block again: nothing written
    assert _pack(dev.get_params(ParamsWhich.STORED).params) == _pack(good)


def test_host_and_device_validation_agree_on_random_blocks(dev):
    rng = np.random.default_rng(5)
    disagreements = []
    outcomes = set()
    for _ in range(60):
        p = PR.identity()
        p.accel_m = tuple(np.eye(3).ravel() + rng.normal(0, 0.25, 9))
        p.gyro_m = tuple(np.eye(3).ravel() + rng.normal(0, 0.05, 9))
        p.accel_b_mps2 = tuple(rng.normal(0, 4, 3))
        p.gyro_b_rad_s = tuple(rng.normal(0, 0.2, 3))
        try:
            PR.validate(p)
            host = Error.OK
        except PR.InvalidParams as e:
            host = e.code
        try:
            dev.set_params(p)
            device = Error.OK
        except DeviceError as e:
            device = e.code
        if host != device:
            disagreements.append((host, device, p))
        outcomes.add(host)
    assert not disagreements
    assert {Error.OK, Error.PARAM_OUT_OF_RANGE} <= outcomes    # both kinds were exercised


def test_calibrated_output_equals_the_host_correction(vb, dev):
    """Noise-free parts, a tilted board turning at a constant rate: every raw sample is the
    same, so the device's calibrated output can be compared with the host's correction."""
    vb.set_truth(accel={"noise_n": 0.0, "rw_k": 0.0},
                 gyro=[{"noise_n": 0.0, **GYRO_NO_DRIFT, "bias_rad_s": 0.01 * (k + 1)} for k in range(3)])
    g = np.array([0.3, -0.5, 0.81])
    vb.set_orientation(gravity=list(g))
    vb.set_rate(list(25.0 * g / np.linalg.norm(g)))   # turning about the vertical: gravity stays put
    vb.set_temperature(31.0)
    vb.wait(0.1)            # turning for a while: no sample averages the start of the turn
    p = _params_example()
    dev.set_params(p)
    dev.start_stream(1000)
    raw = dev.read(n_samples=300)
    dev.stop_stream()
    dev.start_stream(1000, calibrated=True)
    cal = dev.read(n_samples=300)
    dev.stop_stream()
    assert len(np.unique(raw.accel_counts, axis=0)) == 1 and len(np.unique(raw.gyro_counts, axis=0)) == 1
    u_acc = U.accel_counts_to_mps2(raw.accel_counts[:1], raw.accel_range_g[:1])
    u_gyr = U.gyro_counts_to_rad_s(raw.gyro_counts[:1])
    t_acc = U.accel_temp_counts_to_c(raw.accel_temp_counts[:1])
    t_gyr = U.gyro_temp_counts_to_c(raw.gyro_temp_counts[:1])
    want_a = PR.correct(PR.accel(p), u_acc, t_acc)[0]
    want_g = PR.correct(PR.gyro(p), u_gyr, t_gyr)[0]
    assert np.allclose(cal.accel_mps2, want_a, rtol=2e-6, atol=2e-6)
    assert np.allclose(cal.rate_rad_s, want_g, rtol=2e-6, atol=1e-8)
    assert not np.allclose(want_a, u_acc[0], atol=1e-3)        # the correction did something


# --------------------------------------------------------------------- faults
def _collect(dev, vb, n, inject=None, **kw):
    dev.start_stream(1000)
    dev.read(n_samples=100)
    if inject:
        vb.inject(inject, **kw)
    b = dev.read(n_samples=n)
    dev.stop_stream()
    return b


def test_gyro_fault_bits_show_in_frames_events_and_counters(vb, dev):
    before = dev.stats().sensor_faults
    b = _collect(dev, vb, 400, "gyro_fault_bits", sensor="gyro_y", bits=0x40, persistent=True)
    bad = b.status & SampleStatus.GYRO_Y_BAD
    assert bad[-100:].all()                                   # Q fault: every later sample bad
    assert (b.gyro_faults[:, 1] & 0x40).any()
    assert not (b.status & (SampleStatus.GYRO_X_BAD | SampleStatus.ACCEL_BAD)).any()
    events = [e for _, e in dev.link.fault_events]
    assert any(e.sensor == Sensor.GYRO_Y and e.kind == FaultKind.GYRO_FAULT_BITS and e.active and e.detail & 0x40
               for e in events)
    assert dev.stats().sensor_faults > before


def test_gyro_parity_errors_are_detected_per_sample(vb, dev):
    b = _collect(dev, vb, 400, "gyro_parity", sensor="gyro_x", count=5)
    n_bad = int(np.count_nonzero(b.status & SampleStatus.GYRO_X_BAD))
    assert 1 <= n_bad <= 5
    assert (b.gyro_faults[:, 0] & 1).any()
    assert any(e.kind == FaultKind.PARITY and e.sensor == Sensor.GYRO_X for _, e in dev.link.fault_events)


def test_spi_errors_are_counted_and_flagged(vb, dev):
    before = dev.stats().spi_errors
    b = _collect(dev, vb, 300, "spi_error", sensor="gyro_z", count=4)
    assert dev.stats().spi_errors - before >= 4
    assert (b.sensor_flags & BatchFlags.SPI_ERROR).any()
    assert (b.status & SampleStatus.GYRO_Z_BAD).any()


def test_a_missing_sensor_is_reported_and_commands_still_work(vb):
    vb.inject("missing", sensor="accel")
    vb.power_cut()
    with _connect(vb) as d:
        info = d.info()
        assert info.sensors_present == 0b1110
        assert info.accel_ids[:3] != (0xAD, 0x1D, 0xED)
        d.start_stream(500)
        b = d.read(n_samples=200)
        d.stop_stream()
        assert (b.status & SampleStatus.ACCEL_BAD).all()
        assert not (b.status & SampleStatus.GYRO_X_BAD).any()
        assert (b.sensor_flags & BatchFlags.ACCEL_MISSING).all()
        assert d.ping() < 2.0


def test_link_corruption_is_counted_and_never_accepted(vb, dev):
    dev.start_stream(1000)
    dev.read(n_samples=200)
    vb.inject("link_flip", count=40)
    vb.inject("link_drop", count=300)
    b = dev.read(n_samples=3000)
    dev.stop_stream()
    st = dev.link.decoder.stats
    assert st.frames_rejected > 0
    assert st.samples_missing > 0 and st.sample_gaps > 0
    # every accepted sample is a real one: a still level board, within 8 sigma of 1 g
    acc = U.accel_counts_to_mps2(b.accel_counts, b.accel_range_g)
    sigma = 22.5e-6 * U.G0_MPS2 * np.sqrt(1000)
    assert np.all(np.abs(acc[:, 2] - U.G0_MPS2) < 8 * sigma)
    assert np.all(np.abs(acc[:, :2]) < 8 * sigma)
    assert np.all(np.diff(b.sample_index) >= 1)


def test_a_link_too_slow_for_the_stream_drops_whole_batches_and_says_so():
    """At 115200 baud a 4 kHz raw stream (650 kbit/s) cannot fit: the device drops whole
    batches, counts them, flags the next batch, and the host sees exactly those gaps."""
    with VirtualBench(speed=0, seed=2, baud=115200) as vb, _connect(vb) as d:
        d.start_stream(4000)
        b = d.read(n_samples=20000, timeout=60)
        d.stop_stream()
        d.clock.sleep(0.3)
        d.discard_buffered()             # take (and count) everything that arrived
        dev_stats = d.stats()
        host = d.link.decoder.stats
    assert dev_stats.samples_dropped > 0 and dev_stats.frames_dropped > 0
    assert host.frames_rejected == 0                     # nothing cut or corrupted
    gaps = np.diff(b.sample_index)
    assert (gaps > 1).any()
    assert 0 < int((gaps - 1).sum()) <= host.samples_missing
    after_gap = np.flatnonzero(gaps > 1) + 1
    assert (b.sensor_flags[after_gap] & BatchFlags.SAMPLES_DROPPED).all()
    # every sample the device produced and did not drop arrived; the host's gaps are the
    # device's drops (drops after the last batch that arrived show in no gap)
    assert host.samples == dev_stats.samples_produced - dev_stats.samples_dropped
    assert host.samples_missing <= dev_stats.samples_dropped


@pytest.mark.parametrize("call", ["get_params", "info", "stats"])
def test_a_damaged_data_frame_is_retried_not_a_failure(vb, dev, call):
    """The ack of get_params/info/stats arrives but the data frame before it is damaged (one
    flipped byte at its start): the client asks again with the same request id, and the device
    resends both stored frames. Five times in a row, each must succeed."""
    want = {"get_params": lambda: dev.get_params().params.values(),
            "info": lambda: dev.info().mcu_uid,
            "stats": lambda: dev.stats().rx_frame_errors}[call]
    expected = want()
    rejected = dev.link.decoder.stats.frames_rejected
    for _ in range(5):
        vb.inject("link_flip", count=1)
        assert want() == expected
    assert dev.link.decoder.stats.frames_rejected >= rejected + 5   # the damage did happen


@pytest.mark.parametrize("call", ["get_params", "info", "stats"])
def test_data_commands_survive_the_link_fault_rates(vb, call):
    """The rates of test_link_corruption_is_counted_and_never_accepted: 40 flipped bytes on
    an idle link land on the reply itself; during a stream, 40 flipped and 300 dropped bytes
    land on batches and replies alike. The default bounded retries (3 sends) get through."""
    with _connect(vb, timeout=0.5) as d:
        fn = getattr(d, call)
        for _ in range(3):
            vb.inject("link_flip", count=40)
            assert fn() is not None
        d.start_stream(1000)
        d.read(n_samples=200)
        for _ in range(3):
            vb.inject("link_flip", count=40)
            vb.inject("link_drop", count=300)
            assert fn() is not None
        d.stop_stream()
