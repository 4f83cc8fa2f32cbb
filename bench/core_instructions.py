#!/usr/bin/env python3
"""Instructions per sample of the firmware core, counted by callgrind on the host build.

Builds bench/core_cost.c (the real core and drivers with an in-process board whose SPI goes
to the sensor models and whose link discards bytes), runs it under
`valgrind --tool=callgrind --toggle-collect=ib_core_tick`, and reports

    core instructions per sample = (Ir inside ib_core_tick
                                    - Ir inside board_spi_transfer (the sensor models)
                                    - Ir inside board_link_write) / samples

i.e. the sample pipeline, the drivers' frame building/parsing, batching, calibration and
framing, without the sensors and the link. Callgrind counts instructions, not time, so the
figure is repeatable; it is x86-64 instructions, a proxy to hold the core's cost steady on a
Cortex-M, not a Cortex-M cycle count. Prints a final JSON line.

    python bench/core_instructions.py [--ticks N] [--no-publish]

Prints the markdown table README states and publishes it (bench/publish.py).
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def build(out: Path) -> None:
    srcs = [str(p) for d in ("firmware/core", "firmware/drivers", "firmware/boards/sim/models")
            for p in sorted((ROOT / d).glob("*.c"))]
    cmd = ["gcc", "-std=c11", "-O2", "-g", "-Wall", "-Wextra", "-Werror",
           f"-I{ROOT}/firmware/core", f"-I{ROOT}/firmware/drivers", f"-I{ROOT}/firmware/boards/sim/models",
           str(ROOT / "bench" / "core_cost.c"), *srcs, "-lm", "-o", str(out)]
    subprocess.run(cmd, check=True)


def inclusive(annotate_out: str, fn: str) -> int:
    for line in annotate_out.splitlines():
        m = re.match(r"\s*([\d,]+)\s+\(.*?\)\s+\S*:(\S+)", line) or re.match(r"\s*([\d,]+)\s+\S*:(\S+)", line)
        if m and m.group(2).split("'")[0] == fn:
            return int(m.group(1).replace(",", ""))
    return 0


def measure(binary: Path, rate: int, mode: int, ticks: int, tmp: Path) -> dict:
    out = tmp / f"cg.{rate}.{mode}"
    r = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}",
                        "--toggle-collect=ib_core_tick", str(binary), str(rate), str(mode), str(ticks)],
                       capture_output=True, text=True, check=True)
    run = json.loads(r.stdout.strip().splitlines()[-1])
    ann = subprocess.run(["callgrind_annotate", "--inclusive=yes", "--threshold=100", str(out)],
                         capture_output=True, text=True, check=True).stdout
    tick = inclusive(ann, "ib_core_tick")
    spi = inclusive(ann, "board_spi_transfer")
    link = inclusive(ann, "board_link_write")
    samples = run["samples_produced"]
    core = tick - spi - link
    return {"rate_hz": rate, "mode": "calibrated" if mode else "raw", "samples": samples,
            "ir_tick_total": tick, "ir_sensor_models": spi, "ir_link": link,
            "core_instructions_per_sample": round(core / samples, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=20000)
    add_arguments(ap)
    a = ap.parse_args()
    if not shutil.which("valgrind") or not shutil.which("callgrind_annotate"):
        print("valgrind is missing: apt-get install valgrind", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        binary = tmp / "core_cost"
        build(binary)
        results = [measure(binary, rate, mode, a.ticks, tmp) for rate, mode in ((4000, 0), (1000, 0), (1000, 1))]
    for r in results:
        print(f"{r['mode']:>10} {r['rate_hz']:>5} Hz: {r['core_instructions_per_sample']:8.1f} core instructions/sample "
              f"(models {r['ir_sensor_models'] / r['samples']:.0f}, link {r['ir_link'] / r['samples']:.0f} excluded)")
    md = "| stream | core instructions per sample |\n|---|---|\n" + "".join(
        f"| {r['mode']}, {r['rate_hz']} Hz | {r['core_instructions_per_sample']:.0f} |\n" for r in results)
    print("\n" + md, end="")
    publish("core_instructions", md, {"ticks": a.ticks, "callgrind": "x86-64 instructions"},
            enabled=not a.no_publish)
    summary = {f"{r['mode']}_{r['rate_hz']}hz_instr_per_sample": r["core_instructions_per_sample"] for r in results}
    summary["details"] = results
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
