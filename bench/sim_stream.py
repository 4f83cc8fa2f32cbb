#!/usr/bin/env python3
"""End-to-end stream throughput of the virtual device through the host decoder.

Starts the virtual device (firmware core + drivers + sensor models) with no pacing
(--speed 0: device time runs as fast as the process can go), on each clock: lockstep (the
default: the device runs only as far as the host's reads grant, in steps of up to 0.1 s) and
realtime (free running), streams raw samples over its
TCP serial port into imubench.device.link.Device, and reports samples per second of wall time
and that as a multiple of real time (samples/s divided by the stream rate). Target: at
least 20x real time at 1 kHz. Every sample is checked for continuity (no gap, no rejected
frame). Each rate runs twice: with the dies' thermal model off (the default) and on, the chamber
ramping all the while (docs/simulator.md), and reports the simulator process's own CPU time per
device second (/proc/PID/schedstat), the cost the thermal model must not raise. Every case runs
--repeats times, interleaved, and the table gives the medians (one run on a shared machine
moves by tens of percent). Prints a final JSON line.

    python bench/sim_stream.py [--seconds 120] [--rates 1000 4000] [--repeats 3] [--no-publish]

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


def cpu_s(pid: int) -> float:
    """CPU time of process pid's main thread, s, to the nanosecond (/proc/PID/schedstat; the
    simulator is one thread). /proc/PID/stat's clock ticks (10 ms) would be too coarse."""
    with open(f"/proc/{pid}/schedstat", "rb") as f:
        return int(f.read().split()[0]) * 1e-9


def run(rate: int, device_s: float, thermal: bool = False, clock: str = "lockstep") -> dict:
    n = int(rate * device_s)
    with VirtualBench(speed=0, seed=1, thermal=thermal, clock=clock) as vb, Device.open(vb.port_url, timeout=5.0) as dev:
        dev.ping()
        if thermal:   # every die lagging a moving chamber: the model's every branch runs
            vb.set_temperature(5.0, soak=True)
            vb.set_temperature(45.0, ramp_c_per_s=40.0 / device_s)
        # a client that connects while the device is sending (its boot info) may catch the
        # tail of a frame: that is counted, but it is not part of the stream measured here
        rejected_before = dev.link.decoder.stats.frames_rejected
        batch = dev.start_stream(rate)
        t0, c0 = time.perf_counter(), cpu_s(vb.pid)
        block = dev.read(n_samples=n, timeout=600)
        wall, cpu = time.perf_counter() - t0, cpu_s(vb.pid) - c0
        dev.stop_stream()
        st = dev.link.decoder.stats
        dropped = dev.stats().samples_dropped
        ok = (len(block) == n and st.frames_rejected == rejected_before and st.samples_missing == 0 and dropped == 0
              and np.array_equal(block.sample_index, np.arange(n)))
    return {"rate_hz": rate, "thermal": thermal, "clock": clock, "batch": batch, "samples": n, "device_s": device_s,
            "wall_s": round(wall, 3), "sim_cpu_ms_per_device_s": round(cpu / device_s * 1e3, 2),
            "samples_per_s": round(n / wall), "x_real_time": round(n / wall / rate, 1), "lossless": bool(ok),
            "device_samples_dropped": dropped}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="device seconds streamed per rate")
    ap.add_argument("--rates", type=int, nargs="+", default=[1000, 4000])
    ap.add_argument("--repeats", type=int, default=3, help="runs per case; the table gives the medians")
    ap.add_argument("--clocks", default="lockstep,realtime",
                    help="lockstep (the default clock: device time granted by the host's reads) and/or realtime "
                         "(free running at --speed 0, as fast as the process goes)")
    add_arguments(ap)
    a = ap.parse_args()
    build_sim()
    clocks = [c for c in a.clocks.split(",") if c]
    cases = [(r, th, c) for c in clocks for r in a.rates for th in (False, True)]
    runs = [run(r, a.seconds, th, c) for _ in range(max(1, a.repeats)) for r, th, c in cases]
    for r in runs:
        print(f"{r['clock']:8s} {r['rate_hz']:>5} Hz (batch {r['batch']:>2}), thermal model {'on ' if r['thermal'] else 'off'}: "
              f"{r['samples']} samples in {r['wall_s']:.2f} s wall = {r['samples_per_s']:,} samples/s = "
              f"{r['x_real_time']}x real time, simulator CPU {r['sim_cpu_ms_per_device_s']:.1f} ms per device s, "
              f"lossless {r['lossless']}")
    results = []
    for rate, th, c in cases:               # the median run of each case (by simulator CPU)
        mine = [r for r in runs if r["rate_hz"] == rate and r["thermal"] == th and r["clock"] == c]
        med = dict(sorted(mine, key=lambda r: r["sim_cpu_ms_per_device_s"])[len(mine) // 2])
        for k in ("samples_per_s", "x_real_time"):
            med[k] = float(np.median([r[k] for r in mine]))
        med["lossless"] = all(r["lossless"] for r in mine)
        results.append(med)
    one_k = next((r for r in results if r["rate_hz"] == 1000 and not r["thermal"] and r["clock"] == clocks[0]), None)
    if one_k:
        print(f"target >= 20x real time at 1 kHz: {'MET' if one_k['x_real_time'] >= 20 else 'MISSED'}")
    md = ("| clock | rate | dies' thermal model | samples/s (wall clock) | multiple of real time (target ≥ 20 at 1 kHz) "
          "| simulator CPU per device s |\n|---|---|---|---|---|---|\n" + "".join(
              f"| {r['clock']} | {r['rate_hz']} Hz, batch {r['batch']} | {'on, chamber ramping' if r['thermal'] else 'off'} "
              f"| {r['samples_per_s'] / 1e3:.0f} k | {r['x_real_time']:.0f}× | {r['sim_cpu_ms_per_device_s']:.1f} ms |\n"
              for r in results))
    print("\n" + md, end="")
    lossless = all(r["lossless"] for r in results)
    if not lossless:
        print("a stream lost samples: not published")
    publish("sim_stream", md, {"device s per rate": f"{a.seconds:g}", "medians of": f"{max(1, a.repeats)} runs"},
            enabled=lossless and not a.no_publish)
    summary = {"x_real_time_1khz": one_k["x_real_time"] if one_k else None,
               "samples_per_s_1khz": one_k["samples_per_s"] if one_k else None,
               "cpus": os.cpu_count(), "medians": results, "runs": runs}
    print(json.dumps(summary))
    return 0 if all(r["lossless"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
