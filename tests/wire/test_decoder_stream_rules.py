"""The decoder's rules for what a stream may do (issue 16): every sample from a stream's first
one on is delivered or counted; indices and times only move forward; fields hold only what the
definition allows; memory stays bounded. Each test states the old behaviour it replaces."""
from __future__ import annotations

import json
import math
import tracemalloc

import numpy as np
import pytest
from imubench.wire import frame as P
from imubench.wire import protocol_gen as G
from imubench.wire.decoder import MAX_PENDING_SAMPLES, StreamDecoder, decode_bytes

PERIOD_US = 250      # 4 kHz


def raw_batch(seq: int, first: int, n: int = 16, ts: int | None = None, **hdr) -> bytes:
    recs = {"accel_x_counts": np.arange(n) + first, "accel_y_counts": np.zeros(n, int),
            "accel_z_counts": np.full(n, 256000), "status": np.zeros(n, int), "gyro_counts": np.zeros((n, 3), int)}
    h = dict(sample_index=first, period_us=PERIOD_US, count=n, accel_range_g=2)
    h.update(hdr)
    return P.encode(G.RawBatch(header=G.BatchHeader(**h)), seq,
                    first * PERIOD_US + 1000 if ts is None else ts, records=recs)


def cal_batch(seq: int, first: int, accel, ts: int | None = None, status=None) -> bytes:
    n = len(accel)
    recs = {"accel_mps2": np.asarray(accel, np.float32), "rate_rad_s": np.zeros((n, 3), np.float32),
            "status": np.zeros(n, int) if status is None else np.asarray(status)}
    return P.encode(G.CalBatch(header=G.BatchHeader(sample_index=first, period_us=1000, count=n, accel_range_g=2)),
                    seq, first * 1000 + 1000 if ts is None else ts, records=recs)


def start_ack(seq: int, request_id: int = 77, ts: int = 500) -> bytes:
    return P.encode(G.Ack(request_id=request_id, command=G.MsgType.START_STREAM, error=0, value=16), seq, ts)


# ---------------------------------------------------------------- start of a stream
def test_samples_lost_at_the_start_of_a_stream_are_counted():
    """The start_stream ack says a stream starts at index 0 (SPEC.md); with the first two
    batches lost the first delivered sample is 32. Before: samples_missing 0, gaps 0."""
    data = start_ack(1) + raw_batch(4, 32) + raw_batch(5, 48)
    _, raw, _, s = decode_bytes(data)
    assert raw.sample_index[0] == 32
    assert (s.samples_missing, s.sample_gaps, s.stream_starts) == (32, 1, 1)


def test_begin_stream_counts_from_the_given_first_index():
    dec = StreamDecoder()
    dec.begin_stream(0)
    dec.feed(raw_batch(1, 16))
    assert (dec.stats.samples_missing, dec.stats.sample_gaps) == (16, 1)


def test_a_resent_start_stream_ack_does_not_restart_the_count():
    """A retried start_stream is answered with the stored ack (same request id): one stream."""
    data = start_ack(1) + raw_batch(2, 0) + raw_batch(3, 16) + start_ack(1) + raw_batch(4, 32)
    _, raw, _, s = decode_bytes(data)
    assert len(raw) == 48 and (s.samples_missing, s.stream_starts) == (0, 1)


def test_a_late_start_stream_ack_still_counts_the_lost_first_samples():
    """The ack was lost and comes again (resent, old time) after the stream's batches: the
    samples before the first one that arrived are still counted, and nothing twice."""
    data = raw_batch(10, 32) + raw_batch(11, 48) + start_ack(2, ts=500) + raw_batch(12, 64)
    _, raw, _, s = decode_bytes(data)
    assert len(raw) == 48 and (s.samples_missing, s.sample_gaps) == (32, 1)


def test_start_of_stream_through_the_virtual_device():
    """The virtual device with its link dropping the bytes right after start_stream (4 kHz,
    batches of 16): the ack and the first batches are lost, the host retries and gets the
    stored ack. The samples lost at the start are counted: delivered + missing covers every
    index from 0. Before: the first delivered index was 32+ and samples_missing 0."""
    from imubench.device.link import Device
    from imubench.device.sim import VirtualBench
    with VirtualBench(speed=1, seed=3) as vb:
        with Device.open(vb.port_url, timeout=1.0) as dev:
            dev.ping()
            vb.inject("link_drop", count=600)               # the ack and about two batches
            dev.start_stream(4000, batch=16)
            b = dev.read(n_samples=2000, timeout=30)
            dev.stop_stream()
            st = dev.link.decoder.stats
    first = int(b.sample_index[0])
    assert first > 0, "the drop did not hit the start of the stream"
    assert st.samples_missing >= first and st.stream_starts == 1


# ---------------------------------------------------------------- forward only
def test_replayed_batch_is_counted_and_not_delivered_twice():
    """Before: the same batch (same seq) twice delivered its samples twice, counted a restart."""
    b = raw_batch(7, 16)
    data = start_ack(5) + raw_batch(6, 0) + b + b + raw_batch(8, 32)
    _, raw, _, s = decode_bytes(data)
    assert list(raw.sample_index) == list(range(48))
    assert (s.frames_replayed, s.samples_rejected, s.seq_restarts, s.frames_missing) == (1, 16, 0, 0)


def test_backward_timestamp_is_counted_and_not_delivered():
    """Before: a batch whose time runs backwards gave non-monotonic t_us."""
    data = raw_batch(1, 0, ts=100_000) + raw_batch(2, 16, ts=50_000) + raw_batch(3, 32, ts=108_000)
    _, raw, _, s = decode_bytes(data)
    assert np.all(np.diff(raw.t_us) > 0)
    assert s.batches_time_backwards == 1 and s.samples_rejected == 16
    assert len(raw) == 32 and (s.samples_missing, s.sample_gaps) == (16, 1)


def test_empty_batch_with_huge_index_is_rejected_not_four_billion_missing():
    """Before: one empty batch with sample_index near 2^32 added ~4e9 missing samples. Now an
    empty batch is refused by its field rule (count ≥ 1: out_of_range) before the stream sees it."""
    data = raw_batch(1, 0) + raw_batch(2, 0xFFFF_FF00, n=0, ts=1000 + 16 * PERIOD_US) + raw_batch(3, 16)
    _, raw, _, s = decode_bytes(data)
    assert s.samples_missing == 0 and s.out_of_range == 1 and s.seq_gaps == 1
    assert list(raw.sample_index) == list(range(32))


def test_index_behind_the_stream_is_rejected():
    data = raw_batch(1, 100) + raw_batch(2, 116) + raw_batch(3, 50, ts=1000 + 132 * PERIOD_US) + raw_batch(4, 132)
    _, raw, _, s = decode_bytes(data)
    assert s.batches_index_backwards == 1 and list(raw.sample_index) == list(range(100, 148))


def test_device_drops_are_still_counted_as_missing():
    """A jump the elapsed time explains (the device dropped 64 samples) is a loss, not an error."""
    data = raw_batch(1, 0) + raw_batch(2, 80) + raw_batch(3, 96)
    s = decode_bytes(data)[3]
    assert (s.samples_missing, s.sample_gaps, s.batches_index_jump) == (64, 1, 0)


# ---------------------------------------------------------------- meaning
@pytest.mark.parametrize("hdr, reason", [
    ({"accel_range_g": 7}, "bad_enum"),
    ({"accel_range_g": 0}, "bad_enum"),
    ({"period_us": 0}, "out_of_range"),
    ({"sensor_flags": 0x80}, "bad_flags"),
])
def test_batch_with_a_field_outside_its_definition_is_counted_by_reason(hdr, reason):
    """Before: accel_range_g 7 was delivered and `decode` scaled it as 2 g; period 0 too."""
    data = raw_batch(1, 0) + raw_batch(2, 16, **hdr) + raw_batch(3, 32)
    _, raw, _, s = decode_bytes(data)
    assert getattr(s, reason) == 1 and s.frames_rejected == 1
    assert set(raw.accel_range_g.tolist()) == {2} and len(raw) == 32


@pytest.mark.parametrize("bad, reason", [(math.nan, "not_finite"), (math.inf, "not_finite")])
def test_calibrated_batch_with_nan_or_inf_is_counted(bad, reason):
    good = [[0.0, 0.0, 9.80665]] * 2
    data = cal_batch(1, 0, good) + cal_batch(2, 2, [[0.0, bad, 9.8], [0, 0, 9.8]]) + cal_batch(3, 4, good)
    _, _, cal, s = decode_bytes(data)
    assert getattr(s, reason) == 1 and len(cal) == 4 and np.all(np.isfinite(cal.accel_mps2))


def test_calibrated_sample_with_undefined_status_bits_is_counted():
    good = [[0.0, 0.0, 9.80665]] * 2
    data = cal_batch(1, 0, good) + cal_batch(2, 2, good, status=[0, 0x20])
    _, _, cal, s = decode_bytes(data)
    assert s.bad_flags == 1 and len(cal) == 2


def test_message_with_undefined_enum_value_is_counted():
    data = P.encode(G.FaultEvent(sensor=9, kind=1, active=1), 1) + P.encode(G.FaultEvent(sensor=1, kind=1, active=1), 2)
    msgs, _, _, s = decode_bytes(data)
    assert s.bad_enum == 1 and [m.msg.sensor for m in msgs] == [1]


def test_unknown_board_code_is_delivered_and_named():
    """Board is an open enum: a newer firmware's board is a device we can still talk to."""
    from imubench.wire.ids import board_name
    msgs, _, _, s = decode_bytes(P.encode(G.Info(request_id=3, board=7, accel_range_g=2), 1))
    assert len(msgs) == 1 and s.frames_rejected == 0
    assert board_name(msgs[0].msg.board) == "unknown board code 7 (firmware newer than this imubench? update imubench)"


def test_units_refuse_an_unknown_range_instead_of_guessing():
    from imubench import units as U
    with pytest.raises(ValueError):
        U.accel_counts_to_mps2(np.array([[256000, 0, 0]]), np.array([7]))


def test_decode_json_is_strict_json(tmp_path):
    """A recording with a NaN calibrated sample: the JSON summary has no bare NaN."""
    from imubench.cli.main import main
    path = tmp_path / "rec.bin"
    good = [[0.0, 0.0, 9.80665]]
    path.write_bytes(cal_batch(1, 0, good) + cal_batch(2, 1, [[math.nan, 0, 9.8]]) + cal_batch(3, 2, good))
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["decode", str(path), "--json"]) == 0

    def refuse(name):
        raise ValueError(f"bare {name} in JSON")
    summary = json.loads(out.getvalue(), parse_constant=refuse)
    assert summary["calibrated"]["samples"] == 2 and summary["decoder"]["not_finite"] == 1


# ---------------------------------------------------------------- bounded memory
def _batches(n_bytes: int) -> bytes:
    one = b"".join(raw_batch(k, 16 * k) for k in range(256))   # 256 frames, seq wraps below
    return one * (n_bytes // len(one))


def test_undelivered_samples_are_capped_and_counted():
    """Before: 100 MB of batches never taken grew the decoder by ~580 MB (no cap)."""
    dec = StreamDecoder(max_pending_samples=10_000)
    data = b"".join(raw_batch(k & 0xFFFF, 16 * k, ts=16 * k * PERIOD_US + 1000) for k in range(2000))
    dec.feed(data)
    assert dec.pending_samples() <= 10_000
    assert dec.stats.samples_overflow == 2000 * 16 - dec.pending_samples()
    assert dec.stats.samples_missing == 0     # an overflow is not a link loss
    assert len(dec.take_samples()) == dec.stats.samples


def test_memory_of_a_stream_never_taken_is_bounded():
    """Batches fed and never taken: the decoder holds at most its cap of samples (about 16 bytes
    of frame per sample plus the per-batch objects), not the input. Eight times the cap is fed,
    with a cap of 2^16 samples: the memory is linear in the cap (the default, 2^20, holds 16
    times as much), and a decoder without a cap grows by 13 MB here (the input is 8.5 MB)."""
    cap = 1 << 16
    assert StreamDecoder().max_pending_samples == MAX_PENDING_SAMPLES == 1 << 20
    data = b"".join(raw_batch(k & 0xFFFF, 16 * k, ts=(16 * k * PERIOD_US + 1000) & 0xFFFFFFFF)
                    for k in range(8 * cap // 16))
    dec = StreamDecoder(max_pending_samples=cap)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for i in range(0, len(data), 1 << 20):
            dec.feed(data[i:i + (1 << 20)])
        grown = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert dec.pending_samples() <= cap and dec.stats.samples_overflow == 7 * cap
    # 38 bytes per sample of the cap (the 40 MB the default's 2^20 had), and 2.5 MB for the
    # 1 MB pieces in flight: measured 2.8 MB
    assert grown < 38 * cap + 2.5e6, f"{grown / 1e6:.1f} MB"


def test_one_feed_of_many_zero_bytes_works_in_bounded_pieces():
    """Before: one feed() of 100 MB of zero bytes grew by ~1 GB (a list of 100 M empty pieces)."""
    data = bytes(20_000_000)
    dec = StreamDecoder()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        dec.feed(data)
        grown = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert dec.stats.bytes_in == len(data) and dec.stats.frames_rejected == 0
    assert grown < 5e6, f"{grown / 1e6:.0f} MB"
