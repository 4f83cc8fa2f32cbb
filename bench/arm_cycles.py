#!/usr/bin/env python3
"""What the exact STM32 images cost on their CPUs: Cortex-M instructions per sample, CPU load,
SPI bus time, and the emulator's speed, measured under the ARM emulator (imubench.device.arm).

For each image (f103: Cortex-M3 at 72 MHz, f4: Cortex-M4F at 168 MHz) and each stream (raw
4 kHz, raw 1 kHz, calibrated 1 kHz, calibrated 4 kHz) it starts the image against the sensor
models, streams, and over a window of samples reads the emulator's counters:

  instructions/sample   executed Thumb instructions, split by the address range they run in
                        (the linker map: firmware/core = core, firmware/drivers = drivers,
                        firmware/boards = board, newlib/libgcc = lib); the main loop's passes
                        that did nothing (before the idle fast-forward caught them) are left
                        out of "board" and reported apart
  CPU load              (window - idle) / window, idle = the WFI / idle-main-loop time the
                        emulator skipped + the idle passes it executed; busy-waits (SPI flag
                        polling, delays, flash stalls) count as load, as on the chip. It
                        scales with CPI, the cycles-per-instruction figure of the targets
                        (1.5, an estimate from ARM's instruction timings: targets.py)
  SPI bus time/sample   SCK time of the bytes the image actually clocked, at the SPI clock it
                        configured (f_PCLK2 / 2^(BR+1))
  emulator speed        device seconds per wall second while streaming as fast as it goes

and compares the core's instructions/sample with the x86-64 count of bench/core_instructions.py
(callgrind on the host build) in the same run. Targets (issue 13): F103 raw 4 kHz <= 30 % CPU,
F4 calibrated 4 kHz <= 10 %, the emulated 1 kHz session >= 0.5x real time.

    python bench/arm_cycles.py [--seconds S] [--no-x86] [--no-publish]

Prints the markdown table README.md and docs/firmware.md state and publishes it
(bench/publish.py).
Prints a table and a final JSON line.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "host"))

from imubench.device.link import Device
from imubench.device.sim import VirtualBench

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

CONFIGS = [(4000, False), (1000, False), (1000, True), (4000, True)]
CLOCK_HZ = {"f103": 72e6, "f4": 168e6}
TARGET_LOAD = {("f103", 4000, False): 0.30, ("f4", 4000, True): 0.10}


def measure(target: str, rate: int, calibrated: bool, seconds: float) -> dict:
    with VirtualBench(speed=0, seed=1, target=target) as vb, Device.open(vb.port_url, timeout=20) as d:
        d.ping()
        d.start_stream(rate, calibrated=calibrated)
        d.read(n_samples=max(50, rate // 10), timeout=60)        # settle
        s0, w0 = vb.status(), time.monotonic()
        n = int(rate * seconds)
        d.read(n_samples=n, timeout=300)
        s1, w1 = vb.status(), time.monotonic()
        d.stop_stream()
        lost = d.link.decoder.stats.samples_missing
    a0, a1 = s0["arm"], s1["arm"]
    dt = (s1["time_us"] - s0["time_us"]) * 1e-6
    samples = (s1["time_us"] - s0["time_us"]) * 1e-6 * rate    # samples produced in the window
    reg = {k: (a1["instructions_by_range"][k] - a0["instructions_by_range"][k]) / samples
           for k in ("core", "drivers", "board", "lib", "other")}
    idle_instr = (a1["idle_loop_instructions"] - a0["idle_loop_instructions"]) / samples
    reg["board"] -= idle_instr
    f = a1["sysclk_hz"]
    idle_s = (a1["idle_s"] - a0["idle_s"]) + idle_instr * samples * a1["cpi"] / f
    return {
        "target": target, "rate_hz": rate, "mode": "calibrated" if calibrated else "raw",
        "window_device_s": round(dt, 3), "samples_lost": lost,
        "instr_per_sample": {k: round(v, 1) for k, v in reg.items()},
        "instr_per_sample_total": round(sum(reg.values()), 1),
        "idle_loop_instr_per_sample": round(idle_instr, 1),
        "cpu_load": round(1.0 - idle_s / dt, 4),
        "busy_wait_us_per_sample": round((a1["busy_wait_s"] - a0["busy_wait_s"]) / samples * 1e6, 2),
        "spi_bus_us_per_sample": round((a1["spi_bus_s"] - a0["spi_bus_s"]) / samples * 1e6, 2),
        "spi_bytes_per_sample": round((a1["spi_bytes"] - a0["spi_bytes"]) / samples, 1),
        "spi_transactions_per_sample": round((a1["spi_transactions"] - a0["spi_transactions"]) / samples, 2),
        "sysclk_hz": f, "cpi": a1["cpi"],
        "emulator_device_s_per_wall_s": round(dt / (w1 - w0), 3),
    }


def x86_figures() -> dict | None:
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "core_instructions.py"), "--ticks", "4000",
                        "--no-publish"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        print(f"(bench/core_instructions.py failed: {r.stderr.strip().splitlines()[-1:]})", file=sys.stderr)
        return None
    return json.loads(r.stdout.strip().splitlines()[-1])


def _pct(x: float) -> str:
    return f"{x * 100:.0f} %" if x >= 0.1 else f"{x * 100:.1f} %"


def table(rows: list[dict], x86: dict | None) -> str:
    """The markdown table README.md and docs/firmware.md state."""
    out = ("| image | stream | core | drivers | board | lib | total instr/sample | CPU load (target) | "
           "SPI bus time/sample (bytes) | x86 core instr/sample | emulator speed (device s per wall-clock s) |\n" + "|---" * 11 + "|\n")
    for r in rows:
        ips = r["instr_per_sample"]
        key = (r["target"], r["rate_hz"], r["mode"] == "calibrated")
        load = _pct(r["cpu_load"])
        if key in TARGET_LOAD:
            load += f" (≤ {TARGET_LOAD[key] * 100:.0f} %, {'met' if r['cpu_load'] <= TARGET_LOAD[key] else 'MISSED'})"
        x = (x86 or {}).get(f"{r['mode']}_{r['rate_hz']}hz_instr_per_sample")
        out += (f"| {r['target']} | {r['mode']} {r['rate_hz']} Hz | {ips['core']:.0f} | {ips['drivers']:.0f} | "
                f"{ips['board']:.0f} | {ips['lib']:.0f} | {r['instr_per_sample_total']:.0f} | {load} | "
                f"{r['spi_bus_us_per_sample']:.0f} µs ({r['spi_bytes_per_sample']:.0f}) | "
                f"{'—' if x is None else f'{x:.1f}'} | {r['emulator_device_s_per_wall_s']:.2f}x |\n")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0, help="device seconds measured per stream")
    ap.add_argument("--no-x86", action="store_true", help="skip the callgrind comparison")
    add_arguments(ap)
    a = ap.parse_args()
    subprocess.run(["make", "-s", "-C", str(ROOT), "sim", "arm-f103", "arm-f4"], check=True)
    rows = [measure(t, rate, cal, a.seconds) for t in ("f103", "f4") for rate, cal in CONFIGS]
    x86 = None if a.no_x86 else x86_figures()
    print(f"{'image':5} {'stream':>15} | {'core':>6} {'drivers':>7} {'board':>6} {'lib':>6} {'total':>7} "
          f"instr/sample | {'CPU load':>8} {'target':>6} | {'SPI bus':>8} {'bytes':>5} | {'x86 core':>8} | emu speed")
    for r in rows:
        ips = r["instr_per_sample"]
        key = (r["target"], r["rate_hz"], r["mode"] == "calibrated")
        tgt = f"<={TARGET_LOAD[key]:.0%}" if key in TARGET_LOAD else ""
        x = ""
        if x86 is not None:
            x = str(x86.get(f"{r['mode']}_{r['rate_hz']}hz_instr_per_sample", ""))
        print(f"{r['target']:5} {r['mode'] + ' ' + str(r['rate_hz']) + ' Hz':>15} | {ips['core']:6.0f} "
              f"{ips['drivers']:7.0f} {ips['board']:6.0f} {ips['lib']:6.0f} {r['instr_per_sample_total']:7.0f}"
              f"              | {r['cpu_load']:8.1%} {tgt:>6} | {r['spi_bus_us_per_sample']:6.1f}us "
              f"{r['spi_bytes_per_sample']:5.0f} | {x:>8} | {r['emulator_device_s_per_wall_s']:.2f}x")
    print(f"CPI {rows[0]['cpi']} (an estimate from ARM DDI 0337/0439 instruction timings; every load figure "
          "scales with it); F103 at 72 MHz, F4 at 168 MHz as the images configure them")
    md = table(rows, x86)
    print("\n" + md, end="")
    publish("arm_cycles", md, {"device s per stream": f"{a.seconds:g}", "CPI": rows[0]["cpi"]},
            enabled=not a.no_publish)
    print(json.dumps({"rows": rows, "x86": x86}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
