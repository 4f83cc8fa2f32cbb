"""Shared fixtures. C programs are built through the top-level Makefile, the same way
`make test` builds them, so a test never runs a stale binary."""
from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import tempfile
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

# The suite never reads or writes the user's own data: the default history database
# (platformdirs' user data directory) goes to a folder of this test run, for every worker and
# every command a test starts. A database a newer imubench left in ~/.local/share must not
# fail the suite, nor the suite fill it.
if "IMUBENCH_TEST_DATA_HOME" not in os.environ:
    os.environ["IMUBENCH_TEST_DATA_HOME"] = tempfile.mkdtemp(prefix="imubench-test-data-")
os.environ["XDG_DATA_HOME"] = os.environ["IMUBENCH_TEST_DATA_HOME"]
os.environ.pop("IMUBENCH_DB", None)

# Tests send Ctrl-C (SIGINT) to commands they start and expect them to stop. A shell without job
# control starts a background job (`make test &`, a CI step run that way) with SIGINT ignored, and
# a child inherits an ignored signal across exec: such a command never sees the Ctrl-C and runs
# to its end (test_warmup's Ctrl-C test then failed with exit 0). The suite's processes take
# SIGINT as Python does by default, so that the commands they start do too.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

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


CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium for the station page tests (Debian's chromium, installed by `make
    system-deps`): a missing browser fails the test, it never skips it."""
    if not CHROMIUM.is_file():
        pytest.fail("chromium is missing: `make system-deps` installs Debian's chromium (SYSTEM_PKGS)")
    from playwright.sync_api import sync_playwright
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS)
        try:
            yield b
        finally:
            b.close()


# The heaviest modules first. `make test` runs pytest-xdist with --dist loadscope (a module stays on
# one worker) and --no-loadscope-reorder (the workers take modules in collection order), so this
# order is the schedule: longest first (Graham's LPT rule), and no worker is left at the end with
# a two-minute module while the others are idle. The seconds come from a whole run (JUnit report,
# tools/test-weights.py); a module not listed yet counts half a second a test.
MODULE_SECONDS = ROOT / "tests" / "module_seconds.json"


def pytest_collection_modifyitems(session, config, items):
    import json
    try:
        seconds = json.loads(MODULE_SECONDS.read_text())
    except (OSError, ValueError) as e:
        raise pytest.UsageError(f"{MODULE_SECONDS}: {e} (rewrite it with tools/test-weights.py)") from e
    count: dict[str, int] = {}
    for item in items:
        m = item.nodeid.split("::")[0]
        count[m] = count.get(m, 0) + 1
    weight = {m: float(seconds.get(m, 0.5 * n)) for m, n in count.items()}
    first_seen = {m: i for i, m in enumerate(count)}
    items.sort(key=lambda it: (-weight[it.nodeid.split("::")[0]], first_seen[it.nodeid.split("::")[0]]))
