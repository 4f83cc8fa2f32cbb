"""What the station's pages show, keyed per device: one DeviceBoard per device, so that a
multi-board fixture can show one column per board. Thread-safe: the session threads write,
the server's event streams wait for a new version and send a snapshot."""
from __future__ import annotations

import copy
import secrets
import threading
import time
from dataclasses import asdict, dataclass, field

OWNER_GRACE_S = 20.0        # an owner page not heard from for this long gives the device up


@dataclass
class DeviceBoard:
    key: str                                  # the device: its port URL, or "sim" for the virtual bench
    status: str = "idle"                      # idle | running | done | failed | interrupted
    device: dict = field(default_factory=dict)        # board, uid once known
    config: dict = field(default_factory=dict)        # the session's options
    session_dir: str | None = None
    plan: list = field(default_factory=list)          # cards: name, words, direction, state, ...
    method: str | None = None
    phase: str = ""                                   # rest | poses | turns | fit | write | verify | end
    live: dict = field(default_factory=dict)
    targets: dict = field(default_factory=dict)       # sigmas, targets, reached
    steps: list = field(default_factory=list)         # kind, text, state
    turns: list = field(default_factory=list)         # axis, rate_dps, duration_s, state
    log: list = field(default_factory=list)
    result: dict | None = None                        # verdict, parameters, report link
    error: str | None = None
    resumable: bool = False
    done_seq: int = 0                                 # how many poses are done (order of capture)
    suggested: str | None = None                      # the missing attitude that helps the fit most
    fixture: dict = field(default_factory=dict)       # a station session's board: slot, stage, state,
                                                      # message, progress, reason, waiting (fixture.BoardStatus)
    owner: str | None = field(default=None, repr=False)
    owner_seen: float = 0.0


class StationState:
    def __init__(self):
        self._lock = threading.Condition()
        self.version = 0
        self.boards: dict[str, DeviceBoard] = {}
        self.mode = "idle"                    # "idle": the page chooses; "session": started by the command
        self.sim_available = True             # the page may choose the virtual bench
        self.closed = False                   # the server is stopping: event streams end
        self.plate: dict = {}                 # a station session's plate: its last move, the deadlines

    def close(self) -> None:
        """Wake every event stream and let it end (before the web server stops, so that no
        open page holds the shutdown up)."""
        with self._lock:
            self.closed = True
            self._lock.notify_all()

    # ----------------------------------------------------------------- writing
    def board(self, key: str) -> DeviceBoard:
        with self._lock:
            if key not in self.boards:
                self.boards[key] = DeviceBoard(key=key)
                self._bump()
            return self.boards[key]

    def update(self, key: str, fn) -> None:
        """Apply fn(board) under the lock and wake every event stream."""
        with self._lock:
            b = self.boards.get(key) or self.boards.setdefault(key, DeviceBoard(key=key))
            fn(b)
            self._bump()

    def _bump(self) -> None:
        self.version += 1
        self._lock.notify_all()

    # ----------------------------------------------------------------- owning
    def claim(self, key: str, token: str | None) -> str | None:
        """The token that owns the device now: the given one if it owns it already or the
        device is free (a new token when none is given), else None (read-only)."""
        with self._lock:
            b = self.boards.get(key) or self.boards.setdefault(key, DeviceBoard(key=key))
            now = time.monotonic()
            if b.owner is not None and b.owner != token and now - b.owner_seen < OWNER_GRACE_S:
                return None
            if b.owner is None or b.owner != token:
                b.owner = token or secrets.token_urlsafe(16)
                self._bump()
            b.owner_seen = now
            return b.owner

    def owns(self, key: str, token: str | None) -> bool:
        with self._lock:
            b = self.boards.get(key)
            return bool(b is not None and token and b.owner == token)

    def seen(self, token: str | None) -> None:
        """An owner's page is still there (its event stream is open)."""
        if not token:
            return
        with self._lock:
            now = time.monotonic()
            for b in self.boards.values():
                if b.owner == token:
                    b.owner_seen = now

    # ----------------------------------------------------------------- reading
    def snapshot(self, token: str | None = None) -> dict:
        with self._lock:
            boards = []
            for b in self.boards.values():
                d = asdict(b)
                d.pop("owner")
                d.pop("owner_seen")
                d["yours"] = bool(token and b.owner == token)
                d["owned"] = b.owner is not None
                boards.append(copy.deepcopy(d))
            return {"version": self.version, "mode": self.mode, "sim": self.sim_available, "boards": boards,
                    "plate": copy.deepcopy(self.plate)}

    def set_plate(self, **kw) -> None:
        """A station session's plate: what it presents now (fixture.Plate's move), the deadlines."""
        with self._lock:
            self.plate.update(kw)
            self._bump()

    def wait(self, version: int, timeout: float) -> int:
        with self._lock:
            self._lock.wait_for(lambda: self.version != version or self.closed, timeout=timeout)
            return self.version
