#!/usr/bin/env python3
"""The virtual ADXRS450's Allan curve against its data sheet, and the model's own CPU cost.

Records one chip of the C model at rest through its SPI protocol (libimumodels.so:
imubench.device.sim_gyro.record, no virtual session, device time as fast as the CPU goes),
and prints its overlapping Allan deviation at τ = 1, 10, 100, 1000 and 10^4 s beside the
curve the model's truth gives and the data sheet (Analog Devices, ADXRS450 data sheet,
Rev. C: 0.015 °/s/√Hz, in-run bias stability 25 °/h, i.e. an Allan floor of 0.664·25 =
16.6 °/h by IEEE Std 952-1997), with imubench's read-offs N and B (docs/noise.md). All
figures are in device time: they do not depend on the machine or its load.

Then the model's cost: CPU time of recording --cost-s device seconds of one chip at 1 kHz
(advance + one sensor-data frame per sample), per device second of one chip.

    PYTHONPATH=host python bench/gyro_allan.py [--seed 1] [--hours 111] [--rate 10] [--cost-s 600]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "host"))

import allantools  # noqa: E402
from imubench import units as U  # noqa: E402
from imubench.analysis.allan import allan_axis  # noqa: E402
from imubench.device import sim_gyro as G  # noqa: E402

DPH = U.DEG / 3600.0
TAUS_S = (1.0, 10.0, 100.0, 1000.0, 10000.0)
DS_FLOOR = 0.664 * 25.0 * DPH


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--hours", type=float, default=111.0, help="device hours recorded")
    ap.add_argument("--rate", type=float, default=10.0, help="samples per device second")
    ap.add_argument("--cost-s", type=float, default=600.0, help="device seconds at 1 kHz for the cost")
    a = ap.parse_args(argv)
    n = int(a.hours * 3600 * a.rate)
    t0 = time.perf_counter()
    x = G.record(a.seed, n, a.rate)
    wall = time.perf_counter() - t0
    taus, adev, _e, _n = allantools.oadev(x, rate=a.rate, data_type="freq", taus=list(TAUS_S))
    try:
        truth = G.model_adev(taus, 0.015 * U.DEG, 25.0 * DPH, 8e-5 * U.DEG)
    except AttributeError:                    # a model without the bias-instability bank
        truth = None
    r = allan_axis(x, a.rate)
    print(f"seed {a.seed}, {a.hours:g} h of device time at {a.rate:g} Hz ({wall:.1f} s wall)\n")
    print("| τ (s) | recorded ADEV (°/h) | model truth (°/h) | data sheet floor 0.664·25 (°/h) |")
    print("|---|---|---|---|")
    for i, t in enumerate(taus):
        m = f"{truth[i] / DPH:.1f}" if truth is not None else "n/a"
        print(f"| {t:g} | {adev[i] / DPH:.1f} | {m} | {DS_FLOOR / DPH:.1f} |")
    b = f"{r['B'] / DPH:.1f} °/h at τ = {r['B_tau']:g} s" if r["B"] is not None else f"withheld ({r['B_reason']})"
    k = f"{r['K'] / U.DEG:.2g} °/s·√Hz" if r["K"] is not None else "no +1/2 region in τ ≤ T/8"
    print(f"\nread-offs: N {r['N'] / U.DEG:.4f} °/s/√Hz (data sheet 0.015), B = min/0.664 {b} "
          f"(data sheet 25), K {k}")
    n_cost = int(a.cost_s * 1000)
    t0 = time.process_time()
    G.record(a.seed, n_cost, 1000.0)
    cost = time.process_time() - t0
    print(f"model cost: {cost / a.cost_s * 1e6:.0f} µs of CPU per device second of one chip at 1 kHz "
          f"({a.cost_s:g} device s in {cost:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
