"""Files that are either the old or the new version, never half written: a crash mid-write
(power, Ctrl-C, a lost link mid-session) must not cost the user the results on disk."""
from __future__ import annotations

import json
import os
from pathlib import Path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write text to path via a temporary file beside it, flushed to the disk, then renamed
    over path (os.replace is atomic on POSIX and Windows)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def write_json_atomic(path: str | os.PathLike, obj) -> Path:
    """json.dumps(obj, indent=1) written with write_text_atomic."""
    return write_text_atomic(path, json.dumps(obj, indent=1))
