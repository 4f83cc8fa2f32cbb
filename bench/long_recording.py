#!/usr/bin/env python3
"""Long still recordings (issue 41): `imubench allan --from` on 1, 2, 8 and 24 h at 200 Hz.

Each recording is made here, with numpy, as a CSV of a resting IMU (`t_s,ax,ay,az,gx,gy,gz`, g and
°/s: white noise plus a rate random walk on each axis, seeded), and one 24 h ROS 2 bag of the same
(sensor_msgs/Imu, written with the rosbags library). For each, in a fresh child process:

* allan: `imubench allan --from FILE` (the whole command: read, timing check, Allan deviation of six
  axes, plots, allan.json): wall time, peak resident set (ru_maxrss) and bytes per sample;
* peer: in the same child after the command, `allantools.oadev` (octave τ) on the same six arrays,
  already in memory as float64: its time alone, the computation imubench's Allan step is compared to;
* read: the time of the read alone (imubench.recordings.read) in another child, so that the 8 h target
  (allan --from within 1.5x of reading the file plus allantools) is checked against both parts.

    .venv/bin/python bench/long_recording.py                      # 1, 2, 8, 24 h CSV and a 24 h bag
    .venv/bin/python bench/long_recording.py --hours 1 2 --no-bag # quicker
    .venv/bin/python bench/long_recording.py --keep /tmp/long     # keep (and reuse) the files
    .venv/bin/python bench/long_recording.py --table-from run.log # publish the JSON line of an earlier run

Prints the markdown table docs/noise.md states and publishes it (bench/publish.py; --no-publish to leave
the docs alone).

Targets (issue 41): 24 h at 200 Hz in < 1 GB peak and < 2 min; 8 h within 1.5x of read + allantools.
Human-readable lines first; the last line of stdout is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
from publish import add_arguments, publish  # noqa: E402

RATE_HZ = 200.0
#: the simulated IMU (SI): white noise density and rate random walk of each sensor
ACC_N = 100e-6 * 9.80665        # 100 µg/√Hz in m/s²/√Hz
ACC_K = 2e-6 * 9.80665          # m/s²·√Hz (accelerometer random walk)
GYR_N = np.radians(0.01)        # 0.01 °/s/√Hz in rad/s/√Hz
GYR_K = np.radians(1e-4)        # rad/s·√Hz
BLOCK = 200_000


def still_blocks(hours: float, seed: int = 1):
    """(t_s, accel_g, gyro_dps) of a resting IMU at 200 Hz, BLOCK samples at a time (seeded)."""
    n = int(round(hours * 3600 * RATE_HZ))
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE_HZ
    walk = np.zeros(6)
    for i in range(0, n, BLOCK):
        m = min(BLOCK, n - i)
        white = rng.normal(0, 1, (m, 6)) * np.r_[[ACC_N] * 3, [GYR_N] * 3] / np.sqrt(dt)
        steps = rng.normal(0, 1, (m, 6)) * np.r_[[ACC_K] * 3, [GYR_K] * 3] * np.sqrt(dt)
        rw = walk + np.cumsum(steps, axis=0)
        walk = rw[-1]
        v = white + rw
        yield (np.arange(m) + i) * dt, v[:, :3] / G0 + [0.0, 0.0, 1.0], np.degrees(v[:, 3:])


G0 = 9.80665


def write_csv(path: Path, hours: float, seed: int = 1) -> int:
    """A still recording of `hours` at 200 Hz as CSV (accel in g, gyro in °/s); its sample count."""
    n = 0
    with open(path, "w") as f:
        f.write("t_s,ax,ay,az,gx,gy,gz\n")
        for t, acc_g, gyr_dps in still_blocks(hours, seed):
            np.savetxt(f, np.column_stack([t, acc_g, gyr_dps]), delimiter=",", fmt=["%.3f"] + ["%.7f"] * 6)
            n += len(t)
    return n


def write_bag(path: Path, hours: float, seed: int = 1) -> int:
    """The same still signal as write_csv's (unrounded, in m/s² and rad/s) as a ROS 2 bag (MCAP) of
    sensor_msgs/Imu on /imu0, stamped from 2023-11-14: each message packed as CDR here (rosbags'
    own serializer takes ~25 µs a message; a day has 17 M of them) and written with rosbags' Writer."""
    import struct
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_HUMBLE)
    imu_t = "sensor_msgs/msg/Imu"
    # CDR little-endian: stamp, frame_id "imu" (length 4 with its NUL: the doubles start at 16, aligned)
    pack = struct.Struct("<4siII4s4d9d3d9d3d9d").pack
    zero9 = (0.0,) * 9
    t0_ns = 1_700_000_000 * 10 ** 9
    n = 0
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/imu0", imu_t, typestore=ts)
        write = w.write
        for t, acc_g, gyr_dps in still_blocks(hours, seed):
            stamps = t0_ns + np.round(t * 1e9).astype(np.int64)
            acc, gyr = (acc_g * G0).tolist(), np.radians(gyr_dps).tolist()
            for ns, a, g in zip(stamps.tolist(), acc, gyr):
                write(conn, ns, pack(b"\x00\x01\x00\x00", ns // 10 ** 9, ns % 10 ** 9, 4, b"imu\x00",
                                     0.0, 0.0, 0.0, 1.0, *zero9, *g, *zero9, *a, *zero9))
            n += len(t)
    return n


CHILD_ALLAN = r"""
import json, resource, sys, time, io, contextlib
from imubench.cli.main import main
t = time.perf_counter()
buf = io.StringIO()
with contextlib.redirect_stdout(buf):
    rc = main(["allan", "--from", sys.argv[1], "--out", sys.argv[2]] + sys.argv[4:])
wall = time.perf_counter() - t
ru = resource.getrusage(resource.RUSAGE_SELF)
rss, cpu = ru.ru_maxrss * 1024, ru.ru_utime + ru.ru_stime
res = json.load(open(sys.argv[2] + "/allan.json"))
peer = None
if sys.argv[3] == "peer":
    import numpy as np, allantools
    from imubench.recordings import read
    r = read(sys.argv[1], accel_unit="g", gyro_unit="dps")
    acc = r.accel_mps2().astype(np.float64); gyr = r.gyro_rad_s().astype(np.float64)
    del r
    t1, c1 = time.perf_counter(), time.process_time()
    for x in (acc, gyr):
        for k in range(3):
            allantools.oadev(x[:, k].copy(), rate=res["rate_hz"], data_type="freq", taus="octave")
    peer, peer_cpu = time.perf_counter() - t1, time.process_time() - c1
else:
    peer_cpu = None
print(json.dumps({"rc": rc, "wall_s": wall, "cpu_s": cpu, "peak_rss_bytes": rss, "samples": res["samples"],
                  "peer_s": peer, "peer_cpu_s": peer_cpu,
                  "N_gyro_x": res["gyro"]["x"]["N"], "N_accel_x": res["accel"]["x"]["N"],
                  "method": res.get("method"), "tail": buf.getvalue().splitlines()[-3:]}))
"""

CHILD_READ = r"""
import json, resource, sys, time
from imubench.recordings import read
t, c = time.perf_counter(), time.process_time()
kw = {} if sys.argv[1].endswith((".mcap", ".bag")) or "bag" in sys.argv[1] else {"accel_unit": "g", "gyro_unit": "dps"}
r = read(sys.argv[1], **kw)
print(json.dumps({"read_s": time.perf_counter() - t, "read_cpu_s": time.process_time() - c, "n": len(r),
                  "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def child(code: str, *args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "host")}
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env)
    if p.returncode:
        raise SystemExit(f"child failed: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hours", type=float, nargs="*", default=[1, 2, 8, 24], help="CSV lengths (none: only the bag)")
    ap.add_argument("--bag-hours", type=float, default=24.0, help="length of the ROS 2 bag (0: none)")
    ap.add_argument("--no-bag", action="store_true")
    ap.add_argument("--keep", type=Path, help="directory to keep (and reuse) the recordings in")
    ap.add_argument("--no-peer", action="store_true", help="skip allantools on the same arrays")
    ap.add_argument("--table-from", type=Path, nargs="+", metavar="LOG",
                    help="publish the table of earlier runs' output (the last JSON line of each) instead of measuring")
    add_arguments(ap)
    a = ap.parse_args(argv)
    if a.table_from:
        rows = [row for log in a.table_from for row in
                json.loads([ln for ln in log.read_text().splitlines() if ln.startswith('{"rate_hz"')][-1])["rows"]]
        md = table(rows)
        print(md)
        publish("long_recording", md, {"measured by": "earlier runs: " + ", ".join(p.name for p in a.table_from)},
                enabled=not a.no_publish)
        return 0
    work = a.keep or Path(tempfile.mkdtemp(prefix="imubench-long-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    jobs = [(h, "csv") for h in a.hours] + ([] if a.no_bag or not a.bag_hours else [(a.bag_hours, "bag")])
    for hours, kind in jobs:
        csv_path = work / f"still-{hours:g}h.csv"
        if not csv_path.exists():
            t = time.perf_counter()
            write_csv(csv_path, hours)
            print(f"made {csv_path} ({csv_path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - t:.0f} s",
                  flush=True)
        src = csv_path
        extra = ["--accel-unit", "g", "--gyro-unit", "dps"]
        if kind == "bag":
            src = work / f"still-{hours:g}h-bag"
            if not src.exists():
                t = time.perf_counter()
                write_bag(src, hours)
                print(f"made {src} in {time.perf_counter() - t:.0f} s", flush=True)
            extra = []
        out = work / f"out-{kind}-{hours:g}h"
        r = child(CHILD_ALLAN, str(src), str(out), "none" if a.no_peer else "peer", *extra)
        rd = child(CHILD_READ, str(src))
        size = sum(p.stat().st_size for p in ([src] if src.is_file() else src.rglob("*")) if p.is_file())
        row = {"hours": hours, "kind": kind, "file_bytes": size, **r, "read_s": rd["read_s"],
               "read_cpu_s": rd.get("read_cpu_s"), "load_avg_1min": os.getloadavg()[0],
               "read_peak_rss_bytes": rd["peak_rss_bytes"], "bytes_per_sample": r["peak_rss_bytes"] / r["samples"]}
        if r["peer_s"] is not None:
            row["ratio_to_read_plus_peer"] = r["wall_s"] / (rd["read_s"] + r["peer_s"])
            row["cpu_ratio_to_read_plus_peer"] = r["cpu_s"] / (rd["read_cpu_s"] + r["peer_cpu_s"])
        rows.append(row)
        print(f"{hours:>4g} h {kind:<4} {r['samples']:>10} samples {size / 1e6:7.0f} MB: allan --from "
              f"{r['wall_s']:6.1f} s, peak {r['peak_rss_bytes'] / 1e6:6.0f} MB ({row['bytes_per_sample']:5.1f} B/sample)"
              f"; read alone {rd['read_s']:5.1f} s"
              + (f"; allantools.oadev on the 6 arrays {r['peer_s']:5.1f} s; ratio {row['ratio_to_read_plus_peer']:.2f}"
                 if r["peer_s"] is not None else ""), flush=True)
    md = table(rows)
    print(md)
    publish("long_recording", md, {}, enabled=not a.no_publish)
    print(json.dumps({"rate_hz": RATE_HZ, "rows": rows}))
    return 0


def table(rows: list[dict]) -> str:
    """The markdown table of the rows: allan --from beside read alone and allantools on the same arrays."""
    out = ["| recording at 200 Hz | samples | file | `allan --from` wall (CPU) | peak RSS | per sample | method "
           "| read alone | allantools.oadev, 6 axes | wall / (read + allantools) | load |",
           "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        method = ("chunked sums" if str(r.get("method") or "").startswith("chunked") else
                  "allantools in memory" if r.get("method") else "?")
        peer = f"{r['peer_s']:.1f} s" if r.get("peer_s") is not None else "not run"
        ratio = f"{r['ratio_to_read_plus_peer']:.2f}" if "ratio_to_read_plus_peer" in r else ""
        if r.get("cpu_ratio_to_read_plus_peer") is not None:
            ratio += f" (CPU {r['cpu_ratio_to_read_plus_peer']:.2f})"
        cpu = f" ({r['cpu_s']:.1f} s)" if r.get("cpu_s") is not None else ""
        load = f"{r['load_avg_1min']:.0f}" if r.get("load_avg_1min") is not None else "16–21"
        out.append(f"| {r['hours']:g} h {'CSV' if r['kind'] == 'csv' else 'ROS 2 bag (MCAP)'} | {r['samples']:,} "
                   f"| {r['file_bytes'] / 1e6:.0f} MB | {r['wall_s']:.1f} s{cpu} | {r['peak_rss_bytes'] / 1e6:.0f} MB "
                   f"| {r['bytes_per_sample']:.0f} B | {method} | {r['read_s']:.1f} s | {peer} | {ratio} | {load} |")
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main())
