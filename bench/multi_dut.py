#!/usr/bin/env python3
"""How many boards one station serves: station sessions (imubench.procedures.fixture) on N
virtual devices at 1 kHz in real time (speed 1), one virtual plate, N = 1, 2, 4, ...

Two configurations, each against its own one-board session:
  defaults   what `imubench calibrate` does when nothing is chosen: adaptive multi-position
             (each attitude held until its |a| is known, attitudes added until every
             parameter's sigma is at its target; every board's own targets, the plate
             presenting the union of what they still need), gyro bias, write-back, verification
  six-plan   six-position, a fixed plan (every face, --hold s each), gyro bias, write-back,
             verification

For each N: the session's wall time, the samples each board's link lost (gaps in the
sample index) or rejected (bad frames), the samples the decoder had to drop (overflow), the
host process's CPU time, and whether every board passed. A count of boards is served when
every board passed with zero lost, rejected and dropped samples and the session took at most
10 % longer than one board's. Target: at least 8.

Clocks: the virtual devices run on the real-time clock (`clock="realtime"`, as real boards do:
bytes the host does not read in time are lost), because the question is whether the host keeps
up with N boards in real time; on the lockstep clock it always would. Every time in the table is
wall-clock time.

The virtual devices are processes on the same machine (their CPU shows in the "sims CPU"
column): on a real line that work is done by the boards themselves, so the figure here is a
lower bound of what the station's host can serve.

    python bench/multi_dut.py [--boards 1 2 4 8 12 16] [--rate 1000] [--hold 2] [--configs defaults six-plan]

Prints a table and a final JSON line; each configuration's markdown table (README.md, "A
production line") is printed and published (bench/publish.py; --no-publish to leave the docs
alone) as soon as its sessions are done.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "host"))

from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT  # noqa: E402
from imubench.device.sim import VirtualBench, build_sim  # noqa: E402
from imubench.procedures.fixture import FixtureRun, Station  # noqa: E402
from imubench.procedures.virtual import PlatePresenter  # noqa: E402
from imubench.procedures.session import SessionConfig  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402


def _proc_cpu_s(pid: int) -> float:
    """utime + stime of a running process (the simulator), from /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


CONFIGS = {
    "defaults": lambda rate, hold_s: SessionConfig(method="multi", gyro="bias", adaptive=True, rate_hz=rate),
    "six-plan": lambda rate, hold_s: SessionConfig(method="six", gyro="bias", adaptive=False, rate_hz=rate,
                                                   hold_s=hold_s),
}


def run(n: int, rate: int, hold_s: float, speed: float, config: str = "six-plan") -> dict:
    benches = []
    try:
        for k in range(n):
            vb = VirtualBench(speed=speed, seed=500 + k, truth="random", clock="realtime")
            vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
            benches.append(vb)
        with tempfile.TemporaryDirectory(prefix="imubench-multi-") as d:
            cfg = CONFIGS[config](rate, hold_s)
            cpu0 = time.process_time()
            sims0 = sum(_proc_cpu_s(vb.pid) for vb in benches)
            fr = FixtureRun([vb.port_url for vb in benches], Path(d) / "station", cfg,
                            PlatePresenter(benches, quiet=True), station=Station("bench"), db=str(Path(d) / "h.sqlite"),
                            say=lambda s: None, plots=False)
            res = fr.run()
            cpu = time.process_time() - cpu0
            sims = sum(_proc_cpu_s(vb.pid) for vb in benches) - sims0
    finally:
        for vb in benches:
            vb.close()
    lost = rejected = overflow = 0
    for rec in res.results.values():
        link = rec.get("link") or {}
        lost += int(link.get("samples_missing") or 0)
        rejected += int(link.get("frames_rejected") or 0)
        overflow += int(link.get("samples_overflow") or 0)
    waits = [w for w in fr.plate.waits]
    return {"config": config, "boards": n, "wall_s": res.wall_s,
            "plate_moves": fr.plate.moves, "longest_plate_wait_s": max((w["waited_s"] for w in waits), default=0.0), "passed": len(res.passed), "lost": lost, "rejected": rejected,
            "overflow": overflow, "host_cpu_s": cpu, "sims_cpu_s": sims,
            "failures": [f"slot {b.slot}: {b.reason}" for b in res.boards if b.state != "passed"]}


BLOCKS = {"defaults": "multi_dut-defaults", "six-plan": "multi_dut-six"}


def table(rows: list[dict]) -> str:
    """One configuration's rows as the markdown table README states."""
    out = ("| boards | session (wall clock, real-time virtual devices) | vs 1 board | passed | samples lost / rejected / dropped | host CPU | "
           "virtual devices' CPU | plate moves |\n|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    for k, r in enumerate(rows):
        vs = "—" if k == 0 else f"{100 * (r['vs_single'] - 1):+.1f} %".replace("-", "−")
        out += (f"| {r['boards']} | {r['wall_s']:.1f} s | {vs} | {r['passed']}/{r['boards']} | "
                f"{r['lost']} / {r['rejected']} / {r['overflow']} | {r['host_cpu_s']:.1f} s | {r['sims_cpu_s']:.1f} s | "
                f"{r['plate_moves']} |\n")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--boards", type=int, nargs="+", default=[1, 2, 4, 8, 12, 16])
    ap.add_argument("--rate", type=int, default=1000, help="stream rate of every board, Hz")
    ap.add_argument("--hold", type=float, default=2.0, help="six-plan: seconds captured per attitude")
    ap.add_argument("--speed", type=float, default=1.0, help="virtual device time per wall time (1 = real time)")
    ap.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS))
    add_arguments(ap)
    a = ap.parse_args()
    build_sim()
    out, served_by = [], {}
    for config in a.configs:
        print(f"\n{config}: station sessions at {a.rate} Hz, speed {a.speed:g}, on {os.cpu_count()} cores "
              "(write-back and verification included)")
        print(f"{'boards':>6} {'session s':>10} {'vs 1':>7} {'passed':>7} {'lost':>6} {'rejected':>9} "
              f"{'dropped':>8} {'host CPU s':>11} {'sims CPU s':>11} {'moves':>6} {'max wait s':>10}  served")
        base, served = None, 0
        for n in a.boards:
            r = run(n, a.rate, a.hold, a.speed, config)
            if base is None:
                base = r["wall_s"]
            r["vs_single"] = r["wall_s"] / base
            r["served"] = (r["passed"] == n and r["lost"] == 0 and r["rejected"] == 0 and r["overflow"] == 0
                           and r["vs_single"] <= 1.10)
            if r["served"]:
                served = max(served, n)
            out.append(r)
            print(f"{n:>6} {r['wall_s']:>10.1f} {100 * (r['vs_single'] - 1):>+6.1f}% {r['passed']:>4}/{n:<2} "
                  f"{r['lost']:>6} {r['rejected']:>9} {r['overflow']:>8} {r['host_cpu_s']:>11.1f} "
                  f"{r['sims_cpu_s']:>11.1f} {r['plate_moves']:>6} {r['longest_plate_wait_s']:>10.1f}  "
                  f"{'yes' if r['served'] else 'NO'}", flush=True)
            for f in r["failures"]:
                print(f"         {f}")
        served_by[config] = served
        md = table([r for r in out if r["config"] == config])
        print("\n" + md, end="")
        publish(BLOCKS[config], md, {"rate": f"{a.rate} Hz", "speed": f"{a.speed:g}", "boards served": served},
                enabled=not a.no_publish)
        print(f"{config}: boards served by one station at {a.rate} Hz (all passed, zero lost samples, session within "
              f"10 % of one board's): {served} (target 8)")
    print(json.dumps({"rate_hz": a.rate, "served": served_by, "target": 8, "rows": out}))
    return 0 if served_by.get("defaults", served_by.get(a.configs[0], 0)) >= 8 else 1


if __name__ == "__main__":
    sys.exit(main())
