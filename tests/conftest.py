"""Shared fixtures. C programs are built through the top-level Makefile, the same way
`make test` builds them, so a test never runs a stale binary."""
from __future__ import annotations

import fcntl
import subprocess
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parent.parent
HOST_BUILD = ROOT / "build" / "host"


def make(*targets: str) -> None:
    """Build targets through the Makefile; one make at a time (pytest-xdist runs tests in
    several processes, and two makes building one file would race)."""
    (ROOT / "build").mkdir(exist_ok=True)
    with open(ROOT / "build" / ".tests-make.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        r = subprocess.run(["make", "-s", "-C", str(ROOT), *targets], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"make {' '.join(targets)} failed:\n{r.stdout}\n{r.stderr}")


@pytest.fixture(scope="session")
def c_harness() -> Path:
    """The C vector harness (tests/c/vector_harness.c), built for the host."""
    make("build/host/tests/vector_harness")
    return HOST_BUILD / "tests" / "vector_harness"
