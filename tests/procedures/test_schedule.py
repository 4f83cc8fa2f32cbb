"""The fixture's plate at full size (issue 24): every board on the plate is served, the
attitudes the boards still need come before any verification, every wait has an end.

Two layers, because 16 real virtual devices per example are too slow for the suite:

* the scheduling logic with fakes, many seeds (a seeded loop, 80 cases): 2 to 16 boards run
  as threads against the real `fixture.Plate` (and so `schedule.next_move`), each with its own
  "truth" (how many attitudes its adaptive session needs, which it prefers, captures that
  fail and are asked again), faulted boards among them (one that fails and leaves, one whose
  capture hangs until its own 120 s attitude deadline, one whose link dies half-way),
  on a fake device clock that the plate's moves and the boards' captures advance;
* end to end on real virtual devices, once: 8 boards with the defaults (adaptive
  multi-position, gyro bias, write-back and verification), two of them faulted
  (test_eight_real_boards_with_the_defaults_two_faulted).

Checked on every case: every session ends, every board passed or failed with a stage and a
reason, no board waited at the plate past its deadline (device time), the plate never left
an attitude phase for verification while a board still needed attitudes, and every move
served at least one board (healthy sets: no more attitude moves than the most demanding
board needs: each move helps every board that still misses it).
"""
from __future__ import annotations

import random
import threading
import time

import numpy as np
import pytest
from imubench.procedures import fixture as FX
from imubench.procedures.fixture import BoardFailed, Plate
from imubench.procedures.schedule import PHASES, Need, next_move

PLAN = [f"att{k:02d}" for k in range(26)]
VERIFY = ["+Z up (level)", "-Z up (upside down)", "+X up (nose up)"]


class Clock:
    """Device time shared by the fake boards (all on one plate, all at the same rate). It
    records the time each board last read, so a board that advances it can wait until the
    boards waiting at the plate have looked (a busy machine must not let the time run past a
    waiting board's deadline check: issue 33)."""

    def __init__(self):
        self.t = 0.0
        self._lock = threading.Lock()
        self.slot_of: dict[int, int] = {}      # thread ident -> slot
        self.seen: dict[int, float] = {}       # slot -> the time it last read

    def __call__(self) -> float:
        t = self.t
        slot = self.slot_of.get(threading.get_ident())
        if slot is not None:
            self.seen[slot] = t
        return t

    def advance(self, dt: float) -> None:
        with self._lock:
            self.t += dt

    def advance_seen(self, dt: float, plate, me: int, timeout_s: float = 30.0) -> None:
        """advance(dt), then wait (wall time, at most timeout_s) until every other board
        waiting at the plate (or served and not yet awake) has read the new time under the
        plate's lock, i.e. has made its deadline check for it or taken its attitude."""
        self.advance(dt)
        t, end = self.t, time.monotonic() + timeout_s
        while time.monotonic() < end:
            with plate._cv:
                plate._cv.notify_all()
                waiting = (set(plate.needs) | set(plate.served)) - {me}
                if all(self.seen.get(s, -1.0) >= t for s in waiting):
                    return
            threading.Event().wait(0.0005)
        raise AssertionError(f"boards {sorted(waiting)} never looked at the time {t:g}")


class Mover:
    def __init__(self, clock: Clock, plate_ref: list, phases: dict):
        self.clock, self.plate_ref, self.phases = clock, plate_ref, phases
        self.moves: list[tuple[str, str, tuple]] = []

    def present_pose(self, name, direction, index, total):
        pos = self.plate_ref[0].position
        # which boards still needed attitudes when this move was made (checked after the run)
        self.moves.append((pos["kind"], name, tuple(pos["serves"]), {s for s, p in self.phases.items() if p == "pose"}))
        self.clock.advance(1.5 + 4.0)    # the plate turns, the boards it serves settle and hold

    def present_turn(self, *a):
        raise AssertionError("no turns in these sessions")


def _board(slot, plate, clock, rng_seed, kind, need_n, prefer_order, out, phases):
    rng = random.Random(rng_seed)
    captured: list[str] = []
    clock.slot_of[threading.get_ident()] = slot
    try:
        phases[slot] = "pose"
        while len(captured) < need_n:
            todo = [p for p in PLAN if p not in captured]
            if not todo:
                break
            prefer = next(p for p in prefer_order if p in todo)
            if kind == "fails" and len(captured) == need_n // 2:
                raise BoardFailed("sensor", "gyro Z flagged bad during capture (fake)")
            if kind == "dies_waiting" and len(captured) == need_n // 2:
                raise BoardFailed("link", "link lost: no data from the device for 10 s (fake)")
            key = plate.request(slot, Need("pose", tuple(todo), prefer=prefer), {p: (p, None) for p in todo},
                                clock=clock, stage="poses")
            assert key in todo
            if kind == "hangs" and len(captured) == need_n // 3:
                for _ in range(121):                     # never still: its own 120 s attitude deadline
                    clock.advance_seen(1.0, plate, slot)     # the waiting boards check every second
                raise BoardFailed("poses", "no still attitude from the plan within 120 s (fake)")
            if rng.random() < 0.1:
                continue                                 # the capture was rejected: asked again
            captured.append(key)
        phases[slot] = "fit"
        threading.Event().wait(rng.uniform(0.0, 0.003))  # fit, write-back, read-back, reboot (off the plate)
        phases[slot] = "verify"
        for i, name in enumerate(VERIFY):
            key = plate.request(slot, Need("verify", (name,)), {name: (name, None, i, 3)}, clock=clock, stage="verify")
            assert key == name
        out[slot] = ("passed", "done", None, captured)
    except BoardFailed as e:
        out[slot] = ("failed", e.stage, e.reason, captured)
    finally:
        phases[slot] = "gone"
        plate.leave(slot)


def _case(seed: int, monkeypatch):
    rng = random.Random(seed)
    n = rng.randint(2, 16)
    deadline = 300.0
    clock = Clock()
    phases: dict[int, str] = {}
    ref: list = []
    mover = Mover(clock, ref, phases)
    plate = Plate(mover, list(range(1, n + 1)), deadline_s=deadline)
    ref.append(plate)
    kinds = {s: "healthy" for s in range(1, n + 1)}
    for s in rng.sample(range(1, n + 1), k=rng.randint(0, min(3, n - 1))):
        kinds[s] = rng.choice(["fails", "hangs", "dies_waiting"])
    needs = {s: rng.randint(12, 26) for s in kinds}
    if any(k == "hangs" for k in kinds.values()) and rng.random() < 0.5:
        deadline = 60.0                 # shorter than the hang: the boards waiting for it fail, in time
    plate.deadline_s = deadline
    order = {s: rng.sample(PLAN, len(PLAN)) if rng.random() < 0.5 else list(PLAN) for s in kinds}
    out: dict = {}
    ts = [threading.Thread(target=_board, args=(s, plate, clock, seed * 100 + s, kinds[s], needs[s], order[s], out,
                                                phases), daemon=True) for s in kinds]
    for t in ts:
        t.start()
    for t in ts:
        t.join(30)
    return n, deadline, kinds, needs, plate, mover, out, ts


@pytest.mark.parametrize("block", range(4))
def test_every_board_is_served_or_fails_in_time(block, monkeypatch):
    monkeypatch.setattr(Plate, "CHECK_S", 0.002)
    for seed in range(block * 20, block * 20 + 20):
        n, deadline, kinds, needs, plate, mover, out, ts = _case(seed, monkeypatch)
        where = f"seed {seed}: {n} boards, deadline {deadline:g} s, {kinds}"
        assert not any(t.is_alive() for t in ts), f"{where}: a session did not end"
        assert set(out) == set(kinds), where
        for s, (state, stage, reason, captured) in out.items():
            if state == "failed":
                assert stage and reason, where
            else:
                assert state == "passed" and len(captured) >= needs[s], where
        # no wait past its deadline (the fake clock moves in steps of at most 5.5 s)
        assert plate.waits and all(w["waited_s"] <= w["deadline_s"] + 5.5 for w in plate.waits), (
            where, [w for w in plate.waits if w["waited_s"] > w["deadline_s"] + 5.5])
        late = [w for w in plate.waits if w["outcome"] == "deadline"]
        assert all(out[w["slot"]][0] == "failed" and "past its deadline" in out[w["slot"]][2] for w in late), where
        # the plate never served a verification while a board still needed attitudes
        kinds_moved = [m[0] for m in mover.moves]
        assert kinds_moved == sorted(kinds_moved, key=PHASES.index), where
        assert all(not still for kind, _, _, still in mover.moves if kind == "verify"), where
        assert all(serves for _, _, serves, _ in mover.moves), where
        healthy = all(k == "healthy" for k in kinds.values())
        if healthy:
            assert all(v[0] == "passed" for v in out.values()), where
        # a healthy board is only failed by a deadline that another board's hang made it wait past
        for s, (state, stage, reason, _) in out.items():
            if kinds[s] == "healthy" and state == "failed":
                assert "past its deadline" in reason and any(k == "hangs" for k in kinds.values()), where


def test_the_union_is_served_most_shared_first():
    """Pure scheduling: the attitude the most boards miss comes first; their votes break ties;
    verification waits while any board still needs attitudes; a move serves every board
    whose need it meets."""
    needs = {1: Need("pose", ("a", "b", "c")), 2: Need("pose", ("b", "c")), 3: Need("pose", ("c",)),
             4: Need("verify", ("+Z",))}
    m = next_move(needs)
    assert (m.kind, m.key, m.serves, m.waiting) == ("pose", "c", (1, 2, 3), (4,))
    m = next_move({1: Need("pose", ("a", "b"), prefer="b"), 2: Need("pose", ("a", "b"), prefer="b"),
                   3: Need("pose", ("a", "b"), prefer="a")})
    assert m.key == "b" and m.serves == (1, 2, 3)
    m = next_move({1: Need("verify", ("+Z",)), 2: Need("verify", ("+Z",)), 3: Need("turn", ("t1",))})
    assert (m.kind, m.key, m.serves) == ("turn", "t1", (3,))
    # with identical plans and no votes, the plan's order
    assert next_move({1: Need("pose", ("a", "b")), 2: Need("pose", ("a", "b"))}).key == "a"
    # greedy over random sets: each move serves the largest group possible
    rng = np.random.default_rng(5)
    for _ in range(200):
        sets = {s: tuple(sorted(set(rng.choice(list("abcdefgh"), size=rng.integers(1, 6))))) for s in range(1, 9)}
        m = next_move({s: Need("pose", v) for s, v in sets.items()})
        best = max(sum(1 for v in sets.values() if k in v) for k in "abcdefgh")
        assert len(m.serves) == best


def test_a_healthy_line_needs_no_more_moves_than_its_most_demanding_board(monkeypatch):
    monkeypatch.setattr(Plate, "CHECK_S", 0.002)
    for seed in range(1000, 1010):
        rng = random.Random(seed)
        n = rng.randint(2, 16)
        clock, phases, ref = Clock(), {}, []
        mover = Mover(clock, ref, phases)
        plate = Plate(mover, list(range(1, n + 1)))
        ref.append(plate)
        needs = {s: rng.randint(12, 26) for s in range(1, n + 1)}
        out: dict = {}

        def board(s):
            captured = []
            while len(captured) < needs[s]:
                todo = [p for p in PLAN if p not in captured]
                captured.append(plate.request(s, Need("pose", tuple(todo)), {p: (p, None) for p in todo}, clock=clock))
            plate.leave(s)
            out[s] = captured
        ts = [threading.Thread(target=board, args=(s,), daemon=True) for s in needs]
        for t in ts:
            t.start()
        for t in ts:
            t.join(20)
        assert not any(t.is_alive() for t in ts)
        assert len(mover.moves) == max(needs.values()), (seed, needs)


def test_eight_real_boards_with_the_defaults_two_faulted(tmp_path):
    """End to end, once: 8 virtual devices (random truths) on the virtual plate with the
    command's defaults (adaptive multi-position, gyro bias, write-back, verification; no
    attitude timeout given: the station session sets its own). Slot 3's gyro is faulted from
    the start, slot 6's link dies after its fourth attitude. Every other board passes; the
    two fail with their stage and reason; no wait at the plate went past its deadline."""
    from imubench.device.sim import VirtualBench
    from imubench.procedures.fixture import FixtureRun, Station
    from imubench.procedures.virtual import PlatePresenter
    from imubench.procedures.session import SessionConfig
    benches = []
    try:
        for k in range(8):
            benches.append(VirtualBench(speed=0, seed=700 + k, truth="random"))
        benches[2].inject("gyro_fault_bits", sensor="gyro_y", bits=0x10, persistent=True)
        cut = threading.Event()

        def on_event(st):
            if st["slot"] == 6 and st["message"].startswith("[5/") and not cut.is_set():
                cut.set()
                benches[5].inject("link_drop", count=10**9)
        cfg = SessionConfig(method="multi", gyro="bias", adaptive=True, pose_timeout_s=None)
        run = FixtureRun([vb.port_url for vb in benches], tmp_path / "st", cfg, PlatePresenter(benches, quiet=True),
                         station=Station("S-e2e"), db=str(tmp_path / "h.sqlite"), on_event=on_event,
                         link_timeout_s=3.0, say=lambda s: None, plots=False)
        res = run.run()
    finally:
        for vb in benches:
            vb.close()
    states = {b.slot: (b.state, b.stage) for b in res.boards}
    want = {k: ("passed", "done") for k in range(1, 9)} | {3: ("failed", "health"), 6: ("failed", "link")}
    assert cut.is_set() and states == want, [(b.slot, b.reason) for b in res.boards]
    assert all(b.reason for b in res.boards if b.state == "failed")
    assert run.cfg.pose_timeout_s == FX.POSE_TIMEOUT_S
    assert all(w["waited_s"] <= w["deadline_s"] for w in run.plate.waits) and run.plate.waits
    for slot in (1, 2, 4, 5, 7, 8):
        rec = res.results[slot]
        assert rec["verified"] and rec["adaptive"] and len(rec["poses"]) >= 12
        assert rec["link"]["samples_missing"] == 0


def test_a_board_stopped_while_it_waits_leaves_the_plate_at_once(monkeypatch):
    """Stop on the page (check() raises) reaches a board waiting at the plate: it leaves,
    and the plate no longer waits for it."""
    monkeypatch.setattr(Plate, "CHECK_S", 0.002)
    clock, phases, ref = Clock(), {}, []
    mover = Mover(clock, ref, phases)
    plate = Plate(mover, [1, 2, 3])
    ref.append(plate)
    stop = threading.Event()

    class Stopped(Exception):
        pass

    def check():
        if stop.is_set():
            raise Stopped("stopped on the page")
    got = {}

    def waiter():           # slot 1 waits for verification while slot 3 still needs attitudes
        try:
            plate.request(1, Need("verify", ("+Z",)), {"+Z": ("+Z", None, 0, 3)}, clock=clock, check=check)
        except Stopped as e:
            got[1] = str(e)
    t = threading.Thread(target=waiter)
    t.start()
    threading.Thread(target=lambda: got.setdefault(2, plate.request(2, Need("verify", ("+Z",)),
                                                                    {"+Z": ("+Z", None, 0, 3)}, clock=clock))).start()
    threading.Event().wait(0.05)
    assert t.is_alive() and not mover.moves          # slot 3 has not asked yet: nothing moves
    stop.set()
    t.join(5)
    assert not t.is_alive() and got[1] == "stopped on the page" and 1 not in plate.live
    assert plate.waits[-1]["outcome"] == "stopped"
    assert plate.request(3, Need("pose", ("a",)), {"a": ("a", None)}, clock=clock) == "a"
    plate.leave(3)
    for _ in range(500):
        if 2 in got:
            break
        threading.Event().wait(0.01)
    assert got.get(2) == "+Z" and [m[1] for m in mover.moves] == ["a", "+Z"]


def test_boards_waiting_at_the_plate_do_not_spin():
    """Fifteen boards wait at the plate (done with their attitudes) while the sixteenth is
    busy elsewhere for a second: the waiting costs next to no CPU (the issue's hang kept
    most of a core busy). Default wake-up period, real condition waits."""
    import time
    clock, phases, ref = Clock(), {}, []
    mover = Mover(clock, ref, phases)
    plate = Plate(mover, list(range(1, 17)))
    ref.append(plate)
    ts = [threading.Thread(target=plate.request, args=(s, Need("verify", ("+Z",)), {"+Z": ("+Z", None, 0, 3)}),
                           kwargs={"clock": clock}, daemon=True) for s in range(1, 16)]
    for t in ts:
        t.start()
    threading.Event().wait(0.2)
    cpu0, wall0 = time.process_time(), time.monotonic()
    threading.Event().wait(1.0)                 # slot 16 is fitting and writing back
    cpu = time.process_time() - cpu0
    wall = time.monotonic() - wall0
    assert all(t.is_alive() for t in ts) and not mover.moves
    assert cpu < 0.1 * wall, f"{cpu:.3f} s of CPU in {wall:.2f} s of waiting"
    plate.request(16, Need("verify", ("+Z",)), {"+Z": ("+Z", None, 0, 3)}, clock=clock)
    for t in ts:
        t.join(5)
    assert not any(t.is_alive() for t in ts) and [m[1] for m in mover.moves] == ["+Z"]
