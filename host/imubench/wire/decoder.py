"""Streaming decoder: bytes in (chunks of any size), checked messages and sample arrays out.

    dec = StreamDecoder()
    for chunk in chunks:
        for frame in dec.feed(chunk):      # non-sample messages (ack, info, stats, ...)
            ...
    block = dec.take_samples()             # all raw samples so far as numpy arrays
    print(dec.stats)                       # every rejected byte and frame is counted

It never raises on input: a bad frame is counted by reason (protocol.FrameError) and the
decoder resynchronises at the next 0x00 delimiter. Sample batches are decoded with numpy,
without a Python loop per sample.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field, fields

import numpy as np
from cobs import cobs

from imubench import units as U
from imubench.wire import frame as P
from imubench.wire.protocol_gen import BATCH_HEADER_DTYPE, MsgType

_HDR = struct.Struct("<BBHI")
_RAW = P.MESSAGES[MsgType.RAW_BATCH]


def time_step_us(now: int, prev: int) -> int:
    """The step from u32 device time prev to now, (now - prev) mod 2^32 in [-2^31, 2^31): a step
    of exactly 2^31 us is -2^31, a step back (protocol/SPEC.md, Header fields; C: ib_time_step_us)."""
    return ((now - prev + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)



_INFO = int(MsgType.INFO)
_CAL = P.MESSAGES[MsgType.CAL_BATCH]
_BH = BATCH_HEADER_DTYPE.itemsize
_COUNT_OFF = _RAW.count_offset
_BATCH = struct.Struct(P.MESSAGES[MsgType.RAW_BATCH].cls.FORMAT)   # the batch header's values
# A raw batch has rules on its header only (none on its records, RECORD_RULES): one compiled
# check of the header (frame.VALUE_OK) says it is valid; a definition with record rules for it
# sends every raw batch through value_error again.
_RAW_HEADER_OK = (P.VALUE_OK[int(MsgType.RAW_BATCH)] if _RAW.record not in P.gen.RECORD_RULES
                  else (lambda _hdr: False))
# CRC-32C over a frame *including* its little-endian CRC field is this constant when the
# frame is intact (the CRC's residue), which saves slicing the CRC off every frame.
_CRC_RESIDUE = P.crc32c(b"\0\0\0\0")
_CRC_RESIDUE = P.crc32c(b"\0\0\0\0" + _CRC_RESIDUE.to_bytes(4, "little"))


@dataclass
class DecoderStats:
    """What the decoder saw: rejected frames by reason, gaps in what arrived, and samples that
    were received but not delivered, by reason. Every sample of a stream from its first one on
    is delivered or counted here (samples_missing, samples_rejected or samples_overflow)."""

    bytes_in: int = 0
    frames_ok: int = 0         # frames that passed every check of SPEC.md, "Receiving"
    oversize: int = 0
    cobs: int = 0
    too_short: int = 0
    crc: int = 0
    bad_version: int = 0
    unknown_type: int = 0
    bad_length: int = 0
    bad_enum: int = 0          # a field not one of its defined values (accel_range_g 7, ...)
    out_of_range: int = 0      # a field below its min or above its max (period_us 0)
    not_finite: int = 0        # a calibrated sample NaN or infinite
    bad_flags: int = 0         # status or flag bits that the definition does not have
    seq_gaps: int = 0          # places where the device's frame sequence jumped
    seq_restarts: int = 0      # backward jumps (the device restarted its sequence: a reboot)
    frames_missing: int = 0    # frames lost in those jumps
    frames_replayed: int = 0   # a frame whose seq was seen just before (the same seq again, or a
                               # little behind): a sample batch among them is not delivered
    sample_gaps: int = 0       # places where sample_index jumped
    samples_missing: int = 0   # samples lost in those jumps (link or device drops), also at the
                               # start of a stream (its first index is 0, SPEC.md)
    samples: int = 0           # samples accepted for delivery
    stream_starts: int = 0     # streams begun: a start_stream ack seen, or begin_stream()
    batches_index_backwards: int = 0  # sample_index behind the stream's (not delivered)
    batches_time_backwards: int = 0   # first sample not after the stream's last one (not delivered)
    batches_index_jump: int = 0       # a sample_index jump the elapsed device time cannot explain
    samples_rejected: int = 0  # samples in batches not delivered for the four reasons above
    samples_overflow: int = 0  # samples dropped because max_pending_samples were waiting

    @property
    def frames_rejected(self) -> int:
        return (self.oversize + self.cobs + self.too_short + self.crc + self.bad_version
                + self.unknown_type + self.bad_length + self.bad_enum + self.out_of_range
                + self.not_finite + self.bad_flags)

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["frames_rejected"] = self.frames_rejected
        return d


@dataclass
class DecodedFrame:
    """A checked non-sample frame and its decoded message object; t_us is its timestamp
    unwrapped to 64 bits on the same time line as the samples."""

    type: int
    seq: int
    timestamp_us: int
    msg: object
    t_us: int = 0


@dataclass
class SampleBlock:
    """Samples as arrays, one row per sample. Raw blocks carry counts; calibrated blocks
    carry SI values. Batch-level fields are repeated on each sample of their batch."""

    calibrated: bool
    t_us: np.ndarray                  # int64, device time of each sample, unwrapped
    sample_index: np.ndarray          # int64, since start_stream
    status: np.ndarray                # uint8, SampleStatus bits
    sensor_flags: np.ndarray          # uint8, BatchFlags bits
    accel_temp_counts: np.ndarray     # uint16
    gyro_temp_counts: np.ndarray      # (n, 3) int16
    gyro_faults: np.ndarray           # (n, 3) uint8
    accel_status: np.ndarray          # uint8
    accel_range_g: np.ndarray         # uint8
    accel_counts: np.ndarray | None = None   # (n, 3) int32, raw only
    gyro_counts: np.ndarray | None = None    # (n, 3) int16, raw only
    accel_mps2: np.ndarray | None = None     # (n, 3) float32, calibrated only
    rate_rad_s: np.ndarray | None = None     # (n, 3) float32, calibrated only

    def __len__(self) -> int:
        return len(self.t_us)

    def __getitem__(self, s: slice) -> "SampleBlock":
        """The samples of a slice, as a block: block[-n:], block[:n]."""
        if not isinstance(s, slice):
            raise TypeError("index a SampleBlock with a slice")
        return SampleBlock(**{f.name: (getattr(self, f.name) if f.name == "calibrated" or getattr(self, f.name) is None
                                       else getattr(self, f.name)[s]) for f in fields(self)})

    def si(self) -> tuple[np.ndarray, np.ndarray]:
        """(accel m/s², rate rad/s) as float64: nominal scaling of raw counts
        (docs/conventions.md), or the device's calibrated values."""
        if self.calibrated:
            return self.accel_mps2.astype(np.float64), self.rate_rad_s.astype(np.float64)
        return (U.accel_counts_to_mps2(self.accel_counts, self.accel_range_g),
                U.gyro_counts_to_rad_s(self.gyro_counts))

    @classmethod
    def concat(cls, blocks: list["SampleBlock"]) -> "SampleBlock":
        if not blocks:
            raise ValueError("no blocks")
        kw = {}
        for f in fields(cls):
            if f.name == "calibrated":
                kw[f.name] = blocks[0].calibrated
                continue
            vals = [getattr(b, f.name) for b in blocks]
            kw[f.name] = None if vals[0] is None else np.concatenate(vals)
        return cls(**kw)


# The decoder's memory bound: samples received and not yet taken wait in the decoder, up to
# this many per kind (raw, calibrated); a batch that would go over is dropped and counted in
# samples_overflow. 2^20 raw samples (4.4 min at 4 kHz) hold about 17 MB of frame bytes.
MAX_PENDING_SAMPLES = 1 << 20
# feed() works through its input in pieces of this many bytes, so one call with any amount of
# data holds at most one piece of split frames at a time.
FEED_PIECE_BYTES = 1 << 16
# A frame whose seq is the last one seen, or at most this many behind it, is a replay (a
# retransmission); further behind, the device restarted its sequence (a reboot).
REPLAY_WINDOW_FRAMES = 32
# An index jump of more samples than twice the device time elapsed since the stream's last
# sample (plus this many periods) can hold is not a loss but a bad index: the batch is rejected.
JUMP_SLACK_PERIODS = 10


@dataclass
class _Pending:
    headers: list = field(default_factory=list)    # batch header bytes
    records: list = field(default_factory=list)    # record bytes
    ts: list = field(default_factory=list)         # unwrapped timestamp of each batch
    n: int = 0                                     # samples held

    def clear(self):
        self.headers.clear()
        self.records.clear()
        self.ts.clear()
        self.n = 0


@dataclass
class _Stream:
    """Where one kind's (raw or calibrated) sample stream stands."""

    next_index: int | None = None   # the index the next batch should start at (None: unknown)
    t_last: int | None = None       # unwrapped device time of the last sample delivered
    t_ref: int | None = None        # time of index next_index - 1 (t_last, or the stream's start)
    first: tuple | None = None      # (index, time) of the first batch seen without a known start


class StreamDecoder:
    """Incremental decoder of a device-to-host byte stream (see module doc).

    Memory: at most max_pending_samples undelivered samples per kind (the rest is counted in
    stats.samples_overflow), one FEED_PIECE_BYTES piece of input at a time inside feed(), and
    the non-sample frames feed() returns."""

    def __init__(self, max_pending_samples: int = MAX_PENDING_SAMPLES):
        self.stats = DecoderStats()
        self.max_pending_samples = max_pending_samples
        self._buf = bytearray()
        self._discarding = False     # inside an over-long run with no delimiter
        self.foreign_version: int | None = None   # the first other protocol version an intact frame had
        self._last_seq: int | None = None
        self._raw = _Pending()
        self._cal = _Pending()
        self._streams = {False: _Stream(), True: _Stream()}
        self._start_rid: int | None = None   # request id of the last start_stream ack acted on
        self._ts_last: int | None = None
        self._ts_offset = 0
        #: (request_id, field, value, rule kind, rule argument) of the last info refused for a value this side
        #: does not know (a newer firmware's), or None
        self.refused_info: tuple | None = None
        self._crc = P.crc32c
        self._decode = cobs.decode

    # -------------------------------------------------------------- bytes in
    def feed(self, data: bytes | bytearray | memoryview) -> list[DecodedFrame]:
        """Consume bytes; return the non-sample frames completed by them, in order."""
        self.stats.bytes_in += len(data)
        out: list[DecodedFrame] = []
        mv = memoryview(data).cast("B") if not isinstance(data, bytes) else data
        for i in range(0, len(mv), FEED_PIECE_BYTES):
            self._feed_piece(mv[i:i + FEED_PIECE_BYTES], out)
        return out

    def _feed_piece(self, data, out: list) -> None:
        st = self.stats
        buf = self._buf
        buf += data
        end = buf.rfind(0)
        if end < 0:
            if len(buf) > P.MAX_ENCODED:
                # no delimiter in sight: drop what we hold, count one oversize at the next 0x00
                self._discarding = True
                buf.clear()
            return
        parts = bytes(buf[:end]).split(b"\0")
        del buf[:end + 1]
        if self._discarding:
            st.oversize += 1
            self._discarding = False
            parts = parts[1:]
        crc = self._crc
        residue = _CRC_RESIDUE
        decode = self._decode
        max_enc = P.MAX_ENCODED
        max_frame = P.MAX_FRAME
        raw_ok = _RAW_HEADER_OK
        for chunk in parts:
            if not chunk:
                continue           # back-to-back delimiters: idle fill, not an error
            if len(chunk) > max_enc:
                st.oversize += 1
                continue
            try:
                raw = decode(chunk)
            except cobs.DecodeError:
                st.cobs += 1
                continue
            n = len(raw)
            if n > max_frame:
                st.oversize += 1
                continue
            if n < 12:
                st.too_short += 1
                continue
            if crc(raw) != residue:
                st.crc += 1
                continue
            version, mtype, seq, ts = _HDR.unpack_from(raw)
            if version != P.PROTOCOL_VERSION:
                st.bad_version += 1
                if self.foreign_version is None:
                    self.foreign_version = version
                continue
            if mtype == 0x90 or mtype == 0x91:
                d = _RAW if mtype == 0x90 else _CAL
                rsize = d.record_dtype.itemsize
                body = n - 12 - _BH
                if body < 0:
                    st.bad_length += 1
                    continue
                count = raw[8 + _COUNT_OFF]
                if body != count * rsize or count > d.max_records:
                    st.bad_length += 1
                    continue
                hdr = _BATCH.unpack_from(raw, 8)
                # a raw batch has rules on its header only: when they hold, nothing to name
                err = None if mtype == 0x90 and raw_ok(hdr) else P.value_error(mtype, memoryview(raw)[8:-4], hdr)
                if err is not None:
                    setattr(st, err.value, getattr(st, err.value) + 1)
                    continue
                st.frames_ok += 1
                replay, t = self._sequence(seq, ts)
                self._batch(mtype == 0x91, raw, hdr[0], hdr[1], count, t, replay)
                continue
            payload = raw[8:-4]
            values = None
            err = P.payload_error(mtype, payload)
            if err is None:
                values = P.MESSAGES[mtype].cls.STRUCT.unpack_from(payload, 0)
                err = P.value_error(mtype, payload, values)
            if err is not None:
                setattr(st, err.value, getattr(st, err.value) + 1)
                if mtype == _INFO and values is not None:
                    # CRC good, layout right, a value this side does not know: a newer firmware's
                    # info, named for the one waiting for it (device.link: "newer firmware")
                    self.refused_info = (values[0], *P.value_problem(mtype, payload, values))
                continue
            st.frames_ok += 1
            replay, t = self._sequence(seq, ts)
            msg = P.MESSAGES[mtype].cls.from_values(values)
            out.append(DecodedFrame(mtype, seq, ts, msg, t))
            self._marker(mtype, msg, t, replay)

    def _sequence(self, seq: int, ts: int) -> tuple[bool, int]:
        """Count the frame's place in the device's sequence; (is it a replay, its unwrapped
        time). A replay does not move the sequence or the clock."""
        st = self.stats
        if self._ts_last is None:
            self._ts_last = ts
        last = self._last_seq
        if last is not None:
            ahead = (seq - last) & 0xFFFF
            if ahead == 0 or ahead >= 0x10000 - REPLAY_WINDOW_FRAMES:
                st.frames_replayed += 1
                return True, ts + self._ts_offset
            if ahead >= 0x8000:
                # far behind: the device restarted its count (a reboot; its boot info resets the
                # streams) or resent an old reply; not 30000+ lost frames
                st.seq_restarts += 1
            elif ahead > 1:
                st.seq_gaps += 1
                st.frames_missing += ahead - 1
        self._last_seq = seq
        # 32-bit microseconds wrap every 71.6 min: the step is taken modulo 2^32 in [-2^31, 2^31),
        # as the C side's ib_time_step_us (exactly 2^31 is a step back, whichever way it wrapped)
        t = self._ts_last + self._ts_offset + time_step_us(ts, self._ts_last)
        self._ts_offset = t - ts
        self._ts_last = ts
        return False, t

    def _marker(self, mtype: int, msg, t: int, replay: bool) -> None:
        """Frames that say where a stream starts: a start_stream ack (its first sample index is
        0, SPEC.md; a resent ack has the old seq and counts once) and the device's unsolicited
        info at boot (no stream runs)."""
        if mtype == MsgType.ACK:
            if msg.command == MsgType.START_STREAM and msg.error == 0 and msg.request_id != self._start_rid:
                self._start_rid = msg.request_id   # a retried command's ack again: same stream
                self._begin(0, t)
        elif mtype == MsgType.INFO and msg.request_id == 0 and not replay:
            self._reset_streams()
            self._start_rid = None

    def _reset_streams(self) -> None:
        for s in self._streams.values():
            s.next_index = s.t_last = s.t_ref = None
            s.first = None

    def _begin(self, first_index: int, t: int | None) -> None:
        self.stats.stream_starts += 1
        for s in self._streams.values():
            if t is not None and s.first is not None and s.first[1] > t:
                # the ack came late (it was lost and resent): this stream's batches were already
                # taken as a stream of unknown start; the ones before its first are missing
                if s.first[0] > first_index:
                    self.stats.sample_gaps += 1
                    self.stats.samples_missing += s.first[0] - first_index
                s.first = None
                continue
            s.next_index = first_index
            s.t_last = None        # a new stream (after a reboot the device clock starts again)
            s.t_ref = t
            s.first = None

    def begin_stream(self, first_index: int = 0) -> None:
        """A new stream starts now: every sample from first_index on is delivered or counted
        (samples_missing and the others). A start_stream ack in the byte stream does this by
        itself; call it when a stream starts without one."""
        self._begin(first_index, None)

    def _batch(self, cal: bool, raw: bytes, index: int, period_us: int, n: int, t: int, replay: bool) -> None:
        st = self.stats
        s = self._streams[cal]
        if replay:
            st.samples_rejected += n
            return
        if s.t_last is not None and t <= s.t_last:
            st.batches_time_backwards += 1
            st.samples_rejected += n
            return
        nxt = s.next_index
        if nxt is not None:
            if index < nxt:
                st.batches_index_backwards += 1
                st.samples_rejected += n
                return
            if index > nxt:
                gap = index - nxt
                if s.t_ref is not None and gap * period_us > 2 * (t - s.t_ref) + JUMP_SLACK_PERIODS * period_us:
                    st.batches_index_jump += 1
                    st.samples_rejected += n
                    return
                st.sample_gaps += 1
                st.samples_missing += gap
        elif s.first is None:
            s.first = (index, t)
        s.next_index = index + n
        if n:
            s.t_last = s.t_ref = t + (n - 1) * period_us
        st.samples += n
        p = self._cal if cal else self._raw
        if p.n + n > self.max_pending_samples:
            st.samples_overflow += n
            st.samples -= n
            return
        p.headers.append(raw[8:8 + _BH])
        p.records.append(raw[8 + _BH:-4])
        p.ts.append(t)
        p.n += n

    def reset_sequence(self) -> None:
        """Forget the last sequence number and where the streams stand (the device rebooted),
        so the next ones are not counted as gaps."""
        self._last_seq = None
        self._reset_streams()

    # ------------------------------------------------------------ samples out
    def pending_samples(self, calibrated: bool = False) -> int:
        return (self._cal if calibrated else self._raw).n

    def take_samples(self, calibrated: bool = False) -> SampleBlock | None:
        """All samples decoded since the last call (raw or calibrated), or None."""
        p = self._cal if calibrated else self._raw
        if not p.headers:
            return None
        d = _CAL if calibrated else _RAW
        hdr = np.frombuffer(b"".join(p.headers), dtype=BATCH_HEADER_DTYPE)
        rec_bytes = b"".join(p.records)
        ts = np.asarray(p.ts, dtype=np.int64)
        p.clear()
        counts = hdr["count"].astype(np.int64)
        per = np.repeat(hdr, counts)                        # batch fields, one row per sample
        starts = np.cumsum(counts) - counts
        within = np.arange(len(per), dtype=np.int64) - np.repeat(starts, counts)
        index = per["sample_index"].astype(np.int64) + within
        t_us = np.repeat(ts, counts) + within * per["period_us"].astype(np.int64)
        recs = P.unpack_record_fields(d, rec_bytes)
        common = dict(
            t_us=t_us, sample_index=index, status=recs["status"].astype(np.uint8),
            sensor_flags=per["sensor_flags"], accel_temp_counts=per["accel_temp_counts"],
            gyro_temp_counts=per["gyro_temp_counts"], gyro_faults=per["gyro_faults"],
            accel_status=per["accel_status"], accel_range_g=per["accel_range_g"],
        )
        if calibrated:
            return SampleBlock(True, accel_mps2=recs["accel_mps2"], rate_rad_s=recs["rate_rad_s"], **common)
        accel = np.empty((len(per), 3), dtype=np.int32)
        accel[:, 0], accel[:, 1], accel[:, 2] = recs["accel_x_counts"], recs["accel_y_counts"], recs["accel_z_counts"]
        return SampleBlock(False, accel_counts=accel, gyro_counts=recs["gyro_counts"], **common)


def decode_bytes(data: bytes) -> tuple[list[DecodedFrame], SampleBlock | None, SampleBlock | None, DecoderStats]:
    """Decode a whole recording: (messages, raw samples, calibrated samples, stats).

    Memory grows with the recording: every sample comes back as arrays, 49 bytes per raw
    sample (3 bytes per byte of a raw recording); the decoder's own queue stays small (samples
    are taken after every megabyte), and joining the pieces at the end doubles that for a
    moment: measured peak about 115 bytes per raw sample, 700 MB for a 100 MB recording
    (bench/decoder_memory.py). For longer recordings, feed a StreamDecoder piece by piece and
    take_samples() as you go (docs/architecture.md)."""
    dec = StreamDecoder()
    msgs = []
    got: dict[bool, list] = {False: [], True: []}
    step = 1 << 20
    for i in range(0, len(data), step):
        msgs += dec.feed(data[i:i + step])
        for cal in (False, True):
            b = dec.take_samples(cal)
            if b is not None:
                got[cal].append(b)
    blocks = [SampleBlock.concat(got[cal]) if got[cal] else None for cal in (False, True)]
    return msgs, blocks[0], blocks[1], dec.stats
