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
_CAL = P.MESSAGES[MsgType.CAL_BATCH]
_BH = BATCH_HEADER_DTYPE.itemsize
_COUNT_OFF = _RAW.count_offset
# CRC-32C over a frame *including* its little-endian CRC field is this constant when the
# frame is intact (the CRC's residue), which saves slicing the CRC off every frame.
_CRC_RESIDUE = P.crc32c(b"\0\0\0\0")
_CRC_RESIDUE = P.crc32c(b"\0\0\0\0" + _CRC_RESIDUE.to_bytes(4, "little"))


@dataclass
class DecoderStats:
    """What the decoder saw. Rejected frames by reason, and gaps in what arrived."""

    bytes_in: int = 0
    frames_ok: int = 0
    oversize: int = 0
    cobs: int = 0
    too_short: int = 0
    crc: int = 0
    bad_version: int = 0
    unknown_type: int = 0
    bad_length: int = 0
    seq_gaps: int = 0          # places where the device's frame sequence jumped
    seq_restarts: int = 0      # backward jumps (the device restarted its sequence: a reboot)
    frames_missing: int = 0    # frames lost in those jumps
    sample_gaps: int = 0       # places where sample_index jumped
    samples_missing: int = 0   # samples lost in those jumps (link or device drops)
    samples: int = 0           # samples decoded

    @property
    def frames_rejected(self) -> int:
        return (self.oversize + self.cobs + self.too_short + self.crc + self.bad_version
                + self.unknown_type + self.bad_length)

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


@dataclass
class _Pending:
    headers: list = field(default_factory=list)    # batch header bytes
    records: list = field(default_factory=list)    # record bytes
    ts: list = field(default_factory=list)         # arrays of unwrapped frame timestamps

    def clear(self):
        self.headers.clear()
        self.records.clear()
        self.ts.clear()


class StreamDecoder:
    """Incremental decoder of a device-to-host byte stream (see module doc)."""

    def __init__(self):
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._discarding = False     # inside an over-long run with no delimiter
        self._last_seq: int | None = None
        self._raw = _Pending()
        self._cal = _Pending()
        self._next_index: dict[bool, int | None] = {False: None, True: None}
        self._ts_last: int | None = None
        self._ts_offset = 0
        self._crc = P.crc32c
        self._decode = cobs.decode

    # -------------------------------------------------------------- bytes in
    def feed(self, data: bytes | bytearray | memoryview) -> list[DecodedFrame]:
        """Consume bytes; return the non-sample frames completed by them, in order."""
        st = self.stats
        st.bytes_in += len(data)
        buf = self._buf
        buf += data
        end = buf.rfind(0)
        if end < 0:
            if len(buf) > P.MAX_ENCODED:
                # no delimiter in sight: drop what we hold, count one oversize at the next 0x00
                self._discarding = True
                buf.clear()
            return []
        parts = bytes(buf[:end]).split(b"\0")
        del buf[:end + 1]
        if self._discarding:
            st.oversize += 1
            self._discarding = False
            parts = parts[1:]
        out: list[DecodedFrame] = []
        seqs: list[int] = []
        tss: list[int] = []          # timestamps of accepted frames, in arrival order
        raw_at: list[int] = []       # which of them are raw / calibrated batches
        cal_at: list[int] = []
        crc = self._crc
        residue = _CRC_RESIDUE
        decode = self._decode
        max_enc = P.MAX_ENCODED
        max_frame = P.MAX_FRAME
        raw_p, cal_p = self._raw, self._cal
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
                seqs.append(seq)
                (raw_at if mtype == 0x90 else cal_at).append(len(tss))
                tss.append(ts)
                pend = raw_p if mtype == 0x90 else cal_p
                pend.headers.append(raw[8:8 + _BH])
                pend.records.append(raw[8 + _BH:-4])
                continue
            payload = raw[8:-4]
            err = P.payload_error(mtype, payload)
            if err is not None:
                if err is P.FrameError.UNKNOWN_TYPE:
                    st.unknown_type += 1
                else:
                    st.bad_length += 1
                continue
            seqs.append(seq)
            out.append(DecodedFrame(mtype, seq, ts, P.decode_message(mtype, payload), len(tss)))
            tss.append(ts)
        if seqs:
            self._count_seq_gaps(seqs)
            t = self._unwrap(np.asarray(tss, dtype=np.int64))
            if raw_at:
                raw_p.ts.append(t[raw_at])
            if cal_at:
                cal_p.ts.append(t[cal_at])
            for f in out:
                f.t_us = int(t[f.t_us])
        return out

    def _count_seq_gaps(self, seqs: list[int]) -> None:
        """Frames accepted in one feed() call, in order: count jumps in the 16-bit sequence."""
        self.stats.frames_ok += len(seqs)
        a = np.asarray(seqs, dtype=np.int64)
        prev = np.empty_like(a)
        prev[0] = a[0] - 1 if self._last_seq is None else self._last_seq
        prev[1:] = a[:-1]
        missing = (a - prev - 1) & 0xFFFF
        # a jump of half the sequence space or more is the device restarting its count
        # (a reboot), not 30000+ lost frames
        restart = missing >= 0x8000
        self.stats.seq_restarts += int(np.count_nonzero(restart))
        missing = np.where(restart, 0, missing)
        self.stats.seq_gaps += int(np.count_nonzero(missing))
        self.stats.frames_missing += int(missing.sum())
        self._last_seq = int(a[-1])

    def reset_sequence(self) -> None:
        """Forget the last sequence number and sample index (the device rebooted or a new
        stream started), so the next ones are not counted as gaps."""
        self._last_seq = None
        self._next_index = {False: None, True: None}

    # ------------------------------------------------------------ samples out
    def pending_samples(self, calibrated: bool = False) -> int:
        p = self._cal if calibrated else self._raw
        return sum(len(r) for r in p.records) // (_CAL if calibrated else _RAW).record_dtype.itemsize

    def take_samples(self, calibrated: bool = False) -> SampleBlock | None:
        """All samples decoded since the last call (raw or calibrated), or None."""
        p = self._cal if calibrated else self._raw
        if not p.headers:
            return None
        d = _CAL if calibrated else _RAW
        hdr = np.frombuffer(b"".join(p.headers), dtype=BATCH_HEADER_DTYPE)
        rec_bytes = b"".join(p.records)
        ts = np.concatenate(p.ts)
        p.clear()
        counts = hdr["count"].astype(np.int64)
        per = np.repeat(hdr, counts)                        # batch fields, one row per sample
        starts = np.cumsum(counts) - counts
        within = np.arange(len(per), dtype=np.int64) - np.repeat(starts, counts)
        index = per["sample_index"].astype(np.int64) + within
        t_us = np.repeat(ts, counts) + within * per["period_us"].astype(np.int64)
        self._count_sample_gaps(calibrated, hdr["sample_index"].astype(np.int64), counts)
        recs = P.unpack_record_fields(d, rec_bytes)
        self.stats.samples += len(per)
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

    def _unwrap(self, ts: np.ndarray) -> np.ndarray:
        """32-bit microsecond timestamps, in arrival order, to a monotonic int64 (they wrap
        every 71.6 min)."""
        if self._ts_last is None:
            self._ts_last = int(ts[0])
        prev = np.concatenate(([self._ts_last], ts[:-1]))
        wraps = np.cumsum((ts - prev) < -(1 << 31)) * (1 << 32)
        out = ts + wraps + self._ts_offset
        self._ts_offset += int(wraps[-1])
        self._ts_last = int(ts[-1])
        return out

    def _count_sample_gaps(self, calibrated: bool, first: np.ndarray, counts: np.ndarray) -> None:
        expected_next = first + counts
        prev = self._next_index[calibrated]
        exp = np.concatenate(([first[0] if prev is None else prev], expected_next[:-1]))
        gap = first - exp                       # negative: a new stream started; not a loss
        jumps = gap[gap > 0]
        self.stats.sample_gaps += int(len(jumps))
        self.stats.samples_missing += int(jumps.sum())
        self._next_index[calibrated] = int(expected_next[-1])


def decode_bytes(data: bytes) -> tuple[list[DecodedFrame], SampleBlock | None, SampleBlock | None, DecoderStats]:
    """Decode a whole recording: (messages, raw samples, calibrated samples, stats)."""
    dec = StreamDecoder()
    msgs = []
    step = 1 << 20
    for i in range(0, len(data), step):
        msgs += dec.feed(data[i:i + step])
    return msgs, dec.take_samples(False), dec.take_samples(True), dec.stats
