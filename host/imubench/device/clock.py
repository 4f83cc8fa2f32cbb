"""The clock a host waits by: the wall clock for a real port, device time for a virtual device
in lockstep.

Every wait of the host against a device (a reply, samples, stillness, a deadline) goes
through the clock of its link (`Link.clock`):

    WallClock       a real board, or a virtual device on the real-time clock: time.monotonic,
                    time.sleep, condition waits (the device runs whatever the host does)
    LockstepClock   a virtual device started with clock="lockstep" (the default of
                    VirtualBench): the device is frozen except while the host waits on it.
                    A wait grants device time in steps ("run" on the control channel,
                    firmware/boards/sim/sim_control.c); after each step every link byte the
                    device produced up to then has arrived and been decoded before the host
                    looks again. What the host sees therefore depends on device time only,
                    not on how busy the machine is: the same seed gives the same bytes.

Timeouts given to a LockstepClock are device seconds. The wall-clock limits that remain
(a device process that hangs) are generous guards, not timing. A frozen device (its process
stopped, its sockets open) never finishes a grant: its device time stands still, so no
device-time deadline of its own can pass; the wall-clock guard of its clock is then the
board's deadline. It is per clock (`guard_wall_s`, default GRANT_GUARD_WALL_S), so a station
session sets each board's to that board's link timeout (procedures.fixture): a frozen board
fails alone, at its first grant past the guard, while the others' grants go on.

The link finds the clock of a virtual device by its URL: VirtualBench registers its clock
under its port's URL (`register`), Link looks it up (`for_url`). Processes started while the
bench runs (a command given `--port URL` in a subprocess) find it too: `register` also lists
the URL with its control channel in the environment variable IMUBENCH_LOCKSTEP, and there
`for_url` opens a control connection of its own (one process grants at a time: the one that
waits). Any other URL has the wall clock.
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time
from typing import Callable

from imubench.errors import ImubenchError

__all__ = ["ClockError", "WallClock", "LockstepClock", "WALL", "for_url", "register", "unregister"]

#: {port URL: {"control": "HOST:PORT", "speed": X}} of the lockstep devices of the processes above
ENV = "IMUBENCH_LOCKSTEP"


class ClockError(ImubenchError, RuntimeError):
    """The lockstep device's control channel failed or refused a grant."""

#: wall-clock guard on one grant of device time (a hung simulator, not a slow one), s
GRANT_GUARD_WALL_S = 600.0
#: wall-clock guard on the link bytes of a finished grant reaching the host, s
BYTES_GUARD_WALL_S = 120.0


class WallClock:
    """Real time: for real boards and the real-time virtual device."""

    lockstep = False

    def now(self) -> float:
        """Seconds on this clock (only differences mean anything)."""
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def wait_for(self, cond: Callable[[], bool], timeout_s: float, condvar: threading.Condition,
                 step_s: float | None = None, poll_wall_s: float = 0.1) -> bool:
        """Wait (holding nothing) until cond() is true, evaluated under condvar, which the
        producer notifies; False when timeout_s passed first."""
        deadline = time.monotonic() + timeout_s
        with condvar:
            while not cond():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                condvar.wait(min(left, poll_wall_s))
        return True


WALL = WallClock()


class LockstepClock:
    """Device time of a lockstep virtual device (VirtualBench(clock="lockstep")).

    The device is frozen between waits. `run(seconds)` grants it that much device time and
    returns when it has run to it and every link byte it sent up to then has reached the
    attached link's reader. `wait_for` grants in steps until the condition holds."""

    lockstep = True
    #: first and largest step of a wait whose end is not known in advance (an ack), s
    STEP_MIN_S = 0.001
    STEP_MAX_S = 0.1

    def __init__(self, bench, first_request_id: int = 1):
        self.bench = bench                  # has control(cmd, timeout=, **fields) and speed
        self.t_us = 0                       # device time at the last grant's end
        self.link = None                    # the Link on this device's port (its byte counts)
        self.grants = 0
        self._next_request_id = first_request_id    # ids continue across links (no repeats)
        self.guard_wall_s = GRANT_GUARD_WALL_S      # wall s a grant may take beyond its own length
        self._lock = threading.RLock()      # one grant at a time (a presenter's thread and a reader's)

    # ------------------------------------------------------------ the link
    def attach(self, link) -> None:
        """The link now on the device's port; the device time is taken afresh (a process
        started from this one may have run the device meanwhile)."""
        self.link = link
        self.sync()

    def detach(self, link) -> None:
        if self.link is link:
            self.link = None

    def request_id(self) -> int:
        rid = self._next_request_id
        self._next_request_id = rid % 0xFFFF + 1
        return rid

    # ------------------------------------------------------------ time
    def now(self) -> float:
        """Device seconds at the last grant's end (the frozen device's time)."""
        return self.t_us * 1e-6

    def sync(self) -> None:
        """Take the device's time (e.g. after it was started)."""
        with self._lock:
            self.t_us = int(self.bench.control("status", timeout=min(10.0, self.guard_wall_s))["time_us"])

    def run(self, seconds: float, stop: str | None = None, die_tolerance_c: float | None = None) -> dict:
        """Grant `seconds` of device time (with stop: until the wait_idle condition holds,
        at most that long) and return the reply {time_us, link_tx, done}."""
        with self._lock:
            return self._run(seconds, stop, die_tolerance_c)

    def _run(self, seconds: float, stop: str | None, die_tolerance_c: float | None) -> dict:
        until = self.t_us + max(0, int(round(seconds * 1e6)))
        link = self.link
        kw: dict = {"until_us": until, "link_rx": link.bytes_out if link is not None else 0}
        if stop is not None:
            kw["stop"] = stop
        if die_tolerance_c is not None:
            kw["die_tolerance_c"] = float(die_tolerance_c)
        sp = float(self.bench.speed)
        guard = self.guard_wall_s + (seconds / sp if sp > 0 else seconds)
        r = self.bench.control("run", timeout=guard, **kw)
        self.t_us = int(r["time_us"])
        self.grants += 1
        if link is not None and link is self.link:
            link.wait_bytes_in(int(r["link_tx"]), BYTES_GUARD_WALL_S)
        return r

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.run(seconds)

    def wait_for(self, cond: Callable[[], bool], timeout_s: float, condvar: threading.Condition,
                 step_s: float | None = None, poll_wall_s: float = 0.1) -> bool:
        """Grant device time until cond() holds (checked under condvar after each grant, when
        every byte sent up to then has arrived); False when timeout_s of device time passed.
        Steps: step_s each, or (None) 1 ms doubling up to 100 ms: a reply comes within a few
        ms, a long wait costs few round trips. The steps depend on nothing but device time."""
        end_us = self.t_us + int(round(timeout_s * 1e6))
        step = step_s if step_s is not None else self.STEP_MIN_S
        while True:
            with condvar:
                if cond():
                    return True
            left = (end_us - self.t_us) * 1e-6
            if left <= 0:
                return False
            self.run(min(step, left))
            if step_s is None:
                step = min(step * 2, self.STEP_MAX_S)


class _Control:
    """A control connection of its own to a lockstep device another process started."""

    def __init__(self, address: str, speed: float):
        self.address = address
        self.speed = float(speed)
        self._sock = self._rfile = None
        self._lock = threading.Lock()
        self._connect()

    def _connect(self) -> None:
        host, _, port = self.address.rpartition(":")
        try:
            self._sock = socket.create_connection((host, int(port)), timeout=10.0)
        except OSError as e:
            raise ClockError(f"cannot reach the virtual device's control channel {self.address}: {e}") from e
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._rfile = self._sock.makefile("rb")

    def _drop(self) -> None:
        for obj in (self._rfile, self._sock):
            try:
                obj.close()
            except (OSError, AttributeError):
                pass
        self._sock = self._rfile = None

    def control(self, _cmd: str, *, timeout: float | None = 10.0, **fields) -> dict:
        with self._lock:
            if self._sock is None:
                self._connect()
            try:
                self._sock.settimeout(timeout)
                self._sock.sendall((json.dumps({"cmd": _cmd, **fields}) + "\n").encode())
                line = self._rfile.readline()
            except OSError as e:
                self._drop()
                raise ClockError(f"the virtual device's control channel {self.address} failed: {e}") from e
            except BaseException:
                # Ctrl-C between the request and its reply: that reply must not answer the
                # next request, so the connection goes and the next one opens afresh
                self._drop()
                raise
        if not line:
            raise ClockError(f"the virtual device closed its control channel {self.address}")
        r = json.loads(line)
        if not r.get("ok"):
            raise ClockError(f"{_cmd}: {r.get('error', 'refused')}")
        return r


_BY_URL: dict[str, LockstepClock] = {}
_BY_URL_LOCK = threading.Lock()


def _env_set(url: str, entry: dict | None) -> None:
    try:
        known = json.loads(os.environ.get(ENV) or "{}")
    except ValueError:
        known = {}
    if entry is None:
        known.pop(url, None)
    else:
        known[url] = entry
    if known:
        os.environ[ENV] = json.dumps(known)
    else:
        os.environ.pop(ENV, None)


def register(url: str, clock: LockstepClock, control: str | None = None) -> None:
    """Make `url` a lockstep device's (control: its control channel "HOST:PORT", for the
    processes this one starts)."""
    with _BY_URL_LOCK:
        _BY_URL[url] = clock
        if control is not None:
            _env_set(url, {"control": control, "speed": float(clock.bench.speed)})


def unregister(clock: LockstepClock) -> None:
    with _BY_URL_LOCK:
        for k in [k for k, v in _BY_URL.items() if v is clock]:
            del _BY_URL[k]
            _env_set(k, None)


def for_url(url: str):
    """The clock of the device on `url`: a lockstep clock registered here or by a process
    above this one (IMUBENCH_LOCKSTEP), else the wall clock."""
    with _BY_URL_LOCK:
        if url in _BY_URL:
            return _BY_URL[url]
        try:
            entry = json.loads(os.environ.get(ENV) or "{}").get(url)
        except ValueError:
            entry = None
        if not isinstance(entry, dict) or "control" not in entry:
            return WALL
        ctl = _Control(str(entry["control"]), float(entry.get("speed", 0.0)))
        t_us = int(ctl.control("status")["time_us"])
        # request ids from the device time: not those the process above used just before
        clock = LockstepClock(ctl, first_request_id=(t_us // 1000) % 0xFFFF + 1)
        clock.t_us = t_us
        _BY_URL[url] = clock
        return clock
