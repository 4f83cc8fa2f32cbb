"""The `imubench` command line run in the test's own process, for the cases where a subprocess
adds nothing but an interpreter start and the imports (about a second of CPU each).

run_main(argv, ...) calls the entry point `python -m imubench` calls, imubench.cli.main, with the
working directory, environment and empty stdin a subprocess would get, and returns what a
subprocess returns (exit code, stdout, stderr). What only a process boundary shows (the exit
status of the interpreter, output printed at exit, a traceback from an exception that escaped
main) stays covered by at least one subprocess run of the same behaviour in each test module;
here an exception escaping main() fails the test, and a warning the run emits is written to
stderr as Python's default filters would show it (DeprecationWarning, PendingDeprecationWarning,
ImportWarning and ResourceWarning are hidden outside __main__), so a test that wants an empty
stderr still sees it."""
from __future__ import annotations

import io
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

HIDDEN_BY_DEFAULT = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def run_main(argv, monkeypatch, capsys, *, cwd: Path | None = None, env: dict | None = None,
             unset: tuple = ()) -> subprocess.CompletedProcess:
    """imubench.cli.main(argv) in cwd, with env set and the names in unset removed from the
    environment (TMPDIR among them is read again, as a new process reads it)."""
    from imubench.cli import main as imubench
    for k in unset:
        monkeypatch.delenv(k, raising=False)
    for k, v in (env or {}).items():
        monkeypatch.setenv(k, str(v))
    monkeypatch.setattr(tempfile, "tempdir", None)
    if cwd is not None:
        monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        code = imubench([str(a) for a in argv])
    out, err = capsys.readouterr()
    shown = [w for w in caught if not issubclass(w.category, HIDDEN_BY_DEFAULT)]
    err += "".join(warnings.formatwarning(w.message, w.category, w.filename, w.lineno) for w in shown)
    return subprocess.CompletedProcess(list(argv), code, out, err)
