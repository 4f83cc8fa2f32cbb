"""The guided calibration session: capture, fit, write back, verify, record.

    imubench calibrate --port URL [--method multi|six] [--capture adaptive|plan] [--gyro turntable|rotation|bias]

One continuous raw stream runs for the whole session; every received byte is appended to
`capture.bin` in the session directory as it arrives, and `session.json` is rewritten
(atomically) after every accepted pose, so a crash or a lost connection loses nothing and
`--resume DIR` continues where the session stopped. The algorithms (imubench.calib) never
see the serial port: this module feeds them arrays.

A Presenter tells the user (or the virtual bench) which attitudes are still missing; the
session itself decides, from the data, when the board is still and which attitude it is in,
and captures the attitudes in whatever order they are presented (procedures.poses names them
in words and says when an adaptive session has enough).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import shlex
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from imubench import units as U
from imubench.calib import CalibrationError, TriadFit
from imubench.device.link import Device
from imubench.errors import ImubenchError
from imubench.files import MAX_CAPTURE_BYTES, open_growing, read_bytes
from imubench.procedures.poses import (
    DETECT_TOL_DEG,
    Targets,
    detect_attitude,
    enough_attitudes,
    hold_sigma_g,
    plan_angles_deg,
    pose_words,
    suggest_next,
)
from imubench.results.atomic import write_json_atomic
from imubench.results.sessionfile import SESSION_SCHEMA, SessionFileError, load_state
from imubench.wire import params as PR
from imubench.wire.decoder import SampleBlock
from imubench.wire.ids import board_name, uid_text
from imubench.wire.protocol_gen import Params, ParamsWhich


# ---------------------------------------------------------------- configuration
@dataclass
class Tolerances:
    accel_rms_mg: float = 1.0        # RMS of |a| - g over the poses after calibration
    verify_mg: float = 2.0           # each verification pose: | |a| - g | of the device's output
    gyro_turntable_rms_dps: float = 0.1
    gyro_rotation_rms_deg: float = 0.5


@dataclass
class SessionConfig:
    method: str = "six"              # "six" | "multi"
    gyro: str | None = "bias"        # "bias" | "turntable" | "rotation" | None
    rate_hz: int = 500
    rest_s: float = 5.0              # still at the start: noise and gyro bias
    settle_s: float = 0.5            # still this long before a pose is captured
    hold_s: float = 2.0              # captured per pose
    pose_timeout_s: float | None = 120.0   # waiting for an attitude, in device time; None: wait
    turntable_rates_dps: tuple = (30.0, 90.0)
    turntable_s: float = 3.0
    verify_poses: int = 3
    write: bool = True               # write the parameters back if the fit passes
    note: str = ""
    tolerances: Tolerances = field(default_factory=Tolerances)
    # adaptive capture (procedures.poses.Targets): each attitude held until its |a| is known to
    # targets.pose_sigma_mg; a multi-position session stops adding attitudes when every
    # parameter's sigma is at its target. False: hold_s per attitude, every planned attitude.
    adaptive: bool = False
    targets: Targets = field(default_factory=Targets)


@dataclass
class PoseRecord:
    name: str
    direction: list                  # planned gravity direction in the board frame
    mean_mps2: list                  # measured mean specific force (nominal scaling)
    sigma_mean_mps2: list            # 1-sigma of that mean
    n: int
    start_index: int                 # sample_index of the first sample used
    stop_index: int
    temp_c: float
    gyro_mean_rad_s: list
    stream: int = 0                  # which continuous stream (capture-<stream>.bin) it is in
    sigma_norm_g: float | None = None      # 1-sigma of the mean |a| over the hold, g
    angle_from_plan_deg: float | None = None   # measured gravity direction vs the planned one


class SessionAborted(ImubenchError, RuntimeError):
    """The session cannot go on; the message says why and what to do."""


# ---------------------------------------------------------------- presenters
class Presenter(Protocol):
    """What a session needs from its face (terminal, station page, virtual bench).

    Optional, called when the presenter has them (see _hook):
      present_plan(plan, method)                       the attitudes planned, before anything
      present_rest(duration_s)                         hold still at the start
      present_todo(todo, done, total)                  attitudes still missing, in any order:
                                                       todo/done are [(name, direction)]
      live(state: dict)                                a few times a second while waiting for a pose:
                                                       a_g, ratio, k, k_move, state, attitude,
                                                       angle_deg, hold, sigma_mg, hint
      pose_event(name, state, detail: dict)            "capturing" (progress) / "done" (before_g,
                                                       after_g later) / "rejected" (why) / "todo"
      targets(sigmas: dict, targets: dict, reached)    an adaptive session's parameter sigmas
      suggest(name)                                    the missing attitude that helps the fit most
      step(kind, text, state)                          fit / write-back / verification steps
    """
    def say(self, text: str) -> None: ...
    def present_pose(self, name: str, direction: np.ndarray, index: int, total: int) -> None: ...
    def present_turn(self, axis: np.ndarray, rate_dps: float, duration_s: float) -> None: ...
    def progress(self, label: str, fraction: float) -> None: ...
    def keep_pose(self, name: str, summary: str) -> bool: ...   # False: redo this pose


def _pieces(b: SampleBlock, n: int):
    """A block in consecutive pieces of at most n samples."""
    for i in range(0, len(b), n):
        yield b[i:i + n]


TURN_POSE_SUFFIX = " (for a turn)"     # names the attitude of a known-angle turn (presenters tell it apart)


def rotation_to(up_now, up_wanted) -> tuple[list[float], float] | None:
    """The turn (unit axis in the board frame, angle in degrees) that brings the board's up
    direction from up_now to up_wanted; None when it is there already."""
    cur = np.asarray(up_now, dtype=float)
    cur = cur / np.linalg.norm(cur)
    target = np.asarray(up_wanted, dtype=float)
    target = target / np.linalg.norm(target)
    axis = np.cross(target, cur)
    s, c = np.linalg.norm(axis), float(np.clip(cur @ target, -1.0, 1.0))
    if s < 1e-9:
        if c > 0:
            return None
        axis = np.cross(cur, [1.0, 0.0, 0.0] if abs(cur[0]) < 0.9 else [0.0, 1.0, 0.0])  # any perpendicular
    return list(axis / np.linalg.norm(axis)), float(np.degrees(np.arctan2(s, c)))


def _hook(ui, name: str, *args) -> None:
    """Call an optional presenter method if this presenter has it."""
    f = getattr(ui, name, None)
    if f is not None:
        f(*args)


class SimPresenter:
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
        d = np.asarray(direction, dtype=float)
        if self.tilt_deg:
            perp = np.cross(d, self.rng.normal(size=3))
            perp /= np.linalg.norm(perp)
            t = np.radians(self.tilt_deg)
            d = np.cos(t) * d + np.sin(t) * perp
        self.say(f"[{index + 1}/{total}] virtual bench presents {name}")
        self._rotate_to(d)

    def present_turn(self, axis, rate_dps, duration_s):
        self.say(f"virtual turntable: {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()} for {duration_s:g} s")
        self.vb.rotate(list(axis), rate_dps=rate_dps, duration_s=duration_s, wait=False)

    def progress(self, label, fraction):
        pass

    def keep_pose(self, name, summary):
        return True

    def present_known_turn(self, up, angle_deg):
        """--gyro turns: turn the virtual board through angle_deg about its current vertical."""
        g = np.asarray(self.vb.status()["gravity_board"], dtype=float)
        g /= np.linalg.norm(g)
        self.say(f"virtual bench turns the board {angle_deg:g}° about the vertical (board {np.round(g, 2).tolist()})")
        self.vb.rotate(list(g), rate_dps=-self.rate_dps, duration_s=angle_deg / self.rate_dps, wait=False)


# ---------------------------------------------------------------- the session
class Session:
    """One calibration run in a directory (created, or resumed)."""

    def __init__(self, device: Device, directory: str | os.PathLike, config: SessionConfig,
                 presenter: Presenter, resume: bool = False):
        self.dev = device
        self.dir = Path(directory)
        self.cfg = config
        self.ui = presenter
        self.poses: list[PoseRecord] = []
        self.rest: dict | None = None
        self.finished: dict | None = None    # the result of a run that went to its end (finish())
        self.state_path = self.dir / "session.json"
        if resume:
            self._load()
        else:
            self.dir.mkdir(parents=True, exist_ok=True)
            if self.state_path.exists():
                raise SessionAborted(f"{self.dir} already holds a session: use --resume {shlex.quote(str(self.dir))}, or another --dir")
            self.started = _now()
            self.save()

    # ------------------------------------------------------------ persistence
    def save(self, **extra) -> None:
        state = {"schema": SESSION_SCHEMA, "started": self.started, "config": _jsonable(asdict(self.cfg)),
                 "rest": self.rest, "poses": [asdict(p) for p in self.poses], **extra}
        write_json_atomic(self.state_path, state)     # a crash leaves the old or the new file

    def finish(self, result: dict) -> None:
        """Save the result of a run that went to its end (fit, write-back, verification, and
        whatever the caller adds). From now on the run is done: resuming this session returns
        this result, with the same identity (device, session start, run start), instead of
        starting a new run, so the history recognises it and never records it twice."""
        self.finished = result
        self.save(result=result, complete=True)

    def _load(self) -> None:
        try:
            state = load_state(self.dir)
        except SessionFileError as e:
            raise SessionAborted(f"cannot resume: {e}") from None
        self.started = state["started"]
        self.rest = state.get("rest")
        fields = {f.name: f for f in dataclasses.fields(PoseRecord)}
        for i, p in enumerate(state["poses"]):      # load_state checked the types of those present
            missing = [k for k, f in fields.items() if k not in p and f.default is dataclasses.MISSING]
            if missing:
                raise SessionAborted(f"cannot resume: {self.state_path} is damaged: 'poses[{i}].{missing[0]}' "
                                     "is missing; restore the file or start a new session")
        self.poses = [PoseRecord(**{k: v for k, v in p.items() if k in fields}) for p in state["poses"]]
        if state.get("complete") and isinstance(state.get("result"), dict):
            self.finished = state["result"]
        saved = state["config"]
        self.saved_write = bool(saved.get("write", self.cfg.write))
        if saved["method"] != self.cfg.method:
            self.ui.say(f"resuming a {saved['method']}-position session (ignoring --method {self.cfg.method})")
            self.cfg.method = saved["method"]

    def redo(self, names: list[str]) -> None:
        """Forget captured poses so that the next run() captures them again (their raw data
        stays in the capture files)."""
        known = {p.name for p in self.poses}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise SessionAborted(f"cannot redo {', '.join(unknown)}: captured poses are {', '.join(sorted(known))}")
        self.poses = [p for p in self.poses if p.name not in names]
        self.finished = None             # a new run: the finished one stays in the history
        self.save()

    # ---------------------------------------------------------------- health
    def check_health(self) -> dict:
        info = self.dev.info()
        names = ["ADXL355", "gyro X", "gyro Y", "gyro Z"]
        missing = [n for i, n in enumerate(names) if not info.sensors_present >> i & 1]
        if missing:
            raise SessionAborted(f"sensors missing: {', '.join(missing)} (device info) — check wiring and power; "
                                 "nothing is calibrated on a device with a missing sensor")
        before = self.dev.link.decoder.stats.frames_rejected
        self.dev.start_stream(self.cfg.rate_hz)
        b = self.dev.read(n_samples=self.cfg.rate_hz, timeout=30)
        self.dev.stop_stream()
        bad = int(np.count_nonzero(b.status))
        faults = [e for _, e in self.dev.link.fault_events if e.active]
        rejected = self.dev.link.decoder.stats.frames_rejected - before
        problems = []
        if bad:
            from imubench.wire.protocol_gen import SampleStatus
            which = [n for bit, n in zip((SampleStatus.ACCEL_BAD, SampleStatus.GYRO_X_BAD, SampleStatus.GYRO_Y_BAD,
                                          SampleStatus.GYRO_Z_BAD), names)
                     if np.any(b.status & bit)]
            problems.append(f"{bad} of {len(b)} samples flagged bad" + (f" ({', '.join(which)})" if which else "")
                            + ": sensor faults, parity or SPI errors")
        if faults:
            from imubench.wire.protocol_gen import FaultKind

            def kind(k: int) -> str:
                try:
                    return FaultKind(k).name.lower().replace("_", " ")
                except ValueError:
                    return f"fault kind {k}"
            seen = dict.fromkeys(f"{names[e.sensor] if 0 <= e.sensor < 4 else f'sensor {e.sensor}'}: {kind(int(e.kind))}"
                                 for e in faults)
            problems.append(f"{len(faults)} fault events from the device ({', '.join(seen)})")
        if rejected:
            problems.append(f"{rejected} corrupted frames on the link (cable, baud rate, ground)")
        if b.status.any() or problems:
            raise SessionAborted("refusing to calibrate on faulted data: " + "; ".join(problems))
        return {"board": board_name(info.board), "uid": uid_text(info.mcu_uid)}

    # ------------------------------------------------------------- streaming
    def _next_block(self, timeout: float = 10.0) -> SampleBlock:
        """The samples of the next 1/20 s (at least one): a pause of the stream shorter than
        `timeout` (a busy host, the buffer just discarded) is waited out, not an error."""
        from imubench.device.link import LinkTimeout
        t_end = time.monotonic() + timeout
        while True:
            try:
                b = self.dev.read(duration_s=0.05, timeout=timeout)
                break
            except LinkTimeout:
                if time.monotonic() > t_end:
                    raise
        self._count_block(b)
        return b

    def _count_block(self, b) -> None:
        """Keep the device sample index of the first and last sample read (the bench time)."""
        if len(b):
            if getattr(self, "_first_index", None) is None:
                self._first_index = int(b.sample_index[0])
            self._last_index = int(b.sample_index[-1]) + 1

    def _fit_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """(means, sigmas) of the captured poses for the accelerometer fit. An adaptive
        multi-position session weights each pose by the sigma of its mean |a| (what that fit
        uses; a hand's tremor tilts the axes, not |a|), the same on every axis."""
        means = np.array([p.mean_mps2 for p in self.poses])
        sigmas = np.array([p.sigma_mean_mps2 for p in self.poses])
        if self.cfg.adaptive and self.cfg.method == "multi":
            sn = [p.sigma_norm_g for p in self.poses]
            if all(v is not None for v in sn):
                sigmas = np.repeat(np.array(sn, float)[:, None] * U.G0_MPS2, 3, axis=1)
        return means, sigmas

    # ------------------------------------------------------------------ rest
    def capture_rest(self) -> dict:
        """Still at the start: the noise that sets every threshold, and the gyro bias."""
        from imubench.calib.static import rest_noise
        if self.rest is not None:
            return self.rest
        self.ui.say(f"hold the board still for {self.cfg.rest_s:g} s (noise and gyro bias)")
        n = int(self.cfg.rest_s * self.cfg.rate_hz)
        got = []
        have = 0
        while have < n:
            b = self._next_block()
            got.append(b)
            have += len(b)
            self.ui.progress("rest", have / n)
        b = SampleBlock.concat(got)
        acc, gyr = b.si()
        self.rest = {"noise_mps2": rest_noise(acc, self.cfg.rate_hz).tolist(),
                     "gyro": gyr.tolist() if self.cfg.gyro in ("bias", "rotation", "turntable", "turns") else None,
                     "start_index": int(b.sample_index[0]), "stop_index": int(b.sample_index[-1]) + 1}
        self.save()
        return self.rest

    # ----------------------------------------------------------------- poses
    def capture_pose(self, plan: list[tuple[str, np.ndarray]], index: int, total: int,
                     full_plan: list[tuple[str, np.ndarray]] | None = None) -> PoseRecord:
        """Wait until the board is still in one of the `plan` attitudes (those not yet
        captured), in whatever order they come, capture it and return it. The attitude the
        board is in is detected live (from the direction of the specific force) and told to
        the presenter; one that is not planned, or already captured, is named with a hint and
        waited past. Motion restarts the capture. The hold is cfg.hold_s, or with cfg.adaptive
        until the mean |a| is known to targets.pose_sigma_mg (hold_min_s .. hold_max_s). No
        timeout unless cfg.pose_timeout_s is set."""
        from imubench.calib.static import StillnessDetector
        fs = self.cfg.rate_hz
        t = self.cfg.targets
        noise = np.asarray(self.rest["noise_mps2"])
        full_plan = full_plan or plan
        todo_names = {n for n, _ in plan}
        done = [(n, v) for n, v in full_plan if n not in todo_names]
        name, direction = plan[0]
        if self.cfg.method == "multi":
            _hook(self.ui, "suggest", suggest_next([v for _, v in done], plan))
        if hasattr(self.ui, "present_todo"):
            self.ui.present_todo(list(plan), done, total)
        else:
            self.ui.present_pose(name, direction, index, total)
        # only what comes after the prompt counts: samples that waited in the buffer (behind a
        # question on the terminal, or a reader behind the device) show the board before the
        # person acted. The capture file on disk keeps every sample (the rotation method's).
        self.dev.discard_buffered()
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
            for b in _pieces(self._next_block(), max(1, fs // 10)):
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
                        _hook(self.ui, "pose_event", capturing, "todo", {"why": "moved"})
                        capturing = None
                    judged = False
                    sigma_g, next_sigma = float("inf"), 0
                was_still, prev_n = still, (st.n if still else 0)
                # which attitude the board is in now (the hold's mean when still, else the last block's)
                now_dir = st.mean if still else acc.mean(axis=0)
                k, ang = detect_attitude(now_dir, full_plan)
                now_name = full_plan[k][0] if k is not None else None
                hint = ""
                frac = 0.0
                if st.state == "moving":
                    pass                             # no hint while the person is still turning it
                elif k is None:
                    near = full_plan[int(np.argmin(plan_angles_deg(now_dir, full_plan)))]
                    hint = (f"the board is in no planned attitude: {ang:.0f}° from the nearest, "
                            f"{near[0]} ({pose_words(near[1])}); turn it until it is within "
                            f"{DETECT_TOL_DEG:.0f}° of a missing one")
                elif now_name not in todo_names:
                    hint = f"{now_name} is already captured: present one of the {len(plan)} missing"
                if (st.state == "settling" and not hint and k is not None and st.still_s > 0
                        and not judged):
                    # quiet, not yet for settle_s: the first half of the card's bar
                    if capturing not in (None, now_name):
                        _hook(self.ui, "pose_event", capturing, "todo", {"why": "left"})
                    capturing = now_name
                    frac = 0.5 * min(1.0, st.still_s / self.cfg.settle_s)
                    self.ui.progress(now_name, frac)
                    _hook(self.ui, "pose_event", now_name, "capturing", {"progress": frac})
                if still and not judged:
                    if hint:
                        last_msg = self._tell(hint, last_msg)
                        judged = True        # wait for the board to move before judging again
                    else:
                        if capturing != now_name:
                            if capturing is not None:     # drifted into another attitude while still
                                _hook(self.ui, "pose_event", capturing, "todo", {"why": "left"})
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
                        _hook(self.ui, "pose_event", now_name, "capturing", {"progress": frac})
                        if enough:
                            # exactly the samples of this still run: the last st.n received (at most the hold)
                            run = SampleBlock.concat(recent)
                            rec = self._pose_from(run[len(run) - min(st.n, hold_n, len(run)):], plan)
                            if isinstance(rec, PoseRecord):
                                return rec
                            _hook(self.ui, "pose_event", now_name, "rejected", {"why": rec})
                            capturing = None
                            last_msg = self._tell(rec, last_msg)
                            judged = True
                if waited >= live_due:
                    live_due = waited + live_every
                    _hook(self.ui, "live", {
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
        done = {p.name for p in self.poses}
        if angles[k] > 20.0:
            return (f"the board is not in a missing attitude (up along board {np.round(d, 2).tolist()}); "
                    f"{len(plan)} missing, e.g. {plan[0][0]}")
        name, direction = plan[k]
        if name in done:
            return f"{name} is already captured: present another attitude"
        a_g = float(np.linalg.norm(mean)) / U.G0_MPS2
        if abs(a_g - 1.0) > 0.1:
            return (f"{name}: |a| = {a_g:.3f} g, more than 10 % from 1 g: the board was being moved or shaken; "
                    "hold it still")
        from imubench.calib.static import detect_static
        iv = detect_static(acc, self.cfg.rate_hz, noise_sigma=np.asarray(self.rest["noise_mps2"]),
                           min_duration_s=min(1.0, 0.5 * len(acc) / self.cfg.rate_hz))
        sigma = (max(iv, key=lambda i: i.n).sigma_mean if iv else acc.std(axis=0) / np.sqrt(len(acc)))
        temp = float(np.mean(U.accel_temp_counts_to_c(b.accel_temp_counts)))
        return PoseRecord(name=name, direction=np.asarray(direction, float).tolist(), mean_mps2=mean.tolist(),
                          sigma_mean_mps2=np.asarray(sigma, float).tolist(), n=len(acc),
                          start_index=int(b.sample_index[0]), stop_index=int(b.sample_index[-1]) + 1,
                          temp_c=temp, gyro_mean_rad_s=gyr.mean(axis=0).tolist(), stream=self.stream_no,
                          sigma_norm_g=hold_sigma_g(acc), angle_from_plan_deg=float(angles[k]))

    # ---------------------------------------------------------------- stream
    def _start_stream(self) -> None:
        """A new continuous stream, captured to its own file as it arrives."""
        self.stream_no = 1 + max([p.stream for p in self.poses] + [getattr(self, "stream_no", 0)])
        old = self.dev.link.capture
        self.dev.link.capture = open_growing(self.dir / f"capture-{self.stream_no}.bin")
        if old is not None:
            old.close()
        self.dev.start_stream(self.cfg.rate_hz)

    def _stop_stream(self) -> None:
        self.dev.stop_stream()
        cap, self.dev.link.capture = self.dev.link.capture, None
        if cap is not None:
            cap.close()

    # ------------------------------------------------------------- turntable
    def capture_turntable(self) -> list:
        """Turns at known rates about each board axis, both ways; returns the segments
        (measured rates, axis, table rate) for calib.gyro.turntable."""
        fs = self.cfg.rate_hz
        segments = []
        for axis_name, axis in (("X", (1.0, 0, 0)), ("Y", (0, 1.0, 0)), ("Z", (0, 0, 1.0))):
            for rate in self.cfg.turntable_rates_dps:
                for sign in (1.0, -1.0):
                    r_dps = sign * rate
                    self.ui.present_turn(np.array(axis), r_dps, self.cfg.turntable_s)
                    need = int(0.6 * self.cfg.turntable_s * fs)     # the steady middle of the turn
                    seg = self._steady_turn(np.array(axis), np.radians(r_dps), need,
                                            int((self.cfg.turntable_s + 30) * fs))
                    if seg is None:
                        raise SessionAborted(f"no steady turn at {r_dps:+g} °/s about {axis_name} was seen")
                    if len(seg) < need // 2:
                        raise SessionAborted(f"the turn at {r_dps:+g} °/s about {axis_name} was too short or unsteady")
                    segments.append((seg, np.array(axis), np.radians(r_dps)))
                    # let the table stop before the next turn
                    self._wait_still(2.0)
        return segments

    def _steady_turn(self, axis: np.ndarray, rate_rad_s: float, need: int, limit: int) -> np.ndarray | None:
        """The gyro samples (rad/s) of one steady turn: the first run of consecutive samples
        within 10 % of the table's rate about axis, up to `need` of them (or shorter when the
        turn ended first); None when none began within `limit` samples. Judged sample by
        sample: a block read after a busy moment may hold the whole turn and its ends."""
        gyr = np.zeros((0, 3))
        waited = 0
        while True:
            b = self._next_block()
            waited += len(b)
            gyr = np.concatenate([gyr, b.si()[1]])
            on = np.abs(gyr @ axis - rate_rad_s) < 0.1 * abs(rate_rad_s)
            while on.any():
                start = int(np.argmax(on))
                off = np.flatnonzero(~on[start:])
                stop = start + int(off[0]) if len(off) else len(on)
                if stop - start >= need:
                    return gyr[start:start + need]
                if not len(off):
                    break                                           # still turning: read on
                if stop - start >= need // 2:
                    return gyr[start:stop]                          # the turn ended early
                gyr, on = gyr[stop:], on[stop:]                     # a blip at the band's edge
            if not on.any():
                gyr = gyr[-1:]                                      # nothing of a turn yet
            if waited > limit:
                return None

    def _wait_still(self, timeout_s: float) -> None:
        from imubench.calib.static import StillnessDetector
        det = StillnessDetector(self.cfg.rate_hz, np.asarray(self.rest["noise_mps2"]), window_s=self.cfg.settle_s)
        waited = 0
        while waited < timeout_s * self.cfg.rate_hz:
            b = self._next_block()
            waited += len(b)
            _, gyr = b.si()
            st = det.update(b.si()[0])
            if getattr(st, "state", st) == "still" and np.abs(gyr.mean(axis=0)).max() < np.radians(2.0):
                return

    # ------------------------------------------------------- known-angle turns
    TURN_DEG = 360.0
    TURN_MOVING_DPS = 5.0            # above the rest bias: the board is turning

    def capture_known_turns(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """--gyro turns: for X, Y and Z up in turn, the board lies still, is turned by hand one
        full turn on the table about the vertical, and lies still again. Returns per turn the
        samples (accel m/s², gyro rad/s) from the rest before to the rest after; the turns are
        found in them by calib.turns.detect_turns and fitted in _known_turns_fit."""
        from imubench.calib.static import StillnessDetector
        fs = self.cfg.rate_hz
        noise = np.asarray(self.rest["noise_mps2"])
        bias = np.mean(np.asarray(self.rest["gyro"]), axis=0) if self.rest.get("gyro") is not None else np.zeros(3)
        hold_n = int(self.cfg.hold_s * fs)
        out = []
        for i, (name, axis) in enumerate((("X", (1.0, 0, 0)), ("Y", (0, 1.0, 0)), ("Z", (0, 0, 1.0)))):
            self.ui.present_pose(f"+{name} up{TURN_POSE_SUFFIX}", np.array(axis), i, 3)
            det = StillnessDetector(fs, noise, window_s=self.cfg.settle_s)
            recent: list[SampleBlock] = []
            got: list[SampleBlock] = []
            phase, moved, waited, after_n = "settle", False, 0, 0
            while True:
                b = self._next_block()
                waited += len(b)
                acc, gyr = b.si()
                st = det.update(acc)
                quiet = np.abs(gyr - bias).max() < np.radians(self.TURN_MOVING_DPS)
                still = st.state == "still" and quiet
                if phase == "settle":
                    recent.append(b)
                    d = acc.mean(axis=0) / np.linalg.norm(acc.mean(axis=0))
                    if still and st.n >= hold_n and d @ np.array(axis) > np.cos(np.radians(20)):
                        run = SampleBlock.concat(recent)
                        got = [run[len(run) - min(st.n, len(run)):]]
                        phase = "turn"
                        turn = getattr(self.ui, "present_known_turn", None)
                        if turn is not None:
                            turn(np.array(axis), self.TURN_DEG)
                        else:
                            self.ui.say(f"turn the board one full turn ({self.TURN_DEG:g}°) on the table about the "
                                        f"vertical (+{name} up), then let it lie still")
                        det.reset()
                    elif len(recent) > 200:
                        recent.pop(0)
                else:
                    got.append(b)
                    after_n = 0 if not quiet else after_n + len(b)
                    moved = moved or not quiet
                    if moved and still and min(st.n, after_n) >= hold_n:
                        break
                if self.cfg.pose_timeout_s is not None and waited > self.cfg.pose_timeout_s * fs:
                    raise SessionAborted(f"known-angle turn about {name}: no "
                                         + ("still attitude with " + name + " up" if phase == "settle" else
                                            "turn followed by a rest") + f" within {self.cfg.pose_timeout_s:g} s")
            blk = SampleBlock.concat(got)
            out.append(blk.si())
            self.ui.say(f"  turn about {name} captured ({len(blk) / fs:.1f} s from rest to rest)")
        return out

    def _known_turns_fit(self, accel: TriadFit, runs, bias: TriadFit) -> TriadFit:
        """Gyro M from the turns of capture_known_turns (calib.turns)."""
        from imubench.calib.static import detect_static
        from imubench.calib.turns import detect_turns, known_angle_turns, split_by_rotation
        fs = self.cfg.rate_hz
        turns, missing = [], []
        for k, (acc, gyr) in enumerate(runs):
            iv = detect_static(acc, fs, noise_sigma=np.asarray(self.rest["noise_mps2"]),
                               min_duration_s=min(1.0, 0.5 * self.cfg.hold_s))
            iv = split_by_rotation(acc, gyr, fs, iv, min_duration_s=min(1.0, 0.5 * self.cfg.hold_s))
            if len(iv) < 2:
                missing.append(f"turn {'XYZ'[k]}: {len(iv)} rest(s) found around it, 2 needed")
                continue
            up = accel.correct(np.array([i.mean for i in iv]))
            found = detect_turns(gyr, fs, iv, up, turn_deg=self.TURN_DEG)
            turns += found
            if not any(t.usable for t in found):
                missing.append(f"turn {'XYZ'[k]}: no whole turn between two rests of the same attitude")
        return known_angle_turns(turns, bias, noise_density_rad_s_rthz=bias.extra["noise_density_rad_s_rthz"],
                                 refused=missing)

    # ------------------------------------------------------------------- run
    def run(self, plan: list[tuple[str, np.ndarray]], history=None, verify_plan=None) -> dict:
        from imubench.calib import accel as CA
        from imubench.calib import gyro as CG
        self.run_started = _now()
        self._first_index = self._last_index = None
        ident = self.check_health()
        self._start_stream()
        try:
            _hook(self.ui, "present_plan", list(plan), self.cfg.method)
            for p in self.poses:
                _hook(self.ui, "pose_event", p.name, "done", {"before_g": float(np.linalg.norm(p.mean_mps2)) / U.G0_MPS2})
            if self.rest is None:
                _hook(self.ui, "present_rest", self.cfg.rest_s)
            self.capture_rest()
            todo = [p for p in plan if p[0] not in {q.name for q in self.poses}]
            total = len(plan)
            if self.cfg.adaptive and self.cfg.method == "multi":
                self.ui.say(self.cfg.targets.describe())
            reached = False
            while todo and not reached:
                rec = self.capture_pose(todo, total - len(todo), total, full_plan=list(plan))
                a_g = np.linalg.norm(rec.mean_mps2) / U.G0_MPS2
                summary = (f"captured {rec.name} ({pose_words(rec.direction)}): |a| = {a_g:.5f} g "
                           f"({rec.n} samples, {rec.n / self.cfg.rate_hz:.1f} s"
                           + (f", σ {rec.sigma_norm_g * 1e6:.0f} µg" if rec.sigma_norm_g is not None else "") + ")")
                if not self.ui.keep_pose(rec.name, summary):
                    self.ui.say(f"  {rec.name} discarded: present it again")
                    _hook(self.ui, "pose_event", rec.name, "rejected", {"why": "discarded by you: present it again"})
                    self.dev.discard_buffered()
                    continue
                self.poses.append(rec)
                self.save()
                todo = [p for p in todo if p[0] != rec.name]
                _hook(self.ui, "pose_event", rec.name, "done",
                      {"before_g": float(a_g), "n": rec.n, "sigma_mg": (rec.sigma_norm_g or float("nan")) * 1e3,
                       "angle_from_plan_deg": rec.angle_from_plan_deg})
                self.ui.say(f"  {summary}, {len(todo)} to go")
                if self.cfg.adaptive and self.cfg.method == "multi":
                    reached, sig, why = enough_attitudes(*self._fit_inputs(), self.cfg.targets)
                    _hook(self.ui, "targets", sig, self.cfg.targets.as_dict(), reached)
                    self.ui.say(f"  {why}" + ("" if not reached else
                                              f": done after {len(self.poses)} attitudes, {len(todo)} not needed"))
            # device time from the first prompt to the last pose: the person's moves included
            self.bench_time_s = (None if self._first_index is None else
                                 (self._last_index - self._first_index) / self.cfg.rate_hz)
            segments = self.capture_turntable() if self.cfg.gyro == "turntable" else None
            turn_runs = self.capture_known_turns() if self.cfg.gyro == "turns" else None
        finally:
            self._stop_stream()

        means, sigmas = self._fit_inputs()
        _hook(self.ui, "step", "fit", f"fitting {self.cfg.method}-position to {len(means)} attitudes", "running")
        if self.cfg.method == "six":
            accel = CA.six_position(means, sigmas)
        else:
            faces = [i for i, p in enumerate(self.poses) if sum(abs(np.array(p.direction)) > 0.9) == 1]
            init = None
            if len(faces) >= 6:
                try:
                    init = CA.six_position(means[faces], sigmas[faces])
                except CalibrationError:
                    init = None
            CA.check_observability(means, "multi_position")
            accel = CA.multi_position(means, sigmas, init=init)
        gyro = None
        rest_gyr = np.asarray(self.rest["gyro"]) if self.rest.get("gyro") is not None else None
        self.gsens = self._gsens(accel, rest_gyr) if self.cfg.gyro else None
        if self.cfg.gyro == "bias":
            gyro = CG.gyro_bias(rest_gyr, self.cfg.rate_hz)
        elif self.cfg.gyro == "turntable":
            gyro = CG.turntable(segments, bias=CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        elif self.cfg.gyro == "rotation":
            gyro = self._rotation_fit(accel, CG.gyro_bias(rest_gyr, self.cfg.rate_hz), self.gsens)
        elif self.cfg.gyro == "turns":
            gyro = self._known_turns_fit(accel, turn_runs, CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        if gyro is not None and self.gsens is not None:   # b + G·f: the bias at zero specific force
            gyro = _with_bias(gyro, self.gsens)
        frame_note = None
        if self.cfg.method == "multi" and self.cfg.gyro == "turntable":
            accel, frame_note = self._align_frames(accel, gyro, CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        self.accel_fit, self.gyro_fit = accel, gyro
        result = self._result(ident, accel, gyro)
        result["gsens"] = getattr(self, "gsens_report", None)
        result["accel_frame"] = accel.extra.get("frame", "board")
        result["bench_time_s"] = getattr(self, "bench_time_s", None)
        result["adaptive"] = bool(self.cfg.adaptive)
        if self.cfg.method == "six":
            off = [p.angle_from_plan_deg for p in self.poses if p.angle_from_plan_deg is not None]
            if off:
                result["faces_off_square_deg"] = float(max(off))
        if accel.method == "multi_position":
            from imubench.procedures.poses import accel_sigmas
            result["accel_sigmas"] = accel_sigmas(accel)
        _hook(self.ui, "step", "fit", f"fitted: RMS of |a| − g after {result['accel_rms_after_mg']:.3g} mg", "done")
        if frame_note:
            result.setdefault("warnings", []).append(frame_note)
        self.save(result=result)
        return result

    def _align_frames(self, accel: TriadFit, gyro: TriadFit, bias: TriadFit) -> tuple[TriadFit, str | None]:
        """Multi-position + turntable: rotate the accelerometer's fit into the gyro (board)
        frame, the rotation measured by the gyros between the poses (calib.frames). Returns
        the fit and, when that is impossible, the fit unchanged and the reason."""
        from imubench.calib.frames import align_accel_to_gyro
        try:
            in_accel_frame = self._rotation_fit(accel, bias)
            aligned = align_accel_to_gyro(accel, gyro, in_accel_frame)
        except (CalibrationError, OSError) as e:
            return accel, (f"accelerometer left in its own frame (not aligned to the gyros): {e}; "
                           "strapdown use of both will see that rotation")
        phi = np.degrees(aligned.extra["alignment_rad"])
        self.ui.say(f"accelerometer frame aligned to the gyro turntable axes: rotation "
                    f"{np.round(phi, 3).tolist()} ° (about board x, y, z)")
        return aligned, None

    def _gsens(self, accel: TriadFit, rest_gyr):
        """The gyro's g-sensitivity from the poses' gyro means against their calibrated specific
        force (calib.gsens), or None when the poses cannot separate it. The ADXRS450 has one
        (0.03 °/s/g typical), so it is always part of the model when it can be fitted: b is then
        the bias at zero specific force and G goes to the device; p_zero says whether this
        session alone resolves it. Reported in self.gsens_report."""
        from imubench.calib.gsens import DPS, fit_gsens
        means = np.array([p.gyro_mean_rad_s for p in self.poses])
        f = accel.correct(np.array([p.mean_mps2 for p in self.poses])) / U.G0_MPS2
        try:
            gs = fit_gsens(means, np.ones_like(means), f, sigma_from_scatter=True)
        except CalibrationError as e:
            self.gsens_report = {"applied": False, "why_not": str(e)}
            return None
        self.gsens_report = {"applied": True, "resolved": bool(gs.significant), "g_dps_per_g": (gs.g * DPS).tolist(),
                             "sigma_dps_per_g": (gs.sigma_g * DPS).tolist(), "p_zero": gs.p_zero,
                             "b_rad_s": gs.b.tolist()}
        self.ui.say(gs.summary())
        return gs

    def _rotation_fit(self, accel: TriadFit, bias: TriadFit, gsens=None) -> TriadFit:
        """Gyro M from the motions between consecutive poses of one stream (on disk); with a
        g-sensitivity the gyro is integrated less G·f(t) (f the calibrated specific force)."""
        from imubench.calib import gyro as CG
        from imubench.wire.decoder import decode_bytes
        by_stream: dict[int, list[PoseRecord]] = {}
        for p in self.poses:
            by_stream.setdefault(p.stream, []).append(p)
        gyro_all, intervals, dirs = [], [], []
        offset = 0
        for k, poses in sorted(by_stream.items()):
            _, raw, _, st = decode_bytes(read_bytes(self.dir / f"capture-{k}.bin", MAX_CAPTURE_BYTES, "the capture"))
            if raw is None or st.samples_missing:
                raise CalibrationError(f"stream {k} has gaps ({st.samples_missing} samples lost): "
                                       "the rotation method needs every sample between poses")
            idx0 = int(raw.sample_index[0])
            acc, gyr = raw.si()
            if gsens is not None:
                gyr = gyr - (accel.correct(acc) / U.G0_MPS2) @ gsens.g.T
            poses = sorted(poses, key=lambda p: p.start_index)
            for p in poses:
                intervals.append((offset + p.start_index - idx0, offset + p.stop_index - idx0))
                x = accel.correct(np.array([p.mean_mps2]))[0]
                dirs.append(x / np.linalg.norm(x))
            gyro_all.append(gyr)
            offset += len(gyr)
        if len(by_stream) > 1:
            raise CalibrationError("the rotation method needs all poses in one continuous stream; "
                                   "this session was resumed — use --gyro bias or turntable, or start a new session")
        if gsens is not None:
            bias = TriadFit(method="bias", m=np.eye(3), b=gsens.b.copy(), cov=CG._cov12(b_cov=gsens.cov[9:, 9:]),
                            estimated=np.array([False] * 9 + [True] * 3), extra=dict(bias.extra))
        return CG.rotation_method(np.concatenate(gyro_all), self.cfg.rate_hz, intervals, np.array(dirs), bias)

    def _result(self, ident: dict, accel: TriadFit, gyro: TriadFit | None) -> dict:
        means = np.array([p.mean_mps2 for p in self.poses])
        sig = np.array([p.sigma_mean_mps2 for p in self.poses])
        before = np.linalg.norm(means, axis=1)
        after = np.linalg.norm(accel.correct(means), axis=1)
        # 1-sigma of |a| from the mean's sigma projected on the gravity direction
        sig_g = np.sqrt(np.sum((means / before[:, None] * sig) ** 2, axis=1)) / U.G0_MPS2
        rms_after_mg = float(np.sqrt(np.mean((after - U.G0_MPS2) ** 2)) / U.G0_MPS2 * 1e3)
        tol = self.cfg.tolerances
        passed = rms_after_mg <= tol.accel_rms_mg
        info = self.dev.info()
        return {
            "schema": 1,
            "device": {"mcu_uid": uid_text(info.mcu_uid), "board": board_name(info.board),
                       "fw_version": ".".join(map(str, info.fw_version)), "fw_build": info.fw_build,
                       "accel_ids": list(info.accel_ids), "gyro_pid": list(info.gyro_pid), "gyro_sn": list(info.gyro_sn)},
            "started": getattr(self, "run_started", self.started), "session_started": self.started,
            "finished": _now(),
            "method": self.cfg.method, "gyro_method": self.cfg.gyro,
            "accel": fit_dict(accel, "mps2") | {"residual_rms_mps2": accel.residual_rms},
            "gyro": fit_dict(gyro, "rad_s"),
            "poses": [{"name": p.name, "n": p.n, "before_g": float(before[i] / U.G0_MPS2),
                       "after_g": float(after[i] / U.G0_MPS2), "sigma_g": float(sig_g[i]), "temp_c": p.temp_c}
                      for i, p in enumerate(self.poses)],
            "temperature_c": {"accel": float(np.mean([p.temp_c for p in self.poses]))},
            "tolerances": asdict(tol), "passed": bool(passed), "accel_rms_after_mg": rms_after_mg,
            "written": False, "verified": False, "verification": [],
            "note": self.cfg.note, "capture_dir": str(self.dir.resolve()),
        }

    def verify(self, plan: list[tuple[str, np.ndarray]]) -> list[dict]:
        """The device's own calibrated output in a few attitudes: | |a| - g | per pose."""
        from imubench.calib.static import StillnessDetector
        fs = self.cfg.rate_hz
        hold_n = int(self.cfg.hold_s * fs)
        out = []
        self.dev.start_stream(fs, calibrated=True)
        try:
            for i, (name, direction) in enumerate(plan):
                self.ui.present_pose(name, direction, i, len(plan))
                self.dev.discard_buffered()          # only what comes after the move counts
                det = StillnessDetector(fs, np.asarray(self.rest["noise_mps2"]), window_s=self.cfg.settle_s)
                recent, waited = [], 0
                while True:
                    b = self.dev.read(duration_s=0.05, timeout=10)
                    recent.append(b.accel_mps2.astype(np.float64))
                    waited += len(b)
                    st = det.update(recent[-1])
                    if st.state == "still" and st.n >= hold_n:
                        run = np.concatenate(recent)[-hold_n:]
                        break
                    if self.cfg.pose_timeout_s is not None and waited > self.cfg.pose_timeout_s * fs:
                        raise SessionAborted(f"verification: no still attitude for {name}")
                a = run.mean(axis=0)
                d = a / np.linalg.norm(a)
                out.append({"name": name, "after_g": float(np.linalg.norm(a) / U.G0_MPS2),
                            "angle_from_plan_deg": float(np.degrees(np.arccos(np.clip(d @ direction, -1, 1))))})
        finally:
            self.dev.stop_stream()
        return out

    def restore(self, previous: Params) -> None:
        """Put a previous parameter block back, in RAM and in flash."""
        self.dev.set_params(previous)
        self.dev.save_params()

    # -------------------------------------------------------------- write-back
    def write_back(self, accel: TriadFit, gyro: TriadFit | None, cal_id: int) -> dict:
        """set_params, read back bit-exactly, save, reboot, read back again. On any failure
        the previous parameters are put back (and saved again if they were saved)."""
        old = self.dev.get_params(ParamsWhich.ACTIVE)
        new = params_from_fits(accel, gyro, old.params, cal_id, getattr(self, "gsens", None))
        PR.validate(new)                                      # the device's own checks, first here
        return write_verified(self.dev, new, previous=old.params, say=self.ui.say)


# Rated erase cycles of a flash page/sector per board (the parameter slots): STM32F103 datasheet
# (DS5319, "Flash memory endurance: 10 kcycles"); STM32F405/407 datasheet (DS8626: 10 kcycles,
# not checked against the datasheet here); the virtual device models the F103's.
ERASE_ENDURANCE = {"STM32F103": 10_000, "STM32F4": 10_000, "SIM": 10_000}
WEAR_WARN_FRACTION = 0.8        # warn before a save that takes a slot past 80 % of its rating


def wear_warning(dev: Device, fraction: float = WEAR_WARN_FRACTION, endurance: int | None = None) -> str | None:
    """The warning to give before a save, or None: a save erases the slot not holding the
    current block; if that takes it past `fraction` of the rated erase cycles, say so with the
    slot, its erase count (the device's lower bound, stats.param_slot_erases) and the rating."""
    from imubench.wire.ids import board_name
    stats = dev.stats()
    info = dev.info()
    rated = endurance or ERASE_ENDURANCE.get(board_name(info.board), 10_000)
    erases = [int(e) for e in stats.param_slot_erases]
    after = min(erases) + 1            # the next save erases the slot not holding the current block
    if after <= fraction * rated:
        return None
    return (f"flash wear: saving a changed block erases a parameter slot for at least the {after}th time (slots erased "
            f"{erases[0]} and {erases[1]} times so far), {100 * after / rated:.0f} % of the {rated} erase cycles "
            f"the flash is rated for (warning from {100 * fraction:.0f} %); save only when the parameters changed")


def write_verified(dev: Device, new: Params, previous: Params | None = None,
                   say=lambda s: None, reboot_wait_s: float = 10.0) -> dict:
    """Write a parameter block and prove it took: set_params, read back bit-exactly, save,
    reboot, read the active parameters back (bit-exactly, and the generation just saved).
    On any failure the previous parameters (`previous`, default: the active ones read
    first) are put back, and saved again if the new ones had been saved; the error is
    re-raised (SessionAborted if the restore failed too). Returns {"generation", "steps",
    "params"}. The caller validates `new` first (params.validate)."""
    if previous is None:
        previous = dev.get_params(ParamsWhich.ACTIVE).params
    steps = []
    try:
        dev.set_params(new)
        steps.append("set")
        if _pack(dev.get_params(ParamsWhich.ACTIVE).params) != _pack(new):
            raise SessionAborted("read-back after set_params differs from what was written")
        steps.append("read back")
        warning = wear_warning(dev)
        if warning:
            say(f"warning: {warning}")
        gen = dev.save_params()
        steps.append(f"already stored, flash untouched (generation {gen})" if dev.last_save_unchanged
                     else f"saved (generation {gen})")
        info = dev.reboot(wait_s=reboot_wait_s)
        dev.discard_buffered()
        steps.append("rebooted")
        stored = dev.get_params(ParamsWhich.ACTIVE)
        if _pack(stored.params) != _pack(new) or stored.generation != gen:
            raise SessionAborted("after reboot the active parameters are not the ones saved")
        steps.append(f"read back after reboot ({info.param_source and 'flash'})")
    except Exception as e:
        say(f"write-back failed after: {', '.join(steps) or 'nothing'} — {e}; restoring the previous parameters")
        try:
            dev.set_params(previous)
            if "saved" in " ".join(steps):
                dev.save_params()
        except Exception as e2:  # noqa: BLE001 - report both failures
            raise SessionAborted(f"write-back failed ({e}) and restoring the previous parameters failed too ({e2})") from e
        raise
    return {"generation": gen, "steps": steps, "params": new}


# ------------------------------------------------------------------- helpers
def _with_bias(fit: TriadFit, gsens) -> TriadFit:
    """fit with b (and its covariance) replaced by the g-sensitivity fit's bias at zero
    specific force (M and its covariance kept)."""
    cov = np.array(fit.cov, dtype=float)
    cov[9:, :] = np.nan
    cov[:, 9:] = np.nan
    cov[9:, 9:] = gsens.cov[9:, 9:]
    extra = dict(fit.extra, bias_source="g-sensitivity fit (b at zero specific force)")
    return TriadFit(method=fit.method, m=fit.m, b=gsens.b.copy(), cov=cov, residual_rms=fit.residual_rms,
                    residuals=fit.residuals, dof=fit.dof, estimated=np.array(list(fit.estimated[:9]) + [True] * 3),
                    extra=extra)


def params_from_fits(accel: TriadFit | None, gyro: TriadFit | None, base: Params, cal_id: int,
                     gsens=None) -> Params:
    """The device parameter block from fits (fields a fit does not cover keep `base`). A gyro
    fit sets the g-sensitivity too: gsens's G (calib.gsens, rad/s per g; stored per m/s²), or
    zero without one (the bias then holds it at the attitudes of the fit)."""
    p = Params.from_values(base.values())
    if accel is not None:
        p.accel_m = tuple(float(v) for v in np.asarray(accel.m).ravel())
        p.accel_b_mps2 = tuple(float(v) for v in accel.b)
    if gyro is not None:
        p.gyro_m = tuple(float(v) for v in np.asarray(gyro.m).ravel())
        p.gyro_b_rad_s = tuple(float(v) for v in gyro.b)
        g = np.zeros(9) if gsens is None else np.asarray(gsens.g, float).ravel() / U.G0_MPS2
        p.gyro_g_rad_s_per_mps2 = tuple(float(v) for v in g)
    p.cal_time_unix_s = int(time.time())
    p.cal_id = cal_id & 0xFFFFFFFF
    return p


def _pack(p: Params) -> bytes:
    return p.STRUCT.pack(*p.values())


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def fit_dict(fit: TriadFit | None, unit: str) -> dict | None:
    if fit is None:
        return None
    return {"method": fit.method, "m": fit.m.tolist(), f"b_{unit}": fit.b.tolist(),
            "sigma_m": fit.sigma_m.tolist(), f"sigma_b_{unit}": fit.sigma_b.tolist(),
            "residual_rms": fit.residual_rms, "extra": _jsonable(fit.extra)}


def plan_for(method: str) -> list[tuple[str, np.ndarray]]:
    """(name, gravity direction) of the attitudes to present: the six faces, or all 26."""
    from imubench.calib.accel import POSE_PLAN
    plan = [(p.name, p.vector) for p in POSE_PLAN]
    if method == "six":
        plan = [(n, v) for n, v in plan if np.count_nonzero(v) == 1]
    return plan


def run_session(dev: Device, directory, cfg: SessionConfig, ui: Presenter, *, resume: bool = False,
                redo: list[str] | None = None, on_start=lambda sess: None,
                report=lambda result: None) -> tuple[dict, Session]:
    """A whole guided session on an open device: capture (or resume) and fit; if the fit
    passes and cfg.write, write back (set, read back, save, reboot, read back), verify the
    device's calibrated output in cfg.verify_poses attitudes and restore the previous
    parameters if that fails. report(result) is called once the fit is known (before anything
    is written); the residual plot (DIR/residuals.png) is drawn at the end, so it shows what
    was written and verified. Returns (result, session); result is saved in session.json."""
    from imubench.results.calibration import plot_pose_residuals
    sess = Session(dev, directory, cfg, ui, resume=resume)
    if redo:
        sess.redo(redo)
    on_start(sess)
    if sess.finished is not None:
        # stopped after its run went to its end (e.g. killed after the history write): that
        # run is done; capturing, fitting or writing again would make it a second run
        result = sess.finished
        cfg.write = sess.saved_write
        ui.say(f"this session's run (started {result.get('started')}) already went to its end "
               f"({'passed' if result.get('passed') else 'FAILED'}, "
               f"{'written' if result.get('written') else 'not written'}): nothing is captured, fitted or "
               "written again (--redo POSE calibrates again)")
        report(result)
        return result, sess
    result = sess.run(plan_for(cfg.method))
    for p in result["poses"]:
        _hook(ui, "pose_event", p["name"], "done", {"before_g": p["before_g"], "after_g": p["after_g"],
                                                    "sigma_mg": p["sigma_g"] * 1e3})
    report(result)
    if result["passed"] and cfg.write:
        previous = dev.get_params(ParamsWhich.ACTIVE).params
        _hook(ui, "step", "write", "writing the parameters: set, read back, save, reboot, read back", "running")
        try:
            wb = sess.write_back(sess.accel_fit, sess.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
        except Exception as e:
            _hook(ui, "step", "write", f"write-back failed: {e}; the previous parameters were put back", "failed")
            raise
        ui.say(f"written: {', '.join(wb['steps'])}")
        _hook(ui, "step", "write", f"written: {', '.join(wb['steps'])}", "done")
        result["written"] = True
        _hook(ui, "step", "verify", f"verifying the device's own output in {cfg.verify_poses} attitudes", "running")
        result["verification"] = sess.verify(plan_for("six")[:cfg.verify_poses])
        worst = max(abs(v["after_g"] - 1.0) * 1e3 for v in result["verification"])
        result["verified"] = worst <= cfg.tolerances.verify_mg
        ui.say(f"verification of the device's calibrated output: worst | |a| - g | = {worst:.3f} mg "
               f"({'within' if result['verified'] else 'OUTSIDE'} {cfg.tolerances.verify_mg} mg)")
        _hook(ui, "step", "verify", f"worst | |a| − g | = {worst:.3f} mg "
              f"({'within' if result['verified'] else 'OUTSIDE'} {cfg.tolerances.verify_mg} mg)",
              "done" if result["verified"] else "failed")
        if not result["verified"]:
            sess.restore(previous)
            result["written"] = False
            ui.say("verification failed: the previous parameters were written back and saved")
    elif not result["passed"]:
        ui.say("the fit did not pass its tolerance: nothing was written to the device")
        _hook(ui, "step", "write", "the fit did not pass its tolerance: nothing was written to the device", "skipped")
    else:
        _hook(ui, "step", "write", "not written to the device (--no-write)", "skipped")
    png = plot_pose_residuals(result, sess.dir / "residuals.png")
    ui.say(f"residual plot: {png}")
    sess.finish(result)
    return result, sess
