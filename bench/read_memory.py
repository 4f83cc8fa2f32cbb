#!/usr/bin/env python3
"""Peak memory of reading recordings (issue 25: "a 280 MB CSV took 4.8 GB").

    .venv/bin/python bench/read_memory.py            # a 3,000,000-row CSV (~270 MB)
    .venv/bin/python bench/read_memory.py --rows 300000 --calibrate   # also the whole from-file run

What is measured, each in a fresh child process (its peak resident set, ru_maxrss):

* read: imubench.recordings.read() of a generated CSV with a header (t_s + 6 axes, 9 decimals
  each: ~90 bytes a row), i.e. the text parsed 65536 lines at a time into one float64 array
  sized from the file; the numbers themselves take rows x 7 x 8 bytes.
* npz bomb: read() of a 1 MB .npz whose two members claim 4.5 GiB each: refused from the .npy
  headers before numpy allocates (the time and the memory it took to say so).
* --calibrate: `imubench calibrate --from` on a six-face recording of the same length (the
  whole pipeline: read, still intervals, fits, plots, report), for comparison.

Human-readable lines first; the last line of stdout is one JSON object.
"""
from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

CHILD_READ = """
import resource, sys, time
from imubench.recordings import RecordingError, read
t = time.perf_counter()
try:
    r = read(sys.argv[1], accel_unit="g", gyro_unit="dps")
    what = f"{len(r)} samples"
except RecordingError as e:
    what = f"refused: {e}"
print(what)
print(time.perf_counter() - t)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def write_csv(path: Path, rows: int, seed: int = 1) -> None:
    rng = np.random.default_rng(seed)
    with open(path, "w") as f:
        f.write("t_s,ax,ay,az,gx,gy,gz\n")
        for i in range(0, rows, 100_000):
            n = min(100_000, rows - i)
            blk = np.column_stack([(np.arange(n) + i) / 1000.0, rng.normal(0, 0.01, (n, 6)) + [0, 0, 1, 0, 0, 0]])
            np.savetxt(f, blk, delimiter=",", fmt="%.9f")


def write_npz_bomb(path: Path) -> None:
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": (201326592, 3)})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name in ("accel_mps2", "rate_rad_s"):
            z.writestr(name + ".npy", hdr.getvalue() + b"\0" * (5 << 20))


def child_read(path: Path) -> tuple[str, float, float]:
    r = subprocess.run([sys.executable, "-c", CHILD_READ, str(path)], capture_output=True, text=True, check=True)
    what, secs, mib = r.stdout.strip().splitlines()[-3:]
    return what, float(secs), float(mib)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=3_000_000)
    ap.add_argument("--calibrate", action="store_true", help="also time `imubench calibrate --from`")
    a = ap.parse_args()
    out: dict = {"rows": a.rows}
    with tempfile.TemporaryDirectory(prefix="imubench-bench-") as td:
        csv_path = Path(td) / "big.csv"
        write_csv(csv_path, a.rows)
        out["csv_mb"] = csv_path.stat().st_size / 1e6
        what, secs, mib = child_read(csv_path)
        out.update(read_what=what, read_s=secs, read_peak_rss_mib=mib,
                   numbers_mib=a.rows * 7 * 8 / 2**20)
        print(f"read {out['csv_mb']:.0f} MB CSV: {what} in {secs:.1f} s, peak RSS {mib:.0f} MiB "
              f"(the float64 numbers alone: {out['numbers_mib']:.0f} MiB)")
        bomb = Path(td) / "bomb.npz"
        write_npz_bomb(bomb)
        what, secs, mib = child_read(bomb)
        out.update(npz_bomb_bytes=bomb.stat().st_size, npz_bomb_s=secs, npz_bomb_peak_rss_mib=mib)
        print(f"read a {bomb.stat().st_size / 1e3:.0f} kB npz whose members claim 4.5 GiB each: {what[-60:]} in {secs:.2f} s, "
              f"peak RSS {mib:.0f} MiB")
        if a.calibrate:
            sys.path.insert(0, str(ROOT / "tests"))
            from imu_synth import G0, ferraris_session, write_csv as write_session
            fs = 1000.0
            rest = max(4.0, a.rows / fs / 12)
            acc, gyr, _, _ = ferraris_session(fs=fs, rest_s=rest, turn_s=8.0)
            sess = Path(td) / "session.csv"
            write_session(sess, acc / G0, np.degrees(gyr), fs)
            t = time.perf_counter()
            r = subprocess.run(["/usr/bin/time", "-f", "%M", sys.executable, "-m", "imubench", "calibrate", "--from",
                                str(sess), "--accel-unit", "g", "--gyro-unit", "dps", "--dir", str(Path(td) / "o"),
                                "--db", str(Path(td) / "h.sqlite")], capture_output=True, text=True)
            kib = int(r.stderr.strip().splitlines()[-1])
            out.update(calibrate_rows=len(acc), calibrate_mb=sess.stat().st_size / 1e6, calibrate_exit=r.returncode,
                       calibrate_s=time.perf_counter() - t, calibrate_peak_rss_mib=kib / 1024)
            print(f"calibrate --from a {out['calibrate_mb']:.0f} MB six-face recording ({len(acc)} samples): exit "
                  f"{r.returncode} in {out['calibrate_s']:.0f} s, peak RSS {kib / 1024:.0f} MiB")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
