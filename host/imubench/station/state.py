"""What the station's pages show, keyed per device: one DeviceBoard per device, so that a
multi-board fixture can show one column per board. Thread-safe: the session threads write,
every change calls the on_change callbacks (the server wakes its event streams on its event
loop, no thread each) and they send a snapshot. Also who is who: the identities the server
issued (one per browser), which one drives each device, how many event streams each has
open; each bounded (MAX_*)."""
from __future__ import annotations

import copy
import secrets
import threading
import time
from dataclasses import asdict, dataclass, field

OWNER_GRACE_S = 20.0        # an owner with no page open for this long gives the device up
MAX_CLIENTS = 32            # browsers (identities the server issued) known at once
MAX_PAGE_BOARDS = 16        # devices pages may add (a command's own boards are not counted)
MAX_STREAMS = 32            # event streams open at once for pages that own nothing
MAX_STREAMS_PER_CLIENT = 8  # one browser's tabs


class Refused(Exception):
    """A bound is reached (too many browsers, devices or streams): says which."""


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
    warmup: dict = field(default_factory=dict)        # a temperature warm-up: config, progress (run_warmup's
                                                      # on_progress), result, dir; {} if none ran
    owner: str | None = field(default=None, repr=False)
    owner_seen: float = 0.0
    by_page: bool = field(default=False, repr=False)  # added by a page's claim (bounded), not by a command


class StationState:
    def __init__(self):
        self._lock = threading.Condition()
        self.version = 0
        self.boards: dict[str, DeviceBoard] = {}
        self.mode = "idle"                    # "idle": the page chooses; "session": started by the command
        self.sim_available = True             # the page may choose the virtual bench
        self.closed = False                   # the server is stopping: event streams end
        self.clients: dict[str, float] = {}   # identity the server issued -> last seen (monotonic)
        self.streams: dict[str | None, int] = {}   # open event streams per identity (None: no identity)
        self._watchers: list = []             # called (under the lock) at every change: async streams wake
        self.plate: dict = {}                 # a station session's plate: its last move, the deadlines

    def on_change(self, fn) -> None:
        """Call fn() at every change (from whichever thread makes it; keep it short)."""
        with self._lock:
            self._watchers.append(fn)

    def close(self) -> None:
        """Wake every event stream and let it end (before the web server stops, so that no
        open page holds the shutdown up)."""
        with self._lock:
            self.closed = True
            self._bump()

    # ----------------------------------------------------------------- writing
    def board(self, key: str) -> DeviceBoard:
        """The device's board, made if new (the command's boards: not bounded)."""
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
        for fn in self._watchers:
            fn()

    # ----------------------------------------------------------------- who
    def new_client(self) -> str:
        """A page's session (issued only for a launch secret, security.Launch; sent back in a
        header, never taken from a body, a URL or a cookie). At most MAX_CLIENTS: the longest
        unseen one that owns nothing and has no page open goes."""
        with self._lock:
            if len(self.clients) >= MAX_CLIENTS:
                idle = [t for t in self.clients if not self.streams.get(t) and not self._owns_any(t)]
                if not idle:
                    raise Refused(f"{MAX_CLIENTS} browsers are driving or watching this station already")
                del self.clients[min(idle, key=self.clients.__getitem__)]
            token = secrets.token_urlsafe(32)
            self.clients[token] = time.monotonic()
            return token

    def client(self, token: str | None) -> str | None:
        """The identity if this server issued it (and still knows it), else None."""
        with self._lock:
            if token and token in self.clients:
                self.clients[token] = time.monotonic()
                return token
            return None

    def _owns_any(self, token: str) -> bool:
        return any(b.owner == token for b in self.boards.values())

    def _present(self, token: str | None) -> bool:
        return bool(token) and self.streams.get(token, 0) > 0

    # ----------------------------------------------------------------- owning
    def claim(self, key: str, token: str, new_ok: bool = True) -> str | None:
        """The token if it owns the device now: it owned it already, or the device is free,
        or its owner is gone (no page open and not seen for OWNER_GRACE_S); else None
        (read-only). An owner with a page open keeps its device, whatever others do.
        new_ok: a device not known yet may be added (at most MAX_PAGE_BOARDS of them)."""
        if not token:
            raise ValueError("claim needs the identity the server issued")
        with self._lock:
            b = self.boards.get(key)
            if b is None:
                if not new_ok:
                    return None
                b = self._new_page_board(key)
            now = time.monotonic()
            if b.owner is not None and b.owner != token and (
                    self._present(b.owner) or now - b.owner_seen < OWNER_GRACE_S):
                return None
            if b.owner != token:
                b.owner = token
                self._bump()
            b.owner_seen = now
            return b.owner

    def _new_page_board(self, key: str) -> DeviceBoard:
        page_boards = [b for b in self.boards.values() if b.by_page]
        if len(page_boards) >= MAX_PAGE_BOARDS:
            now = time.monotonic()
            idle = [b for b in page_boards if b.status == "idle" and not b.session_dir
                    and not self._present(b.owner) and now - b.owner_seen >= OWNER_GRACE_S]
            if not idle:
                raise Refused(f"this station shows {MAX_PAGE_BOARDS} devices already: "
                              "restart it to clear the list")
            del self.boards[idle[0].key]
        b = self.boards[key] = DeviceBoard(key=key, by_page=True)
        return b

    def owns(self, key: str, token: str | None) -> bool:
        with self._lock:
            b = self.boards.get(key)
            return bool(b is not None and token and b.owner == token)

    def stream_opened(self, token: str | None) -> None:
        """An event stream opens (Refused past the bounds; a browser that owns a device always
        gets one, up to MAX_STREAMS_PER_CLIENT)."""
        with self._lock:
            mine = self.streams.get(token, 0)
            if token and mine >= MAX_STREAMS_PER_CLIENT:
                raise Refused(f"this browser has {mine} pages of the station open already: close some")
            others = sum(n for t, n in self.streams.items() if not (t and self._owns_any(t)))
            if not (token and self._owns_any(token)) and others >= MAX_STREAMS:
                raise Refused(f"{others} pages are watching this station already: close some")
            self.streams[token] = mine + 1
            self._seen(token)

    def stream_closed(self, token: str | None) -> None:
        """An event stream ended: its owner's grace time starts now."""
        with self._lock:
            n = self.streams.get(token, 0) - 1
            if n > 0:
                self.streams[token] = n
            else:
                self.streams.pop(token, None)
            self._seen(token)

    def seen(self, token: str | None) -> None:
        """An owner's page is still there."""
        with self._lock:
            self._seen(token)

    def _seen(self, token: str | None) -> None:
        if not token:
            return
        now = time.monotonic()
        if token in self.clients:
            self.clients[token] = now
        for b in self.boards.values():
            if b.owner == token:
                b.owner_seen = now

    # ----------------------------------------------------------------- reading
    def snapshot(self, token: str | None = None) -> dict:
        with self._lock:
            boards = []
            now = time.monotonic()
            for b in self.boards.values():
                d = asdict(b)
                d.pop("owner")
                d.pop("owner_seen")
                d.pop("by_page")
                d["yours"] = bool(token and b.owner == token)
                # driven by a page still there: a device whose driver is gone is free to claim
                d["owned"] = b.owner is not None and (self._present(b.owner) or now - b.owner_seen < OWNER_GRACE_S)
                boards.append(copy.deepcopy(d))
            return {"version": self.version, "mode": self.mode, "sim": self.sim_available, "boards": boards,
                    "plate": copy.deepcopy(self.plate)}

    def set_plate(self, **kw) -> None:
        """A station session's plate: what it presents now (fixture.Plate's move), the deadlines."""
        with self._lock:
            self.plate.update(kw)
            self._bump()
