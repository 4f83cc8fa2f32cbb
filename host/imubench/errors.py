"""The base of every error a user can act on (the bottom layer: imports nothing).

`str(e)` says what happened and, after "; ", what to do. The command line prints such an
error as one line, `imubench CMD: error: <str(e)>`, and exits 1 (imubench.cli.common).
Anything else that escapes a command is a bug and is reported as one.
"""


class ImubenchError(Exception):
    """A failure the user can act on (a wrong file, a device that refuses, a fit that cannot
    be observed); the message names the thing and the remedy."""


class NotACapture(ImubenchError):
    """A file that holds no imubench frames (or not the samples asked for)."""
