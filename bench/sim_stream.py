#!/usr/bin/env python3
"""End-to-end stream throughput of the virtual device through the host decoder.

Starts the virtual device (firmware core + drivers + sensor models) with no pacing
(--speed 0: device time runs as fast as the process can go), streams raw samples over its
TCP serial port into imubench.device.link.Device, and reports samples per second of wall time
and that as a multiple of real time (samples/s divided by the stream rate). Target: at
least 20x real time at 1 kHz. Every sample is checked for continuity (no gap, no rejected
frame). Prints a final JSON line.

    python bench/sim_stream.py [--seconds 120] [--rates 1000 4000] [--no-publish]

Prints the markdown table README states and publishes it (bench/publish.py) when every
stream was lossless.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "host"))

import numpy as np  # noqa: E402
from imubench.device.link import Device  # noqa: E402
from imubench.device.sim import VirtualBench, build_sim  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402


def run(rate: int, device_s: float) -> dict:
    n = int(rate * device_s)
    with VirtualBench(speed=0, seed=1) as vb, Device.open(vb.port_url, timeout=5.0) as dev:
        dev.ping()
        # a client that connects while the device is sending (its boot info) may catch the
        # tail of a frame: that is counted, but it is not part of the stream measured here
        rejected_before = dev.link.decoder.stats.frames_rejected
        batch = dev.start_stream(rate)
        t0 = time.perf_counter()
        block = dev.read(n_samples=n, timeout=600)
        wall = time.perf_counter() - t0
        dev.stop_stream()
        st = dev.link.decoder.stats
        dropped = dev.stats().samples_dropped
        ok = (len(block) == n and st.frames_rejected == rejected_before and st.samples_missing == 0 and dropped == 0
              and np.array_equal(block.sample_index, np.arange(n)))
    return {"rate_hz": rate, "batch": batch, "samples": n, "device_s": device_s, "wall_s": round(wall, 3),
            "samples_per_s": round(n / wall), "x_real_time": round(n / wall / rate, 1), "lossless": bool(ok),
            "device_samples_dropped": dropped}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="device seconds streamed per rate")
    ap.add_argument("--rates", type=int, nargs="+", default=[1000, 4000])
    add_arguments(ap)
    a = ap.parse_args()
    build_sim()
    results = [run(r, a.seconds) for r in a.rates]
    for r in results:
        print(f"{r['rate_hz']:>5} Hz (batch {r['batch']:>2}): {r['samples']} samples in {r['wall_s']:.2f} s wall = "
              f"{r['samples_per_s']:,} samples/s = {r['x_real_time']}x real time, lossless {r['lossless']}")
    one_k = next((r for r in results if r["rate_hz"] == 1000), None)
    if one_k:
        print(f"target >= 20x real time at 1 kHz: {'MET' if one_k['x_real_time'] >= 20 else 'MISSED'}")
    md = "| rate | samples/s (wall) | multiple of real time (target ≥ 20 at 1 kHz) |\n|---|---|---|\n" + "".join(
        f"| {r['rate_hz']} Hz, batch {r['batch']} | {r['samples_per_s'] / 1e3:.0f} k | {r['x_real_time']:.0f}× |\n"
        for r in results)
    print("\n" + md, end="")
    lossless = all(r["lossless"] for r in results)
    if not lossless:
        print("a stream lost samples: not published")
    publish("sim_stream", md, {"device s per rate": f"{a.seconds:g}"}, enabled=lossless and not a.no_publish)
    summary = {"x_real_time_1khz": one_k["x_real_time"] if one_k else None,
               "samples_per_s_1khz": one_k["samples_per_s"] if one_k else None,
               "cpus": os.cpu_count(), "runs": results}
    print(json.dumps(summary))
    return 0 if all(r["lossless"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
