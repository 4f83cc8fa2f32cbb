"""The errors a procedure raises to stop: the message says why and what to do."""
from __future__ import annotations

from imubench.errors import ImubenchError


class SessionAborted(ImubenchError, RuntimeError):
    """The session cannot go on; the message says why and what to do."""
