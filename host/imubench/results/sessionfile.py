"""A calibration session's state file, DIR/session.json: its schema version and the one reader
every part uses (the session resuming, the report), so a damaged or foreign file is named the
same way everywhere. The session rewrites it atomically (results.atomic) after every pose."""
from __future__ import annotations

import json
from pathlib import Path

from imubench.errors import ImubenchError

SESSION_SCHEMA = 1
NAME = "session.json"


class SessionFileError(ImubenchError):
    """session.json is missing, damaged, or of another schema; the message says which."""


def load_state(directory) -> dict:
    """The content of DIR/session.json, checked to be a session of this schema."""
    path = Path(directory) / NAME
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SessionFileError(f"{directory} holds no {NAME}: not a calibration session directory "
                               "(the --dir of imubench calibrate)") from None
    except IsADirectoryError:
        raise SessionFileError(f"{path} is a directory, not a session file") from None
    try:
        state = json.loads(text)
    except ValueError as e:
        raise SessionFileError(f"{path} is damaged (not JSON: {e}); the raw captures beside it are intact: "
                               "start a new session, or restore the file") from None
    if not isinstance(state, dict):
        raise SessionFileError(f"{path} is damaged (a JSON {type(state).__name__}, not a session)")
    if state.get("schema") != SESSION_SCHEMA:
        raise SessionFileError(f"{path} has session schema {state.get('schema')!r}; this imubench reads "
                               f"{SESSION_SCHEMA}")
    for key, kind in (("started", str), ("config", dict), ("poses", list)):
        if not isinstance(state.get(key), kind):
            raise SessionFileError(f"{path} is damaged: {key!r} must be a {kind.__name__}, "
                                   f"got {type(state.get(key)).__name__}")
    return state
