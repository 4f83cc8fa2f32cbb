"""The one `imubench` command line (see cli.main)."""
from imubench.cli.main import main

__all__ = ["main"]
