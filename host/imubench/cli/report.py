"""`imubench report SESSION_DIR`: one self-contained HTML file of a session and what followed it."""
from __future__ import annotations

import argparse
from pathlib import Path

from imubench.cli.common import existing_dir, existing_file, new_file


def _session_dir(s: str) -> Path:
    p = existing_dir(s)
    if not (p / "session.json").is_file():
        raise argparse.ArgumentTypeError(f"{s} has no session.json: give the directory of a calibration session "
                                         "(the --dir of imubench calibrate)")
    return p


def register(sub) -> None:
    p = sub.add_parser("report", help="one self-contained HTML report of a session",
                       description="Write one self-contained HTML report of a calibration session (parameters "
                                   "± sigma, per-pose tables, plots embedded) and, when given, its closure check, "
                                   "noise, attitude and temperature results.")
    p.add_argument("session_dir", type=_session_dir, metavar="SESSION_DIR",
                   help="the calibration session directory (with session.json)")
    p.add_argument("--out", type=new_file, metavar="FILE", help="output HTML file (default: SESSION_DIR/report.html)")
    p.add_argument("--allan", type=existing_dir, metavar="DIR",
                   help="directory with allan.json and its plots (default: SESSION_DIR)")
    p.add_argument("--attitude", type=existing_file, metavar="PNG", help="attitude plot to embed")
    p.add_argument("--thermal", type=existing_file, metavar="JSON", help="DIR/thermal.json of imubench thermal --out DIR")
    p.add_argument("--closure", type=existing_dir, metavar="DIR", help="output directory of imubench closure "
                   "(default: SESSION_DIR/closure, written by imubench calibrate --closure)")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.results.report import build_report
    print(build_report(a.session_dir, a.out, a.allan, a.attitude, a.thermal, a.closure))
    return 0
