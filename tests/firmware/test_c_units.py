"""Builds and runs every C unit test (tests/c/test_*.c, linked against the portable
firmware code built for the host). Each prints 'N passed, N failed' and exits non-zero on
a failure."""
import subprocess

import pytest
from conftest import HOST_BUILD, ROOT, make

C_TESTS = sorted(p.stem for p in (ROOT / "tests" / "c").glob("test_*.c"))


@pytest.fixture(scope="module")
def built():
    make("c-tests")


@pytest.mark.parametrize("name", C_TESTS)
def test_c_unit(built, name):
    r = subprocess.run([str(HOST_BUILD / "tests" / name)], capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert " passed, 0 failed" in r.stdout.splitlines()[-1]
