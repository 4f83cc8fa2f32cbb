"""The plate all boards of a fixture share (procedures.fixture): each board's session asks it
for a move; it moves once every board still running has asked, what procedures.schedule
chooses, with deadlines in device time."""
from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from imubench.procedures.schedule import PHASES, Need, next_move, still_needed


class BoardFailed(Exception):
    """One board cannot go on; the fixture marks it failed and the others carry on."""

    def __init__(self, stage: str, reason: str):
        super().__init__(reason)
        self.stage, self.reason = stage, reason


class BoardStopped(BoardFailed):
    """The board was stopped (Ctrl-C, SIGTERM, Stop on the page): recorded as stopped, with
    the stage it was at."""


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
    waiting board sleeps on a condition, waking 4 times a second to look at its clock.

    Each board is its own failure domain on the plate too. A mover that carries the boards
    one by one (procedures.virtual.PlatePresenter) is told before every move which boards
    are still on the plate (`mover.carry(slots)`) and says after it which of them it could
    not move and why (`mover.take_lost()` -> {slot: reason}): those boards are failed and
    dropped from the plan at once (a waiting one gets BoardFailed with its own stage and
    that reason), and the move stands for the others. Any other error of the mover is the
    whole plate's (a warning; the boards find out by their deadlines)."""

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
        self.lost: dict[int, str] = {}            # slot -> why the mover could not carry it (its fault)
        self.waits: list[dict] = []
        self.deadline_s = float(deadline_s)
        self.say = say
        self.on_wait = on_wait
        self.on_move = on_move
        self._wait_text: dict[int, str | None] = {}
        self._since: dict[int, tuple] = {}         # slot -> (t0, clock) of its current wait
        self.late: dict[int, tuple[str, float]] = {}  # slot -> (why, waited_s): past its deadline, found by the plate
        self._cv = threading.Condition()

    # ------------------------------------------------------------ asking
    def request(self, slot: int, need: Need, args: dict, clock: Callable[[], float] | None = None,
                stage: str = "poses", check: Callable[[], None] | None = None):
        """Wait until the plate presents something `need` accepts; returns its key (None when
        this board is no longer on the plate). args: {key: the mover's arguments for it}.
        Raises BoardFailed(stage, why) when the wait passes its deadline (device time), and
        whatever check() raises (a Stop on the page) after leaving the plate."""
        with self._cv:
            if slot in self.lost:
                raise BoardFailed(stage, self.lost[slot])
            if slot not in self.live:
                return None
            self.needs[slot], self.args[slot], self.phase[slot] = need, args, need.kind
            t0 = clock() if clock is not None else None
            if t0 is not None:
                self._since[slot] = (t0, clock)
            waited = 0.0
            self._refresh_waits()
            try:
                while True:
                    if t0 is not None:
                        waited = clock() - t0
                    if slot in self.late:          # the plate found it past its deadline before a move
                        why, waited = self.late.pop(slot)
                        self._log(slot, need, waited, "deadline")
                        raise BoardFailed(stage, why)
                    if slot in self.lost:
                        self._log(slot, need, waited, "lost")
                        raise BoardFailed(stage, self.lost[slot])
                    if slot in self.served:
                        key = self.served.pop(slot)
                        self._log(slot, need, waited, "served")
                        return key
                    if slot not in self.live:
                        self._log(slot, need, waited, "left")
                        return None
                    if not self.moving and set(self.needs) >= self.live:
                        if self._expire():      # a waiting board is past its deadline: it leaves first
                            continue
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
                self._since.pop(slot, None)
                self._set_wait(slot, None)

    def _expire(self) -> bool:
        """Before a move (lock held): every waiting board past its deadline, on its own clock,
        leaves the plate now and is told why when it wakes. The board making the move is
        not the only one whose deadline counts: under load, a waiting board may not wake
        between two moves, and each move costs device time."""
        expired = False
        for s, (t0, clock) in list(self._since.items()):
            if s not in self.needs or s in self.late:
                continue
            waited = clock() - t0
            if waited > self.deadline_s:
                self.late[s] = (self._why_late(s, self.needs[s], waited), waited)
                self._drop(s)
                expired = True
        return expired

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
        carried = sorted(self.live)
        self._cv.release()
        lost: dict = {}
        try:
            if hasattr(self.mover, "carry"):
                self.mover.carry(carried)
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
            if hasattr(self.mover, "take_lost"):
                try:
                    lost = dict(self.mover.take_lost())
                except Exception:  # noqa: BLE001 - a broken mover's report must not stop the plate
                    lost = {}
            self._cv.acquire()
            self.moving = False
        for s, why in lost.items():         # those boards' faults: failed here, the move stands for the rest
            if s in self.live:
                self.lost[s] = why
                self.say(f"  plate: slot {s} left the plate: {why}")
                self._drop(s)
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
