"""The static check `make test` runs first (ruff, configured in pyproject.toml): the tree passes
it, and it does fail on what issue 32 shipped (an undefined name reaching a user as an internal
error) and on an unused import, so a configuration that checks nothing would be seen here."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUFF = Path(sys.executable).with_name("ruff")


def ruff(*paths, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([str(RUFF), "check", "--no-cache", "--config", str(ROOT / "pyproject.toml"), *map(str, paths)],
                          cwd=cwd, capture_output=True, text=True, timeout=120)


def test_the_tree_passes_the_static_check():
    r = ruff("host", "bench", "tests")
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_static_check_fails_on_an_undefined_name_and_an_unused_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n\n\ndef run(a):\n    return f\"imubench-file-{path.stem}\"\n")
    r = ruff(bad, cwd=tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "F821" in r.stdout and "`path`" in r.stdout and "F401" in r.stdout, r.stdout
