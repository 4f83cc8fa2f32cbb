"""The layers of the host package (docs/architecture.md), checked by import-linter (.importlinter).

The real tree must keep every contract; a copy of it with one rule broken on purpose must make
`lint-imports` fail and name the contract, so a contract that cannot fail would be seen here.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINT = Path(sys.executable).with_name("lint-imports")


def lint(root: Path, package_parent: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(package_parent)}
    return subprocess.run([str(LINT), "--no-cache", "--config", str(root / ".importlinter")],
                          cwd=root, env=env, capture_output=True, text=True, timeout=120)


def test_the_tree_keeps_every_contract():
    r = lint(ROOT, ROOT / "host")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout and "BROKEN" not in r.stdout
    # every contract of the configuration was checked (none silently skipped)
    contracts = (ROOT / ".importlinter").read_text().count("[importlinter:contract:")
    assert contracts >= 5 and r.stdout.count("KEPT") == contracts


BREAKS = [
    # (file to append to, the line, the contract that must fail)
    ("analysis/allan.py", "from imubench.device import link", "Pure numerics"),
    ("calib/static.py", "import sqlite3", "Pure numerics"),
    ("wire/decoder.py", "from imubench.results import atomic", "Layers"),
    ("results/history.py", "import serial", "Only device touches a serial port"),
    ("procedures/closure.py", "import matplotlib", "Only results draws"),
    ("cli/__init__.py", "import imubench.pytest_plugin", "Layers"),
    ("procedures/session.py", "from imubench.calib import acceptance", "One front door for a fit"),
    ("procedures/from_file.py", "from imubench.calib.recording_gyro import Note", "One front door for a fit"),
    ("device/sim_resource.py", "from imubench.device import sim_drivers", "The virtual bench: strategy over drivers"),
    ("device/sim_drivers.py", "import subprocess", "Bench drivers talk, they start no process"),
]


@pytest.mark.parametrize("path,line,contract", BREAKS, ids=[b[0] + ": " + b[1] for b in BREAKS])
def test_a_broken_rule_fails(tmp_path, path, line, contract):
    pkg = tmp_path / "imubench"
    shutil.copytree(ROOT / "host" / "imubench", pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / ".importlinter", tmp_path / ".importlinter")
    with open(pkg / path, "a") as f:
        f.write(f"\n{line}  # noqa: E402,F401 - broken on purpose by tests/repo/test_architecture.py\n")
    r = lint(tmp_path, tmp_path)
    assert r.returncode != 0, r.stdout
    broken = [ln for ln in r.stdout.splitlines() if ln.endswith("BROKEN")]
    assert any(ln.startswith(contract) for ln in broken), r.stdout


def test_a_circle_fails(tmp_path):
    """Two sibling packages importing each other (results -> procedures and back) is a circle."""
    pkg = tmp_path / "imubench"
    shutil.copytree(ROOT / "host" / "imubench", pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / ".importlinter", tmp_path / ".importlinter")
    with open(pkg / "results" / "report.py", "a") as f:
        f.write("\nfrom imubench.procedures import session  # noqa: E402,F401 - a circle on purpose\n")
    r = lint(tmp_path, tmp_path)
    assert r.returncode != 0
    assert "No circle anywhere" in r.stdout and "BROKEN" in r.stdout
