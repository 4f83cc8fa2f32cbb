"""Same seed, same bytes: each virtual-device case run idle, beside two CPU-bound processes and
pinned to one core; the SHA-256 of what it captured and the wall time of each run (issue 33).

    PYTHONPATH=host python bench/determinism.py [--cases host,f103,f4,station,warmup] [--no-publish]

Cases (each a fresh process with a fresh virtual device on the lockstep clock, the default):

* host     `imubench calibrate --sim --sim-seed 5` (the host build; every capture-*.bin)
* f103     the F103 image under the ARM emulator: info, 2 s of a 1 kHz raw stream, a 90° turn
           about Z while streaming, 0.5 s more (the capture file of the link)
* f4       the same on the F4 image
* station  `imubench calibrate --sim --sim-boards 4` (every slot's capture-*.bin)
* warmup   `imubench thermal --sim --warmup --sim-seed 7` (every *.bin it records)

Modes: idle; beside two `python3 -c 'while 1: pass'`; under `taskset -c 0` (one core). A
case is deterministic when the three hashes agree. Times are wall-clock seconds (the only
wall-clock column); the device time each case covers is the same in every mode by design.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "host"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

from imubench.files import tree_digest  # noqa: E402

CASES = ("host", "f103", "f4", "station", "warmup")
MODES = ("idle", "2 busy", "1 core")
HOST = str(Path(__file__).resolve().parents[1] / "host")


def _command(case: str, d: Path) -> list[str]:
    py = [sys.executable]
    if case == "host":
        return py + ["-m", "imubench", "calibrate", "--sim", "--sim-seed", "5", "--sim-speed", "1000",
                     "--dir", str(d / "s"), "--db", str(d / "h.db")]
    if case == "station":
        return py + ["-m", "imubench", "calibrate", "--sim", "--sim-seed", "5", "--sim-boards", "4",
                     "--sim-speed", "1000", "--dir", str(d / "s"), "--db", str(d / "h.db")]
    if case == "warmup":
        return py + ["-m", "imubench", "thermal", "--sim", "--warmup", "--sim-seed", "7", "--sim-speed", "1000",
                     "--out", str(d / "s")]
    return py + [__file__, "--one", case, str(d / "s")]


def _one(case: str, out: Path) -> None:
    """The ARM cases: a short session on the image, the link captured to out/link.bin."""
    from imubench.device.link import Device
    from imubench.device.sim import VirtualBench
    out.mkdir(parents=True)
    with VirtualBench(speed=0, seed=3, target=case) as vb, open(out / "link.bin", "wb") as cap, \
            Device.open(vb.port_url, capture=cap, timeout=5.0) as dev:
        dev.info()
        dev.start_stream(1000)
        dev.read(n_samples=2000)
        vb.rotate("z", rate_dps=90, duration_s=1.0)
        dev.read(duration_s=0.5)
        dev.stop_stream()


def _arm_build_ids(cases: list[str]) -> str:
    """The build id the ARM images were made from (build/arm/build_id.txt), or ""."""
    if not cases:
        return ""
    f = Path(__file__).resolve().parents[1] / "build" / "arm" / "build_id.txt"
    return f.read_text().strip() if f.is_file() else "unknown"


def run(case: str, mode: str) -> tuple[str, float, str]:
    """(SHA-256 of every .bin the case wrote, in path order; wall s; error or "")."""
    d = Path(tempfile.mkdtemp(prefix=f"imubench-det-{case}-"))
    hogs = []
    cmd = _command(case, d)
    if mode == "1 core":
        cmd = ["taskset", "-c", "0", *cmd]
    if mode == "2 busy":
        hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(2)]
    env = {**os.environ, "PYTHONPATH": HOST}
    t0 = time.monotonic()
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
        wall = time.monotonic() - t0
        if r.returncode != 0:
            return "", wall, (r.stderr.strip().splitlines() or r.stdout.strip().splitlines() or ["?"])[-1]
        digest, _ = tree_digest(d / "s")         # imubench.files: the hash tests/device/test_lockstep.py takes
        return digest or "", wall, "" if digest else "no capture written"
    finally:
        for p in hogs:
            p.kill()
            p.wait()
        shutil.rmtree(d, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES), help="comma separated, of " + ", ".join(CASES))
    ap.add_argument("--one", nargs=2, metavar=("CASE", "DIR"), help=argparse.SUPPRESS)
    add_arguments(ap)
    a = ap.parse_args()
    if a.one:
        _one(a.one[0], Path(a.one[1]))
        return 0
    cases = [c for c in a.cases.split(",") if c]
    bad = [c for c in cases if c not in CASES]
    if bad:
        ap.error(f"unknown case {bad[0]!r}: give some of {', '.join(CASES)}")
    rows = []
    for case in cases:
        res = []
        for mode in MODES:
            h, wall, err = run(case, mode)
            print(f"{case:8s} {mode:7s} {h[:16] or 'FAILED: ' + err} wall {wall:.1f} s", flush=True)
            res.append((h, wall, err))
        same = all(r[0] and r[0] == res[0][0] for r in res)
        cells = [f"`{h[:16]}`" if h else f"failed: {err[:80]}" for h, _, err in res]
        rows.append(f"| {case} | " + " | ".join(cells) + f" | {'yes' if same else '**no**'} | "
                    + " / ".join(f"{w:.0f}" for _, w, _ in res) + " |")
    ids = _arm_build_ids([c for c in cases if c in ("f103", "f4")])
    md = ("| case | SHA-256 of the capture (first 16 hex), idle | beside 2 busy processes | one core "
          "(`taskset -c 0`) | identical | wall time, wall clock (s): idle / busy / one core |\n"
          "|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n"
          + (f"\nARM images of build `{ids}` (git describe; their info reply carries it, so another "
             "build gives other bytes). The host build's id is fixed (`sim-0.1.0`).\n" if ids else ""))
    print("\n" + md, end="")
    publish("determinism", md, {"cases": ",".join(cases)}, enabled=not a.no_publish)
    return 0


if __name__ == "__main__":
    sys.exit(main())
