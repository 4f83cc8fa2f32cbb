"""The guided calibration session: capture, fit, write back, verify, record.

    imubench calibrate --port URL [--method six|multi] [--gyro turntable|rotation|bias]

One continuous raw stream runs for the whole session; every received byte is appended to
`capture.bin` in the session directory as it arrives, and `session.json` is rewritten
(atomically) after every accepted pose, so a crash or a lost connection loses nothing and
`--resume DIR` continues where the session stopped. The algorithms (imubench.calib) never
see the serial port: this module feeds them arrays.

A Presenter tells the user (or the virtual bench) which attitude to present next; the
session itself decides, from the data, when the board is still and which attitude it is in.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from imubench.wire import params as PR
from imubench import units as U
from imubench.results.atomic import write_json_atomic
from imubench.calib import CalibrationError, TriadFit
from imubench.wire.decoder import SampleBlock
from imubench.device.link import DEFAULT_BAUD, Device
from imubench.wire.protocol_gen import Board, Params, ParamsWhich

SESSION_SCHEMA = 1


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
    pose_timeout_s: float = 120.0    # waiting for an attitude, in device time
    turntable_rates_dps: tuple = (30.0, 90.0)
    turntable_s: float = 3.0
    verify_poses: int = 3
    write: bool = True               # write the parameters back if the fit passes
    note: str = ""
    tolerances: Tolerances = field(default_factory=Tolerances)


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


class SessionAborted(RuntimeError):
    """The session cannot go on; the message says why and what to do."""


# ---------------------------------------------------------------- presenters
class Presenter(Protocol):
    def say(self, text: str) -> None: ...
    def present_pose(self, name: str, direction: np.ndarray, index: int, total: int) -> None: ...
    def present_turn(self, axis: np.ndarray, rate_dps: float, duration_s: float) -> None: ...
    def progress(self, label: str, fraction: float) -> None: ...
    def keep_pose(self, name: str, summary: str) -> bool: ...   # False: redo this pose


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
        import sys
        if not sys.stdin.isatty():
            return True
        answer = input(f"  {summary} — Enter to keep, r + Enter to redo: ").strip().lower()
        return answer != "r"


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
        cur = np.asarray(self.vb.status()["gravity_board"], dtype=float)
        cur /= np.linalg.norm(cur)
        target = target / np.linalg.norm(target)
        axis = np.cross(target, cur)
        s, c = np.linalg.norm(axis), float(np.clip(cur @ target, -1.0, 1.0))
        angle = np.degrees(np.arctan2(s, c))
        if s < 1e-9:
            if c > 0:
                return
            axis = np.cross(cur, [1.0, 0.0, 0.0] if abs(cur[0]) < 0.9 else [0.0, 1.0, 0.0])  # any perpendicular
        self.vb.rotate(list(axis / np.linalg.norm(axis)), rate_dps=self.rate_dps,
                       duration_s=angle / self.rate_dps, wait=True)

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
        self.state_path = self.dir / "session.json"
        if resume:
            self._load()
        else:
            self.dir.mkdir(parents=True, exist_ok=True)
            if self.state_path.exists():
                raise SessionAborted(f"{self.dir} already holds a session: use --resume {self.dir}, or another --dir")
            self.started = _now()
            self._save()

    # ------------------------------------------------------------ persistence
    def _save(self, **extra) -> None:
        state = {"schema": SESSION_SCHEMA, "started": self.started, "config": _jsonable(asdict(self.cfg)),
                 "rest": self.rest, "poses": [asdict(p) for p in self.poses], **extra}
        write_json_atomic(self.state_path, state)     # a crash leaves the old or the new file

    def _load(self) -> None:
        try:
            state = json.loads(self.state_path.read_text())
        except FileNotFoundError:
            raise SessionAborted(f"nothing to resume in {self.dir}: no session.json") from None
        if state.get("schema") != SESSION_SCHEMA:
            raise SessionAborted(f"{self.state_path} has session schema {state.get('schema')}, this imubench reads {SESSION_SCHEMA}")
        self.started = state["started"]
        self.rest = state.get("rest")
        self.poses = [PoseRecord(**p) for p in state.get("poses", [])]
        saved = state["config"]
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
        self._save()

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
            problems.append(f"{bad} of {len(b)} samples flagged bad (sensor faults, parity or SPI errors)")
        if faults:
            problems.append(f"{len(faults)} fault events from the device (e.g. sensor {faults[-1].sensor}, kind {faults[-1].kind})")
        if rejected:
            problems.append(f"{rejected} corrupted frames on the link (cable, baud rate, ground)")
        if b.status.any() or problems:
            raise SessionAborted("refusing to calibrate on faulted data: " + "; ".join(problems))
        return {"board": Board(info.board).name, "uid": bytes(info.mcu_uid).hex()}

    # ------------------------------------------------------------- streaming
    def _next_block(self, timeout: float = 10.0) -> SampleBlock:
        return self.dev.read(duration_s=0.05, timeout=timeout)

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
                     "gyro": gyr.tolist() if self.cfg.gyro in ("bias", "rotation", "turntable") else None,
                     "start_index": int(b.sample_index[0]), "stop_index": int(b.sample_index[-1]) + 1}
        self._save()
        return self.rest

    # ----------------------------------------------------------------- poses
    def capture_pose(self, plan: list[tuple[str, np.ndarray]], index: int, total: int) -> PoseRecord:
        """Wait until the board is still in one of the `plan` attitudes not yet captured,
        capture hold_s of it, and return it. Motion restarts the capture; an attitude that
        is not in the plan, or already captured, is named and waited past."""
        from imubench.calib.static import StillnessDetector
        fs = self.cfg.rate_hz
        noise = np.asarray(self.rest["noise_mps2"])
        name, direction = plan[0]
        self.ui.present_pose(name, direction, index, total)
        det = StillnessDetector(fs, noise, window_s=self.cfg.settle_s)
        hold_n = int(self.cfg.hold_s * fs)
        recent: list[SampleBlock] = []   # enough trailing blocks to cover the still run
        recent_n = 0
        waited = 0
        last_msg = ""
        was_still = False
        prev_n = 0
        judged = False                   # this still run was already judged (wrong attitude)
        while True:
            b = self._next_block()
            waited += len(b)
            recent.append(b)
            recent_n += len(b)
            st = det.update(b.si()[0])
            still = st.state == "still"
            # the still run restarted inside this block if it is shorter than before + the block
            restarted = still and (not was_still or st.n < prev_n + len(b))
            if not still or restarted:
                if was_still and not judged and (st.state == "moving" or restarted):
                    last_msg = self._tell("detected motion, hold still", last_msg)
                judged = False
            was_still, prev_n = still, (st.n if still else 0)
            if still and not judged:
                self.ui.progress(name, st.n / hold_n)
                if st.n >= hold_n:
                    # exactly the samples of this still run: the last st.n received
                    run = SampleBlock.concat(recent)       # the still run is its last st.n samples
                    rec = self._pose_from(run[len(run) - min(st.n, hold_n, len(run)):], plan)
                    if isinstance(rec, PoseRecord):
                        return rec
                    last_msg = self._tell(rec, last_msg)
                    judged = True        # wait for the board to move before judging again
            while len(recent) > 1 and recent_n - len(recent[0]) >= max(st.n, hold_n) + fs:
                recent_n -= len(recent.pop(0))
            if waited > self.cfg.pose_timeout_s * fs:
                raise SessionAborted(f"no still attitude from the plan within {self.cfg.pose_timeout_s:g} s "
                                     f"(expected {name}); the board must stay still for "
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
            return f"the board is not in a planned attitude (gravity along {np.round(d, 2).tolist()}); expected {plan[0][0]}"
        name, direction = plan[k]
        if name in done:
            return f"{name} is already captured: present another attitude"
        from imubench.calib.static import detect_static
        iv = detect_static(acc, self.cfg.rate_hz, noise_sigma=np.asarray(self.rest["noise_mps2"]),
                           min_duration_s=min(1.0, 0.5 * self.cfg.hold_s))
        sigma = (max(iv, key=lambda i: i.n).sigma_mean if iv else acc.std(axis=0) / np.sqrt(len(acc)))
        temp = float(np.mean(U.accel_temp_counts_to_c(b.accel_temp_counts)))
        return PoseRecord(name=name, direction=np.asarray(direction, float).tolist(), mean_mps2=mean.tolist(),
                          sigma_mean_mps2=np.asarray(sigma, float).tolist(), n=len(acc),
                          start_index=int(b.sample_index[0]), stop_index=int(b.sample_index[-1]) + 1,
                          temp_c=temp, gyro_mean_rad_s=gyr.mean(axis=0).tolist(), stream=self.stream_no)

    # ---------------------------------------------------------------- stream
    def _start_stream(self) -> None:
        """A new continuous stream, captured to its own file as it arrives."""
        self.stream_no = 1 + max([p.stream for p in self.poses] + [getattr(self, "stream_no", 0)])
        old = self.dev.link.capture
        self.dev.link.capture = open(self.dir / f"capture-{self.stream_no}.bin", "ab")
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
                    got, steady = [], 0
                    need = int(0.6 * self.cfg.turntable_s * fs)     # the steady middle of the turn
                    waited = 0
                    while steady < need:
                        b = self._next_block()
                        waited += len(b)
                        _, gyr = b.si()
                        on = np.abs(gyr @ np.array(axis) - np.radians(r_dps)) < 0.1 * abs(np.radians(r_dps))
                        if on.all():
                            got.append(gyr)
                            steady += len(gyr)
                        elif got:
                            break                                   # the turn ended early
                        if waited > (self.cfg.turntable_s + 30) * fs:
                            raise SessionAborted(f"no steady turn at {r_dps:+g} °/s about {axis_name} was seen")
                    if steady < need // 2:
                        raise SessionAborted(f"the turn at {r_dps:+g} °/s about {axis_name} was too short or unsteady")
                    segments.append((np.concatenate(got), np.array(axis), np.radians(r_dps)))
                    # let the table stop before the next turn
                    self._wait_still(2.0)
        return segments

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

    # ------------------------------------------------------------------- run
    def run(self, plan: list[tuple[str, np.ndarray]], history=None, verify_plan=None) -> dict:
        from imubench.calib import accel as CA
        from imubench.calib import gyro as CG
        self.run_started = _now()
        ident = self.check_health()
        self._start_stream()
        try:
            self.capture_rest()
            todo = [p for p in plan if p[0] not in {q.name for q in self.poses}]
            total = len(plan)
            while todo:
                rec = self.capture_pose(todo, total - len(todo), total)
                summary = f"captured {rec.name}: |a| = {np.linalg.norm(rec.mean_mps2) / U.G0_MPS2:.5f} g ({rec.n} samples)"
                if not self.ui.keep_pose(rec.name, summary):
                    self.ui.say(f"  {rec.name} discarded: present it again")
                    self.dev.discard_buffered()
                    continue
                self.poses.append(rec)
                self._save()
                todo = [p for p in todo if p[0] != rec.name]
                self.ui.say(f"  {summary}, {len(todo)} to go")
            segments = self.capture_turntable() if self.cfg.gyro == "turntable" else None
        finally:
            self._stop_stream()

        means = np.array([p.mean_mps2 for p in self.poses])
        sigmas = np.array([p.sigma_mean_mps2 for p in self.poses])
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
        if self.cfg.gyro == "bias":
            gyro = CG.gyro_bias(rest_gyr, self.cfg.rate_hz)
        elif self.cfg.gyro == "turntable":
            gyro = CG.turntable(segments, bias=CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        elif self.cfg.gyro == "rotation":
            gyro = self._rotation_fit(accel, CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        frame_note = None
        if self.cfg.method == "multi" and self.cfg.gyro == "turntable":
            accel, frame_note = self._align_frames(accel, gyro, CG.gyro_bias(rest_gyr, self.cfg.rate_hz))
        self.accel_fit, self.gyro_fit = accel, gyro
        result = self._result(ident, accel, gyro)
        result["accel_frame"] = accel.extra.get("frame", "board")
        if frame_note:
            result.setdefault("warnings", []).append(frame_note)
        self._save(result=result)
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

    def _rotation_fit(self, accel: TriadFit, bias: TriadFit) -> TriadFit:
        """Gyro M from the motions between consecutive poses of one stream (on disk)."""
        from imubench.calib import gyro as CG
        from imubench.wire.decoder import decode_bytes
        by_stream: dict[int, list[PoseRecord]] = {}
        for p in self.poses:
            by_stream.setdefault(p.stream, []).append(p)
        gyro_all, intervals, dirs = [], [], []
        offset = 0
        for k, poses in sorted(by_stream.items()):
            _, raw, _, st = decode_bytes((self.dir / f"capture-{k}.bin").read_bytes())
            if raw is None or st.samples_missing:
                raise CalibrationError(f"stream {k} has gaps ({st.samples_missing} samples lost): "
                                       "the rotation method needs every sample between poses")
            idx0 = int(raw.sample_index[0])
            _, gyr = raw.si()
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
            "device": {"mcu_uid": bytes(info.mcu_uid).hex(), "board": Board(info.board).name,
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
                    if waited > self.cfg.pose_timeout_s * fs:
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
        new = params_from_fits(accel, gyro, old.params, cal_id)
        PR.validate(new)                                      # the device's own checks, first here
        return write_verified(self.dev, new, previous=old.params, say=self.ui.say)


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
        gen = dev.save_params()
        steps.append(f"saved (generation {gen})")
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
def params_from_fits(accel: TriadFit | None, gyro: TriadFit | None, base: Params, cal_id: int) -> Params:
    """The device parameter block from fits (fields a fit does not cover keep `base`)."""
    p = Params.from_values(base.values())
    if accel is not None:
        p.accel_m = tuple(float(v) for v in np.asarray(accel.m).ravel())
        p.accel_b_mps2 = tuple(float(v) for v in accel.b)
    if gyro is not None:
        p.gyro_m = tuple(float(v) for v in np.asarray(gyro.m).ravel())
        p.gyro_b_rad_s = tuple(float(v) for v in gyro.b)
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
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def fit_dict(fit: TriadFit | None, unit: str) -> dict | None:
    if fit is None:
        return None
    return {"method": fit.method, "m": fit.m.tolist(), f"b_{unit}": fit.b.tolist(),
            "sigma_m": fit.sigma_m.tolist(), f"sigma_b_{unit}": fit.sigma_b.tolist(),
            "residual_rms": fit.residual_rms, "extra": _jsonable(fit.extra)}


# ------------------------------------------------------------------------ CLI
def plan_for(method: str) -> list[tuple[str, np.ndarray]]:
    """(name, gravity direction) of the attitudes to present: the six faces, or all 26."""
    from imubench.calib.accel import POSE_PLAN
    plan = [(p.name, p.vector) for p in POSE_PLAN]
    if method == "six":
        plan = [(n, v) for n, v in plan if np.count_nonzero(v) == 1]
    return plan


def truth_in_fit_frame(result: dict, truth: dict) -> dict:
    """The virtual device's truth expressed as the session's fit can observe it.

    The multi-position |a| = g model cannot see the accelerometer triad's rotation Q relative
    to the board (M = L·Q, calib.accel.lower_triangular_form): it returns L, and its calibrated
    output is in the Q-rotated frame. A rotation-method gyro fit, which matches gravity
    directions in that frame, then returns M_gyro·Qᵀ. Six-position and the turntable are
    tied to the board axes and see the truth as it is."""
    from imubench.calib.accel import lower_triangular_form
    m_a = np.array(truth["accel"]["m"], dtype=float)
    m_g = np.array([g["sens"] for g in truth["gyro"]], dtype=float)
    q = np.eye(3)
    if result["method"] == "multi" and not str(result.get("accel_frame", "")).startswith("board"):
        m_a, q = lower_triangular_form(m_a)
    if result.get("gyro_method") == "rotation":
        m_g = m_g @ q.T
    return {"accel_m": m_a, "accel_b_mps2": np.array(truth["accel"]["true_bias_mps2"], dtype=float),
            "gyro_m": m_g, "gyro_b_rad_s": np.array([g["true_bias_rad_s"] for g in truth["gyro"]], dtype=float)}


def truth_table(result: dict, truth: dict) -> str:
    """Recovered parameters beside the virtual device's truth, with 1-sigma and |error|/sigma."""
    t = truth_in_fit_frame(result, truth)
    lines = [f"{'parameter':<14}{'truth':>14}{'recovered':>14}{'1-sigma':>12}{'|err|/σ':>9}"]
    acc = result["accel"]
    for i in range(3):
        for j in range(3):
            if acc["sigma_m"][i][j] > 0:          # entries the model fixes are not listed
                lines.append(_row(f"accel M{i}{j}", t["accel_m"][i, j], acc["m"][i][j], acc["sigma_m"][i][j]))
    for i, ax in enumerate("xyz"):
        lines.append(_row(f"accel b{ax} mg", t["accel_b_mps2"][i] / U.G0_MPS2 * 1e3, acc["b_mps2"][i] / U.G0_MPS2 * 1e3,
                          acc["sigma_b_mps2"][i] / U.G0_MPS2 * 1e3))
    g = result.get("gyro")
    if g:
        for i, ax in enumerate("xyz"):
            lines.append(_row(f"gyro b{ax} °/s", np.degrees(t["gyro_b_rad_s"][i]), np.degrees(g["b_rad_s"][i]),
                              np.degrees(g["sigma_b_rad_s"][i])))
        if g["method"] != "bias":
            for i in range(3):
                for j in range(3):
                    lines.append(_row(f"gyro M{i}{j}", t["gyro_m"][i, j], g["m"][i][j], g["sigma_m"][i][j]))
    if result["method"] == "multi" and not str(result.get("accel_frame", "")).startswith("board"):
        lines.append("(multi-position: M in the frame of the sensor's X axis and X-Y plane; "
                     "see docs/calibration.md)")
    elif result["method"] == "multi":
        lines.append("(multi-position: M rotated into the gyro turntable's board frame by the rotations "
                     "between poses; see docs/calibration.md, \"One frame\")")
    lines.append("(biases: the models' bias random walk moves them during the session; the truth shown is "
                 "the value at the end, the estimate the mean over the session's rest or poses)")
    return "\n".join(lines)


def params_table(result: dict) -> str:
    """The fitted parameters with their 1-sigma uncertainties (docs/conventions.md model)."""
    a = result["accel"]
    L = [f"accelerometer ({a['method']}): u = M·x + b",
         "  M = " + "\n      ".join("  ".join(f"{a['m'][i][j]:+.6f}±{a['sigma_m'][i][j]:.6f}" for j in range(3))
                                   for i in range(3)),
         "  b = " + "  ".join(f"{v / U.G0_MPS2 * 1e3:+.4f}±{s / U.G0_MPS2 * 1e3:.4f} mg"
                              for v, s in zip(a["b_mps2"], a["sigma_b_mps2"]))]
    g = result.get("gyro")
    if g:
        L.append(f"gyro ({g['method']}):")
        if g["method"] != "bias":
            L.append("  M = " + "\n      ".join("  ".join(f"{g['m'][i][j]:+.6f}±{g['sigma_m'][i][j]:.6f}"
                                                         for j in range(3)) for i in range(3)))
        L.append("  b = " + "  ".join(f"{np.degrees(v):+.4f}±{np.degrees(s):.4f} °/s"
                                      for v, s in zip(g["b_rad_s"], g["sigma_b_rad_s"])))
    return "\n".join(L)


def _row(name, truth, got, sigma):
    z = abs(got - truth) / sigma if sigma > 0 else float("nan")
    return f"{name:<14}{truth:>14.6f}{got:>14.6f}{sigma:>12.6f}{z:>9.2f}"


def _closure_after_session(dev, vb, out_dir: Path, params: Params) -> dict:
    """The closure check with the parameters just written (imubench.procedures.closure): a summary for
    the session's result; the details are in out_dir."""
    from imubench.procedures import closure as CL
    print("\nclosure check: integrating a closed path before and after calibration")
    res = CL.run_closure(dev, out_dir, params, vb, "box")
    print(CL.summarize(res))
    print(f"closure details: {out_dir / 'closure.json'}, plot {out_dir / 'closure.png'}")
    return {"dir": str(out_dir), "before_m": res["before"].distance_m, "after_m": res["after"].distance_m,
            "after_rest_bias_m": res["after_rest_bias"].distance_m,
            "noise_floor_m": res["noise_floor"]["sigma_distance_m"]}


def main_calibrate(argv=None) -> int:
    import argparse
    import sys

    from imubench.results import calibration as report
    from imubench.results.history import History
    ap = argparse.ArgumentParser(prog="imubench calibrate", description="guided calibration session")
    ap.add_argument("--port", help="pyserial URL of the device (default: $IMUBENCH_PORT)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"baud rate for a real UART (default {DEFAULT_BAUD})")
    ap.add_argument("--method", choices=("six", "multi"), default="six",
                    help="six faces (linear least squares, full M) or the multi-position |a| = g fit (26 attitudes)")
    ap.add_argument("--gyro", choices=("turntable", "rotation", "bias", "none"), default="bias")
    ap.add_argument("--dir", help="session directory (default: ./imubench-session-<time>)")
    ap.add_argument("--resume", metavar="DIR", help="continue the session in DIR")
    ap.add_argument("--redo", action="append", default=[], metavar="POSE",
                    help="with --resume: capture this pose again (repeatable; names as printed)")
    ap.add_argument("--rate", type=int, default=500, help="sample rate in Hz (default 500)")
    ap.add_argument("--hold", type=float, default=2.0, help="seconds captured per attitude (default 2)")
    ap.add_argument("--no-write", action="store_true", help="fit only; do not write the parameters to the device")
    ap.add_argument("--db", help="history database (default: in the user data directory)")
    ap.add_argument("--note", default="")
    ap.add_argument("--sim", action="store_true", help="run on a virtual device whose bench presents the attitudes")
    ap.add_argument("--sim-speed", type=float, default=20.0, help="virtual device speed factor (default 20)")
    ap.add_argument("--sim-seed", type=int, default=1)
    ap.add_argument("--sim-tilt", type=float, default=0.0, help="misalign each virtual attitude by this many degrees")
    ap.add_argument("--closure", action="store_true",
                    help="after a verified write-back, run the closure check (imubench closure) into DIR/closure: "
                         "the virtual bench drives a closed path, or you carry the board around one")
    a = ap.parse_args(argv)
    cfg = SessionConfig(method=a.method, gyro=None if a.gyro == "none" else a.gyro, rate_hz=a.rate,
                        hold_s=a.hold, write=not a.no_write, note=a.note)
    directory = a.resume or a.dir or f"imubench-session-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    vb = None
    try:
        if a.sim:
            from imubench.device.sim import VirtualBench
            vb = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, truth="random")
            url = vb.port_url
            ui = SimPresenter(vb, tilt_deg=a.sim_tilt, seed=a.sim_seed)
            print(f"virtual device with random truth (seed {a.sim_seed}) on {url}")
        else:
            url = a.port
            ui = HumanPresenter()
        with Device.open(url, baudrate=a.baud, timeout=5.0) as dev:
            sess = Session(dev, directory, cfg, ui, resume=bool(a.resume))
            if a.redo:
                if not a.resume:
                    raise SessionAborted("--redo goes with --resume DIR")
                sess.redo(a.redo)
            print(f"session directory: {sess.dir} (raw captures and state; --resume {sess.dir} continues it)")
            result = sess.run(plan_for(cfg.method))
            png = report.plot_pose_residuals(result, sess.dir / "residuals.png")
            print()
            print(params_table(result))
            print()
            print(report.before_after_table(result))
            print(f"residual plot: {png}")
            if vb is not None:
                print("\nrecovered beside the virtual device's truth:")
                print(truth_table(result, vb.get_truth()))
            if result["passed"] and cfg.write:
                previous = dev.get_params(ParamsWhich.ACTIVE).params
                wb = sess.write_back(sess.accel_fit, sess.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
                print(f"written: {', '.join(wb['steps'])}")
                result["written"] = True
                verify_plan = plan_for("six")[:cfg.verify_poses]
                result["verification"] = sess.verify(verify_plan)
                worst = max(abs(v["after_g"] - 1.0) * 1e3 for v in result["verification"])
                result["verified"] = worst <= cfg.tolerances.verify_mg
                print(f"verification of the device's calibrated output: worst | |a| - g | = {worst:.3f} mg "
                      f"({'within' if result['verified'] else 'OUTSIDE'} {cfg.tolerances.verify_mg} mg)")
                if not result["verified"]:
                    sess.restore(previous)
                    result["written"] = False
                    print("verification failed: the previous parameters were written back and saved")
            elif not result["passed"]:
                print("the fit did not pass its tolerance: nothing was written to the device")
            if a.closure and result["written"]:
                from imubench.procedures.closure import ClosureError
                try:
                    result["closure"] = _closure_after_session(dev, vb, sess.dir / "closure",
                                                               dev.get_params(ParamsWhich.ACTIVE).params)
                except ClosureError as e:       # the calibration stands; say why there is no figure
                    result["closure"] = {"error": str(e)}
                    print(f"closure check not possible: {e}", file=sys.stderr)
            sess._save(result=result)
            try:
                with History(a.db) as h:
                    run_id = h.record(result)
                print(f"recorded in the history as run {run_id}")
            except Exception as e:  # noqa: BLE001 - the result is safe in session.json; say why it is not in the history
                print(f"warning: not recorded in the history ({e}); the result is in {sess.state_path}",
                      file=sys.stderr)
            ok = result["passed"] and (result["verified"] or not cfg.write)
            print("\ncalibration " + ("PASSED" if ok else "FAILED"))
            return 0 if ok else 1
    except (SessionAborted, CalibrationError) as e:
        print(f"imubench calibrate: {e}", file=sys.stderr)
        return 1
    finally:
        if vb is not None:
            vb.stop()
