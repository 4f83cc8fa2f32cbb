"""Temporary folders that name their owner process, so that the folders of a host killed with
SIGKILL are removed by the next one that starts (the virtual device's serial links, flash
files and logs live in one)."""
from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile

OWNER_FILE = "owner.json"      # in a virtual device's temporary folder: the process that made it


def _start_time(pid: int) -> str | None:
    """The start time of process pid (Linux: /proc/PID/stat field 22, clock ticks since boot), so
    that a pid reused by another process is not taken for the owner; None where unknown."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[19].decode()
    except (OSError, IndexError):
        return None


def _alive(owner: dict) -> bool:
    pid = owner.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True                     # another user's live process
    started = owner.get("started")
    return started is None or _start_time(pid) in (None, started)


def owned_tmpdir(prefix: str) -> str:
    """A fresh temporary folder (mkdtemp) that names its owner (this process: pid and start
    time, OWNER_FILE). A host killed with SIGKILL cannot remove it, so every new one first
    removes the folders of this prefix whose owner is dead (sweep_dead_tmpdirs): a folder is
    never left behind for longer than until the next virtual device starts."""
    sweep_dead_tmpdirs(prefix)
    d = tempfile.mkdtemp(prefix=prefix)
    with open(os.path.join(d, OWNER_FILE), "w", encoding="utf-8") as f:
        json.dump({"pid": os.getpid(), "started": _start_time(os.getpid())}, f)
    return d


def sweep_dead_tmpdirs(prefix: str, root: str | None = None) -> list[str]:
    """Remove the folders root/PREFIX* of this user whose OWNER_FILE names a process that is no
    longer alive; folders without an owner file (another program's, or being created) stay.
    Returns the folders removed."""
    root = root or tempfile.gettempdir()
    removed = []
    try:
        names = [n for n in os.listdir(root) if n.startswith(prefix)]
    except OSError:
        return removed
    for n in names:
        d = os.path.join(root, n)
        try:
            st = os.lstat(d)
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
                continue
            with open(os.path.join(d, OWNER_FILE), encoding="utf-8") as f:
                owner = json.load(f)
        except (OSError, ValueError):
            continue
        if isinstance(owner, dict) and not _alive(owner):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed
