"""`python -m imubench` is the `imubench` command."""
from imubench.cli.main import entry

entry()
