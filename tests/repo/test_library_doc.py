"""docs/library.md's example runs as written (a doctest, from the repository's root)."""
from __future__ import annotations

import doctest
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_library_md_examples_run(monkeypatch):
    monkeypatch.chdir(ROOT)
    res = doctest.testfile(str(ROOT / "docs" / "library.md"), module_relative=False,
                           optionflags=doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert res.attempted >= 20, res
    assert res.failed == 0, res
