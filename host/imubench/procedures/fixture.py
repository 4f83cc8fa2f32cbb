"""Many boards on one fixture: one station session calibrates every board on the plate.

    imubench calibrate --port URL1 --port URL2 ... [--station-file FILE] [--station ID] [--operator NAME]
    imubench calibrate --sim --sim-boards 4

The boards are mounted on one plate, so they see the same attitudes and the same turntable
motion. Each board runs the ordinary guided session (imubench.procedures.session: health
check, rest, poses, turns, fit, write-back, verification) in its own thread on its own link,
in its own session directory (DIR/slot-K). The plate is shared: a board's session that asks
for its next move (any attitude it still misses, a turn, a verification attitude) waits at
the Plate until every board still running has asked; then the plate makes the move that
serves the most boards (procedures.schedule: the attitudes boards still need first, the most
shared first; turns; verification last), by the operator or on the virtual bench by a
PlatePresenter that moves every virtual device, and the boards it serves go on. Every wait
has a deadline in device time (PLATE_TIMEOUT_S at the plate, POSE_TIMEOUT_S for a presented
attitude): past it that board fails with the stage and the reason. A board that fails
(its link lost, a sensor faulted, its fit refused or out of tolerance, its write-back or
verification failed) leaves the plate with its stage and reason, and the others carry on:
the verdict is per board.

Every board gets a record (schema 2, results.history) with the station, operator, fixture,
slot and port, firmware and host versions, the parameter block before and after, the
measurements with their limits, and the SHA-256 of its raw capture with where it is stored;
a board that failed before it was fitted gets a record with the stage and reason. They are
recorded as each board finishes (the database may be shared with other stations).

Per-board state is published as it changes: `on_event(status)` is called with a dict
(slot, port, uid, stage, state running/passed/failed, message, progress, reason) for a
station page or a log; `FixtureRun.snapshot()` gives all of them at once.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imubench.calib import CalibrationError
from imubench.device.link import Device, LinkError, LinkTimeout
from imubench.errors import ImubenchError
from imubench.procedures.session import (
    Session,
    SessionAborted,
    SessionConfig,
    SimPresenter,
    _jsonable,
    plan_for,
    rotation_to,
)
from imubench.procedures.schedule import PHASES, Need, next_move, still_needed
from imubench.results.atomic import write_json_atomic
from imubench.wire import params as PR
from imubench.wire.ids import board_name, uid_text
from imubench.wire.protocol_gen import ParamsWhich, SampleStatus

RECORD_SCHEMA = 2


@dataclass
class Station:
    """Who and where: goes into every board's record."""
    station_id: str = ""
    operator: str = ""
    fixture: str = ""
    host_version: str = ""

    def __post_init__(self):
        if not self.station_id:
            self.station_id = socket.gethostname()
        if not self.host_version:
            from imubench import __version__
            self.host_version = __version__


@dataclass
class BoardStatus:
    slot: int
    port: str
    uid: str | None = None
    stage: str = "waiting"          # connect, health, rest, poses, turntable, fit, write, verify, record, done
    state: str = "running"          # running | passed | failed
    message: str = ""
    progress: float = 0.0
    reason: str | None = None
    run_id: int | None = None
    directory: str = ""
    waiting: str | None = None      # done with a phase, waiting for the other boards: for whom, till when

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class BoardFailed(Exception):
    """One board cannot go on; the fixture marks it failed and the others carry on."""

    def __init__(self, stage: str, reason: str):
        super().__init__(reason)
        self.stage, self.reason = stage, reason


# ---------------------------------------------------------------- the plate
#: how long a board waits at the plate for what it needs, in device time (the board's own
#: samples), by default: the other boards' attitudes, write-backs and verifications included
PLATE_TIMEOUT_S = 300.0
#: how long a presented attitude may take to be held still, in device time, when the
#: session's config says "wait" (a station session has no wait without an end)
POSE_TIMEOUT_S = 120.0

_PHASE_WORDS = {"pose": "attitudes", "turn": "turntable turns", "verify": "verification"}


class Plate:
    """The fixture all boards share. Each board's session asks for what it needs next (a
    schedule.Need: any of its missing attitudes, a turn, a verification attitude) and waits;
    when every board still running has asked, the plate makes the move schedule.next_move
    picks (the attitudes the boards still need first, the most shared first; then turns;
    verification last) and the boards it serves go on; the others keep waiting. A board that
    stops leaves, and the plate no longer waits for it.

    Every wait has a deadline in device time (`deadline_s`, measured on the waiting board's
    own samples through `clock`): past it the board leaves the plate and its session fails
    with the stage and the reason (BoardFailed); the others go on. The waits are kept in
    `waits` (slot, kind, waited_s, deadline_s, outcome). No polling loop burns a core: a
    waiting board sleeps on a condition, waking 4 times a second to look at its clock."""

    CHECK_S = 0.25

    def __init__(self, mover, slots: list[int], say=lambda s: None, deadline_s: float = PLATE_TIMEOUT_S,
                 on_wait: Callable[[int, str | None], None] | None = None,
                 on_move: Callable[[dict], None] | None = None):
        self.mover = mover
        self.live = set(slots)
        self.needs: dict[int, Need] = {}
        self.args: dict[int, dict] = {}           # slot -> {key: the mover's arguments}
        self.phase: dict[int, str] = {}           # slot -> the kind of its last need
        self.served: dict[int, object] = {}       # slot -> the key presented for it, not yet taken
        self.moves = 0
        self.pose_moves = 0
        self.moving = False
        self.position: dict = {}                  # the plate's last move: kind, key, serves, waiting
        self.waits: list[dict] = []
        self.deadline_s = float(deadline_s)
        self.say = say
        self.on_wait = on_wait
        self.on_move = on_move
        self._wait_text: dict[int, str | None] = {}
        self._cv = threading.Condition()

    # ------------------------------------------------------------ asking
    def request(self, slot: int, need: Need, args: dict, clock: Callable[[], float] | None = None,
                stage: str = "poses", check: Callable[[], None] | None = None):
        """Wait until the plate presents something `need` accepts; returns its key (None when
        this board is no longer on the plate). args: {key: the mover's arguments for it}.
        Raises BoardFailed(stage, why) when the wait passes its deadline (device time), and
        whatever check() raises (a Stop on the page) after leaving the plate."""
        with self._cv:
            if slot not in self.live:
                return None
            self.needs[slot], self.args[slot], self.phase[slot] = need, args, need.kind
            t0 = clock() if clock is not None else None
            waited = 0.0
            self._refresh_waits()
            try:
                while True:
                    if t0 is not None:
                        waited = clock() - t0
                    if slot in self.served:
                        key = self.served.pop(slot)
                        self._log(slot, need, waited, "served")
                        return key
                    if slot not in self.live:
                        self._log(slot, need, waited, "left")
                        return None
                    if not self.moving and set(self.needs) >= self.live:
                        self._move()
                        continue
                    if check is not None:
                        try:
                            check()
                        except BaseException:
                            self._log(slot, need, waited, "stopped")
                            self._drop(slot)
                            raise
                    if t0 is not None and waited > self.deadline_s:
                        why = self._why_late(slot, need, waited)
                        self._log(slot, need, waited, "deadline")
                        self._drop(slot)
                        raise BoardFailed(stage, why)
                    self._cv.wait(self.CHECK_S)
            finally:
                self.needs.pop(slot, None)
                self.args.pop(slot, None)
                self._set_wait(slot, None)

    def leave(self, slot: int) -> None:
        with self._cv:
            self._drop(slot)

    def _drop(self, slot: int) -> None:
        self.live.discard(slot)
        self.needs.pop(slot, None)
        self.args.pop(slot, None)
        self.served.pop(slot, None)
        self._set_wait(slot, None)
        self._refresh_waits()
        self._cv.notify_all()

    def _log(self, slot: int, need: Need, waited: float, outcome: str) -> None:
        self.waits.append({"slot": slot, "kind": need.kind, "waited_s": float(waited),
                           "deadline_s": self.deadline_s, "outcome": outcome})

    # ------------------------------------------------------------ moving
    def _move(self) -> None:
        """Make the next move (called with the lock held; released while the plate moves)."""
        move = next_move({s: n for s, n in self.needs.items() if s in self.live})
        args = self.args[move.serves[0]][move.key]
        if move.kind == "pose":
            total = self.pose_moves + len(still_needed(self.needs))
            args = (*args[:2], self.pose_moves, total)
            self.pose_moves += 1
        self.moving = True
        self.position = {"kind": move.kind, "key": _key_text(move.key), "serves": list(move.serves),
                         "waiting": list(move.waiting), "move": self.moves + 1}
        if isinstance(move.key, str) and len(args) > 1 and args[1] is not None:     # an attitude: which way is up
            from imubench.procedures.poses import pose_words
            up = np.asarray(args[1], float)
            self.position.update(up=[float(x) for x in up], words=pose_words(up))
        self._refresh_waits()
        self._cv.release()
        try:
            if move.waiting:
                self.say(f"  plate: {_key_text(move.key)} for slot{'s' if len(move.serves) > 1 else ''} "
                         f"{_slots(move.serves)}; slot{'s' if len(move.waiting) > 1 else ''} "
                         f"{_slots(move.waiting)} wait{'' if len(move.waiting) > 1 else 's'}")
            if self.on_move is not None:
                self.on_move(dict(self.position))
            if move.kind == "turn":
                self.mover.present_turn(*args)
            else:
                self.mover.present_pose(*args)
        except Exception as e:  # noqa: BLE001 - the boards find out (no attitude comes, their deadline)
            self.say(f"warning: the plate could not make the move {_key_text(move.key)}: {e}")
        finally:
            self._cv.acquire()
            self.moving = False
        for s in move.serves:
            if s in self.live and s in self.needs:
                self.served[s] = move.key
                del self.needs[s]
        self.moves += 1
        self._cv.notify_all()

    # ------------------------------------------------------------ who waits for whom
    def _refresh_waits(self) -> None:
        """A board whose need comes in a later phase than another running board's (done with
        its attitudes while others still need theirs) says so, with its deadline."""
        for s, need in self.needs.items():
            if s in self.served:
                continue
            rank = PHASES.index(need.kind)
            before = sorted(t for t in self.live if t != s and PHASES.index(self.phase.get(t, "pose")) < rank)
            text = None
            if before:
                text = (f"waits for slot{'s' if len(before) > 1 else ''} {_slots(before)} to come to "
                        f"{_PHASE_WORDS[need.kind]} (the plate serves what they need first); "
                        f"deadline {self.deadline_s:g} s device time")
            self._set_wait(s, text)

    def _set_wait(self, slot: int, text: str | None) -> None:
        if self._wait_text.get(slot) != text:
            self._wait_text[slot] = text
            if self.on_wait is not None:
                try:
                    self.on_wait(slot, text)
                except Exception:  # noqa: BLE001 - a broken listener must not stop the plate
                    pass

    def _why_late(self, slot: int, need: Need, waited: float) -> str:
        what = ("one of its missing attitudes (" + ", ".join(map(_key_text, need.keys[:4]))
                + (", ..." if len(need.keys) > 4 else "") + ")") if need.kind == "pose" else _key_text(need.keys[0])
        busy = sorted(t for t in self.live if t != slot and t not in self.needs)
        held = f"; slot{'s' if len(busy) > 1 else ''} {_slots(busy)} did not come back to the plate" if busy else ""
        return (f"waited {waited:.0f} s (device time) for the plate to present {what}, past its deadline of "
                f"{self.deadline_s:g} s{held}; the other boards went on")


def _key_text(key) -> str:
    if isinstance(key, tuple) and len(key) == 2 and isinstance(key[0], tuple):
        return f"turn {key[1]:+.0f} °/s about {list(key[0])}"
    return str(key)


def _slots(slots) -> str:
    return ", ".join(str(s) for s in slots)


class BoardPresenter:
    """One board's Presenter: instructions go to its status, moves to the shared plate. With
    `page` (a station page's presenter for this board's column, imubench.station.presenter)
    the session's live view, pose cards, fit and steps go there too; the plate stays the one
    that moves: a board asks it for any of the attitudes it still misses (present_todo), and
    the plate presents what most boards need (procedures.schedule). `clock()` is the board's
    device time in seconds (its samples so far): the plate's deadlines are counted on it."""

    PAGE_HOOKS = ("present_plan", "present_rest", "pose_event", "live", "targets", "step")

    def __init__(self, run: "FixtureRun", slot: int, discard=lambda: None, page=None,
                 clock: Callable[[], float] | None = None):
        self.run, self.slot = run, slot
        self.discard = discard          # drop what the board sent while it waited for the plate
        self.page = page
        self.clock = clock
        self.suggested = None

    def __getattr__(self, name):
        # the session's optional hooks (session._hook): only the page's
        page = self.__dict__.get("page")
        if page is not None and name in self.PAGE_HOOKS:
            return getattr(page, name)
        raise AttributeError(name)

    def say(self, text: str) -> None:
        self.run._update(self.slot, message=text)
        if self.page is not None:
            self.page.say(text)

    def _check_page(self) -> None:
        if self.page is not None:
            self.page.check_stop()      # stopped on the page (or the station closed): this board stops here

    def suggest(self, name) -> None:
        """The missing attitude that helps this board's fit most: its vote at the plate."""
        self.suggested = name
        if self.page is not None:
            self.page.suggest(name)

    def present_todo(self, todo, done, total):
        """The attitudes this board still misses, in any order: the plate presents one of
        them (the one most boards miss) when every board has asked."""
        self._check_page()
        self.run._update(self.slot, stage="poses", message=f"{len(done)} of {total} captured; waiting for the plate",
                         progress=len(done) / max(total, 1))
        need = Need("pose", tuple(n for n, _ in todo), prefer=self.suggested)
        args = {n: (n, np.asarray(d, float)) for n, d in todo}
        key = self.run.plate.request(self.slot, need, args, clock=self.clock, stage="poses", check=self._check_page)
        if key is not None:
            self.run._update(self.slot, message=f"[{len(done) + 1}/{total}] {key}")
            if self.page is not None:
                self.page.pose_event(key, "capturing", {"progress": 0.0})
        # while this board waited for the others, its samples of the old attitude piled up: they
        # are in the raw capture, but the session's wait for the new attitude starts now
        self.discard()

    def present_pose(self, name, direction, index, total):
        """A directed attitude: one of verification (after the write-back), or of a known-angle
        turn; every board asks for it in the same order."""
        self._check_page()
        st = self.run.boards[self.slot]
        verify = st.stage in ("write", "verify")
        stage = "verify" if verify else "poses"
        self.run._update(self.slot, stage=stage, message=f"[{index + 1}/{total}] {name}", progress=index / max(total, 1))
        if self.page is not None:
            if verify:
                self.page.present_pose(name, direction, index, total)
            else:
                self.page.pose_event(name, "capturing", {"progress": 0.0})
        need = Need("verify" if verify else "turn", (name,))
        self.run.plate.request(self.slot, need, {name: (name, np.asarray(direction, float), index, total)},
                               clock=self.clock, stage=stage, check=self._check_page)
        self.discard()

    def present_turn(self, axis, rate_dps, duration_s):
        self._check_page()
        self.run._update(self.slot, stage="turntable", message=f"turn {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()}")
        if self.page is not None:
            self.page.present_turn(axis, rate_dps, duration_s)
        key = (tuple(float(x) for x in np.round(np.asarray(axis, float), 6)), float(rate_dps))
        self.run.plate.request(self.slot, Need("turn", (key,)), {key: (np.asarray(axis, float), rate_dps, duration_s)},
                               clock=self.clock, stage="turntable", check=self._check_page)
        self.discard()

    def progress(self, label, fraction):
        self._check_page()
        self.run._update(self.slot, progress=float(fraction), publish=False)
        if self.page is not None:
            self.page.progress(label, fraction)

    def keep_pose(self, name, summary):
        return True


class PlatePresenter(SimPresenter):
    """The virtual fixture: one plate carrying several virtual devices. Every attitude and
    every turn is made on all of them at once (each simulator's own rotation, so each board's
    gyros see the motion); a bench whose simulator is gone is left out."""

    def __init__(self, benches: list, rate_dps: float = 90.0, tilt_deg: float = 0.0, seed: int = 0,
                 quiet: bool = False):
        super().__init__(benches[0], rate_dps=rate_dps, tilt_deg=tilt_deg, seed=seed, quiet=quiet)
        self.benches = list(benches)

    def _alive(self) -> list:
        return [b for b in self.benches if b.running]

    def _rotate_to(self, target: np.ndarray) -> None:
        alive = self._alive()
        if not alive:
            return
        self.vb = alive[0]
        turn = rotation_to(self.vb.status()["gravity_board"], target)
        if turn is None:
            return
        ax, angle = turn
        self._each(lambda b: b.rotate(ax, rate_dps=self.rate_dps, duration_s=angle / self.rate_dps, wait=False))
        self._each(lambda b: b.wait_idle(timeout=b._wait_timeout(angle / self.rate_dps)))

    def present_turn(self, axis, rate_dps, duration_s):
        self.say(f"virtual turntable: {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()} for {duration_s:g} s")
        self._each(lambda b: b.rotate(list(axis), rate_dps=rate_dps, duration_s=duration_s, wait=False))

    def _each(self, fn) -> None:
        from imubench.device.sim import SimError
        for b in self._alive():
            try:
                fn(b)
            except SimError:        # that board's simulator died: the plate carries the others
                pass


# ---------------------------------------------------------------- one board's session
class BoardSession(Session):
    """The ordinary session with the stages published and two production rules: no data for
    link_timeout_s is a lost link, and a sample flagged bad (a sensor fault, parity or SPI
    error) during capture stops the board, naming the sensor."""

    link_timeout_s: float = 10.0
    board_run: "FixtureRun | None" = None
    slot: int = 0

    def _stage(self, stage: str) -> None:
        if self.board_run is not None:
            self.board_run._update(self.slot, stage=stage)

    def check_health(self) -> dict:
        self._stage("health")
        try:
            return super().check_health()
        except SessionAborted as e:
            raise BoardFailed("health", str(e)) from None

    def capture_rest(self) -> dict:
        self._stage("rest")
        return super().capture_rest()

    link_lost: str | None = None

    def _stop_stream(self) -> None:
        """As the session's, but after a lost link only the capture file is closed: asking a
        silent device to stop would just wait out the retries and hide why the board failed."""
        if self.link_lost is None:
            try:
                return super()._stop_stream()
            except (LinkError, TimeoutError) as e:
                self.link_lost = str(e)
        cap, self.dev.link.capture = self.dev.link.capture, None
        if cap is not None:
            cap.close()

    def _leave_plate(self) -> None:
        """Stop holding the plate at once (the session's clean-up may still take a while)."""
        if self.board_run is not None:
            self.board_run.plate.leave(self.slot)

    def _next_block(self, timeout: float = 10.0):
        try:
            b = self.dev.read(duration_s=0.05, timeout=min(timeout, self.link_timeout_s))
        except LinkTimeout:
            self._leave_plate()
            self.link_lost = f"link lost: no data from the device for {self.link_timeout_s:g} s"
            raise BoardFailed("link", self.link_lost) from None
        except LinkError as e:
            self._leave_plate()
            self.link_lost = f"link lost: {e}"
            raise BoardFailed("link", f"link lost: {e}") from None
        bad = int(np.bitwise_or.reduce(b.status)) if len(b) else 0
        if bad:
            names = [n for bit, n in ((SampleStatus.ACCEL_BAD, "accelerometer"), (SampleStatus.GYRO_X_BAD, "gyro X"),
                                      (SampleStatus.GYRO_Y_BAD, "gyro Y"), (SampleStatus.GYRO_Z_BAD, "gyro Z"))
                     if bad & bit]
            self._leave_plate()
            raise BoardFailed("sensor", f"{', '.join(names)} flagged bad during capture "
                                        f"({int(np.count_nonzero(b.status))} of {len(b)} samples): a faulted sensor; "
                                        "nothing is calibrated on faulted data")
        self._count_block(b)
        return b


# ---------------------------------------------------------------- the station session
@dataclass
class FixtureResult:
    session_id: str
    directory: Path
    boards: list[BoardStatus]
    results: dict[int, dict] = field(default_factory=dict)      # slot -> the board's record
    wall_s: float = 0.0

    @property
    def passed(self) -> list[int]:
        return [b.slot for b in self.boards if b.state == "passed"]

    @property
    def failed(self) -> list[int]:
        return [b.slot for b in self.boards if b.state != "passed"]


class FixtureRun:
    """One station session over several boards (see the module's doc)."""

    def __init__(self, ports: list[str], directory, cfg: SessionConfig, mover, station: Station | None = None,
                 db=None, on_event: Callable[[dict], None] | None = None, link_timeout_s: float = 10.0,
                 baudrate: int | None = None, say=print, plots: bool = True,
                 pages: Callable[[int, str], object] | None = None, plate_timeout_s: float = PLATE_TIMEOUT_S,
                 on_plate: Callable[[dict], None] | None = None):
        if not ports:
            raise ValueError("no boards: give at least one port")
        self.ports = list(ports)
        self.dir = Path(directory)
        # a station session has no wait without an end: a presented attitude is held still
        # within pose_timeout_s of device time, or that board fails (the others go on)
        self.cfg = cfg if cfg.pose_timeout_s is not None else dataclasses.replace(cfg, pose_timeout_s=POSE_TIMEOUT_S)
        self.on_plate = on_plate        # on_plate(move): the plate's current attitude or turn, for a page
        self.station = station or Station()
        self.db = db
        self.on_event = on_event
        self.link_timeout_s = link_timeout_s
        self.baudrate = baudrate
        self.say = say
        self.plots = plots
        self.pages = pages              # pages(slot, port): a station page's presenter for that board, or None
        self.session_id = (f"{self.station.station_id}-{_dt.datetime.now(_dt.timezone.utc):%Y%m%dT%H%M%SZ}-"
                           f"{uuid.uuid4().hex[:6]}")
        self.boards = {k + 1: BoardStatus(slot=k + 1, port=p, directory=str(self.dir / f"slot-{k + 1}"))
                       for k, p in enumerate(self.ports)}
        self.plate = Plate(mover, list(self.boards), say=say, deadline_s=plate_timeout_s,
                           on_wait=self._on_wait, on_move=self._on_move)
        self.results: dict[int, dict] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------ state
    def _update(self, slot: int, publish: bool = True, **kw) -> None:
        with self._lock:
            st = self.boards[slot]
            for k, v in kw.items():
                setattr(st, k, v)
            snap = st.as_dict()
        if publish and self.on_event is not None:
            try:
                self.on_event(snap)
            except Exception:  # noqa: BLE001 - a broken listener must not fail a board
                pass

    def _on_wait(self, slot: int, text: str | None) -> None:
        self._update(slot, waiting=text)

    def _on_move(self, move: dict) -> None:
        if self.on_plate is not None:
            try:
                self.on_plate(move)
            except Exception:  # noqa: BLE001 - a broken listener must not stop the plate
                pass

    def deadlines_text(self) -> str:
        return (f"deadlines (device time): a board waits at most {self.plate.deadline_s:g} s for the plate "
                f"(the attitudes other boards still need first, verification last) and "
                f"{self.cfg.pose_timeout_s:g} s for a presented attitude to be held still; past one it fails "
                "with the stage and the reason, and the others go on")

    def snapshot(self) -> list[dict]:
        with self._lock:
            return [b.as_dict() for b in self.boards.values()]

    def _save_station(self, finished: bool = False) -> None:
        write_json_atomic(self.dir / "station.json", {
            "schema": 1, "session_id": self.session_id, "station": dataclasses.asdict(self.station),
            "config": _jsonable(dataclasses.asdict(self.cfg)), "ports": self.ports, "finished": finished,
            "boards": self.snapshot()})

    # ------------------------------------------------------------ run
    def run(self) -> FixtureResult:
        t0 = time.monotonic()
        self.dir.mkdir(parents=True, exist_ok=True)
        if (self.dir / "station.json").exists():
            raise SessionAborted(f"{self.dir} already holds a station session: give another --dir")
        self._save_station()
        self.say(self.deadlines_text())
        self._on_move({"deadlines": self.deadlines_text()})
        threads = [threading.Thread(target=self._board, args=(slot,), name=f"board-{slot}", daemon=True)
                   for slot in self.boards]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if self.plots:                  # after the boards: the plots take CPU the live streams need
            from imubench.results.calibration import plot_pose_residuals
            for slot, rec in sorted(self.results.items()):
                if rec.get("accel") is not None and rec.get("poses"):
                    try:
                        plot_pose_residuals(rec, self.dir / f"slot-{slot}" / "residuals.png")
                    except Exception as e:  # noqa: BLE001 - a plot is not worth a board's verdict
                        self.say(f"warning: slot {slot}: no residual plot ({e})")
        self._save_station(finished=True)
        return FixtureResult(self.session_id, self.dir, [self.boards[s] for s in sorted(self.boards)],
                             dict(self.results), time.monotonic() - t0)

    def _board(self, slot: int) -> None:
        st = self.boards[slot]
        started = _now()
        dev = None
        result: dict | None = None
        info_dev: dict = {"mcu_uid": None}
        params_before = None
        try:
            self._update(slot, stage="connect", message=f"opening {st.port}")
            try:
                kw = {"timeout": 5.0} | ({"baudrate": self.baudrate} if self.baudrate else {})
                dev = Device.open(st.port, **kw)
                info = dev.info()
            except (OSError, LinkError, TimeoutError) as e:
                raise BoardFailed("connect", f"no answer from the device on {st.port}: {e}") from None
            info_dev = _device_ident(info)
            self._update(slot, uid=info_dev["mcu_uid"], message=f"{info_dev['board']} {info_dev['mcu_uid']}")
            params_before = dev.get_params(ParamsWhich.ACTIVE).params
            stats, rate = dev.link.decoder.stats, float(self.cfg.rate_hz)
            sess = BoardSession(dev, self.dir / f"slot-{slot}", dataclasses.replace(self.cfg),
                                BoardPresenter(self, slot, discard=dev.discard_buffered,
                                               page=self.pages(slot, st.port) if self.pages else None,
                                               clock=lambda: stats.samples / rate))
            sess.board_run, sess.slot, sess.link_timeout_s = self, slot, self.link_timeout_s
            try:
                result = sess.run(plan_for(self.cfg.method))
            except CalibrationError as e:
                raise BoardFailed("fit", f"fit refused: {e}") from None
            except (LinkTimeout, LinkError) as e:
                raise BoardFailed("link", f"link lost: {e}") from None
            except (SessionAborted, ImubenchError) as e:   # e.g. stopped on the station page
                raise BoardFailed(self.boards[slot].stage, str(e)) from None
            self._update(slot, stage="fit", message=f"fit: |a| − g RMS {result['accel_rms_after_mg']:.3f} mg")
            result["write_requested"] = bool(self.cfg.write)
            if result["passed"] and self.cfg.write:
                self._write_and_verify(slot, sess, result, params_before)
            elif not result["passed"]:
                self.plate.leave(slot)
            result["params_after"] = PR.to_json(dev.get_params(ParamsWhich.ACTIVE).params)
            sess.finish(result)
        except BoardFailed as e:
            self._fail(slot, e.stage, e.reason)
        except Exception as e:  # noqa: BLE001 - a bug on one board must not stop the others; it is named
            self._fail(slot, self.boards[slot].stage, f"{type(e).__name__}: {e}")
            (self.dir / f"slot-{slot}").mkdir(parents=True, exist_ok=True)
            (self.dir / f"slot-{slot}" / "error.txt").write_text(traceback.format_exc())
        finally:
            self.plate.leave(slot)
            try:
                link_stats = dev.link.decoder.stats if dev is not None else None
                if dev is not None:
                    dev.close()
            except Exception:  # noqa: BLE001
                link_stats = None
        rec = self._record_for(slot, started, result, info_dev, params_before, link_stats)
        self.results[slot] = rec
        self._record(slot, rec)

    def _write_and_verify(self, slot: int, sess: BoardSession, result: dict, previous) -> None:
        self._update(slot, stage="write", message="writing, reading back, saving, rebooting")
        try:
            wb = sess.write_back(sess.accel_fit, sess.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
        except (PR.InvalidParams, SessionAborted, LinkError, TimeoutError) as e:
            self.plate.leave(slot)
            raise BoardFailed("write", f"write-back failed: {e}") from None
        result["written"] = True
        result["write_steps"] = wb["steps"]
        self._update(slot, stage="verify", message="verifying the device's calibrated output")
        try:
            result["verification"] = sess.verify(plan_for("six")[:self.cfg.verify_poses])
        except (BoardFailed, SessionAborted, LinkError, TimeoutError) as e:
            reason = e.reason if isinstance(e, BoardFailed) else str(e)
            self.plate.leave(slot)
            try:
                sess.restore(previous)
                reason += "; the previous parameters were restored"
            except Exception as e2:  # noqa: BLE001
                reason += f"; restoring the previous parameters failed too ({e2})"
            result["written"] = False
            raise BoardFailed("verify", f"verification failed: {reason}") from None
        worst = max(abs(v["after_g"] - 1.0) * 1e3 for v in result["verification"])
        result["verified"] = worst <= self.cfg.tolerances.verify_mg
        if not result["verified"]:
            sess.restore(previous)
            result["written"] = False

    def _fail(self, slot: int, stage: str, reason: str) -> None:
        self.plate.leave(slot)
        self._update(slot, state="failed", stage=stage or "connect", reason=reason, message=f"FAILED: {reason}")
        if self.on_event is None:       # a listener shows the failure with the board's other events
            self.say(f"slot {slot} ({self.boards[slot].port}) FAILED at {stage}: {reason}")

    def _record_for(self, slot: int, started: str, result: dict | None, ident: dict, params_before, link_stats) -> dict:
        st = self.boards[slot]
        base = {"schema": RECORD_SCHEMA, "session_id": self.session_id,
                "station": {"id": self.station.station_id, "operator": self.station.operator,
                            "fixture": self.station.fixture, "slot": slot, "port": st.port,
                            "host_version": self.station.host_version},
                "params_before": PR.to_json(params_before) if params_before is not None else None,
                "capture": capture_ref(self.dir / f"slot-{slot}")}
        if link_stats is not None:
            base["link"] = {"samples_missing": int(link_stats.samples_missing),
                            "frames_rejected": int(link_stats.frames_rejected),
                            "samples_overflow": int(getattr(link_stats, "samples_overflow", 0))}
        if result is not None and st.state != "failed":
            rec = {**result, **base, "schema": RECORD_SCHEMA}
            from imubench.results.export import measurements_of
            rec["measurements"] = measurements_of(rec)
            ok = rec["passed"] and (rec["verified"] or not self.cfg.write) and all(m["passed"] for m in rec["measurements"])
            if not ok:
                why = [f"{m['name']} = {m['value']:.4g} {m['unit']} outside its limit" for m in rec["measurements"]
                       if not m["passed"] and m["value"] is not None]
                if not rec["passed"]:
                    why.insert(0, f"fit out of tolerance: |a| − g RMS {rec['accel_rms_after_mg']:.3f} mg > "
                                  f"{self.cfg.tolerances.accel_rms_mg:g} mg")
                rec["passed"] = False
                self._update(slot, state="failed", stage=st.stage, reason="; ".join(why) or "did not pass",
                             message="FAILED: " + ("; ".join(why) or "did not pass"))
            else:
                self._update(slot, state="passed", stage="done", progress=1.0, message="PASSED")
            return rec
        # failed before or during the run: what is known, the stage and the reason
        rec = {**base, "device": ident, "started": started, "finished": _now(), "passed": False,
               "written": bool(result and result.get("written")), "verified": False,
               "failure": {"stage": st.stage, "reason": st.reason or "failed"}, "params_after": None,
               "method": self.cfg.method, "gyro_method": self.cfg.gyro, "note": self.cfg.note,
               "capture_dir": str((self.dir / f"slot-{slot}").resolve())}
        if result is not None:      # fitted, then failed (write-back, verification): keep the fit
            rec.update({k: result[k] for k in ("accel", "gyro", "poses", "tolerances", "accel_rms_after_mg",
                                               "temperature_c", "verification") if k in result})
            rec["params_after"] = result.get("params_after")
        from imubench.results.export import measurements_of
        rec["measurements"] = measurements_of(rec)
        return rec

    def _record(self, slot: int, rec: dict) -> None:
        if self.db is None:
            return
        from imubench.results.history import History
        self._update(slot, message=self.boards[slot].message, publish=False)
        try:
            with History(self.db) as h:
                run_id, _ = h.record_once(rec)
            self._update(slot, run_id=run_id)
        except Exception as e:  # noqa: BLE001 - the record is safe on disk; say why it is not in the database
            self.say(f"warning: slot {slot} not recorded in the history ({e}); its record is in "
                     f"{self.dir / f'slot-{slot}' / 'record.json'}")
        finally:
            try:
                write_json_atomic(self.dir / f"slot-{slot}" / "record.json", _jsonable(rec))
            except OSError:
                pass


def run_fixture(ports: list[str], directory, cfg: SessionConfig, mover, **kw) -> FixtureResult:
    """One station session over the boards on `ports` (see FixtureRun)."""
    return FixtureRun(ports, directory, cfg, mover, **kw).run()


# ------------------------------------------------------------------- helpers
def _device_ident(info) -> dict:
    return {"mcu_uid": uid_text(info.mcu_uid), "board": board_name(info.board),
            "fw_version": ".".join(map(str, info.fw_version)), "fw_build": info.fw_build,
            "accel_ids": list(info.accel_ids), "gyro_pid": list(info.gyro_pid), "gyro_sn": list(info.gyro_sn)}


def capture_ref(d: Path) -> dict:
    """SHA-256 of the raw capture (the capture files in stream order, as one byte sequence),
    the files, and where they are: a file:// URI naming this station's host."""
    files = sorted(d.glob("capture-*.bin"), key=lambda p: int(p.stem.split("-")[1]) if p.stem.split("-")[1].isdigit() else 0)
    h = hashlib.sha256()
    listed = []
    for p in files:
        fh = hashlib.sha256()
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
                fh.update(chunk)
        listed.append({"name": p.name, "bytes": p.stat().st_size, "sha256": fh.hexdigest()})
    host = socket.gethostname()
    return {"sha256": h.hexdigest() if files else None,
            "uri": f"file://{host}{(files[0] if len(files) == 1 else d).resolve()}" if files else None,
            "files": listed}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")
