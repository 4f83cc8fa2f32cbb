#!/usr/bin/env python3
"""What a new user waits for: the wheel's size, and the time from `pip install` of the wheel
into a fresh virtual environment to the first passed virtual calibration session, with what
that time is made of, on an idle machine and with two busy processes beside it.

    python bench/wheel_install.py                 # builds the wheel first (python -m build --wheel)
    python bench/wheel_install.py --wheel dist/imubench-0.1.0-py3-none-linux_x86_64.whl
    python bench/wheel_install.py --busy 0        # one condition only (0, 2: the default both)

For each condition a fresh environment is made in a temporary directory outside the checkout;
pip installs the wheel and its dependencies from the package index as a user's pip does
(byte-compiling included, its cache as warm as this machine's); `imubench calibrate --sim` then
runs from another working directory with HOME in the temporary directory and PATH holding the
environment's bin/ alone. "Busy" processes are plain CPU loops (one core each) started before
pip and stopped after the session: what a build or a test run beside the user costs.

What the time is made of, from two sources and no guessing:
  pip's own log (--log: a timestamp per line): resolving and fetching (from the start to
    "Installing collected packages") and unpacking + byte-compiling (from there to "Successfully
    installed"); the ten largest wheels it installed (their sizes from pip's cache/download lines
    are not reliable, so from the installed packages' RECORD sizes).
  the first session, run with `python -X importtime` (Python's own import profiler, a few per
    cent of overhead): its import time (every top-level import's cumulative time, summed),
    matplotlib's font cache (matplotlib.font_manager's own time: built once per HOME on first
    import), and the rest (the virtual device's start, the session, the report and the plots).

Prints one line per figure and the markdown table README states, and publishes it
(bench/publish.py; --no-publish to leave the docs alone). tests/repo/test_wheel.py checks the
behaviour; this prints the numbers.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
import venv
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d,\d{3})")


def _stamp(line: str) -> float | None:
    m = LOG_TIME.match(line)
    return datetime.strptime(m.group(1), "%Y-%m-%dT%H:%M:%S,%f").timestamp() if m else None


def pip_phases(log: Path) -> dict:
    """Resolve + fetch and unpack + byte-compile seconds from pip's --log file."""
    first = install = done = None
    for line in log.read_text(errors="replace").splitlines():
        t = _stamp(line)
        if t is None:
            continue
        first = t if first is None else first
        if "Installing collected packages" in line and install is None:
            install = t
        if "Successfully installed" in line:
            done = t
    if None in (first, install, done):
        raise SystemExit(f"wheel_install: cannot find pip's phases in {log}")
    return {"resolve_fetch_s": install - first, "install_s": done - install}


def largest_packages(site: Path, n: int = 6) -> list[tuple[str, float]]:
    """(distribution, installed MB) of the largest distributions, from their RECORD files."""
    out = []
    for rec in site.glob("*.dist-info/RECORD"):
        total = 0
        for line in rec.read_text(errors="replace").splitlines():
            parts = line.rsplit(",", 2)
            if len(parts) == 3 and parts[2].isdigit():
                total += int(parts[2])
        out.append((rec.parent.name.split("-")[0], total / 1e6))
    return sorted(out, key=lambda x: -x[1])[:n]


def import_profile(stderr: str) -> dict:
    """Import seconds of a -X importtime run: top-level imports summed, matplotlib's font
    cache (font_manager's self time), and the five largest top-level imports."""
    top, font = [], 0.0
    for line in stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|( *)(\S+)", line)
        if not m:
            continue
        self_us, cum_us, indent, name = int(m.group(1)), int(m.group(2)), len(m.group(3)), m.group(4)
        if indent == 1:
            top.append((name, cum_us / 1e6))
        if name == "matplotlib.font_manager":
            font = self_us / 1e6
    return {"imports_s": sum(t for _, t in top), "font_cache_s": font,
            "top": sorted(top, key=lambda x: -x[1])[:5]}


def busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def one_run(wheel: Path, n_busy: int, tmp: Path) -> dict:
    base = tmp / f"busy{n_busy}"
    base.mkdir()
    venv.create(base / "venv", with_pip=True)
    bindir = base / "venv" / "bin"
    (base / "home").mkdir()
    (base / "work").mkdir()
    env = {k: v for k, v in os.environ.items() if k.startswith("PIP_")}
    env.update(PATH=str(bindir), HOME=str(base / "home"), LANG="C.UTF-8", TMPDIR=str(base))
    hogs = busy(n_busy)
    try:
        t0 = time.monotonic()
        r = subprocess.run([str(bindir / "pip"), "install", "-q", "--log", str(base / "pip.log"), str(wheel.resolve())],
                           cwd=base / "work", env=env, capture_output=True, text=True)
        t1 = time.monotonic()
        if r.returncode != 0:
            raise SystemExit(r.stdout[-3000:] + r.stderr[-3000:])
        r = subprocess.run([str(bindir / "python"), "-X", "importtime", "-m", "imubench", "calibrate", "--sim",
                            "--dir", str(base / "work" / "s")], cwd=base / "work", env=env, capture_output=True,
                           text=True)
        t2 = time.monotonic()
        load = os.getloadavg()[0]
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    if r.returncode != 0 or "calibration PASSED" not in r.stdout:
        raise SystemExit(r.stdout[-3000:] + r.stderr[-3000:])
    site, = (base / "venv" / "lib").glob("python3*/site-packages")
    return {"busy": n_busy, "load": load, "pip_s": t1 - t0, "session_s": t2 - t1, "total_s": t2 - t0,
            **pip_phases(base / "pip.log"), **import_profile(r.stderr), "largest": largest_packages(site)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--wheel", type=Path, help="the wheel to install (default: build one from this tree)")
    ap.add_argument("--busy", type=int, action="append", choices=range(0, 9), metavar="N",
                    help="busy processes beside the install (repeatable; default: 0 and 2)")
    add_arguments(ap)
    a = ap.parse_args()
    if a.wheel is not None and not a.wheel.is_file():
        print(f"wheel_install: no wheel {a.wheel}", file=sys.stderr)
        return 2
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
        size_mb = wheel.stat().st_size / 1e6
        print(f"wheel {wheel.name}: {size_mb:.2f} MB")
        rows = []
        for n in a.busy or [0, 2]:
            x = one_run(wheel, n, base)
            rows.append(x)
            rest = x["session_s"] - x["imports_s"]
            print(f"\n{n} busy processes (load average {x['load']:.1f} on {os.cpu_count()} cores):")
            print(f"  pip install: {x['pip_s']:.1f} s = resolve and fetch {x['resolve_fetch_s']:.1f} s "
                  f"+ unpack and byte-compile {x['install_s']:.1f} s (+ pip's start and exit)")
            print("  largest installed: " + ", ".join(f"{d} {mb:.0f} MB" for d, mb in x["largest"]))
            print(f"  first session to PASSED: {x['session_s']:.1f} s = imports {x['imports_s']:.1f} s "
                  f"(of which matplotlib's font cache {x['font_cache_s']:.1f} s) + the session {rest:.1f} s")
            print("  largest imports: " + ", ".join(f"{m} {s:.2f} s" for m, s in x["top"]))
            print(f"  from pip install to the first passed session: {x['total_s']:.1f} s")
        md = ("| busy processes | load average | `pip install` (resolve+fetch / unpack+compile) "
              "| session to PASSED (imports / session) | `pip install` to the first passed session |\n"
              "|---|---|---|---|---|\n")
        for x in rows:
            md += (f"| {x['busy']} | {x['load']:.1f} | {x['pip_s']:.1f} s ({x['resolve_fetch_s']:.1f} / "
                   f"{x['install_s']:.1f}) | {x['session_s']:.1f} s ({x['imports_s']:.1f} / "
                   f"{x['session_s'] - x['imports_s']:.1f}) | {x['total_s']:.1f} s |\n")
        print("\n" + md, end="")
        publish("wheel_install", md, {"wheel": f"{wheel.name} {size_mb:.2f} MB"}, enabled=not a.no_publish)
    return 0


if __name__ == "__main__":
    sys.exit(main())
