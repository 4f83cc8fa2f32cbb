"""Pose capture without I/O: fed with sample blocks, it finds the moment the board is still in
a planned attitude and returns the pose captured there.

The session (procedures.session) reads the device and feeds each block; a test feeds arrays.
What the capture tells the person (hints, the live view, the pose cards) goes to a Presenter.
"""
from __future__ import annotations

import numpy as np

from imubench import units as U
from imubench.calib.static import detect_static
from imubench.calib.stillness import StillnessDetector
from imubench.procedures.config import PoseRecord, SessionConfig
from imubench.procedures.errors import SessionAborted
from imubench.procedures.poses import (
    DETECT_TOL_DEG,
    detect_attitude,
    hold_sigma_g,
    plan_angles_deg,
    pose_words,
)
from imubench.procedures.presenter import Presenter
from imubench.wire.decoder import SampleBlock


def _pieces(b: SampleBlock, n: int):
    """A block in consecutive pieces of at most n samples."""
    for i in range(0, len(b), n):
        yield b[i:i + n]






class PoseCapture:
    """One pose of a session: feed(block) until it returns the PoseRecord.

    Waits until the board is still in one of the `plan` attitudes (those not yet captured), in
    whatever order they come. The attitude the board is in is detected live (from the
    direction of the specific force) and told to the presenter; one that is not planned, or
    already captured, is named with a hint and waited past. Motion restarts the capture. The
    hold is cfg.hold_s, or with cfg.adaptive until the mean |a| is known to
    targets.pose_sigma_mg (hold_min_s .. hold_max_s). SessionAborted after cfg.pose_timeout_s
    of samples (device time) when it is set."""

    def __init__(self, cfg: SessionConfig, noise_mps2, plan: list, full_plan: list | None = None,
                 captured: set[str] | frozenset = frozenset(), stream_no: int = 0, ui: Presenter | None = None):
        self.cfg = cfg
        self.noise = np.asarray(noise_mps2, dtype=float)     # the rest's noise: every threshold's scale
        self.plan = list(plan)                               # the attitudes still missing
        self.full_plan = list(full_plan or plan)             # every planned attitude (named when detected)
        self.captured = set(captured)                        # names already captured
        self.stream_no = stream_no                           # goes into the record (capture-<n>.bin)
        self.ui = ui if ui is not None else Presenter()
        self.record: PoseRecord | None = None
        self._steps = self._run()
        next(self._steps)                                    # up to the first block

    def feed(self, block: SampleBlock) -> PoseRecord | None:
        """Judge the next block; the pose once it is captured (then always the same), else None."""
        if self.record is None:
            try:
                self._steps.send(block)
            except StopIteration as done:
                self.record = done.value
        return self.record

    def _run(self):
        fs = self.cfg.rate_hz
        t = self.cfg.targets
        noise = self.noise
        plan, full_plan = self.plan, self.full_plan
        todo_names = {n for n, _ in plan}
        name = plan[0][0]
        det = StillnessDetector(fs, noise, window_s=self.cfg.settle_s)
        if self.cfg.adaptive:
            hold_min, hold_n = int(t.hold_min_s * fs), int(t.hold_max_s * fs)
        else:
            hold_min = hold_n = int(self.cfg.hold_s * fs)
        recent: list[SampleBlock] = []   # enough trailing blocks to cover the still run
        recent_n = 0
        waited = 0
        last_msg = ""
        was_still = False
        prev_n = 0
        judged = False                   # this still run was already judged (wrong attitude)
        capturing = None                 # the planned attitude being held now
        sigma_g = float("inf")
        next_sigma = 0                   # st.n at which sigma is computed next
        live_every = max(1, fs // 8)
        live_due = 0
        while True:
            # a block read after a pause (a virtual bench far ahead of the session) can hold
            # seconds of data: judge it in pieces of 1/10 s, as a live stream would come
            for b in _pieces((yield), max(1, fs // 10)):
                waited += len(b)
                recent.append(b)
                recent_n += len(b)
                acc = b.si()[0]
                st = det.update(acc)
                still = st.state == "still"
                # the still run restarted inside this block if it is shorter than before + the block
                restarted = still and (not was_still or st.n < prev_n + len(b))
                if not still or restarted:
                    if was_still and not judged and (st.state == "moving" or restarted):
                        last_msg = self._tell("detected motion, hold still", last_msg)
                    if capturing is not None:
                        self.ui.pose_event(capturing, "todo", {"why": "moved"})
                        capturing = None
                    judged = False
                    sigma_g, next_sigma = float("inf"), 0
                was_still, prev_n = still, (st.n if still else 0)
                # which attitude the board is in now (the hold's mean when still, else the last block's)
                now_dir = st.mean if still else acc.mean(axis=0)
                k, ang = detect_attitude(now_dir, full_plan)
                now_name = full_plan[k][0] if k is not None else None
                hint = self._hint(st.state, now_dir, now_name, ang, todo_names)
                frac = 0.0
                if (st.state == "settling" and not hint and k is not None and st.still_s > 0
                        and not judged):
                    # quiet, not yet for settle_s: the first half of the card's bar
                    if capturing not in (None, now_name):
                        self.ui.pose_event(capturing, "todo", {"why": "left"})
                    capturing = now_name
                    frac = 0.5 * min(1.0, st.still_s / self.cfg.settle_s)
                    self.ui.progress(now_name, frac)
                    self.ui.pose_event(now_name, "capturing", {"progress": frac})
                if still and not judged:
                    if hint:
                        last_msg = self._tell(hint, last_msg)
                        judged = True        # wait for the board to move before judging again
                    else:
                        if capturing != now_name:
                            if capturing is not None:     # drifted into another attitude while still
                                self.ui.pose_event(capturing, "todo", {"why": "left"})
                            capturing = now_name
                        if self.cfg.adaptive and st.n >= max(hold_min, next_sigma):
                            run = SampleBlock.concat(recent)
                            sigma_g = hold_sigma_g(run.si()[0][len(run) - min(st.n, len(run)):])
                            next_sigma = st.n + max(1, fs // 10)
                        if self.cfg.adaptive:
                            # sigma of the mean falls as 1/sqrt(n): (need/sigma)^2 is the fraction held
                            need = t.pose_sigma_mg * 1e-3
                            by_sigma = min(1.0, (need / sigma_g) ** 2) if np.isfinite(sigma_g) else 0.0
                            frac = max(st.n / hold_n, min(st.n / hold_min, by_sigma) if by_sigma else 0.5 * st.n / hold_min)
                            enough = st.n >= hold_n or (st.n >= hold_min and sigma_g <= need)
                        else:
                            frac = st.n / hold_n
                            enough = st.n >= hold_n
                        frac = 0.5 + 0.5 * min(float(frac), 1.0)     # settled: the second half of the bar
                        self.ui.progress(now_name, frac)
                        self.ui.pose_event(now_name, "capturing", {"progress": frac})
                        if enough:
                            # exactly the samples of this still run: the last st.n received (at most the hold)
                            run = SampleBlock.concat(recent)
                            rec = self._pose_from(run[len(run) - min(st.n, hold_n, len(run)):], plan)
                            if isinstance(rec, PoseRecord):
                                return rec
                            self.ui.pose_event(now_name, "rejected", {"why": rec})
                            capturing = None
                            last_msg = self._tell(rec, last_msg)
                            judged = True
                if waited >= live_due:
                    live_due = waited + live_every
                    self.ui.live({
                        "a_g": float(np.linalg.norm(acc.mean(axis=0)) / U.G0_MPS2), "ratio": float(st.ratio),
                        "k": float(det.k), "k_move": float(det.k_move), "state": st.state,
                        "attitude": now_name, "words": pose_words(full_plan[k][1]) if k is not None else None,
                        "angle_deg": ang, "captured": bool(now_name and now_name not in todo_names),
                        "hold": float(min(frac, 1.0)),
                        "sigma_mg": (sigma_g * 1e3 if np.isfinite(sigma_g) else None),
                        "target_mg": t.pose_sigma_mg if self.cfg.adaptive else None, "hint": hint,
                        "device_s": float(b.sample_index[-1]) / fs})
                while len(recent) > 1 and recent_n - len(recent[0]) >= max(st.n, hold_n) + fs:
                    recent_n -= len(recent.pop(0))
                if self.cfg.pose_timeout_s is not None and waited > self.cfg.pose_timeout_s * fs:
                    raise SessionAborted(f"no still attitude from the plan within {self.cfg.pose_timeout_s:g} s "
                                         f"({len(plan)} missing, e.g. {name}); the board must stay still for "
                                         f"{self.cfg.settle_s + self.cfg.hold_s:g} s in each attitude")

    def _hint(self, state: str, now_dir: np.ndarray, now_name: str | None, ang: float, todo_names: set) -> str:
        """What to tell the person about the attitude the board is in ("" when it is a missing one)."""
        if state == "moving":
            return ""                             # no hint while the person is still turning it
        if now_name is None:
            near = self.full_plan[int(np.argmin(plan_angles_deg(now_dir, self.full_plan)))]
            return (f"the board is in no planned attitude: {ang:.0f}° from the nearest, "
                    f"{near[0]} ({pose_words(near[1])}); turn it until it is within "
                    f"{DETECT_TOL_DEG:.0f}° of a missing one")
        if now_name not in todo_names:
            return f"{now_name} is already captured: present one of the {len(self.plan)} missing"
        return ""

    def _tell(self, msg: str, last: str) -> str:
        if msg != last:
            self.ui.say(msg)
        return msg

    def _pose_from(self, b: SampleBlock, plan) -> PoseRecord | str:
        acc, gyr = b.si()
        mean = acc.mean(axis=0)
        d = mean / np.linalg.norm(mean)
        angles = [np.degrees(np.arccos(np.clip(d @ (v / np.linalg.norm(v)), -1, 1))) for _, v in plan]
        k = int(np.argmin(angles))
        done = self.captured
        if angles[k] > DETECT_TOL_DEG:
            return (f"the board is not in a missing attitude (up along board {np.round(d, 2).tolist()}); "
                    f"{len(plan)} missing, e.g. {plan[0][0]}")
        name, direction = plan[k]
        if name in done:
            return f"{name} is already captured: present another attitude"
        a_g = float(np.linalg.norm(mean)) / U.G0_MPS2
        if abs(a_g - 1.0) > 0.1:
            return (f"{name}: |a| = {a_g:.3f} g, more than 10 % from 1 g: the board was being moved or shaken; "
                    "hold it still")
        iv = detect_static(acc, self.cfg.rate_hz, noise_sigma=self.noise,
                           min_duration_s=min(1.0, 0.5 * len(acc) / self.cfg.rate_hz))
        sigma = (max(iv, key=lambda i: i.n).sigma_mean if iv else acc.std(axis=0) / np.sqrt(len(acc)))
        temp = float(np.mean(U.accel_temp_counts_to_c(b.accel_temp_counts)))
        return PoseRecord(name=name, direction=np.asarray(direction, float).tolist(), mean_mps2=mean.tolist(),
                          sigma_mean_mps2=np.asarray(sigma, float).tolist(), n=len(acc),
                          start_index=int(b.sample_index[0]), stop_index=int(b.sample_index[-1]) + 1,
                          temp_c=temp, gyro_mean_rad_s=gyr.mean(axis=0).tolist(), stream=self.stream_no,
                          sigma_norm_g=hold_sigma_g(acc), angle_from_plan_deg=float(angles[k]))

