"""`imubench demo` (and `make demo`): a whole guided calibration session on the virtual device.

The virtual device (firmware core + drivers + register-level sensor models, imubench.device.sim)
is started with random, non-trivial truth errors (scale, misalignment and bias of every sensor).
Its virtual bench presents the 26 attitudes of the multi-position plan and turns the table
at known rates about each axis, both ways, while `imubench calibrate` captures, detects
stillness and attitude from the data, fits (six-position pre-calibration, then |a| = g;
gyro scale/misalignment from the turntable, bias from rest), writes the parameters back,
reads them back, saves, reboots, verifies the device's own calibrated output, records the
run in a history database, and prints the recovered parameters beside the truth with their
uncertainties. Then the closure check: the virtual bench drives a closed 3-D path and the
accelerations are integrated with and without the new calibration. Everything is written to
a temporary session directory (--dir DIR to keep it somewhere else).

It needs nothing but the installed package: the virtual device comes with the wheel
(imubench.device.artifacts), or is built with `make sim` in the source checkout.
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from imubench.files import make_dir


def register(sub) -> None:
    p = sub.add_parser("demo", help="a whole guided calibration session on the virtual device",
                       description="A guided calibration session on the virtual device with random truth "
                                   "errors (multi-position + turntable), write-back, verification, history and "
                                   "the closure check; the recovered parameters are printed beside the truth.")
    p.add_argument("--dir", metavar="DIR", type=Path,
                   help="where the session and its history database go (default: a new temporary directory)")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.cli import calibrate
    from imubench.cli.common import Parser, UsageError
    from imubench.device.sim import build_sim
    build_sim()
    work = a.dir
    if work is None:
        work = Path(tempfile.mkdtemp(prefix="imubench-demo-"))
    elif work.exists() and (not work.is_dir() or any(work.iterdir())):
        raise UsageError(f"{work} exists and is not an empty directory", "give a new or empty --dir")
    make_dir(work)
    print("imubench demo: a guided calibration session on the virtual device (random truth errors;")
    print(f"               the virtual bench presents the attitudes and turns the table). Files in {work}\n")
    # `imubench calibrate ...` through calibrate's own parser (not cli.main's: main imports this module)
    ap = Parser(prog="imubench")
    calibrate.register(ap.add_subparsers(dest="cmd", required=True, parser_class=Parser))
    session = ap.parse_args(["calibrate", "--sim", "--sim-seed", "7", "--method", "multi", "--gyro", "turntable",
                             "--dir", str(work / "session"), "--db", str(work / "history.sqlite"),
                             "--note", "imubench demo", "--closure"])
    try:
        return session.run(session)
    finally:
        if hasattr(session, "on_interrupt"):
            a.on_interrupt = session.on_interrupt     # the Ctrl-C hint (how to resume) reaches cli.main
