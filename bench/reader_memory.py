#!/usr/bin/env python3
"""The peak memory of each `--from` reader (issue 41): the same 2 h still recording at 200 Hz (the
signal of bench/long_recording.py, seed 1) as CSV, a ROS 2 bag (MCAP), imubench's npz (the members of
`imubench decode --npz`), imu_tk's pair of `t x y z` files, a capture .bin (raw frames of 16 samples,
counts) and a ROS 1 bag, each read by imubench.recordings.read alone in a fresh process.

    .venv/bin/python bench/reader_memory.py                       # makes the files in a temporary dir
    .venv/bin/python bench/reader_memory.py --keep /tmp/i41long   # keep (and reuse) them
    .venv/bin/python bench/reader_memory.py --hours 0.5 --only ROS

Prints a markdown table: the peak resident set of the read, the same beyond what the process held
after its imports (per sample), what the samples themselves take, the read's wall and CPU time.
The last line of stdout is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
import long_recording as lr  # noqa: E402

CHILD = r'''
import json, resource, sys, time
from imubench.recordings import read
import imubench.recordings.readers, zipfile, tqdm
try:
    import rosbags.highlevel, rosbags.typesys, rosbags.rosbag1.reader
except ImportError:
    pass
def rss_now():
    with open("/proc/self/status") as f:
        return next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmRSS"))
base = rss_now()
t, c = time.perf_counter(), time.process_time()
r = read(sys.argv[1], **json.loads(sys.argv[2]))
print(json.dumps({"n": len(r), "base": base, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c, "dtype": r.accel.dtype.name,
                  "held": r.accel.nbytes + r.gyro.nbytes + (0 if r.t_s is None else r.t_s.nbytes)}))
'''


def make(kind: str, d: Path, hours: float) -> tuple[Path, dict, int]:
    """The recording of `kind` in d (made when missing): (path, read options, bytes on disk)."""
    tag = f"{hours:g}h"
    g_units = {"accel_unit": "g", "gyro_unit": "dps"}
    if kind == "CSV":
        p = d / f"still-{tag}.csv"
        if not p.exists():
            lr.write_csv(p, hours)
        return p, g_units, p.stat().st_size
    if kind == "ROS 2 bag (MCAP)":
        p = d / f"still-{tag}-bag"
        if not p.exists():
            lr.write_bag(p, hours)
        return p, {}, sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
    if kind == "npz":
        p = d / f"still-{tag}.npz"
        if not p.exists():
            ts, A, G = [], [], []
            for t, a, g in lr.still_blocks(hours):
                ts.append(t)
                A.append(a * lr.G0)
                G.append(np.radians(g))
            t = np.concatenate(ts)
            n = len(t)
            np.savez_compressed(p, t_us=np.round(t * 1e6).astype(np.int64), sample_index=np.arange(n, dtype=np.int64),
                                status=np.zeros(n, np.uint8), accel_mps2=np.concatenate(A).astype(np.float32),
                                rate_rad_s=np.concatenate(G).astype(np.float32))
        return p, {}, p.stat().st_size
    if kind == "imu_tk pair":
        p, q = d / f"still-{tag}-acc.txt", d / f"still-{tag}-gyro.txt"
        if not (p.exists() and q.exists()):
            with open(p, "w") as fa, open(q, "w") as fg:
                for t, a, g in lr.still_blocks(hours):
                    np.savetxt(fa, np.column_stack([t, a]), fmt=["%.3f"] + ["%.7f"] * 3)
                    np.savetxt(fg, np.column_stack([t, g]), fmt=["%.3f"] + ["%.7f"] * 3)
        return p, g_units, p.stat().st_size + q.stat().st_size
    if kind == "capture .bin":
        p = d / f"still-{tag}-capture.bin"
        if not p.exists():
            from imubench.wire import frame as P
            from imubench.wire.protocol_gen import BatchHeader, RawBatch
            k = seq = 0
            with open(p, "wb") as f:
                for t, a, g in lr.still_blocks(hours):
                    ac, gc = np.round(a * 256000).astype(np.int64), np.round(g * 80).astype(np.int64)
                    for i in range(0, len(t), 16):
                        m = min(16, len(t) - i)
                        recs = dict(accel_x_counts=ac[i:i + m, 0], accel_y_counts=ac[i:i + m, 1],
                                    accel_z_counts=ac[i:i + m, 2], status=np.zeros(m, int), gyro_counts=gc[i:i + m])
                        hdr = BatchHeader(sample_index=k, period_us=5000, count=m, accel_range_g=2,
                                          accel_temp_counts=1885)
                        f.write(P.encode(RawBatch(header=hdr), seq & 0xFFFF, (k * 5000) & 0xFFFFFFFF, records=recs))
                        k += m
                        seq += 1
        return p, {}, p.stat().st_size
    if kind == "ROS 1 bag":
        p = d / f"still-{tag}-ros1.bag"
        if not p.exists():
            from rosbags.rosbag1 import Writer
            from rosbags.typesys import Stores, get_typestore
            pack = struct.Struct("<IIII3s4d9d3d9d3d9d").pack       # sensor_msgs/Imu, ROS 1, frame_id "imu"
            z9 = (0.0,) * 9
            with Writer(p) as w:
                conn = w.add_connection("/imu0", "sensor_msgs/msg/Imu",
                                        typestore=get_typestore(Stores.ROS1_NOETIC))
                seq = 0
                for t, a, g in lr.still_blocks(hours):
                    stamps = 1_700_000_000 * 10 ** 9 + np.round(t * 1e9).astype(np.int64)
                    for ns, av, gv in zip(stamps.tolist(), (a * lr.G0).tolist(), np.radians(g).tolist()):
                        w.write(conn, ns, pack(seq, ns // 10 ** 9, ns % 10 ** 9, 3, b"imu", 0.0, 0.0, 0.0, 1.0,
                                               *z9, *gv, *z9, *av, *z9))
                        seq += 1
        return p, {}, p.stat().st_size
    raise ValueError(kind)


KINDS = ("CSV", "ROS 2 bag (MCAP)", "npz", "imu_tk pair", "capture .bin", "ROS 1 bag")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--keep", type=Path, help="directory to keep (and reuse) the recordings in")
    ap.add_argument("--only", nargs="*", help="formats whose name holds one of these words")
    a = ap.parse_args(argv)
    d = a.keep or Path(tempfile.mkdtemp(prefix="imubench-readers-"))
    d.mkdir(parents=True, exist_ok=True)
    rows = []
    out = ["| format | file | peak RSS | beyond the imports, a sample | samples held, a sample | read (CPU) |",
           "|---|---:|---:|---:|---:|---:|"]
    for kind in KINDS:
        if a.only and not any(w.lower() in kind.lower() for w in a.only):
            continue
        t = time.perf_counter()
        path, opts, size = make(kind, d, a.hours)
        made = time.perf_counter() - t
        env = {**os.environ, "PYTHONPATH": str(ROOT / "host")}
        p = subprocess.run([sys.executable, "-c", CHILD, str(path), json.dumps(opts)], capture_output=True, text=True,
                           env=env)
        if p.returncode:
            raise SystemExit(f"{kind}: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode}")
        r = json.loads(p.stdout.strip().splitlines()[-1])
        n = r["n"]
        rows.append({"format": kind, "file_bytes": size, "made_s": made, **r})
        out.append(f"| {kind} | {size / 1e6:.0f} MB | {r['peak'] / 1e6:.0f} MB | {(r['peak'] - r['base']) / n:.0f} B "
                   f"| {r['held'] / n:.0f} B ({r['dtype']}) | {r['wall_s']:.1f} s ({r['cpu_s']:.1f} s) |")
        print(out[-1], flush=True)
    print("\n".join(out))
    print(json.dumps({"hours": a.hours, "load_avg": os.getloadavg(), "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
