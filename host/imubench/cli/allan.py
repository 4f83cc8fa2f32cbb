"""`imubench allan`: record a resting IMU for hours (crash-safe) and read the Allan deviation."""
from __future__ import annotations

import argparse
import re
import shlex
import signal
from pathlib import Path

from imubench.cli.common import (
    CommandError,
    UsageError,
    add_port,
    existing_file,
    out_dir,
    stream_rate,
)


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


def register(sub) -> None:
    p = sub.add_parser("allan", help="record for hours and read the Allan deviation (noise terms)",
                       description="Record a resting IMU for a long time (every byte on disk as it arrives) and "
                                   "compute the overlapping Allan deviation and the read-offs N, B, K per axis "
                                   "(docs/noise.md).")
    add_port(p)
    p.add_argument("--duration", type=parse_duration, default=None,
                   help="recording length in device time: 90s, 30m, 2h, 1h30m (required unless --analyse)")
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=100, help="sample rate in Hz")
    p.add_argument("--out", type=out_dir, default=Path("allan-out"), help="output directory")
    p.add_argument("--analyse", nargs="+", metavar="FILE", type=existing_file,
                   help="analyse existing capture file(s) (e.g. of an interrupted recording) without a device")
    p.add_argument("--progress", type=float, default=5.0, help="seconds between progress lines")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.procedures.allan import analyse_capture, record
    out = a.out
    if a.analyse:
        analyse_capture(a.analyse, out)
        return 0
    if a.duration is None:
        raise UsageError("--duration is required to record", "give e.g. --duration 2h, or --analyse FILE")
    out.mkdir(parents=True, exist_ok=True)
    cap = out / "capture.bin"
    if cap.exists() and cap.stat().st_size:
        raise CommandError(f"{cap} exists", f"analyse it with --analyse {shlex.quote(str(cap))}, or choose another --out")
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
    analyse_capture([cap], out, rate_hz=float(a.rate))
    if why not in ("done", "interrupted"):
        raise CommandError(f"the recording ended early ({why}); what was recorded is analysed in {out}",
                           f"record again, or analyse more files with --analyse {shlex.quote(str(cap))} FILE...")
    return 0
