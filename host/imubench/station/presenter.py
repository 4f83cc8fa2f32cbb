"""WebPresenter: the Presenter (imubench.procedures.presenter) of a session driven from the
station page. Everything the session says or measures goes into the device's DeviceBoard;
the page shows it. A stop asked for on the page raises SessionStopped at the next live
update, so the session stops where a Ctrl-C would stop it (everything captured is kept)."""
from __future__ import annotations

import threading
import time

import numpy as np

from imubench.errors import ImubenchError
from imubench.procedures.poses import pose_words
from imubench.procedures.presenter import TURN_POSE_SUFFIX, Presenter
from imubench.station.state import StationState

LOG_LINES = 200
LIVE_MIN_INTERVAL_S = 0.1       # at most ten live updates a second reach the pages


class SessionStopped(ImubenchError, RuntimeError):
    """The owner of the device stopped the session on the page."""


class WebPresenter(Presenter):
    def __init__(self, state: StationState, key: str):
        self.state = state
        self.key = key
        self.stop_event = threading.Event()
        self.stop_reason = "stopped on the station page: everything captured is kept; resume it there"
        self._last_live = 0.0
        self.turns_total = 0            # turntable turns the session will ask for (set by the runner)

    def _upd(self, fn) -> None:
        self.state.update(self.key, fn)

    def stop(self, reason: str | None = None) -> None:
        """Ask the session to stop at its next update (SessionStopped with the reason)."""
        if reason:
            self.stop_reason = reason
        self.stop_event.set()

    def check_stop(self) -> None:
        if self.stop_event.is_set():
            raise SessionStopped(self.stop_reason)

    # ------------------------------------------------------------- Presenter
    def say(self, text: str) -> None:
        stamp = time.strftime("%H:%M:%S")

        def f(b):
            b.log.append(f"{stamp} {text}")
            del b.log[:-LOG_LINES]
        self._upd(f)

    def present_plan(self, plan, method) -> None:
        cards = [{"name": n, "words": pose_words(v), "direction": [float(x) for x in np.asarray(v)],
                  "state": "todo", "progress": 0.0, "seq": None, "why": None, "before_g": None, "after_g": None}
                 for n, v in plan]

        def f(b):
            keep = {c["name"]: c for c in b.plan}    # a resumed session keeps what the page knew
            b.plan = [keep.get(c["name"], c) for c in cards]
            b.method = method
            b.phase = "poses"
        self._upd(f)

    def present_rest(self, duration_s) -> None:
        self._upd(lambda b: setattr(b, "phase", "rest"))

    def present_todo(self, todo, done, total) -> None:
        self.check_stop()
        self._upd(lambda b: setattr(b, "phase", "poses"))

    def present_pose(self, name, direction, index, total) -> None:
        """Directed poses: the attitude before a known-angle turn (--gyro turns), or a
        verification pose after the write-back; one step each."""
        self.check_stop()
        if name.endswith(TURN_POSE_SUFFIX):
            kind, text = "turn-pose", (f"turn {index + 1} of {total}: lay the board on the table, "
                                       f"{pose_words(direction)}, and let it lie still")
        else:
            kind, text = "verify-pose", f"verify: {name} ({pose_words(direction)})"

        def f(b):
            for s in b.steps:
                if s["state"] == "running" and s["kind"] in ("turn-pose", "verify-pose"):
                    s["state"] = "done"
            b.steps.append({"kind": kind, "text": text, "state": "running", "direction": [float(x) for x in direction]})
            if kind == "turn-pose":
                b.phase = "turns"
        self._upd(f)

    def present_known_turn(self, up, angle_deg) -> None:
        """--gyro turns: the person turns the board by hand through angle_deg about the vertical."""
        self.check_stop()

        def f(b):
            for t in b.turns:
                t["state"] = "done"
            b.turns.append({"axis": [float(x) for x in up], "rate_dps": None, "angle_deg": float(angle_deg),
                            "duration_s": None, "state": "running", "by_hand": True, "total": 3})
            b.phase = "turns"
        self._upd(f)

    def present_turn(self, axis, rate_dps, duration_s) -> None:
        self.check_stop()

        def f(b):
            for t in b.turns:
                t["state"] = "done"
            b.turns.append({"axis": [float(x) for x in axis], "rate_dps": float(rate_dps),
                            "duration_s": float(duration_s), "state": "running",
                            "total": self.turns_total or None})
            b.phase = "turns"
        self._upd(f)

    def progress(self, label, fraction) -> None:
        if label == "rest":
            self._upd(lambda b: b.live.update({"rest": float(fraction)}))

    def keep_pose(self, name, summary) -> bool:
        return True

    def live(self, st: dict) -> None:
        self.check_stop()
        now = time.monotonic()
        if now - self._last_live < LIVE_MIN_INTERVAL_S:
            return
        self._last_live = now
        self._upd(lambda b: setattr(b, "live", dict(st)))

    def pose_event(self, name, state, detail) -> None:
        def f(b):
            for c in b.plan:
                if c["name"] != name:
                    continue
                if state == "done" and c["state"] != "done":
                    b.done_seq += 1
                    c["seq"] = b.done_seq
                if state == "done":
                    c["progress"] = 1.0
                    for k in ("before_g", "after_g", "sigma_mg", "angle_from_plan_deg"):
                        if detail.get(k) is not None:
                            c[k] = detail[k]
                elif state == "capturing":
                    c["progress"] = float(detail.get("progress", 0.0))
                elif state == "rejected":
                    c["why"] = detail.get("why")
                elif state == "todo":
                    c["progress"] = 0.0
                if not (c["state"] == "done" and state != "done"):
                    c["state"] = state
        self._upd(f)

    def suggest(self, name) -> None:
        self._upd(lambda b: setattr(b, "suggested", name))

    def targets(self, sigmas, targets, reached) -> None:
        self._upd(lambda b: setattr(b, "targets", {"sigmas": sigmas, "targets": targets, "reached": bool(reached)}))

    def step(self, kind, text, state) -> None:
        def f(b):
            for s in b.steps:
                if s["kind"] in ("verify-pose", "turn-pose") and s["state"] == "running":
                    s["state"] = "done"
            if kind == "fit":
                for t in b.turns:
                    t["state"] = "done"
                for c in b.plan:                 # the attitudes are over: nothing is being captured
                    if c["state"] == "capturing":
                        c["state"], c["progress"] = "todo", 0.0
            for s in b.steps:
                if s["kind"] == kind:
                    s.update(text=text, state=state)
                    break
            else:
                b.steps.append({"kind": kind, "text": text, "state": state})
            b.phase = kind
        self._upd(f)
