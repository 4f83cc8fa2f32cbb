#!/usr/bin/env python3
"""What a new user waits for: the wheel's size, and the time from `pip install` of the wheel
into a fresh virtual environment to the first passed virtual calibration session.

    python bench/wheel_install.py                 # builds the wheel first (python -m build --wheel)
    python bench/wheel_install.py --wheel dist/imubench-0.1.0-py3-none-linux_x86_64.whl

The environment is made in a temporary directory outside the checkout; pip installs the wheel
and its dependencies from the package index as a user's pip does (byte-compiling included, its
cache as warm as this machine's); `imubench calibrate --sim` then runs from another working
directory with HOME in the temporary directory and PATH holding the environment's bin/ alone.
Prints one line per figure and the markdown table README states, and publishes it
(bench/publish.py; --no-publish to leave the docs alone). tests/repo/test_wheel.py checks the
behaviour; this prints the numbers.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import venv
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--wheel", type=Path, help="the wheel to install (default: build one from this tree)")
    add_arguments(ap)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="imubench-wheel-bench-") as tmp:
        base = Path(tmp)
        wheel = a.wheel
        if wheel is None:
            t0 = time.monotonic()
            r = subprocess.run([sys.executable, "-m", "build", "--wheel", "--outdir", str(base / "dist"), str(ROOT)],
                               capture_output=True, text=True)
            if r.returncode != 0:
                print(r.stdout[-3000:] + r.stderr[-3000:], file=sys.stderr)
                return 1
            wheel, = (base / "dist").glob("*.whl")
            print(f"wheel build (python -m build --wheel, compiles the C parts): {time.monotonic() - t0:.0f} s")
        print(f"wheel {wheel.name}: {wheel.stat().st_size / 1e6:.2f} MB")
        venv.create(base / "venv", with_pip=True)
        bindir = base / "venv" / "bin"
        (base / "home").mkdir()
        (base / "work").mkdir()
        env = {k: v for k, v in os.environ.items() if k.startswith("PIP_")}
        env.update(PATH=str(bindir), HOME=str(base / "home"), LANG="C.UTF-8", TMPDIR=str(base))
        t0 = time.monotonic()
        r = subprocess.run([str(bindir / "pip"), "install", "-q", str(wheel.resolve())], cwd=base / "work", env=env,
                           capture_output=True, text=True)
        t1 = time.monotonic()
        if r.returncode != 0:
            print(r.stdout[-3000:] + r.stderr[-3000:], file=sys.stderr)
            return 1
        r = subprocess.run([str(bindir / "imubench"), "calibrate", "--sim", "--dir", str(base / "work" / "s")],
                           cwd=base / "work", env=env, capture_output=True, text=True)
        t2 = time.monotonic()
        if r.returncode != 0 or "calibration PASSED" not in r.stdout:
            print(r.stdout[-3000:] + r.stderr[-3000:], file=sys.stderr)
            return 1
        load = os.getloadavg()[0]
        print(f"pip install of the wheel and its dependencies: {t1 - t0:.1f} s")
        print(f"imubench calibrate --sim to PASSED: {t2 - t1:.1f} s")
        print(f"from pip install to the first passed virtual session: {t2 - t0:.1f} s "
              f"(load average {load:.1f} on {os.cpu_count()} cores)")
        md = ("| load average | `pip install` | session to PASSED | `pip install` to the first passed session |\n"
              "|---|---|---|---|\n"
              f"| {load:.1f} | {t1 - t0:.1f} s | {t2 - t1:.1f} s | {t2 - t0:.1f} s |\n")
        print("\n" + md, end="")
        publish("wheel_install", md, {"wheel": f"{wheel.name} {wheel.stat().st_size / 1e6:.2f} MB"},
                enabled=not a.no_publish)
    return 0


if __name__ == "__main__":
    sys.exit(main())
