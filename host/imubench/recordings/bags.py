"""Reading ROS bags (imubench.recordings.read, format ``rosbag``): ROS 1 (.bag) and ROS 2
(a directory with metadata.yaml, .db3 or .mcap) with sensor_msgs/Imu messages, through the
optional ``rosbags`` library, decoded a block of one message layout at a time."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from imubench import memory
from imubench.recordings import Recording, RecordingError, from_arrays
from imubench.recordings.progress import progress
INSTALL_ROSBAGS = "pip install 'imubench[rosbag]' (the rosbags library)"


def _imu_offsets(raw: bytes, ros1: bool) -> tuple[int, int, int] | None:
    """(stamp, angular_velocity, linear_acceleration) byte offsets of a serialized sensor_msgs/Imu whose
    frame_id is as long as this message's: ROS 1 (Header seq, stamp, frame_id; no alignment) or ROS 2
    CDR little-endian (a 4-byte encapsulation header; stamp, frame_id; the doubles aligned to 8 from
    after the encapsulation header). None when the layout is not one of those two."""
    import struct
    try:
        if ros1:
            (flen,) = struct.unpack_from("<I", raw, 12)
            base = 16 + flen
            stamp = 4
        else:
            if raw[:2] != b"\x00\x01":               # CDR_LE
                return None
            (flen,) = struct.unpack_from("<I", raw, 4 + 8)
            base = 4 + ((12 + flen + 7) // 8) * 8
            stamp = 4
        av, la = base + 32 + 72, base + 32 + 72 + 24 + 72
        return (stamp, av, la) if la + 24 + 72 == len(raw) else None
    except struct.error:
        return None


def read_rosbag(path: Path, *, topic: str | None = None, **opt) -> Recording:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RecordingError(f"reading ROS bags needs the optional rosbags library: {INSTALL_ROSBAGS}") from None
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        if not reader.is2:                  # ROS 1: the message index counted, not held (_Ros1Reader)
            reader.readers = [_ros1_reader()(path)]
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises its own classes for every damaged bag
        raise RecordingError(f"{path}: not a readable ROS bag ({type(e).__name__}: {e})") from None
    try:
        imu = [c for c in reader.connections if c.msgtype in ("sensor_msgs/msg/Imu", "sensor_msgs/Imu")]
        if not imu:
            raise RecordingError(f"{path.name} has no sensor_msgs/Imu topic (topics: "
                                 f"{', '.join(sorted({c.topic for c in reader.connections})) or 'none'})")
        topics = sorted({c.topic for c in imu})
        if topic is None and len(topics) > 1:
            raise RecordingError(f"{path.name} has several sensor_msgs/Imu topics ({', '.join(topics)}): "
                                 "choose one with --topic")
        topic = topic or topics[0]
        conns = [c for c in imu if c.topic == topic]
        if not conns:
            raise RecordingError(f"{path.name} has no sensor_msgs/Imu topic {topic!r} (it has {', '.join(topics)})")
        t, recv, a, g, k = _rosbag_messages(reader, conns, path, opt.get("memory_budget"))
    finally:
        reader.close()
    notes = [f"topic {topic}: {k} sensor_msgs/Imu messages (m/s², rad/s by the message definition, REP 103)"]
    if k and not _advances(t):
        t = recv
        notes.append("the messages' header stamps are not set: the bag's receive times are used")
    else:
        del recv
    return from_arrays(a, g, t_s=t, source=str(path), fmt="rosbag", notes=notes, device=opt.get("device"),
                       copy=False)


_ROS1_READER = None


def _ros1_reader():
    """rosbags' ROS 1 bag reader, with the bag's message index counted instead of held: rosbags keeps
    an IndexData tuple for every message (~170 B: 3 GB for a day at 200 Hz, before a sample is read);
    this one keeps each connection's count, and reads the messages chunk by chunk in the file's
    order, each chunk's records one after the other (as rosbags' own messages() reads a record).
    The order is the file's: _rosbag_messages puts the samples in receive-time order when it is not."""
    global _ROS1_READER
    if _ROS1_READER is not None:
        return _ROS1_READER
    import os
    from io import BytesIO

    from rosbags.rosbag1.reader import Header, Reader, RecordType, read_bytes, read_uint32

    class Ros1Reader(Reader):
        def open(self) -> None:
            self.counts: dict = {}
            super().open()

        def read_index_data(self, pos, indexes) -> None:          # noqa: ARG002 - rosbags' signature
            header = Header.read(self.bio, RecordType.IDXDATA)
            conn, count = header.get_uint32("conn"), header.get_uint32("count")
            self.bio.seek(read_uint32(self.bio), os.SEEK_CUR)
            self.counts[conn] = self.counts.get(conn, 0) + count

        def messages(self, connections=(), start=None, stop=None):
            self._check_open()
            ids = {c.id for c in (connections or self.connections)}
            byid = {c.id: c for c in self.connections}
            for info in sorted(self.chunk_infos, key=lambda c: (c.start_time, c.pos)):
                if not ids & set(info.connection_counts):
                    continue
                ch = self.chunks[info.pos]
                self.bio.seek(ch.datapos)
                raw = ch.decompressor(read_bytes(self.bio, ch.datasize))
                buf, end = BytesIO(raw), len(raw)
                del raw
                while buf.tell() < end:
                    header = Header.read(buf)
                    size = read_uint32(buf)
                    if header.get_uint8("op") == RecordType.MSGDATA and header.get_uint32("conn") in ids:
                        t = header.get_time("time")
                        if (start is None or t >= start) and (stop is None or t < stop):
                            yield byid[header.get_uint32("conn")], t, read_bytes(buf, size)
                            continue
                    buf.seek(size, os.SEEK_CUR)

    _ROS1_READER = Ros1Reader
    return Ros1Reader


def _advances(t: np.ndarray) -> bool:
    """True when any time stamp is later than the one before (a block at a time)."""
    return any(np.any(np.diff(t[i:i + (1 << 20) + 1]) > 0) for i in range(0, max(len(t) - 1, 0), 1 << 20))


def _rosbag_messages(reader, conns, path: Path, budget: int | None):
    """(header stamps s, receive times s, accel, gyro, count) of the messages of conns, into arrays
    allocated once from the bag's message count (the budget's sample limit checked first; float64 or
    float32 values by the budget). Each message is read at the offsets of its layout (_imu_offsets,
    checked against the full deserializer on the first message of each connection and whenever the
    layout changes), else deserialized; a tqdm bar counts the messages on reads over a second."""
    counts = [getattr(r, "counts", None) for r in getattr(reader, "readers", [])]
    if counts and all(x is not None for x in counts):             # ROS 1 (_ros1_reader): counted
        total = sum(x.get(c.id, 0) for x in counts for c in conns)
    else:
        total = sum(int(getattr(c, "msgcount", 0) or 0) for c in conns)
    limit = memory.sample_limit(budget, 6, True)
    if total > limit:
        raise RecordingError(f"{path}: {total:,} messages on the topic, more than the limit of {limit:,} samples "
                             f"of the memory budget of {memory.budget_text(budget)}; give a "
                             "larger --memory-budget, or cut the bag")
    dtype = memory.storage_dtype(total, budget, 6, True) or np.float32
    size = max(total, 1)
    t = np.empty(size)
    recv = np.empty(size)
    a = np.empty((size, 3), dtype=dtype)
    g = np.empty((size, 3), dtype=dtype)
    known: dict = {}
    k = 0
    bar = progress(total, f"reading {path.name}", unit="msg") if total > 100_000 else None
    # messages of one layout are gathered and decoded together, a block at a time (numpy views of
    # their bytes at the layout's offsets: the same values as struct.unpack_from, without a Python
    # call for each number); one that changes the layout, or needs the deserializer, ends a block
    block: list = []
    stamps: list = []
    layout = None                                   # (offsets, length) of the block's messages

    def room(m: int) -> None:
        nonlocal t, recv, a, g
        if k + m > len(t):
            if total:
                raise RecordingError(f"{path}: more messages than the bag's index counts ({total}); damaged?")
            size = max(2 * len(t), k + m)
            t, recv = np.resize(t, size), np.resize(recv, size)
            a, g = np.resize(a, (size, 3)), np.resize(g, (size, 3))

    def flush() -> None:
        nonlocal k
        m = len(block)
        if not m:
            return
        room(m)
        (o0, o1, o2), length = layout
        raw = np.frombuffer(b"".join(block), np.uint8).reshape(m, length)
        sec = raw[:, o0:o0 + 4].copy().view("<i4")[:, 0].astype(np.float64)
        nsec = raw[:, o0 + 4:o0 + 8].copy().view("<u4")[:, 0].astype(np.float64)
        t[k:k + m] = sec + 1e-9 * nsec
        g[k:k + m] = raw[:, o1:o1 + 24].copy().view("<f8")
        a[k:k + m] = raw[:, o2:o2 + 24].copy().view("<f8")
        recv[k:k + m] = np.array(stamps, dtype=np.int64) * 1e-9
        k += m
        block.clear()
        stamps.clear()
        if bar is not None:
            bar.update(m)
    try:
        for c, ts, raw in reader.messages(connections=conns):
            key = (c.id, len(raw))
            off = known.get(key, False)
            if off is False:
                off = _imu_offsets(raw, not getattr(reader, "is2", True))
                off = off if off is not None and _offsets_agree(reader, c, raw, off) else None
                known[key] = off
            if off is not None:
                if layout != (off, len(raw)) or len(block) >= 16384:
                    flush()
                    layout = (off, len(raw))
                block.append(raw)
                stamps.append(ts)
                continue
            flush()
            room(1)
            m = reader.deserialize(raw, c.msgtype)
            t[k] = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
            la, av = m.linear_acceleration, m.angular_velocity
            a[k] = (la.x, la.y, la.z)
            g[k] = (av.x, av.y, av.z)
            recv[k] = ts * 1e-9
            k += 1
        flush()
    except RecordingError:
        raise
    except Exception as e:  # noqa: BLE001 - rosbags raises its own classes for a damaged bag
        raise RecordingError(f"{path}: damaged after {k} messages ({type(e).__name__}: {e})") from None
    finally:
        if bar is not None:
            bar.close()
    t, recv, a, g = t[:k], recv[:k], a[:k], g[:k]
    if any(np.any(np.diff(recv[i:i + (1 << 20) + 1]) < 0) for i in range(0, max(k - 1, 0), 1 << 20)):
        order = np.argsort(recv, kind="stable")     # chunks written out of time order: the bag's time order
        t, recv, a, g = t[order], recv[order], a[order], g[order]
    return t, recv, a, g, k


def _offsets_agree(reader, c, raw: bytes, off) -> bool:
    """True when the values read at off are those the full deserializer gives for this message."""
    import struct
    try:
        m = reader.deserialize(raw, c.msgtype)
    except Exception:  # noqa: BLE001
        return False
    la, av = m.linear_acceleration, m.angular_velocity
    sec, nsec = struct.unpack_from("<iI", raw, off[0])
    return (struct.unpack_from("<3d", raw, off[1]) == (av.x, av.y, av.z)
            and struct.unpack_from("<3d", raw, off[2]) == (la.x, la.y, la.z)
            and (sec, nsec) == (m.header.stamp.sec, m.header.stamp.nanosec))
