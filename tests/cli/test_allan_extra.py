"""allantools is the allan extra, not a dependency (pyproject.toml says why): without it
`imubench allan` stops with one line naming the extra, before it records anything."""
from __future__ import annotations

import sys

from imubench.cli.main import main as imubench


def test_allan_without_allantools_names_the_extra(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "allantools", None)       # import allantools -> ImportError
    rc = imubench(["allan", "--port", "socket://127.0.0.1:9", "--duration", "1", "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert err.strip().splitlines() == ["imubench allan: error: the Allan analysis needs allantools, the allan extra: "
                                        "pip install 'imubench[allan]' (or pip install allantools)"]
    assert not (tmp_path / "a").exists()                       # nothing recorded, no port opened
