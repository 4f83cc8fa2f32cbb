#!/usr/bin/env python3
"""Throughput of the host stream decoder, measured against pymavlink in the same run.

    /work/main/.venv/bin/python bench/decode_throughput.py            # 2,000,000 samples
    /work/main/.venv/bin/python bench/decode_throughput.py --quick    # smoke run (200k samples)

A run prints the markdown table README states and publishes it (bench/publish.py);
--quick and --no-publish runs do not publish.

What is measured:

* imubench: a device stream of raw_batch frames (16 samples of 14 bytes each by default,
  4 kHz, accel noise around 1 g on Z, small gyro counts), built once with
  imubench.wire.frame (pack_records + build_frame), then decoded by a fresh
  imubench.wire.decoder.StreamDecoder per run, fed in fixed-size chunks; the time runs from
  the first feed() to the samples taken (every 16 chunks, as a reader takes them) joined into one
  block. Best of --repeat.
* pymavlink: a MAVLink v2 stream of RAW_IMU messages (one sample per message, the same
  sample values rescaled to mg / mrad/s), encoded with pymavlink's own MAVLink class and
  parsed by a fresh MAVLink instance's parse_buffer() in the same chunk size. Only the
  parse is timed. pymavlink parses ~1e5 messages/s or fewer, so by default it is timed on
  a subset (--mavlink-samples) and reported as messages per second.

The input chunks are sliced before the clock starts (they stand for reads from the port).
Human-readable lines first; the last line of stdout is one JSON object. The exit status is
non-zero only for a correctness failure (wrong sample count or values, rejected frames,
MAVLink parse errors); a missed throughput target is reported, not fatal.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from imubench.wire import frame as P
from imubench.wire.decoder import StreamDecoder
from imubench.wire.protocol_gen import (
    BATCH_HEADER_DTYPE,
    BatchHeader,
    MsgType,
    RawBatch,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

RATE_HZ = 4000
PERIOD_US = 1_000_000 // RATE_HZ
LSB_PER_G = 256_000            # ADXL355 at +-2 g (docs/conventions.md)
GYRO_LSB_PER_DPS = 80          # ADXRS450
TARGET_SAMPLES_PER_S = 2_000_000
TARGET_RATIO = 20.0
RAW = P.MESSAGES[MsgType.RAW_BATCH]


class BenchFailure(RuntimeError):
    pass


def check(cond: bool, what: str) -> None:
    if not cond:
        raise BenchFailure(what)


# ------------------------------------------------------------------ the simulated device
def make_samples(n: int, seed: int = 1) -> dict[str, np.ndarray]:
    """Realistic raw samples of a sensor at rest, Z up: counts and per-sample indices/times."""
    rng = np.random.default_rng(seed)
    # ~1 mg rms accel noise at 4 kHz (25 ug/rtHz over ~1.6 kHz), a few mg of bias per axis,
    # and a slow wobble (table vibration) so that the values are not plain white noise
    t = np.arange(n) / RATE_HZ
    wobble = (40 * np.sin(2 * np.pi * 0.7 * t))[:, None]
    accel = (np.array([310.0, -620.0, LSB_PER_G + 450.0])
             + rng.normal(0.0, 256.0, size=(n, 3)) + wobble)
    # ADXRS450: ~0.15 deg/s rms noise, biases of a few tenths of a deg/s
    gyro = np.array([12.0, -7.0, 3.0]) + rng.normal(0.0, 12.0, size=(n, 3))
    return {
        "accel_counts": np.rint(accel).astype(np.int32),
        "gyro_counts": np.rint(gyro).astype(np.int16),
        "status": np.zeros(n, dtype=np.uint8),
    }


def build_device_stream(samples: dict[str, np.ndarray], batch: int, t0_us: int):
    """raw_batch frames of `batch` samples (the last one may be short), concatenated.
    Returns (stream bytes, number of frames, frame timestamps)."""
    n = len(samples["status"])
    rsize = RAW.record_dtype.itemsize
    # every record of the stream in one vectorised pack, sliced per frame below
    rec_bytes = P.pack_records(RAW, {
        "accel_x_counts": samples["accel_counts"][:, 0],
        "accel_y_counts": samples["accel_counts"][:, 1],
        "accel_z_counts": samples["accel_counts"][:, 2],
        "status": samples["status"],
        "gyro_counts": samples["gyro_counts"],
    })
    assert len(rec_bytes) == n * rsize
    nframes = -(-n // batch)
    first = np.arange(nframes, dtype=np.int64) * batch
    counts = np.minimum(batch, n - first)
    hdr = np.zeros(nframes, dtype=BATCH_HEADER_DTYPE)
    hdr["sample_index"] = first
    hdr["period_us"] = PERIOD_US
    hdr["count"] = counts
    hdr["sensor_flags"] = 0
    # temperatures drift slowly (a 25.0 -> 25.5 degC warm-up over the run)
    drift = np.linspace(0.0, 0.5, nframes)
    hdr["accel_temp_counts"] = np.rint(1885 - 9.05 * drift).astype(np.uint16)
    hdr["accel_status"] = 0x01                    # DATA_RDY
    hdr["accel_range_g"] = 2
    hdr["gyro_temp_counts"] = np.rint(-100 + 5 * drift)[:, None].astype(np.int16)
    ts = (t0_us + first * PERIOD_US) & 0xFFFFFFFF  # first sample of each frame
    hdr_bytes = hdr.tobytes()
    bh = BATCH_HEADER_DTYPE.itemsize

    build = P.build_frame
    mtype = int(MsgType.RAW_BATCH)
    frames = [build(mtype, hdr_bytes[i * bh:(i + 1) * bh]
                    + rec_bytes[int(first[i]) * rsize:(int(first[i]) + int(counts[i])) * rsize],
                    i & 0xFFFF, int(ts[i]))
              for i in range(nframes)]

    # the fast path above must produce what the message-level encoder produces
    c0 = int(counts[0])
    msg = RawBatch(header=BatchHeader.from_values(BatchHeader.STRUCT.unpack(hdr_bytes[:bh])))
    ref = P.encode(msg, 0, int(ts[0]), records={
        "accel_x_counts": samples["accel_counts"][:c0, 0],
        "accel_y_counts": samples["accel_counts"][:c0, 1],
        "accel_z_counts": samples["accel_counts"][:c0, 2],
        "status": samples["status"][:c0],
        "gyro_counts": samples["gyro_counts"][:c0],
    })
    check(ref == frames[0], "vectorised frame build differs from protocol.encode()")
    return b"".join(frames), nframes, ts


def chunked(data: bytes, size: int) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]


# ------------------------------------------------------------------ imubench decoder
def decode_once(chunks: list[bytes]):
    """Feed every chunk and take the samples as a reader does (imubench.device.link takes
    them as they arrive: the decoder holds at most max_pending_samples undelivered), here
    every 16 chunks, then join them: the time runs from the first feed() to the joined arrays."""
    from imubench.wire.decoder import SampleBlock
    dec = StreamDecoder()
    t = time.perf_counter()
    msgs = 0
    blocks = []
    for i, c in enumerate(chunks):
        msgs += len(dec.feed(c))
        if i % 16 == 15:
            b = dec.take_samples()
            if b is not None:
                blocks.append(b)
    b = dec.take_samples()
    if b is not None:
        blocks.append(b)
    block = SampleBlock.concat(blocks) if blocks else None
    dt = time.perf_counter() - t
    return dt, dec, block, msgs


def verify_decode(dec, block, msgs, samples, nframes, t0_us) -> None:
    n = len(samples["status"])
    st = dec.stats
    check(block is not None, "take_samples() returned None")
    check(len(block) == n, f"decoded {len(block)} samples, encoded {n}")
    check(st.frames_rejected == 0, f"decoder rejected frames: {st.as_dict()}")
    check(st.frames_ok == nframes, f"frames_ok {st.frames_ok} != {nframes} frames sent")
    check(msgs == 0, f"{msgs} unexpected non-sample messages")
    check(st.seq_gaps == 0 and st.sample_gaps == 0,
          f"gaps reported in a gap-free stream: {st.as_dict()}")
    check(st.samples == n, f"stats.samples {st.samples} != {n}")
    check(np.array_equal(block.accel_counts, samples["accel_counts"]), "accel_counts differ")
    check(np.array_equal(block.gyro_counts, samples["gyro_counts"]), "gyro_counts differ")
    check(np.array_equal(block.status, samples["status"]), "status differs")
    idx = np.arange(n, dtype=np.int64)
    check(np.array_equal(block.sample_index, idx), "sample_index differs")
    check(np.array_equal(block.t_us, t0_us + idx * PERIOD_US), "t_us differs")
    check(bool(np.all(block.accel_range_g == 2)), "accel_range_g differs")


# ------------------------------------------------------------------ pymavlink
def build_mavlink_stream(samples: dict[str, np.ndarray], m: int, t0_us: int):
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    rng = np.random.default_rng(2)
    acc_mg = np.rint(samples["accel_counts"][:m] * (1000.0 / LSB_PER_G)).astype(int).tolist()
    gyro_mrad = np.rint(samples["gyro_counts"][:m] * (np.pi / 180 / GYRO_LSB_PER_DPS * 1000)
                        ).astype(int).tolist()
    mag_mgauss = np.rint(np.array([210.0, -45.0, 395.0]) + rng.normal(0, 3.0, size=(m, 3))
                         ).astype(int).tolist()
    temp_cdeg = 2500 + (np.arange(m) * 50 // max(m, 1))
    enc = mav.raw_imu_encode
    out = []
    for i in range(m):
        a, g, mg = acc_mg[i], gyro_mrad[i], mag_mgauss[i]
        out.append(enc(t0_us + i * PERIOD_US, a[0], a[1], a[2], g[0], g[1], g[2],
                       mg[0], mg[1], mg[2], 0, int(temp_cdeg[i])).pack(mav))
    return b"".join(out), mavlink2


def mavlink_parse_once(chunks: list[bytes], mavlink2):
    mav = mavlink2.MAVLink(None)
    got = []
    t = time.perf_counter()
    for c in chunks:
        msgs = mav.parse_buffer(c)
        if msgs:
            got.extend(msgs)
    dt = time.perf_counter() - t
    return dt, mav, got


def verify_mavlink(mav, got, m: int, samples, t0_us: int) -> None:
    check(len(got) == m, f"pymavlink parsed {len(got)} messages, {m} were sent")
    check(mav.total_receive_errors == 0, f"pymavlink receive errors: {mav.total_receive_errors}")
    check(all(x.get_type() == "RAW_IMU" for x in got), "pymavlink returned non-RAW_IMU messages")
    check(got[-1].time_usec == t0_us + (m - 1) * PERIOD_US, "pymavlink: last time_usec differs")


# ------------------------------------------------------------------ main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=2_000_000, help="samples in the device stream")
    ap.add_argument("--batch", type=int, default=16, help=f"samples per raw_batch frame (1..{RAW.max_records})")
    ap.add_argument("--chunk", type=int, default=64 * 1024, help="bytes per feed()/parse_buffer() call")
    ap.add_argument("--mavlink-samples", type=int, default=200_000,
                    help="RAW_IMU messages pymavlink is timed on (0 = as many as --samples)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each decoder; the best is reported")
    ap.add_argument("--quick", action="store_true", help="smoke run: 200k samples, 50k MAVLink messages (not published)")
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.quick:
        args.samples = min(args.samples, 200_000)
        args.mavlink_samples = min(args.mavlink_samples or args.samples, 50_000)
    if not 1 <= args.batch <= RAW.max_records:
        ap.error(f"--batch must be 1..{RAW.max_records}")
    if args.samples < 1 or args.chunk < 1 or args.repeat < 1:
        ap.error("--samples, --chunk and --repeat must be positive")
    n = args.samples
    m = min(args.mavlink_samples or n, n)
    t0_us = 12_345_678                      # device uptime at the first sample

    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    tb = time.perf_counter()
    samples = make_samples(n)
    stream, nframes, _ = build_device_stream(samples, args.batch, t0_us)
    chunks = chunked(stream, args.chunk)
    print(f"imubench stream: {n:,} samples in {nframes:,} raw_batch frames of {args.batch}, "
          f"{len(stream):,} bytes ({len(stream) / n:.2f} B/sample), built in "
          f"{time.perf_counter() - tb:.2f} s; fed in {len(chunks):,} chunks of {args.chunk:,} B")

    times = []
    for r in range(args.repeat):
        dt, dec, block, msgs = decode_once(chunks)
        verify_decode(dec, block, msgs, samples, nframes, t0_us)
        times.append(dt)
        print(f"  run {r + 1}: {dt:.3f} s  {n / dt:,.0f} samples/s  {nframes / dt:,.0f} frames/s")
        del block, dec
    best = min(times)
    sps, fps = n / best, nframes / best
    print(f"imubench StreamDecoder (best of {args.repeat}): {sps:,.0f} samples/s, {fps:,.0f} frames/s, "
          f"{len(stream) / best / 1e6:.1f} MB/s; all {n:,} samples verified, 0 frames rejected")

    tb = time.perf_counter()
    mstream, mavlink2 = build_mavlink_stream(samples, m, t0_us)
    mchunks = chunked(mstream, args.chunk)
    print(f"pymavlink stream: {m:,} RAW_IMU messages (MAVLink v2), {len(mstream):,} bytes "
          f"({len(mstream) / m:.2f} B/msg), built in {time.perf_counter() - tb:.2f} s"
          + (f"; timed on this subset of the {n:,} samples, reported per message" if m < n else ""))
    mtimes = []
    for r in range(args.repeat):
        dt, mav, got = mavlink_parse_once(mchunks, mavlink2)
        verify_mavlink(mav, got, m, samples, t0_us)
        mtimes.append(dt)
        print(f"  run {r + 1}: {dt:.3f} s  {m / dt:,.0f} msgs/s")
        del got, mav
    mbest = min(mtimes)
    mps = m / mbest
    ratio = sps / mps
    print(f"pymavlink parse_buffer (best of {args.repeat}): {mps:,.0f} msgs/s (1 sample per message)")

    ok_rate = sps >= TARGET_SAMPLES_PER_S
    ok_ratio = ratio >= TARGET_RATIO
    print(f"ratio imubench samples/s / pymavlink msgs/s: {ratio:.1f}x")
    print(f"target samples/s >= {TARGET_SAMPLES_PER_S:,}: {'MET' if ok_rate else 'MISSED'} ({sps:,.0f})")
    print(f"target ratio >= {TARGET_RATIO:g}: {'MET' if ok_ratio else 'MISSED'} ({ratio:.1f})")

    from importlib.metadata import version
    md = ("| figure | value |\n|---|---|\n"
          f"| samples_per_s | {sps / 1e6:.2f} M (target ≥ {TARGET_SAMPLES_PER_S / 1e6:g} M) |\n"
          f"| frames_per_s | {fps / 1e3:.0f} k |\n"
          f"| pymavlink_msgs_per_s | {mps / 1e3:.0f} k |\n"
          f"| ratio_vs_pymavlink | {ratio:.0f} (target ≥ {TARGET_RATIO:g}) |\n")
    print("\n" + md, end="")
    publish("decode_throughput", md,
            {"numpy": np.__version__, "pymavlink": version("pymavlink"), "samples": f"{n:,}",
             "best of": args.repeat}, enabled=not (args.no_publish or args.quick))
    result = {
        "samples_per_s": round(sps),
        "frames_per_s": round(fps),
        "pymavlink_msgs_per_s": round(mps),
        "ratio_vs_pymavlink": round(ratio, 2),
        "samples": n,
        "frames": nframes,
        "batch": args.batch,
        "bytes": len(stream),
        "bytes_per_sample": round(len(stream) / n, 3),
        "decode_s_best": round(best, 4),
        "decode_s_runs": [round(t, 4) for t in times],
        "mavlink_messages": m,
        "mavlink_bytes": len(mstream),
        "mavlink_subset": m < n,
        "mavlink_parse_s_best": round(mbest, 4),
        "chunk_bytes": args.chunk,
        "repeat": args.repeat,
        "target_samples_per_s": TARGET_SAMPLES_PER_S,
        "target_samples_per_s_met": ok_rate,
        "target_ratio": TARGET_RATIO,
        "target_ratio_met": ok_ratio,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "pymavlink": version("pymavlink"),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BenchFailure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        sys.exit(1)
