"""The terminal face of a calibration session: what a person at the bench reads and answers
(a Presenter, imubench.procedures.session)."""
from __future__ import annotations

import sys

import numpy as np


class HumanPresenter:
    """Instructions on the terminal, progress bars with tqdm."""

    def __init__(self):
        self._bar = None
        self._label = None

    def say(self, text: str) -> None:
        self._close_bar()
        print(text, flush=True)

    def present_pose(self, name, direction, index, total):
        self.say(f"[{index + 1}/{total}] place the board: {name} "
                 f"(gravity along board {np.round(direction, 2).tolist()}), then hold it still")

    def present_turn(self, axis, rate_dps, duration_s):
        self.say(f"turn the table about board axis {np.round(axis, 2).tolist()} at {rate_dps:+.1f} °/s "
                 f"for {duration_s:.1f} s (start the turn now)")

    def present_known_turn(self, up, angle_deg):
        self.say(f"now turn the board by hand {angle_deg:g}° (one full turn) on the table about the vertical "
                 f"(board {np.round(up, 2).tolist()} up), keeping it flat, back to where it was; then let it lie still")

    def progress(self, label, fraction):
        from tqdm import tqdm
        if self._bar is None or self._label != label:
            self._close_bar()
            self._bar = tqdm(total=100, desc=label, leave=False, bar_format="{desc} {bar} {percentage:3.0f}%")
            self._label = label
        self._bar.n = int(round(100 * min(max(fraction, 0.0), 1.0)))
        self._bar.refresh()

    def _close_bar(self):
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def keep_pose(self, name, summary):
        """On a terminal the user may redo the pose just captured; otherwise keep it."""
        if not sys.stdin.isatty():
            return True
        answer = input(f"  {summary} — Enter to keep, r + Enter to redo: ").strip().lower()
        return answer != "r"
