"""Files that are either the old or the new version, never half written: a crash mid-write
(power, Ctrl-C, a lost link mid-session) must not cost the user the results on disk. Every
result file, report, plot and export is written through here (or imubench.files directly),
so none follows a symlink it did not create (imubench.files.atomic_output)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from imubench.files import atomic_output, write_text


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write text to path via a fresh temporary file beside it, flushed to the disk, then
    renamed over path (imubench.files.atomic_output: a symlink at path is refused)."""
    return write_text(path, text)


def write_json_atomic(path: str | os.PathLike, obj, indent: int | None = 1) -> Path:
    """json.dumps(obj, indent=indent) written with write_text_atomic (indent=None: one line,
    by json's C encoder, about 4x faster than its pure-Python indenting one)."""
    return write_text_atomic(path, json.dumps(obj, indent=indent))


def save_figure(fig, path: str | os.PathLike, **kw) -> Path:
    """fig.savefig into path atomically (the format from the suffix unless given)."""
    path = Path(path)
    kw.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    with atomic_output(path, binary=True) as fh:
        fig.savefig(fh, **kw)
    return path
