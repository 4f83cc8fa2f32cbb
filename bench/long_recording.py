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
RATE_HZ = 200.0
#: the simulated IMU (SI): white noise density and rate random walk of each sensor
ACC_N = 100e-6 * 9.80665        # 100 µg/√Hz in m/s²/√Hz
ACC_K = 2e-6 * 9.80665          # m/s²·√Hz (accelerometer random walk)
GYR_N = np.radians(0.01)        # 0.01 °/s/√Hz in rad/s/√Hz
GYR_K = np.radians(1e-4)        # rad/s·√Hz
BLOCK = 200_000


def write_csv(path: Path, hours: float, seed: int = 1) -> int:
    """A still recording of `hours` at 200 Hz as CSV (accel in g, gyro in °/s); its sample count."""
    n = int(round(hours * 3600 * RATE_HZ))
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE_HZ
    walk = np.zeros(6)
    g0 = 9.80665
    with open(path, "w") as f:
        f.write("t_s,ax,ay,az,gx,gy,gz\n")
        for i in range(0, n, BLOCK):
            m = min(BLOCK, n - i)
            white = rng.normal(0, 1, (m, 6)) * np.r_[[ACC_N] * 3, [GYR_N] * 3] / np.sqrt(dt)
            steps = rng.normal(0, 1, (m, 6)) * np.r_[[ACC_K] * 3, [GYR_K] * 3] * np.sqrt(dt)
            rw = walk + np.cumsum(steps, axis=0)
            walk = rw[-1]
            v = white + rw
            acc_g = v[:, :3] / g0 + [0.0, 0.0, 1.0]
            gyr_dps = np.degrees(v[:, 3:])
            blk = np.column_stack([(np.arange(m) + i) * dt, acc_g, gyr_dps])
            np.savetxt(f, blk, delimiter=",", fmt=["%.3f"] + ["%.7f"] * 6)
    return n


def write_bag(path: Path, csv_path: Path) -> int:
    """The CSV's samples as a ROS 2 bag (.mcap) of sensor_msgs/Imu on /imu0 (m/s², rad/s)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_HUMBLE)
    Imu, Header, Time = ts.types["sensor_msgs/msg/Imu"], ts.types["std_msgs/msg/Header"], ts.types[
        "builtin_interfaces/msg/Time"]
    Q, V = ts.types["geometry_msgs/msg/Quaternion"], ts.types["geometry_msgs/msg/Vector3"]
    cov = np.zeros(9)
    n = 0
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/imu0", Imu.__msgtype__, typestore=ts)
        with open(csv_path) as f:
            f.readline()
            while True:
                lines = [ln for _, ln in zip(range(BLOCK), f)]
                if not lines:
                    break
                d = np.loadtxt(lines, delimiter=",", ndmin=2)
                for row in d:
                    t_ns = int(round(row[0] * 1e9)) + 1_700_000_000_000_000_000
                    a = row[1:4] * 9.80665
                    g = np.radians(row[4:7])
                    msg = Imu(Header(Time(t_ns // 1_000_000_000, t_ns % 1_000_000_000), "imu"), Q(0.0, 0.0, 0.0, 1.0),
                              cov, V(*g), cov, V(*a), cov)
                    w.write(conn, t_ns, ts.serialize_cdr(msg, Imu.__msgtype__))
                    n += 1
    return n


CHILD_ALLAN = r"""
import json, resource, sys, time, io, contextlib
from imubench.cli.main import main
t = time.perf_counter()
buf = io.StringIO()
with contextlib.redirect_stdout(buf):
    rc = main(["allan", "--from", sys.argv[1], "--out", sys.argv[2]] + sys.argv[4:])
wall = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
res = json.load(open(sys.argv[2] + "/allan.json"))
peer = None
if sys.argv[3] == "peer":
    import numpy as np, allantools
    from imubench.recordings import read
    r = read(sys.argv[1], accel_unit="g", gyro_unit="dps")
    acc = r.accel_mps2().astype(np.float64); gyr = r.gyro_rad_s().astype(np.float64)
    del r
    t1 = time.perf_counter()
    for x in (acc, gyr):
        for k in range(3):
            allantools.oadev(x[:, k].copy(), rate=res["rate_hz"], data_type="freq", taus="octave")
    peer = time.perf_counter() - t1
print(json.dumps({"rc": rc, "wall_s": wall, "peak_rss_bytes": rss, "samples": res["samples"], "peer_s": peer,
                  "N_gyro_x": res["gyro"]["x"]["N"], "N_accel_x": res["accel"]["x"]["N"],
                  "method": res.get("method"), "tail": buf.getvalue().splitlines()[-3:]}))
"""

CHILD_READ = r"""
import json, resource, sys, time
from imubench.recordings import read
t = time.perf_counter()
kw = {} if sys.argv[1].endswith((".mcap", ".bag")) or "bag" in sys.argv[1] else {"accel_unit": "g", "gyro_unit": "dps"}
r = read(sys.argv[1], **kw)
print(json.dumps({"read_s": time.perf_counter() - t, "n": len(r),
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
    ap.add_argument("--hours", type=float, nargs="+", default=[1, 2, 8, 24])
    ap.add_argument("--bag-hours", type=float, default=24.0, help="length of the ROS 2 bag (0: none)")
    ap.add_argument("--no-bag", action="store_true")
    ap.add_argument("--keep", type=Path, help="directory to keep (and reuse) the recordings in")
    ap.add_argument("--no-peer", action="store_true", help="skip allantools on the same arrays")
    a = ap.parse_args(argv)
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
                write_bag(src, csv_path)
                print(f"made {src} in {time.perf_counter() - t:.0f} s", flush=True)
            extra = []
        out = work / f"out-{kind}-{hours:g}h"
        r = child(CHILD_ALLAN, str(src), str(out), "none" if a.no_peer else "peer", *extra)
        rd = child(CHILD_READ, str(src))
        size = sum(p.stat().st_size for p in ([src] if src.is_file() else src.rglob("*")) if p.is_file())
        row = {"hours": hours, "kind": kind, "file_bytes": size, **r, "read_s": rd["read_s"],
               "read_peak_rss_bytes": rd["peak_rss_bytes"], "bytes_per_sample": r["peak_rss_bytes"] / r["samples"]}
        if r["peer_s"] is not None:
            row["ratio_to_read_plus_peer"] = r["wall_s"] / (rd["read_s"] + r["peer_s"])
        rows.append(row)
        print(f"{hours:>4g} h {kind:<4} {r['samples']:>10} samples {size / 1e6:7.0f} MB: allan --from "
              f"{r['wall_s']:6.1f} s, peak {r['peak_rss_bytes'] / 1e6:6.0f} MB ({row['bytes_per_sample']:5.1f} B/sample)"
              f"; read alone {rd['read_s']:5.1f} s"
              + (f"; allantools.oadev on the 6 arrays {r['peer_s']:5.1f} s; ratio {row['ratio_to_read_plus_peer']:.2f}"
                 if r["peer_s"] is not None else ""), flush=True)
    print(json.dumps({"rate_hz": RATE_HZ, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
