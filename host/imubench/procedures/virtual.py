"""The virtual presenters: what moves the virtual bench for a session.

SimPresenter (one virtual board: every attitude by a real rotation, the turntable),
PlatePresenter (the virtual fixture: one plate carrying several virtual boards) and SimPerson
(a simulated person at the virtual bench: any order, hand moves, tremor).
"""
from __future__ import annotations

import math

import numpy as np

from imubench.calib.geometry import rotation_to
from imubench.procedures.presenter import Presenter


#: how long the virtual person waits after the prompt before a known-angle turn, device s
KNOWN_TURN_PAUSE_S = 1.0


class SimPresenter(Presenter):
    """Drives the virtual bench: moves the board by real rotations (so the gyros see the
    motion) and runs the turntable. Optional tilt_deg misaligns every pose (a box that is
    not square, a table that is not level)."""

    def __init__(self, vb, rate_dps: float = 90.0, tilt_deg: float = 0.0, seed: int = 0, quiet: bool = False):
        self.vb = vb
        self.rate_dps = rate_dps
        self.tilt_deg = tilt_deg
        self.rng = np.random.default_rng(seed)
        self.quiet = quiet

    def say(self, text):
        if not self.quiet:
            print(text, flush=True)

    def _rotate_to(self, target: np.ndarray) -> None:
        turn = rotation_to(self.vb.status()["gravity_board"], target)
        if turn is not None:
            axis, angle = turn
            self.vb.rotate(axis, rate_dps=self.rate_dps, duration_s=angle / self.rate_dps, wait=True)

    def present_pose(self, name, direction, index, total):
        d = _tilted(direction, self.tilt_deg, self.rng) if self.tilt_deg else np.asarray(direction, dtype=float)
        self.say(f"[{index + 1}/{total}] virtual bench presents {name}")
        self._rotate_to(d)

    def present_turn(self, axis, rate_dps, duration_s):
        self.say(f"virtual turntable: {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()} for {duration_s:g} s")
        self.vb.rotate(list(axis), rate_dps=rate_dps, duration_s=duration_s, wait=False)

    def present_known_turn(self, up, angle_deg):
        """--gyro turns: turn the virtual board through angle_deg about its current vertical."""
        g = np.asarray(self.vb.status()["gravity_board"], dtype=float)
        g /= np.linalg.norm(g)
        self.say(f"virtual bench turns the board {angle_deg:g}° about the vertical (board {np.round(g, 2).tolist()})")
        # a person reads the prompt first: the board lies still a moment longer (in lockstep the
        # turn would otherwise start on the sample the rest was seen complete, and a recording
        # analysed later finds that rest cut short by its own detection windows)
        self.vb.wait(KNOWN_TURN_PAUSE_S)
        self.vb.rotate(list(g), rate_dps=-self.rate_dps, duration_s=angle_deg / self.rate_dps, wait=False)


class PlatePresenter(SimPresenter):
    """The virtual fixture: one plate carrying several virtual devices (benches[k] is slot
    k + 1). Every attitude and every turn is made on all of them at once (each simulator's
    own rotation, so each board's gyros see the motion).

    Each board is its own failure domain: the plate moves only the boards still on it
    (`carry(slots)`, told by fixture.Plate before each move), and a bench that does not
    answer within guard_wall_s of wall time (a frozen process: its device time stands
    still, so only the wall clock can tell), fails a command in any way, or whose process
    is gone, is left out from then on and reported once by `take_lost()` ({slot: reason});
    the move goes on for the others."""

    def __init__(self, benches: list, rate_dps: float = 90.0, tilt_deg: float = 0.0, seed: int = 0,
                 quiet: bool = False, guard_wall_s: float = 10.0):
        super().__init__(benches[0], rate_dps=rate_dps, tilt_deg=tilt_deg, seed=seed, quiet=quiet)
        self.benches = list(benches)
        self.guard_wall_s = float(guard_wall_s)
        self._carry: set[int] | None = None      # None: every bench (no plate told otherwise)
        self._gone: dict[int, str] = {}          # slot -> why it was left out (kept)
        self._new_lost: dict[int, str] = {}      # reported by the next take_lost()

    def carry(self, slots) -> None:
        """The boards still on the plate (1-based slots): the others are not moved."""
        self._carry = set(slots)

    def take_lost(self) -> dict[int, str]:
        """The boards this plate could not move since the last call, with why."""
        out, self._new_lost = self._new_lost, {}
        return out

    def _carried(self) -> list[tuple[int, object]]:
        out = []
        for slot, b in enumerate(self.benches, 1):
            if slot in self._gone or (self._carry is not None and slot not in self._carry):
                continue
            if not b.running:
                self._lose(slot, "its virtual device is gone (the simulator process ended)")
                continue
            out.append((slot, b))
        return out

    def _lose(self, slot: int, why: str) -> None:
        self._gone[slot] = why
        self._new_lost[slot] = why

    def _alive(self) -> list:
        return [b for _, b in self._carried()]

    def _rotate_to(self, target: np.ndarray) -> None:
        g = None
        for slot, b in self._carried():              # where the plate is: the first bench that answers
            try:
                g = b.control("status", timeout=self.guard_wall_s)["gravity_board"]
                self.vb = b
                break
            except Exception as e:  # noqa: BLE001 - that board's fault, not the plate's
                self._lose(slot, _no_answer(e, self.guard_wall_s))
        if g is None:
            return
        turn = rotation_to(g, target)
        if turn is None:
            return
        ax, angle = turn
        d = angle / self.rate_dps
        self._each(lambda b: b.control("rotate", axis=[float(x) for x in ax], rate_dps=float(self.rate_dps),
                                       duration_s=float(d), timeout=self.guard_wall_s))
        self._each(lambda b: b.wait_idle(timeout=self.guard_wall_s + b.time.timeout_for(d), device_limit_s=d + 30.0))

    def present_turn(self, axis, rate_dps, duration_s):
        self.say(f"virtual turntable: {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()} for {duration_s:g} s")
        self._each(lambda b: b.control("rotate", axis=[float(x) for x in axis], rate_dps=float(rate_dps),
                                       duration_s=float(duration_s), timeout=self.guard_wall_s))

    def _each(self, fn) -> None:
        for slot, b in self._carried():
            try:
                fn(b)
            except Exception as e:  # noqa: BLE001 - that board's simulator failed: the plate carries the others
                self._lose(slot, _no_answer(e, self.guard_wall_s))


def _no_answer(e: BaseException, guard_s: float) -> str:
    import re
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    m = re.search(r"no reply to (\w+)", text)
    if m or "timed out" in text:
        what = f" to {m.group(1)}" if m else ""
        return (f"its virtual device stopped answering the plate (no reply{what} within {guard_s:g} s of wall "
                "time: a frozen simulator)")
    return f"the plate could not move its virtual device ({text})"


#: tremor: legs of this length, each turning by a random angle of this RMS about a random
#: axis and back (a few hundredths of a degree RMS of attitude, a few Hz)
TREMOR_LEG_S = 0.15
TREMOR_RMS_DEG = 0.04
TREMOR_LEGS = 30      # the simulator's path takes at most 32 legs (SIM_PATH_MAX_LEGS)


class SimPerson(SimPresenter):
    """A SimPresenter that behaves like a person: any order, hand moves, tremor.

    move_s       (min, max) duration of a move between attitudes, device seconds
    offset_deg   (min, max) how far from the planned attitude the board is placed
    tremor_deg   RMS of the tremor's turns (0: a fixture)
    wrong_first  present one attitude that is in no plan first (to see the session's hint), then
                 the right one
    forward      another presenter (e.g. the station page's) that also gets every call
    """

    def __init__(self, vb, seed: int = 0, move_s=(3.0, 8.0), offset_deg=(5.0, 10.0),
                 tremor_deg: float = TREMOR_RMS_DEG, wrong_first: bool = False, forward=None, quiet: bool = True):
        super().__init__(vb, seed=seed, quiet=quiet)
        self.move_s = move_s
        self.offset_deg = offset_deg
        self.tremor_deg = tremor_deg
        self.wrong_first = wrong_first
        self.forward = forward if forward is not None else Presenter()     # a face that shows nothing
        self.order: list[str] = []          # attitudes in the order presented
        self.moves_s = 0.0                  # device time spent moving

    # everything the session says or shows also goes to the forwarded presenter
    def present_plan(self, plan, method):
        self.forward.present_plan(plan, method)

    def live(self, state):
        self.forward.live(state)

    def pose_event(self, name, state, detail):
        self.forward.pose_event(name, state, detail)

    def targets(self, sigmas, targets, reached):
        self.forward.targets(sigmas, targets, reached)

    def step(self, kind, text, state):
        self.forward.step(kind, text, state)

    def suggest(self, name):
        self.forward.suggest(name)

    def say(self, text):
        super().say(text)
        self.forward.say(text)

    def progress(self, label, fraction):
        self.forward.progress(label, fraction)

    def keep_pose(self, name, summary):
        return self.forward.keep_pose(name, summary)

    def present_turn(self, axis, rate_dps, duration_s):
        self.forward.present_turn(axis, rate_dps, duration_s)
        super().present_turn(axis, rate_dps, duration_s)

    # ------------------------------------------------------------------ the person
    def present_known_turn(self, up, angle_deg):
        self.forward.present_known_turn(up, angle_deg)
        super().present_known_turn(up, angle_deg)

    def present_rest(self, duration_s):
        self.forward.present_rest(duration_s)
        self._tremor()

    def present_todo(self, todo, done, total):
        self.forward.present_todo(todo, done, total)
        name, direction = todo[int(self.rng.integers(len(todo)))]
        self.order.append(name)
        self.say(f"simulated person presents {name}")
        if self.wrong_first:
            # first between two planned attitudes, held there ~4 s (the session hints), then
            # on to the one meant: one path, so the session sees it as it happens
            self.wrong_first = False
            cur = self._gravity()
            off = self._off_plan(direction)
            legs = self._legs(cur, off) + self._tremor_legs()[:26] + self._legs(off, self._placed(direction))
            self.vb.path(legs + self._tremor_legs()[:32 - len(legs)], wait=False)
            return
        self._move_to(self._placed(direction))

    def present_pose(self, name, direction, index, total):
        """Verification (and presenters without present_todo): the attitude asked for."""
        self.forward.present_pose(name, direction, index, total)
        self._move_to(self._placed(direction))

    def _placed(self, direction) -> np.ndarray:
        lo, hi = self.offset_deg
        return _tilted(direction, self.rng.uniform(lo, hi), self.rng)

    def _off_plan(self, direction) -> np.ndarray:
        """An attitude between planned ones: of a few hundred random directions, the farthest
        from every planned attitude (the plan leaves gaps of up to 27° between them)."""
        from imubench.calib.accel import POSE_PLAN
        plan = np.array([p.vector for p in POSE_PLAN], float)
        plan /= np.linalg.norm(plan, axis=1)[:, None]
        c = self.rng.normal(size=(500, 3))
        c /= np.linalg.norm(c, axis=1)[:, None]
        nearest = np.max(c @ plan.T, axis=1)             # cosine to the nearest planned attitude
        return c[int(np.argmin(nearest))]

    def _gravity(self) -> np.ndarray:
        cur = np.asarray(self.vb.status()["gravity_board"], dtype=float)
        return cur / np.linalg.norm(cur)

    def _legs(self, cur, target) -> list[dict]:
        """One hand move (a random 3-8 s, minimum jerk) turning gravity direction cur into target."""
        turn = rotation_to(cur, target)
        t = float(self.rng.uniform(*self.move_s))
        self.moves_s += t
        if turn is None:
            return []
        axis, angle = turn
        return [{"duration_s": t, "axis": [float(x) for x in axis], "turn_deg": angle}] if angle > 1e-6 else []

    def _move_to(self, target) -> None:
        self.vb.path(self._legs(self._gravity(), target) + self._tremor_legs(), wait=False)

    def _tremor_legs(self) -> list[dict]:
        if not self.tremor_deg:
            return []
        legs = []
        for _ in range(TREMOR_LEGS // 2):
            ax = self.rng.normal(size=3)
            ax /= np.linalg.norm(ax)
            a = float(self.rng.normal(0.0, self.tremor_deg))
            legs += [{"duration_s": TREMOR_LEG_S, "axis": ax.tolist(), "turn_deg": a},
                     {"duration_s": TREMOR_LEG_S, "axis": ax.tolist(), "turn_deg": -a}]
        return legs

    def _tremor(self) -> None:
        legs = self._tremor_legs()
        if legs:
            self.vb.path(legs, wait=False)


def _tilted(direction, deg: float, rng) -> np.ndarray:
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    perp = np.cross(d, rng.normal(size=3))
    perp /= np.linalg.norm(perp)
    t = math.radians(deg)
    return math.cos(t) * d + math.sin(t) * perp
