"""`imubench allan`: record a resting IMU for hours (crash-safe) and read the Allan deviation."""
from __future__ import annotations

import argparse
import re
import shlex
import signal
import stat
from pathlib import Path

from imubench.results import exports as X
from imubench.cli.common import (
    CommandError,
    UsageError,
    add_port,
    existing_file,
    out_dir,
    positive_float,
    stream_rate,
)
from imubench.files import make_dir


def parse_duration(s: str) -> float:
    """'90s', '30m', '2h', '1h30m', '45' (seconds) -> seconds."""
    s = s.strip().lower()
    if re.fullmatch(r"\d+(\.\d+)?", s):
        v = float(s)
    else:
        parts = re.findall(r"(\d+(?:\.\d+)?)\s*([hms])", s)
        if not parts or "".join(n + u for n, u in parts) != s.replace(" ", ""):
            raise argparse.ArgumentTypeError(f"bad duration {s!r} (use e.g. 90s, 30m, 2h, 1h30m)")
        v = sum(float(n) * {"h": 3600, "m": 60, "s": 1}[u] for n, u in parts)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"the duration must be longer than zero (got {s!r})")
    return v


def rate_hz(s: str) -> float:
    """allan's --rate: as calibrate's (a positive number here; a protocol stream rate when a
    device records, any rate for a file's --from — checked in run())."""
    from imubench.cli.calibrate import rate_hz as calibrate_rate
    return calibrate_rate(s)


def register(sub) -> None:
    p = sub.add_parser("allan", help="record for hours and read the Allan deviation (noise terms)",
                       description="Record a resting IMU for a long time (every byte on disk as it arrives) and "
                                   "compute the overlapping Allan deviation and the read-offs N, B, K per axis "
                                   "(docs/noise.md).")
    add_port(p)
    p.add_argument("--duration", type=parse_duration, default=None,
                   help="recording length in device time: 90s, 30m, 2h, 1h30m (required unless --analyse)")
    p.add_argument("--rate", type=rate_hz, metavar="HZ", default=None,
                   help="sample rate in Hz: the device's stream rate (default 100), or with --from the file's rate "
                        "when it has no time column")
    p.add_argument("--out", type=out_dir, default=Path("allan-out"), help="output directory")
    p.add_argument("--analyse", nargs="+", metavar="FILE", type=existing_file,
                   help="analyse existing capture file(s) (e.g. of an interrupted recording) without a device")
    p.add_argument("--progress", type=float, default=5.0, help="seconds between progress lines")
    g = p.add_argument_group("a long still recording of any IMU (the formats and checks of calibrate --from)")
    g.add_argument("--from", dest="from_file", metavar="FILE", help="analyse a recording instead of a device")
    g.add_argument("--format", choices=FORMATS, help="the recording's format (default: from its name and content)")
    g.add_argument("--gyro-file", type=existing_file, metavar="FILE", help="with --format imutk: the gyro file")
    g.add_argument("--accel-unit", metavar="UNIT", help="accelerometer unit in the file: mps2, g, mg or counts")
    g.add_argument("--gyro-unit", metavar="UNIT", help="gyro unit in the file: rad_s, dps or counts")
    g.add_argument("--accel-scale", type=positive_float, metavar="COUNTS_PER_G", help="nominal scale of raw counts")
    g.add_argument("--gyro-scale", type=positive_float, metavar="COUNTS_PER_DPS", help="nominal scale of raw counts")
    from imubench.cli.calibrate import add_reader_options
    add_reader_options(g)
    g.add_argument("--gyro-range", type=positive_float, metavar="DPS",
                   help="with --sensor: the gyro's full-scale setting in the recording")
    g.add_argument("--columns", metavar="KEY=NAME,...", help="CSV columns (as calibrate --from)")
    g.add_argument("--time-column", metavar="NAME", help="CSV: the time column")
    g.add_argument("--time-unit", choices=("s", "ms", "us", "ns"), help="CSV: the time column's unit")
    g.add_argument("--profile", type=existing_file, metavar="TOML", help="a CSV layout file (as calibrate --from)")
    g.add_argument("--topic", metavar="TOPIC", help="ROS bag: the sensor_msgs/Imu topic")
    g.add_argument("--device", metavar="NAME", help="a name for the IMU")
    X.add_option(p, "noise")
    g.add_argument("--imu-topic", metavar="TOPIC", default="/imu0", help="the rostopic written into the exports")
    p.set_defaults(run=run)


FORMATS = ("csv", "imutk", "imucal", "npz", "capture", "rosbag")


def _run_from_file(a) -> int:
    from imubench.cli.calibrate import read_recording_args
    from imubench.procedures.allan import analyse_recording
    if a.port or a.analyse or a.duration is not None:
        raise UsageError("--from analyses a recording: it goes without --port, --analyse and --duration",
                         "drop those, or drop --from to record a device")
    rec = read_recording_args(a)
    for n in rec.notes:
        print(f"  {n}")
    analyse_recording(rec, a.out, exports=a.export, topic=a.imu_topic, memory_budget=a.memory_budget)
    return 0


def run(a) -> int:
    from imubench.analysis.allan import require_allantools
    from imubench.procedures.allan import analyse_capture, record
    require_allantools()                      # before hours of recording, not after
    if a.from_file is not None:
        return _run_from_file(a)
    file_only = [k for k in ("format", "gyro_file", "accel_unit", "gyro_unit", "accel_scale", "gyro_scale", "columns",
                             "time_column", "time_unit", "profile", "topic", "device", "skip_rows", "accel_offset",
                             "gyro_offset", "sensor", "gyro_range", "memory_budget") if getattr(a, k) is not None]
    if file_only:
        raise UsageError(f"--{file_only[0].replace('_', '-')} goes with --from FILE",
                         "give the recording with --from, or drop it")
    if a.rate is None:
        a.rate = 100
    try:
        a.rate = stream_rate(f"{a.rate:g}")
    except argparse.ArgumentTypeError as e:
        raise UsageError(f"--rate {a.rate:g}: {e}", "the device streams at the protocol's rates") from None
    out = a.out
    if a.analyse:
        analyse_capture(a.analyse, out, exports=a.export, topic=a.imu_topic)
        return 0
    if a.duration is None:
        raise UsageError("--duration is required to record", "give e.g. --duration 2h, or --analyse FILE")
    make_dir(out)
    cap = out / "capture.bin"
    if cap.exists() and cap.stat().st_size:
        raise CommandError(f"{cap} exists", f"analyse it with --analyse {shlex.quote(str(cap))}, or choose another --out")
    st = cap.lstat() if cap.is_symlink() or cap.exists() else None
    if st is not None and stat.S_ISREG(st.st_mode) and st.st_size == 0 and st.st_nlink == 1:
        cap.unlink()                # left empty by a start whose port did not open: a capture is a new file
    stop = {"now": False}
    old = None
    try:
        old = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("now", True))
    except ValueError:                        # not the main thread: no Ctrl-C handling
        pass
    try:
        why = record(a.port, a.duration, a.rate, cap, a.baud, a.progress, stop)
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)
    if not cap.exists() or cap.stat().st_size == 0:
        raise CommandError(f"nothing was recorded ({why})", "check the device with imubench info")
    print(f"recording ended: {why}; analysing {cap}", flush=True)
    analyse_capture([cap], out, rate_hz=float(a.rate), exports=a.export, topic=a.imu_topic, duration_s=a.duration)
    if why not in ("done", "interrupted"):
        raise CommandError(f"the recording ended early ({why}); what was recorded is analysed in {out}",
                           f"record again, or analyse more files with --analyse {shlex.quote(str(cap))} FILE...")
    return 0
