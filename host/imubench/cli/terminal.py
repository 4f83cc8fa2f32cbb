"""The terminal face of a calibration session: what a person at the bench reads and answers
(a Presenter, imubench.procedures.presenter)."""
from __future__ import annotations

import sys

import numpy as np

from imubench.procedures.presenter import Presenter


class HumanPresenter(Presenter):
    """Instructions on the terminal, progress bars with tqdm."""

    def __init__(self):
        self._bar = None
        self._label = None
        self._listed = False            # the missing attitudes were listed with their words once
        self._suggested = None          # the attitude the multi-position fit wants next
        self._last_attitude = None      # (attitude, hint shown) last named by live()

    def say(self, text: str) -> None:
        self._close_bar()
        print(text, flush=True)

    def present_pose(self, name, direction, index, total):
        from imubench.procedures.poses import pose_words
        from imubench.results.boardpic import board_text
        self.say(f"[{index + 1}/{total}] place the board: {name}: {pose_words(direction)} "
                 f"(up along board {np.round(direction, 2).tolist()}), then hold it still\n"
                 + _indent(board_text(direction)))

    def present_todo(self, todo, done, total):
        """The attitudes still missing: the first time each with its words, then their names."""
        import textwrap

        from imubench.procedures.poses import pose_words
        head = f"[{len(done)}/{total} captured] present any missing attitude, in any order, and hold it still"
        if not self._listed:
            self._listed = True
            width = max(len(n) for n, _ in todo) + 2
            self.say(head + ":\n" + "\n".join(f"    {n:{width}s}{pose_words(d)}" for n, d in todo))
        else:
            self.say(textwrap.fill(f"{head}; missing: " + ", ".join(n for n, _ in todo), width=110,
                                   subsequent_indent="    "))
        sug = self._suggested
        if sug and sug in {n for n, _ in todo}:
            from imubench.calib.accel import POSE_PLAN
            d = next(p.vector for p in POSE_PLAN if p.name == sug)
            self.say(f"  suggested next (helps the fit most): {sug}: {pose_words(d)}")
        self._last_attitude = None

    def live(self, st):
        """Name the attitude the board is in as soon as it changes (and the hint, if any)."""
        att = st.get("attitude")
        key = (att, bool(st.get("hint")))
        if key == self._last_attitude or st.get("state") != "still":
            return
        self._last_attitude = key
        if att is None:
            return                                   # the session says the hint itself when still
        from imubench.calib.accel import POSE_PLAN
        d = next((p.vector for p in POSE_PLAN if p.name == att), None)
        if d is None:
            return
        from imubench.results.boardpic import board_text
        where = "already captured" if st.get("captured") else "capturing, hold still"
        self.say(f"  the board is in {att}: {st.get('words')} ({where})\n" + _indent(board_text(d)))

    def suggest(self, name):
        self._suggested = name

    def pose_event(self, name, state, detail):
        if state == "rejected":
            self.say(f"  {name} rejected: {detail.get('why')}")

    def targets(self, sigmas, targets, reached):
        pass                                          # the session says the line

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


def _indent(text: str, pad: str = "      ") -> str:
    return "\n".join(pad + line for line in text.splitlines())
