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
import os
import shlex
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.calib import TriadFit
from imubench.calib.fit import Calibration, Evidence, RotationEvidence, data_needed, fit
from imubench.calib.geometry import rotation_to  # noqa: F401 - where callers found it
from imubench.device.link import Device
from imubench.files import MAX_CAPTURE_BYTES, make_dir, open_growing, read_bytes
from imubench.procedures.capture import PoseCapture
from imubench.procedures.config import PoseRecord, SessionConfig, Tolerances  # noqa: F401 - where callers found them
from imubench.procedures.errors import SessionAborted
from imubench.procedures.motion import MotionCapture
from imubench.procedures.poses import enough_attitudes, pose_words, suggest_next
from imubench.procedures.presenter import TURN_POSE_SUFFIX, Presenter  # noqa: F401 - TURN_POSE_SUFFIX: where callers found it
from imubench.procedures.virtual import SimPresenter  # noqa: F401 - where callers found it
from imubench.procedures.writeback import (  # noqa: F401 - wear_warning: where callers found it
    WriteOutcome,
    params_from_fits,
    wear_warning,
    write_and_verify,
    write_verified,
)
from imubench.results.atomic import write_json_atomic
from imubench.results.record import CalibrationRecord, device_ident, jsonable, now_utc
from imubench.results.sessionfile import SESSION_SCHEMA, SessionFileError, load_state
from imubench.wire import params as PR
from imubench.wire.decoder import SampleBlock
from imubench.wire.ids import SENSOR_BAD_BITS, SENSOR_NAMES, board_name, part_names, parts_text, uid_text
from imubench.wire.protocol_gen import Params, ParamsWhich


# ---------------------------------------------------------------- the device a session belongs to
#: what names one device: its MCU's UID, its gyros' serial numbers, the firmware it runs
IDENTITY = (("mcu_uid", "MCU UID"), ("gyro_sn", "gyro serial numbers"), ("fw_build", "firmware build"),
            ("board", "board"))


def identity_differs(saved: dict, now: dict) -> str | None:
    """The first identity field that differs between two devices (device_ident), or None."""
    for key, words in IDENTITY:
        if key in saved and saved.get(key) != now.get(key):
            return words
    return None


def device_text(d: dict) -> str:
    """One device in a line: board, UID, gyro serials, firmware build."""
    sn = "/".join(str(x) for x in d.get("gyro_sn") or []) or "?"
    return (f"{d.get('board', '?')} UID {d.get('mcu_uid', '?')} (gyro S/N {sn}, firmware {d.get('fw_version', '?')} "
            f"build {d.get('fw_build', '?')})")


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
        self.started = now_utc()             # the session's start (a resumed session: the saved one)
        self.saved_write = config.write      # a resumed session: whether its run was to write
        self.run_started: str | None = None  # this run's start (run())
        self.stream_no = 0                   # the continuous stream being captured (capture-<n>.bin)
        self._first_index: int | None = None     # device sample index of the first and last sample read
        self._last_index: int | None = None
        self.bench_time_s: float | None = None   # device time from the first prompt to the last pose
        self.accel_fit: TriadFit | None = None   # the fits of the last run()
        self.gyro_fit: TriadFit | None = None
        self.gsens = None                        # the gyro's g-sensitivity fit (calib.gsens), when resolved
        self.gsens_report: dict | None = None    # what the fit found of it, for the record
        self.calibration: Calibration | None = None   # the last run()'s calib.fit.Calibration
        # the device it is captured on (UID, sensors' serial numbers, firmware build): a resumed
        # session belongs to its board, and refuses another
        self.device = device_ident(self.dev.info())
        if resume:
            self._load()
        else:
            make_dir(self.dir)
            if self.state_path.exists():
                raise SessionAborted(f"{self.dir} already holds a session: use --resume {shlex.quote(str(self.dir))}, or another --dir")
            self.save()

    # ------------------------------------------------------------ persistence
    def save(self, **extra) -> None:
        """The session file: rewritten after every attitude as a checkpoint (one line: the
        rest's samples make it ~250 KB, and indenting them through json's pure-Python encoder
        took a second of the first session), indented once a result is in it."""
        state = {"schema": SESSION_SCHEMA, "started": self.started, "device": self.device,
                 "config": jsonable(asdict(self.cfg)),
                 "rest": self.rest, "poses": [asdict(p) for p in self.poses], **extra}
        write_json_atomic(self.state_path, state, indent=1 if extra else None)   # a crash leaves the old or the new file

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
        saved_dev = state.get("device")
        if isinstance(saved_dev, dict):
            other = identity_differs(saved_dev, self.device)
            if other:
                raise SessionAborted(f"cannot resume: {self.dir} was captured on {device_text(saved_dev)}, but the "
                                     f"device on this port is {device_text(self.device)} ({other} differs): connect "
                                     "that board, or start a new session with another --dir")
        else:
            self.ui.say(f"warning: {self.state_path} names no device (saved by an older imubench): it cannot be "
                        f"checked to be {device_text(self.device)}'s")
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
        names = SENSOR_NAMES
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
            which = [n for bit, n in zip(SENSOR_BAD_BITS, names) if np.any(b.status & bit)]
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
        return {"board": board_name(info.board), "uid": uid_text(info.mcu_uid), "parts": part_names(info)}

    # ------------------------------------------------------------- streaming
    def _next_block(self, timeout: float = 10.0) -> SampleBlock:
        """The samples of the next 1/20 s (at least one): a pause of the stream shorter than
        `timeout` (a busy host, the buffer just discarded) is waited out, not an error."""
        from imubench.device.link import LinkTimeout
        clock = self.dev.clock          # the wall clock, or a lockstep virtual device's time
        t_end = clock.now() + timeout
        while True:
            try:
                b = self.dev.read(duration_s=0.05, timeout=timeout)
                break
            except LinkTimeout:
                if clock.now() > t_end:
                    raise
        self._count_block(b)
        return b

    def _count_block(self, b) -> None:
        """Keep the device sample index of the first and last sample read (the bench time)."""
        if len(b):
            if self._first_index is None:
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
                     "gyro": gyr.tolist() if "rest" in data_needed(self.cfg.method, self.cfg.gyro) else None,
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
        noise = np.asarray(self.rest["noise_mps2"])
        full_plan = full_plan or plan
        todo_names = {n for n, _ in plan}
        done = [(n, v) for n, v in full_plan if n not in todo_names]
        if self.cfg.method == "multi":
            self.ui.suggest(suggest_next([v for _, v in done], plan))
        self.ui.present_todo(list(plan), done, total)
        # only what comes after the prompt counts: samples that waited in the buffer (behind a
        # question on the terminal, or a reader behind the device) show the board before the
        # person acted. The capture file on disk keeps every sample (the rotation method's).
        self.dev.discard_buffered()
        cap = PoseCapture(self.cfg, noise, plan, full_plan, {p.name for p in self.poses}, self.stream_no, self.ui)
        while True:
            rec = cap.feed(self._next_block())
            if rec is not None:
                return rec

    # ---------------------------------------------------------------- stream
    def _start_stream(self) -> None:
        """A new continuous stream, captured to its own file as it arrives."""
        self.stream_no = 1 + max([p.stream for p in self.poses] + [self.stream_no])
        while (self.dir / f"capture-{self.stream_no}.bin").exists():
            self.stream_no += 1     # a resumed session stopped before a pose: its stream keeps its file
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

    # ------------------------------------------------------------------- run
    def run(self, plan: list[tuple[str, np.ndarray]], history=None, verify_plan=None) -> dict:
        self.run_started = now_utc()
        self._first_index = self._last_index = None
        health = self.check_health()
        self.ui.say(f"device {health['board']} {health['uid']}: {parts_text(health['parts'])}")
        self._start_stream()
        try:
            self.ui.present_plan(list(plan), self.cfg.method)
            for p in self.poses:
                self.ui.pose_event(p.name, "done", {"before_g": float(np.linalg.norm(p.mean_mps2)) / U.G0_MPS2})
            if self.rest is None:
                self.ui.present_rest(self.cfg.rest_s)
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
                    self.ui.pose_event(rec.name, "rejected", {"why": "discarded by you: present it again"})
                    self.dev.discard_buffered()
                    continue
                self.poses.append(rec)
                self.save()
                todo = [p for p in todo if p[0] != rec.name]
                self.ui.pose_event(rec.name, "done",
                      {"before_g": float(a_g), "n": rec.n, "sigma_mg": (rec.sigma_norm_g or float("nan")) * 1e3,
                       "angle_from_plan_deg": rec.angle_from_plan_deg})
                self.ui.say(f"  {summary}, {len(todo)} to go")
                if self.cfg.adaptive and self.cfg.method == "multi":
                    reached, sig, why = enough_attitudes(*self._fit_inputs(), self.cfg.targets)
                    self.ui.targets(sig, self.cfg.targets.as_dict(), reached)
                    self.ui.say(f"  {why}" + ("" if not reached else
                                              f": done after {len(self.poses)} attitudes, {len(todo)} not needed"))
            # device time from the first prompt to the last pose: the person's moves included
            self.bench_time_s = (None if self._first_index is None else
                                 (self._last_index - self._first_index) / self.cfg.rate_hz)
            motion = MotionCapture(self.cfg, self.rest, self.ui, self._next_block)
            needs = data_needed(self.cfg.method, self.cfg.gyro)     # calib.fit: what its strategy needs
            segments = motion.capture_turntable() if "turntable" in needs else None
            turn_runs = motion.capture_known_turns() if "turns" in needs else None
        finally:
            self._stop_stream()

        means, sigmas = self._fit_inputs()
        self.ui.step("fit", f"fitting {self.cfg.method}-position to {len(means)} attitudes", "running")
        rest_gyr = np.asarray(self.rest["gyro"]) if self.rest.get("gyro") is not None else None
        ev = Evidence(means_mps2=means, sigmas_mps2=sigmas, rate_hz=self.cfg.rate_hz,
                      gyro_means_rad_s=np.array([p.gyro_mean_rad_s for p in self.poses]),
                      rest_gyro_rad_s=rest_gyr, turntable_segments=segments, turn_runs=turn_runs,
                      turn_noise_mps2=np.asarray(self.rest["noise_mps2"]),
                      turn_min_still_s=min(1.0, 0.5 * self.cfg.hold_s),
                      rotation=self._rotation_evidence() if "stream" in needs else None)
        cal = fit(ev, method=self.cfg.method, gyro=self.cfg.gyro,
                  excess_limit_mps2=self.cfg.tolerances.accel_rms_mg * 1e-3 * U.G0_MPS2)
        for line in cal.said:
            self.ui.say(line)
        accel, gyro, gyro_refused, frame_note = cal.accel, cal.gyro, cal.gyro_refused, cal.frame_note
        self.calibration = cal
        self.gsens, self.gsens_report = cal.gsens, cal.gsens_report
        self.accel_fit, self.gyro_fit = accel, gyro
        result = self._result(accel, gyro)
        result["gsens"] = self.gsens_report
        if gyro_refused:
            result["gyro_refused"] = gyro_refused
        result["accel_frame"] = accel.extra.get("frame", "board")
        result["bench_time_s"] = self.bench_time_s
        result["adaptive"] = bool(self.cfg.adaptive)
        if self.cfg.method == "six":
            off = [p.angle_from_plan_deg for p in self.poses if p.angle_from_plan_deg is not None]
            if off:
                result["faces_off_square_deg"] = float(max(off))
        if accel.method == "multi_position":
            from imubench.procedures.poses import accel_sigmas
            result["accel_sigmas"] = accel_sigmas(accel)
        self.ui.step("fit", f"fitted: RMS of |a| − g after {result['accel_rms_after_mg']:.3g} mg", "done")
        if frame_note:
            result.setdefault("warnings", []).append(frame_note)
        self.save(result=result)
        return result

    def _rotation_evidence(self) -> RotationEvidence:
        """The poses' continuous stream (capture-<n>.bin) for the rotation method: every sample
        between the poses, or why it cannot serve (gaps, several streams, unreadable)."""
        from imubench.wire.decoder import decode_bytes
        by_stream: dict[int, list[PoseRecord]] = {}
        for p in self.poses:
            by_stream.setdefault(p.stream, []).append(p)
        for k in sorted(by_stream):
            try:
                _, raw, _, st = decode_bytes(read_bytes(self.dir / f"capture-{k}.bin", MAX_CAPTURE_BYTES, "the capture"))
            except OSError as e:
                return RotationEvidence(problem=str(e))
            if raw is None or st.samples_missing:
                return RotationEvidence(problem=f"stream {k} has gaps ({st.samples_missing} samples lost): "
                                                "the rotation method needs every sample between poses")
        if len(by_stream) > 1:
            return RotationEvidence(problem="the rotation method needs all poses in one continuous stream; this "
                                            "session was resumed — use --gyro bias or turntable, or start a new session")
        idx0 = int(raw.sample_index[0])
        acc, gyr = raw.si()
        poses = sorted(next(iter(by_stream.values())), key=lambda p: p.start_index)
        return RotationEvidence(accel_mps2=acc, gyro_rad_s=gyr,
                                intervals=[(p.start_index - idx0, p.stop_index - idx0) for p in poses],
                                rest_means_mps2=np.array([p.mean_mps2 for p in poses]))

    def _result(self, accel: TriadFit, gyro: TriadFit | None) -> dict:
        means = np.array([p.mean_mps2 for p in self.poses])
        sig = np.array([p.sigma_mean_mps2 for p in self.poses])
        before = np.linalg.norm(means, axis=1)
        after = np.linalg.norm(accel.correct(means), axis=1)
        # 1-sigma of |a| from the mean's sigma projected on the gravity direction
        sig_g = np.sqrt(np.sum((means / before[:, None] * sig) ** 2, axis=1)) / U.G0_MPS2
        rms_after_mg = float(np.sqrt(np.mean((after - U.G0_MPS2) ** 2)) / U.G0_MPS2 * 1e3)
        return CalibrationRecord.from_fit(
            device=device_ident(self.dev.info()), started=self.run_started, session_started=self.started,
            method=self.cfg.method, gyro_method=self.cfg.gyro, accel=accel, gyro=gyro,
            poses=[{"name": p.name, "n": p.n, "before_g": float(before[i] / U.G0_MPS2),
                    "after_g": float(after[i] / U.G0_MPS2), "sigma_g": float(sig_g[i]), "temp_c": p.temp_c}
                   for i, p in enumerate(self.poses)],
            temperature_c={"accel": float(np.mean([p.temp_c for p in self.poses]))},
            tolerances=asdict(self.cfg.tolerances), accel_rms_after_mg=rms_after_mg,
            note=self.cfg.note, capture_dir=str(self.dir.resolve())).to_json()

    def verify(self, plan: list[tuple[str, np.ndarray]]) -> list[dict]:
        """The device's own calibrated output in a few attitudes: | |a| - g | per pose."""
        from imubench.calib.stillness import StillnessDetector
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

    # -------------------------------------------------------------- write-back
    def _new_params(self, accel: TriadFit, gyro: TriadFit | None, cal_id: int) -> tuple[Params, Params]:
        """(the block from the fits, the active block it replaces), checked as the device checks."""
        old = self.dev.get_params(ParamsWhich.ACTIVE)
        new = params_from_fits(accel, gyro, old.params, cal_id, self.gsens)
        PR.validate(new)                                      # the device's own checks, first here
        return new, old.params

    def write_back(self, accel: TriadFit, gyro: TriadFit | None, cal_id: int) -> dict:
        """set_params, read back bit-exactly, save, reboot, read back again. On any failure
        the previous parameters are put back (and saved again if they were saved)."""
        new, old = self._new_params(accel, gyro, cal_id)
        return write_verified(self.dev, new, previous=old, say=self.ui.say)

    def write_and_verify(self) -> WriteOutcome:
        """The last run()'s fits written back and the device's own output verified in
        cfg.verify_poses attitudes; the previous parameters put back when that fails
        (procedures.writeback.write_and_verify, the fixture's too)."""
        new, old = self._new_params(self.accel_fit, self.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
        return write_and_verify(self.dev, new, old, lambda: self.verify(plan_for("six")[:self.cfg.verify_poses]),
                                self.cfg.tolerances.verify_mg, self.ui)


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
        ui.pose_event(p["name"], "done", {"before_g": p["before_g"], "after_g": p["after_g"],
                                                    "sigma_mg": p["sigma_g"] * 1e3})
    report(result)
    if result["passed"] and cfg.write and not result.get("gyro_refused"):
        out = sess.write_and_verify()
        result.update(written=out.written, verified=out.verified, verification=out.verification)
    elif result.get("gyro_refused"):
        why = ("the gyro part was refused: nothing was written to the device (its gyro calibration would be "
               "lost); the accelerometer's result is kept in session.json and the history")
        ui.say(why)
        ui.step("write", why, "skipped")
    elif not result["passed"]:
        ui.say("the fit did not pass its tolerance: nothing was written to the device")
        ui.step("write", "the fit did not pass its tolerance: nothing was written to the device", "skipped")
    else:
        ui.step("write", "not written to the device (--no-write)", "skipped")
    png = plot_pose_residuals(result, sess.dir / "residuals.png")
    ui.say(f"residual plot: {png}")
    sess.finish(result)
    return result, sess
