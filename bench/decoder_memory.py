#!/usr/bin/env python3
"""Memory of the stream decoder on the issue-16 cases, measured with tracemalloc.

    PYTHONPATH=host python bench/decoder_memory.py [--mb 100]

Prints, for N MB of input: the growth of a StreamDecoder fed raw 4 kHz batches whose samples
are never taken (bounded by MAX_PENDING_SAMPLES), of one feed() of N MB of zero bytes (bounded
by the feed piece), and the peak of decode_bytes() of an N MB recording (grows with the
recording: it returns every sample). tests/wire/test_decoder_stream_rules.py checks the first two
at 20 MB. Prints the markdown table docs/architecture.md states and publishes it
(bench/publish.py; --no-publish to leave the docs alone).
"""
from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "host"))

from imubench.wire import frame as P  # noqa: E402
from imubench.wire import protocol_gen as G  # noqa: E402
from imubench.wire.decoder import MAX_PENDING_SAMPLES, StreamDecoder, decode_bytes  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402


def recording(n_bytes: int) -> bytes:
    n = 16
    recs = {"accel_x_counts": np.arange(n), "accel_y_counts": np.zeros(n, int), "accel_z_counts": np.full(n, 256000),
            "status": np.zeros(n, int), "gyro_counts": np.zeros((n, 3), int)}
    frames = []
    total = 0
    k = 0
    while total < n_bytes:
        f = P.encode(G.RawBatch(header=G.BatchHeader(sample_index=(16 * k) & 0xFFFFFFFF, period_us=250, count=n,
                                                     accel_range_g=2)),
                     k & 0xFFFF, (16 * k * 250) & 0xFFFFFFFF, records=recs)
        frames.append(f)
        total += len(f)
        k += 1
    return b"".join(frames)


def measure(fn) -> tuple[float, float]:
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    keep = fn()
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    del keep
    return peak / 1e6, dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=100.0, help="input size in MB")
    add_arguments(ap)
    a = ap.parse_args()
    n = int(a.mb * 1e6)
    data = recording(n)
    zeros = bytes(n)
    print(f"input: {len(data) / 1e6:.0f} MB of raw batches ({len(data) // 260 * 16} samples); "
          f"cap MAX_PENDING_SAMPLES = {MAX_PENDING_SAMPLES}")

    def never_taken():
        dec = StreamDecoder()
        for i in range(0, len(data), 1 << 20):
            dec.feed(data[i:i + (1 << 20)])
        return dec

    mb1, dt = measure(never_taken)
    print(f"StreamDecoder fed {a.mb:g} MB, samples never taken: peak growth {mb1:.0f} MB ({dt:.1f} s)")
    mb2, dt = measure(lambda: StreamDecoder().feed(zeros))
    print(f"one feed() of {a.mb:g} MB of zero bytes:          peak growth {mb2:.1f} MB ({dt:.1f} s)")
    mb3, dt = measure(lambda: decode_bytes(data))
    per = mb3 * 1e6 / (len(data) // 260 * 16)
    print(f"decode_bytes of the {a.mb:g} MB recording:          peak growth {mb3:.0f} MB ({dt:.1f} s), "
          f"{per:.0f} bytes per sample")
    md = (f"| {a.mb:g} MB of input | peak memory growth (tracemalloc) |\n|---|---|\n"
          f"| StreamDecoder fed raw 4 kHz batches, samples never taken | {mb1:.0f} MB |\n"
          f"| one feed() of zero bytes | {mb2:.1f} MB |\n"
          f"| decode_bytes of the recording | {mb3:.0f} MB ({per:.0f} bytes per sample) |\n")
    print("\n" + md, end="")
    publish("decoder_memory", md, {"cap MAX_PENDING_SAMPLES": MAX_PENDING_SAMPLES}, enabled=not a.no_publish)
    return 0


if __name__ == "__main__":
    sys.exit(main())
