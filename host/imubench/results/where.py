"""Where the calibration history lives by default, without importing the database layer:
every command's --help names it, and SQLAlchemy takes about 0.3 s to import (results.db
and results.history re-export these)."""
from __future__ import annotations

from pathlib import Path

ENV_DB = "IMUBENCH_DB"      # the environment variable naming the database (path or URL)


def default_path() -> Path:
    """The history file when neither --db nor $IMUBENCH_DB names one: history.sqlite in the
    user's data folder (platformdirs: ~/.local/share/imubench on Linux)."""
    import platformdirs
    return Path(platformdirs.user_data_dir("imubench")) / "history.sqlite"
