"""`python -m imubench` is the `imubench` command."""
import sys

from imubench.cli import main

sys.exit(main())
