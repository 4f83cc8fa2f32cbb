"""Calibrate from a recording of any 6-axis IMU: the analysis a live session runs, on a file.

    imubench calibrate --from FILE [--format csv|imutk|imucal|npz|capture|rosbag] --accel-unit U --gyro-unit U

A recording (imubench.recordings) is cut into still intervals by the data alone
(calib.static.detect_static), the accelerometer is fitted on them (six-position or
multi-position, with the same observability refusals as a session), the gyro bias comes from
the longest still interval, and gyro scale and misalignment from the known-angle turns in the
recording (calib.turns) and/or the rotations between the still intervals
(calib.gyro.rotation_method), combined when both are present. The result has the form of a
session's result (procedures.session): the same DIR/session.json, residual plot, HTML report
(results.report) and history record, plus the recording's own section (timing, segmentation,
turns) and the result in other tools' layouts (results.paramfiles).

Nothing here reads the file's bytes (imubench.recordings does) or fits: the fit, the gyro's
found in the recording included, is calib.fit's, the one front door a session's is too; this
module gathers the recording's rests and stream for it and presents what it returns; what is
written to the session directory is procedures.from_file_write's (calibrate_recording).
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.calib import TriadFit, face_of
from imubench.calib.fit import (Evidence, Note, RecordingEvidence, accel_model_words, fit,
                                gyro_method_names)
from imubench.procedures.recording_checks import check_accel_unit, check_gyro_unit, compare_annotation
from imubench.procedures.session import Tolerances
from imubench.recordings import Recording, RecordingError, command_line, command_options, timing_lines
from imubench.results.record import CalibrationRecord, now_utc

GYRO_FILE_METHODS = gyro_method_names(recording=True)   # calib.fit.GYRO_METHODS, the one list
# what a class of accelerometer reaches after a linear calibration (RMS of |a| − g over the rests),
# by its noise density measured at rest: (upper density µg/√Hz, tolerance mg, class, example)
ACCEL_CLASSES = ((60.0, 1.0, "low-noise MEMS", "ADXL355, 25 µg/√Hz"),
                 (200.0, 2.0, "mid-range MEMS", "BMI160, 180 µg/√Hz"),
                 (float("inf"), 3.0, "consumer MEMS", "MPU-6050/MPU-9150, 400 µg/√Hz"))
RECORD_ADVICE = ("record turns about each board axis while it is off the vertical, both ways and from several "
                 "attitudes (rotation method: 12-24 motions between rests), or one full turn about X, Y and Z each "
                 "pointing up with a rest before and after (--gyro turns)")


@dataclass
class FileConfig:
    method: str = "auto"                 # "six" | "multi" | "auto": multi when the attitudes constrain it, else six
    gyro: str | None = "auto"            # "auto" (turns and/or rotation, whatever the recording has) | "bias" |
                                         # "turns" | "rotation" | None
    turn_deg: float = 360.0              # the known angle of one turn
    angle_sigma_deg: float = 1.0         # hand placement after a turn
    axis_sigma_deg: float = 0.5          # turn axis off the measured vertical
    gyro_range_dps: float | None = None  # the gyro's range: samples at it are clipped
    window_s: float = 0.5                # still detection window
    min_still_s: float = 1.0             # shortest still interval kept
    note: str = ""
    command: str = ""                    # the command line that ran (the folder's README repeats it)
    device: str | None = None            # a name for the IMU (the history groups runs by it)
    writers: tuple = ()                  # results.paramfiles.WRITERS to write
    px4_acc_id: int | None = None        # PX4 device ids for CAL_ACC0_ID / CAL_GYRO0_ID (--export px4)
    px4_gyro_id: int | None = None
    annotation: list | None = None       # (name, start, stop) sections to compare the segmentation with
    tolerances: Tolerances = field(default_factory=Tolerances)
    tolerance_from_imu: bool = True      # the pass tolerance from this IMU's noise and class (else tolerances')


def device_id(name: str) -> str:
    """A stable 24-hex-digit identifier for an IMU known by name (the history's device key):
    the first 12 bytes of SHA-256 of the name."""
    return hashlib.sha256(name.encode()).hexdigest()[:24].upper()


# ------------------------------------------------------------------ the analysis
class FileAnalysis:
    """The analysis of one recording (no files written): run() fills accel, gyro, result."""

    def __init__(self, rec: Recording, cfg: FileConfig, say=print):
        self.rec, self.cfg, self.say = rec, cfg, say
        self.notes: list[str] = []
        self.accel: TriadFit | None = None
        self.gyro: TriadFit | None = None
        self.gyro_parts: dict = {}
        self.turns: list = []
        self.method = cfg.method        # "auto" becomes "six" or "multi" in run()
        self.fg = rec.gyro_factor()
        self.gyro_refused: str | None = None
        self.gsens: dict | None = None
        self.fa: float | None = None
        self.intervals: list = []       # the rests the fits use (updated as the analysis goes)
        self._fit_rests: list = []      # the still intervals handed to the accelerometer fit, parallel to self.rests
        self.rests: list = []           # calib.rests.RestRecord per rest the fit weighed, in time order: how it used it
        self.accel_choice = None        # calib.acceptance.AccelChoice: the model kept and why
        self.accel_candidates: list = []  # every accelerometer model tried: kept, refused or unresolved, and why
        self._clipped_rests: list = []  # still intervals left out because the accelerometer sat at full scale
        self._left_out: dict[int, str] = {}      # id(rest) -> why it was left out before the fit (clipping)
        self.clipping: dict = {"gyro": [], "accel": []}
        self._acc_clip: list = []       # calib.clipping.ClipRun of the accelerometer

    def _note(self, text: str) -> None:
        self.notes.append(text)
        self.say(f"  note: {text}")

    def run(self) -> dict:
        from imubench.calib.static import detect_static, require_static
        rec, cfg = self.rec, self.cfg
        self.started = now_utc()
        fs = rec.fs_hz
        # ---- accelerometer scale: declared, or provisional (raw counts without a scale)
        fa = rec.accel_factor()
        if fa is None:
            iv0 = detect_static(rec.accel, fs, window_s=cfg.window_s, min_duration_s=cfg.min_still_s)
            if not len(iv0):
                require_static(iv0, 6)
            fa = U.G0_MPS2 / float(np.median([np.linalg.norm(i.mean) for i in iv0]))
            self._note(f"accelerometer in counts without a nominal scale: fitted in counts; M is reported in "
                       f"counts per g (the still intervals' median |a| = {U.G0_MPS2 / fa:.6g} counts)")
        self.fa = fa
        acc = rec.accel * fa
        from imubench.calib.clipping import find_clipping
        self._acc_clip = find_clipping(rec.accel)
        noise = None
        if self._acc_clip:          # a clipped axis is noiseless there: the rest noise from the samples that are not
            from imubench.calib.static import rest_noise
            ok = np.ones(len(acc), bool)
            for r in self._acc_clip:
                ok[r.start:r.stop] = False
            noise = rest_noise(acc[ok], fs, cfg.window_s)
        ivs = detect_static(acc, fs, noise_sigma=noise, window_s=cfg.window_s, min_duration_s=cfg.min_still_s)
        clipped = self._rests_at_full_scale(ivs)
        self._clipped_rests = [i for i in ivs if id(i) in clipped]
        # a rest that moved is weighed by its motion, not dropped (calib.rests); one at full scale is left out
        keep = [i for i in ivs if id(i) not in clipped]
        self.intervals = self._fit_rests = list(keep)
        self.gyro_refused = None        # why the gyro (scale, misalignment; or all of it) was not calibrated
        warn = None
        if keep:
            check_accel_unit(rec, np.linalg.norm([i.mean for i in keep], axis=1) / fa)
            longest0 = max(keep, key=lambda i: i.n)
            if rec.gyro_scaled and cfg.gyro:   # median: robust to a smooth turn inside an accelerometer-still interval
                try:
                    warn = check_gyro_unit(rec, np.median(rec.gyro[longest0.start:longest0.stop], axis=0),
                                           rec.gyro_factor())
                    if warn:
                        self._note(warn)
                except RecordingError as e:  # the accelerometer is still calibrated
                    self.gyro_refused = str(e)
                    warn = None
        if keep and self.gyro_refused is None and not warn:   # a turn the accelerometer did not see (smooth, about the vertical)
            from imubench.calib.turns import split_by_rotation
            n0 = len(keep)
            if rec.gyro_scaled:
                keep = split_by_rotation(acc, rec.gyro * rec.gyro_factor(), fs, keep, min_duration_s=cfg.min_still_s)
            else:                    # raw counts: 20 × the typical rest noise, in counts
                noise = float(np.median([np.max(np.std(rec.gyro[i.start:i.stop], axis=0)) for i in keep]))
                keep = split_by_rotation(acc, rec.gyro, fs, keep, min_duration_s=cfg.min_still_s,
                                         threshold=20.0 * max(noise, 1e-12))
            if len(keep) < min(n0, 9 if cfg.method == "multi" else 6):
                self._note(f"cutting where the gyro turned would leave {len(keep)} of {n0} still intervals: not cut "
                           "(check the gyro unit)")
                keep = [i for i in ivs if id(i) not in clipped]
            elif len(keep) != n0:
                self._note(f"{len(keep) - n0:+d} still intervals after cutting where the gyro turned "
                           "(the accelerometer alone did not show it)")
        self.intervals = self._fit_rests = list(keep)
        need = 9 if cfg.method == "multi" else 6
        require_static(keep if len(keep) < len(ivs) else ivs, need)
        means = np.array([i.mean for i in keep])
        sigmas = np.array([i.sigma_mean for i in keep])
        self.faces = [face_of(m) for m in means]
        self.say(f"still intervals: {len(keep)} found by the data (window {cfg.window_s:g} s, k = {ivs.k:g} × the "
                 f"rest noise): " + ", ".join(f"{f} {i.t_start_s:.1f}–{i.t_start_s + i.duration_s:.1f} s"
                                            for f, i in zip(self.faces, keep)))
        from imubench.calib.fit import FitRefused
        ev = self._evidence(means, sigmas, acc)
        ev.recording = self._recording_evidence(keep, acc)
        try:
            cal = fit(ev, method=cfg.method, gyro=cfg.gyro if self.gyro_refused is None else None,
                      excess_limit_mps2=self._excess_limit(means, sigmas), gsens=False)
        except FitRefused as e:             # how the rests were seen stays for the evidence of the refusal
            self._records(e.rests)
            self.accel_candidates = e.candidates
            raise
        self.calibration = cal
        used = self._accel_chosen(cal.accel_choice)      # the rests the accelerometer's fit used: the gyro's too
        self.intervals, self.faces = [keep[k] for k in used], [self.faces[k] for k in used]
        means, sigmas = means[used], sigmas[used]
        self._present(cal)
        if cal.gyro_refused is not None:    # a refusal keeps the accelerometer's result
            self.gyro_refused, self.gyro = cal.gyro_refused, cal.gyro
        elif cfg.gyro and self.gyro_refused is None:
            self.gyro = cal.gyro
        elif self.gyro_refused:             # refused before the fit (the declared gyro unit)
            self.say(f"gyro not calibrated: {self.gyro_refused}")
        if self.fg is None:         # raw gyro counts that no turn scaled: nothing of the gyro can be said in °/s
            raise RecordingError("the gyro is in counts without a nominal scale and no known-angle turn in the "
                                 "recording scales it: give --gyro-scale COUNTS_PER_DPS (the data sheet's), or "
                                 "--sensor NAME with --gyro-range DPS (its full-scale setting)")
        return self._result(means, sigmas)

    def _present(self, cal) -> None:
        """What the fit found of the gyro, kept for the result and said in order (its notes among
        the result's notes; the gyro's full scale found in the data among the recording's detected)."""
        from imubench.results.record import fit_dict
        for line in cal.said:
            if isinstance(line, Note):
                self._note(str(line))
            else:
                self.say(line)
        if cal.gyro_scale is not None:
            self.fg = cal.gyro_scale
        self.turns = cal.turns
        self.gyro_parts = ({"fits": {k: fit_dict(v, "rad_s") for k, v in cal.gyro_parts["fits"].items()},
                            "refused": cal.gyro_parts["refused"]} if cal.gyro_parts else {})
        self.gsens = cal.gsens_report
        self.clipping["gyro"] = list(cal.gyro_clipping)
        if cal.detected is not None:
            line, dps = cal.detected
            self.rec.detected.append(line)
            self.rec.options["gyro_range_dps"] = dps

    def _recording_evidence(self, rests: list, acc: np.ndarray | None = None) -> RecordingEvidence:
        """The recording's one stream as calib.fit takes it for the gyro (its rests: `rests`)."""
        rec, cfg = self.rec, self.cfg
        return RecordingEvidence(
            gyro=rec.gyro, gyro_scale=rec.gyro_factor(), accel_mps2=rec.accel * self.fa if acc is None else acc,
            rests=list(rests), rate_hz=rec.fs_hz, breaks=tuple(b for b, _ in rec.breaks), parts=rec.parts,
            turn_deg=cfg.turn_deg, angle_sigma_deg=cfg.angle_sigma_deg, axis_sigma_deg=cfg.axis_sigma_deg,
            gyro_range_dps=cfg.gyro_range_dps, range_known="gyro_range_dps" in rec.options)

    def _clipped_motions(self, rests) -> None:
        """The gyro's clipping between the rests as the fit finds it (calib.fit.gyro_clipping), for
        the evidence of a refusal before the gyro was fitted: kept and noted."""
        from imubench.calib.fit import gyro_clipping
        clip = gyro_clipping(self._recording_evidence(rests), rests)
        self.clipping["gyro"] = clip.rows
        if clip.detected is not None:
            self.rec.detected.append(clip.detected[0])
            self.rec.options["gyro_range_dps"] = clip.detected[1]
        for line in clip.said:
            if isinstance(line, Note):
                self._note(str(line))

    def _rests_at_full_scale(self, ivs) -> set[int]:
        """The rests where the accelerometer sat at its full scale (calib.clipping, from the data):
        left out of the fit and named; returns their ids."""
        from imubench.calib.clipping import runs_in
        runs = self._acc_clip
        out = set()
        fs = self.rec.fs_hz
        for iv in ivs:
            inside = runs_in(runs, iv.start, iv.stop)
            if not inside:
                continue
            r = max(inside, key=lambda x: x.n)
            level = r.level * self.fa / U.G0_MPS2
            why = (f"accelerometer {r.axis_name} held at {level:+.4g} g (its full scale, found in the data) for "
                   f"{sum(x.n for x in inside)} samples from {r.start / fs:.2f} s")
            out.add(id(iv))
            self._left_out[id(iv)] = f"clipped: {why}"
            self.clipping["accel"].append({"rest_t_start_s": iv.t_start_s, "axis": r.axis_name, "level_g": level,
                                           "samples": sum(x.n for x in inside), "first_s": r.start / fs})
            self._note(f"still interval at {iv.t_start_s:.1f} s ({iv.duration_s:.1f} s) not used: {why}")
        return out

    def _evidence(self, means: np.ndarray, sigmas: np.ndarray, acc: np.ndarray) -> Evidence:
        """The rests as the fit takes them (calib.fit): each weighed by its noise and its own
        motion (calib.rests, the covariance it adds and why)."""
        from imubench.calib.rests import motion_covariances
        covs, self._motion = motion_covariances(acc, self.intervals)
        texts = [m.describe(U.G0_MPS2) if m.significant else "" for m in self._motion]
        return Evidence(means_mps2=means, sigmas_mps2=sigmas, rate_hz=self.rec.fs_hz, covs=covs, motions_text=texts)

    def _excess_limit(self, means: np.ndarray, sigmas: np.ndarray) -> float:
        """The scatter beyond the noise the accelerometer fit accepts: this IMU's tolerance, m/s²."""
        sig_g = np.linalg.norm(means / np.linalg.norm(means, axis=1)[:, None] * sigmas, axis=1) / U.G0_MPS2
        tol, _ = self._tolerance(sig_g)
        return tol.accel_rms_mg * 1e-3 * U.G0_MPS2

    def _records(self, uses) -> None:
        """self.rests from the fit's use of each rest (calib.acceptance.RestUse), each use noted."""
        from imubench.calib.rests import RestRecord
        self.rests = [RestRecord(start=int(i.start), stop=int(i.stop), t_start_s=i.t_start_s,
                                 duration_s=i.duration_s, face=f, use=r.use, use_reason=r.use_reason,
                                 sigma_inflation=r.sigma_inflation,
                                 motion={"direction_deg": m.direction_deg,
                                         "magnitude_change_mg": m.magnitude_change / U.G0_MPS2 * 1e3,
                                         "drift_chi2": m.chi2, "drift_p": m.p, "significant": m.significant})
                      for i, f, r, m in zip(self.intervals, self.faces, uses, self._motion)]
        for r in self.rests:
            if r.use != "used":
                self._note(f"rest at {r.t_start_s:.1f} s ({r.duration_s:.1f} s, {r.face}) {r.use}: {r.use_reason}")

    def _accel_chosen(self, choice) -> list[int]:
        """Keep and tell the accelerometer model the fit chose (calib.acceptance.AccelChoice):
        how each rest was used, the model and why; returns the indices of the rests it used."""
        self._records(choice.rests)
        self.accel_choice = choice
        self.accel_candidates = choice.candidates
        self.method = self.calibration.method
        short = accel_model_words(choice.fit.method)
        first = choice.candidates[0]
        if first["status"] == "kept":
            self.say(f"method: {short} (the rests resolve its parameters and it fits them)")
        else:
            self.say(f"method: {short} (the {first['model'].split(',')[0]} fit cannot be used: "
                     f"{first['reason']})")
        self.say(f"accelerometer model: {choice.summary}")
        self.accel = choice.fit
        return [k for k, r in enumerate(self.rests) if r.use != "left out"]

    def _result(self, means, sigmas) -> dict:
        rec, cfg, accel = self.rec, self.cfg, self.accel
        before = np.linalg.norm(means, axis=1)
        after = np.linalg.norm(accel.correct(means), axis=1)
        sig_g = np.sqrt(np.sum((means / before[:, None] * sigmas) ** 2, axis=1)) / U.G0_MPS2
        rms_after_mg = float(np.sqrt(np.mean((after - U.G0_MPS2) ** 2)) / U.G0_MPS2 * 1e3)
        name = cfg.device or rec.device or Path(rec.source.split(" + ")[0]).stem
        fs = rec.fs_hz
        poses = [{"name": f"{self.faces[i]} @{iv.t_start_s:.1f}s", "n": int(iv.n),
                  "before_g": float(before[i] / U.G0_MPS2), "after_g": float(after[i] / U.G0_MPS2),
                  "sigma_g": float(sig_g[i]), "temp_c": None}
                 for i, iv in enumerate(self.intervals)]
        source = self.source()
        seg = [{"face": self.faces[i], "start": iv.start, "stop": iv.stop, "t_start_s": iv.t_start_s,
                "duration_s": iv.duration_s} for i, iv in enumerate(self.intervals)]
        turns = [{"label": t.label, "start": t.start, "stop": t.stop, "t_start_s": t.start / fs,
                  "duration_s": t.duration_s, "known_deg": math.degrees(t.angle_rad),
                  "before_deg": math.degrees(t.measured_rad), "off_axis_deg": t.off_axis_deg,
                  "usable": t.usable, "reason": t.reason} for t in self.turns]
        fitted = {row["start"]: row for row in ((self.gyro_parts.get("fits", {}).get("turns") or {}).get("extra")
                                                 or {}).get("turns", [])}
        for row in turns:
            if row["start"] in fitted:
                row["sigma_deg"] = fitted[row["start"]]["sigma_deg"]
        if self.gyro is not None and self.gyro.method != "bias":
            minv = np.linalg.inv(self.gyro.m)
            for row, t in zip(turns, self.turns):
                row["after_deg"] = math.degrees(float((minv @ t.integral_rad) @ t.up))
        annotation = None
        if cfg.annotation or rec.parts:
            annotation = compare_annotation(cfg.annotation or rec.parts, self.intervals, self.faces, self.turns, fs)
        tol, tol_text = self._tolerance(sig_g)
        verdict = verdict_text(rms_after_mg <= tol.accel_rms_mg, rms_after_mg, tol.accel_rms_mg, cfg.gyro,
                               self.gyro, self.gyro_refused)
        if self.accel_choice is not None and self.accel_choice.held:
            verdict = verdict.replace("accelerometer calibrated", f"accelerometer calibrated ({self.accel_choice.model}; "
                                      f"{', '.join(self.accel_choice.held)} held at nominal)", 1)
        result = CalibrationRecord.from_fit(
            device={"mcu_uid": device_id(name), "board": f"IMU '{name}' (from a file)", "fw_version": "",
                    "fw_build": "", "accel_ids": [], "gyro_pid": [], "gyro_sn": []},
            started=self.started, session_started=self.started, method=self.method, gyro_method=cfg.gyro,
            accel=accel, gyro=self.gyro, poses=poses, tolerances=asdict(tol),
            accel_rms_after_mg=rms_after_mg, note=cfg.note,
            sections={"source": source, "segmentation": seg, "turns": turns, "gyro_parts": self.gyro_parts,
                      "notes": list(self.notes), "annotation": annotation, "device_name": name,
                      "tolerance_source": tol_text, "gyro_refused": self.gyro_refused, "verdict": verdict,
                      "accel_noise_ug_rthz": self.accel_noise_ug, "gsens": self.gsens,
                      "rests": self.rest_rows(), "clipping": self.clipping,
                      "accel_model": self.accel_choice.summary if self.accel_choice else None,
                      "accel_held": self.accel_choice.held if self.accel_choice else [],
                      "accel_candidates": self.accel_candidates}).to_json()
        if not rec.accel_scaled:
            result["accel_counts_per_g"] = (accel.m / self.fa * U.G0_MPS2).tolist()
        if not rec.gyro_scaled and self.gyro is not None:
            result["gyro_counts_per_dps"] = (self.gyro.m / self.fg * math.pi / 180.0).tolist()
        return result


    def source(self) -> dict:
        """The recording as the result and the evidence describe it."""
        rec = self.rec
        return {"file": rec.source, "format": rec.fmt, "units": rec.unit_text(), "rate_hz": rec.fs_hz,
                "samples": len(rec), "duration_s": rec.duration_s, "timing": timing_lines(rec),
                "reader_notes": list(rec.notes), "breaks": [[int(b), r] for b, r in rec.breaks],
                "detected": list(rec.detected), "options": command_options(rec), "command": command_line(rec),
                "accel_factor_si": self.fa, "gyro_factor_si": self.fg,
                "accel_scaled": rec.accel_scaled, "gyro_scaled": rec.gyro_scaled}

    def rest_rows(self) -> list[dict]:
        """Every rest found, in time order, with its use in the accelerometer fit: "used",
        "down-weighted" (its σ inflated by sigma_inflation) or "left out", and the reason with its
        numbers. The rests the fit weighed carry their calib.rests.RestRecord; a rest at full
        scale was left out before the fit; a refusal before the fit leaves every rest "used" by
        nothing yet, so their use is what the analysis had kept."""
        weighed = len(self.rests) == len(self._fit_rests)
        items = [(iv, self.rests[k] if weighed else None) for k, iv in enumerate(self._fit_rests)]
        items += [(iv, None) for iv in self._clipped_rests]
        rows = []
        for k, (iv, rr) in enumerate(sorted(items, key=lambda x: x[0].start)):
            if rr is not None:
                use, reason, infl, motion = rr.use, rr.use_reason, rr.sigma_inflation, rr.motion
            else:
                left = self._left_out.get(id(iv))
                use, reason, infl, motion = ("left out", left, 1.0, None) if left else ("used", "", 1.0, None)
            mean = np.asarray(iv.mean, float)
            rows.append({"index": k, "start": int(iv.start), "stop": int(iv.stop), "t_start_s": float(iv.t_start_s),
                         "duration_s": float(iv.duration_s), "face": face_of(mean),
                         "mean_g": (mean / U.G0_MPS2).tolist(),
                         "sigma_mg": (np.asarray(iv.sigma_mean, float) / U.G0_MPS2 * 1e3).tolist(),
                         "use": use, "use_reason": str(reason or ""), "sigma_inflation": float(infl),
                         "motion": motion})
        return rows

    def _tolerance(self, sig_g: np.ndarray) -> tuple[Tolerances, str]:
        """The pass tolerance for this IMU: given (--tolerance-mg), or from its class by the
        accelerometer noise density measured at rest (ACCEL_CLASSES), and never below 3× the RMS
        its rests' noise alone leaves; with the reason, as printed."""
        rec, fs = self.rec, self.rec.fs_hz
        acc = rec.accel * self.fa
        sd = np.median([np.std(acc[i.start:i.stop], axis=0, ddof=1) for i in self.intervals], axis=0)
        self.accel_noise_ug = float(np.max(sd) / U.G0_MPS2 * 1e6 / math.sqrt(fs / 2.0))
        tol = self.cfg.tolerances
        if not self.cfg.tolerance_from_imu:
            return tol, f"{tol.accel_rms_mg:g} mg RMS (given)"
        for top, mg, cls, example in ACCEL_CLASSES:
            if self.accel_noise_ug <= top:
                break
        floor = 3.0 * float(np.sqrt(np.mean(sig_g**2))) * 1e3
        value = max(mg, floor)
        why = (f"{value:.3g} mg RMS from this IMU: accelerometer noise {self.accel_noise_ug:.0f} µg/√Hz at rest "
               f"(worst axis, white over the {fs / 2:g} Hz band), {cls} class ({example}), which a linear "
               f"calibration brings to about {mg:g} mg"
               + (f"; raised to 3× the {floor / 3:.2g} mg RMS its rests' noise alone leaves" if floor > mg else "")
               + "; --tolerance-mg sets another")
        from dataclasses import replace
        return replace(tol, accel_rms_mg=value), why


def verdict_text(accel_ok: bool, rms_mg: float, tol_mg: float, gyro_method, gyro: TriadFit | None,
                 refused: str | None) -> str:
    """One line: what was calibrated, what not and why, and what to record differently."""
    acc = (f"accelerometer calibrated (|a| − g {rms_mg:.3g} mg RMS, tolerance {tol_mg:.3g} mg)" if accel_ok else
           f"accelerometer fitted but above its tolerance (|a| − g {rms_mg:.3g} mg RMS > {tol_mg:.3g} mg)")
    if not gyro_method:
        return acc + "; gyro not asked for"
    if refused:
        kept = "its bias at rest is kept" if gyro is not None else "nothing of it is kept"
        return f"{acc}; gyro not: {refused} ({kept}). To calibrate it, {RECORD_ADVICE}"
    if gyro is None or gyro.method == "bias":
        return acc + "; gyro bias at rest only (scale and misalignment not asked for)"
    held = (gyro.extra or {}).get("held") or []
    return acc + f"; gyro calibrated ({gyro.method}" + (f"; {', '.join(held)} held at nominal)" if held else ")")
