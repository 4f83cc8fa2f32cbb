"""The face of a session: what a session tells the person (or the virtual bench) and asks of them.

A presenter subclasses Presenter and overrides what it shows; every hook the session calls is
a method here, so a presenter that does not show something inherits a no-op (or the sensible
default written here), and a misspelt override is a method the session never calls that a
test of the presenter finds, not a hook silently skipped. The session calls these and nothing
else: no hook is discovered by name at run time.

The faces: cli/terminal.py (HumanPresenter), station/presenter.py (WebPresenter, the station
page), procedures/virtual.py (SimPresenter, PlatePresenter, SimPerson: the virtual bench) and
procedures/fixture.py (BoardPresenter: one board of several on a shared plate).
"""
from __future__ import annotations

import numpy as np

TURN_POSE_SUFFIX = " (for a turn)"     # names the attitude of a known-angle turn (presenters tell it apart)


class Presenter:
    """What a session needs from its face. Every method is a hook with a default."""

    # ------------------------------------------------------------ telling
    def say(self, text: str) -> None:
        """A line for the person (instructions, results, warnings)."""

    def progress(self, label: str, fraction: float) -> None:
        """How far a hold or the rest is, 0..1."""

    # ------------------------------------------------------------ moving the board
    def present_plan(self, plan: list, method: str) -> None:
        """The attitudes planned [(name, direction)], before anything (six or multi)."""

    def present_rest(self, duration_s: float) -> None:
        """Hold the board still for duration_s at the start (noise and gyro bias)."""

    def present_todo(self, todo: list, done: list, total: int) -> None:
        """The attitudes still missing, to be presented in any order ([(name, direction)];
        `done` those captured). Default: present the first missing one as a directed pose."""
        name, direction = todo[0]
        self.present_pose(name, direction, len(done), total)

    def present_pose(self, name: str, direction: np.ndarray, index: int, total: int) -> None:
        """One attitude, asked for directly (verification; a fixture's directed poses)."""

    def present_turn(self, axis: np.ndarray, rate_dps: float, duration_s: float) -> None:
        """A turntable turn at rate_dps about the board axis `axis` for duration_s."""

    def present_known_turn(self, up: np.ndarray, angle_deg: float) -> None:
        """A known-angle turn by hand about the vertical (board `up` up): --gyro turns."""
        self.say(f"turn the board one full turn ({angle_deg:g}°) on the table about the vertical "
                 f"(board {np.round(up, 2).tolist()} up), then let it lie still")

    def keep_pose(self, name: str, summary: str) -> bool:
        """Keep the pose just captured (True) or capture it again (False)."""
        return True

    # ------------------------------------------------------------ what the session measures
    def live(self, state: dict) -> None:
        """A few times a second while waiting for a pose: a_g, ratio, k, k_move, state,
        attitude, words, angle_deg, captured, hold, sigma_mg, target_mg, hint, device_s."""

    def pose_event(self, name: str, state: str, detail: dict) -> None:
        """A pose card: "capturing" (progress), "done" (before_g, after_g later), "rejected"
        (why), "todo" (why: moved, left)."""

    def targets(self, sigmas: dict, targets: dict, reached: bool) -> None:
        """An adaptive session's parameter sigmas against their targets."""

    def suggest(self, name: str) -> None:
        """The missing attitude that helps the multi-position fit most."""

    def step(self, kind: str, text: str, state: str) -> None:
        """A step after the capture: kind fit/write/verify; state running/done/failed/skipped."""
