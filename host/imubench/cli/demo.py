"""`make demo`: a whole guided calibration session on the virtual device.

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
a temporary session directory.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from imubench.cli.main import main as imubench
from imubench.device.sim import build_sim


def main() -> int:
    build_sim()
    work = Path(tempfile.mkdtemp(prefix="imubench-demo-"))
    print("imubench demo: a guided calibration session on the virtual device (random truth errors;")
    print(f"               the virtual bench presents the attitudes and turns the table). Files in {work}\n")
    return imubench(["calibrate", "--sim", "--sim-seed", "7", "--method", "multi", "--gyro", "turntable",
                     "--dir", str(work / "session"), "--db", str(work / "history.sqlite"),
                     "--note", "make demo", "--closure"])


if __name__ == "__main__":
    sys.exit(main())
