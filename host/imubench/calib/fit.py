"""The one front door of a calibration fit: the data gathered in, one Calibration out.

    fit(Evidence(...), method="multi", gyro="rotation", excess_limit_mps2=...) -> Calibration

Whoever gathers the data (a live session on a device, the station's boards, a recording read
by `--from`, a user's own script) hands the same kinds of arrays to `fit` and gets the same
result type back; what is done with them is decided here, once:

- the accelerometer: the acceptance rules of calib.acceptance (the largest model the rests
  resolve and that is better than none, outlying rests left out, FitRefused when none is);
- the gyro's g-sensitivity from the rests (calib.gsens) when it can be fitted;
- the gyro by the method asked for, from GYRO_METHODS, the one list of gyro methods (the command
  line's choices, the station's, the session's and the recording's are all taken from it);
- the gyro of a live session from its separate captures (the rest, the turntable's segments, the
  known-angle turns' runs, the continuous stream between the poses); the gyro of a recording
  (Evidence.recording) from what its one stream holds, found there (calib.recording_gyro: its
  turns, clipped motions, rest bias, the known-angle turns and the rotation method combined);
- a gyro refused never discards the accelerometer: the Calibration keeps the accelerometer's fit,
  the gyro's bias at rest and the reason (Calibration.gyro_refused).

Nothing here touches a port, a file or a presenter: what the fit has to say is returned in
Calibration.said, in order, for the caller to show (a recording_gyro.Note among them is also
one of the result's notes).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imubench import units as U
from imubench.calib import CalibrationError, TriadFit
from imubench.calib.recording_gyro import Note, RecordingEvidence
from imubench.calib.recording_gyro import clipped_motions as gyro_clipping

__all__ = ["GyroMethod", "GYRO_METHODS", "gyro_method_names", "gyro_method", "AccelMethod", "ACCEL_METHOD_LIST",
           "ACCEL_METHODS", "accel_method_names", "accel_method_words", "accel_model_words",
           "FIT_TEXTS", "fit_text",
           "data_needed", "aligns_frames", "RotationEvidence", "RecordingEvidence", "Evidence", "Calibration", "Note", "fit", "fit_gyro_method",
           "gyro_clipping"]


def __getattr__(name: str):
    """FitRefused (calib.acceptance's, raised by fit()) named here without loading scipy when only
    the methods are wanted (the command line's parser reads GYRO_METHODS at start-up)."""
    if name == "FitRefused":
        from imubench.calib.acceptance import FitRefused
        return FitRefused
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ------------------------------------------------------------------ the methods
@dataclass(frozen=True)
class GyroMethod:
    """One gyro method: its name (as typed), whether a live session can gather its data,
    whether a recording can, one line on what it needs, the fits it gives (the name a TriadFit
    of it carries, TriadFit.method, and how a report names that fit), and what a live session
    captures for it (data_needed: "rest" the gyro at rest, "turntable" the turntable's segments,
    "turns" the known-angle turns, "stream" the continuous stream between the poses)."""
    name: str
    live: bool
    recording: bool
    text: str
    fits: tuple[tuple[str, str], ...] = ()
    needs: tuple[str, ...] = ()


GYRO_METHODS: tuple[GyroMethod, ...] = (
    GyroMethod("turntable", True, False, "scale and misalignment from turns at known rates on a turntable",
               (("turntable", "turntable (known rates about each axis, both ways)"),), ("rest", "turntable")),
    GyroMethod("rotation", True, True, "scale and misalignment from the rotations between the attitudes",
               (("rotation", "rotation method (gyro integrated between attitudes)"),), ("rest", "stream")),
    GyroMethod("turns", True, True, "scale and misalignment from known-angle turns by hand (one full turn "
                                    "about X, Y and Z pointing up)",
               (("turns", "known-angle turns (Ferraris: hand turns of a known angle about the vertical)"),),
               ("rest", "turns")),
    GyroMethod("bias", True, True, "the bias at rest only",
               (("bias", "bias at rest (scale and misalignment not estimated)"),), ("rest",)),
    GyroMethod("auto", False, True, "known-angle turns and/or the rotation method, whatever a recording holds",
               (("turns+rotation", "known-angle turns and the rotation method, combined (inverse-covariance)"),)),
    GyroMethod("none", True, True, "no gyro calibration"),
)


@dataclass(frozen=True)
class AccelMethod:
    """One accelerometer method: its name (as typed, --method), whether a live session can ask
    for it, its name in words, and the model it keeps (TriadFit.method and how a report names
    that fit; "auto" keeps whichever of the others the rests resolve, calib.acceptance.ORDER)."""
    name: str
    live: bool
    words: str
    fits: tuple[tuple[str, str], ...] = ()
    model_words: str = ""               # the model kept, as a line of the fit says it


ACCEL_METHOD_LIST: tuple[AccelMethod, ...] = (
    AccelMethod("multi", True, "multi-position",
                (("multi_position", "multi-position |a| = g (3 biases, 3 scales, 3 non-orthogonality angles)"),),
                "multi-position |a| = g"),
    AccelMethod("six", True, "six-position", (("six_position", "six-position least squares (full M and b)"),),
                "six-position"),
    AccelMethod("auto", False, "multi- or six-position, whatever the rests resolve"),
)
# accelerometer models a caller may ask for: "auto" (a recording: multi when the rests constrain it,
# else six) is what calib.acceptance.ORDER tries
ACCEL_METHODS = tuple(m.name for m in ACCEL_METHOD_LIST)
# how a report names each fit a method gives (TriadFit.method -> words), from the two lists above
FIT_TEXTS: dict[str, str] = {k: v for m in ACCEL_METHOD_LIST + GYRO_METHODS for k, v in m.fits}


def accel_method_names(*, live: bool | None = None) -> tuple[str, ...]:
    """The names of ACCEL_METHOD_LIST, in order; only those a live session can ask for (live=True)."""
    return tuple(m.name for m in ACCEL_METHOD_LIST if live is None or m.live == live)


def accel_method_words(name: str | None) -> str:
    """An accelerometer method in words ("six" -> "six-position"); an unknown name as it is."""
    return next((m.words for m in ACCEL_METHOD_LIST if m.name == name), str(name))


def accel_model_words(fit_method: str) -> str:
    """The accelerometer model of a fit (TriadFit.method) in a few words, as a line says it."""
    return next((m.model_words for m in ACCEL_METHOD_LIST if any(f == fit_method for f, _ in m.fits)), fit_method)


def fit_text(fit_method: str) -> str:
    """How a report names a fit by its TriadFit.method ("six_position", "turns+rotation", ...);
    an unknown one as it is."""
    return FIT_TEXTS.get(fit_method, fit_method)


def gyro_method_names(*, live: bool | None = None, recording: bool | None = None) -> tuple[str, ...]:
    """The names of GYRO_METHODS, in order; only those a live session (live=True) or a
    recording (recording=True) can use when asked."""
    return tuple(m.name for m in GYRO_METHODS
                 if (live is None or m.live == live) and (recording is None or m.recording == recording))


def data_needed(method: str, gyro: str | None) -> frozenset[str]:
    """What a live session captures for a fit by these methods (GyroMethod.needs): the gyro's
    own data, and the continuous stream when a multi-position fit with the turntable is rotated
    into the gyro frame (align_frames: the rotation between the rests is measured on it)."""
    gm = gyro_method(gyro)
    needs = set(gm.needs) if gm is not None else set()
    if aligns_frames(method, gyro):
        needs.add("stream")
    return frozenset(needs)


def aligns_frames(method: str, gyro: str | None) -> bool:
    """Whether fit() rotates the accelerometer's fit into the gyro frame by default: the
    multi-position model (which leaves the triad's rotation free) with the turntable's axes."""
    return method == "multi" and gyro == "turntable"


def gyro_method(name: str | None) -> GyroMethod | None:
    """The GyroMethod named (None and "none": None); ValueError for an unknown name."""
    if name is None or name == "none":
        return None
    for m in GYRO_METHODS:
        if m.name == name:
            return m
    raise ValueError(f"unknown gyro method {name!r}: one of {', '.join(gyro_method_names())}")


# ------------------------------------------------------------------ what goes in
@dataclass
class RotationEvidence:
    """One continuous stream for the rotation method: its samples and where the rests are in
    it. problem: why the stream cannot be used (gaps, several streams, a file that cannot be
    read), raised as the gyro's refusal when the rotation method is asked for."""
    accel_mps2: np.ndarray | None = None          # (n, 3), nominally scaled
    gyro_rad_s: np.ndarray | None = None          # (n, 3)
    intervals: list = field(default_factory=list)   # (start, stop) sample of each rest in the stream
    rest_means_mps2: np.ndarray | None = None     # (m, 3): each rest's mean, in the order of intervals
    problem: str | None = None


@dataclass
class Evidence:
    """What a fit is given. The rests (still attitudes): their mean specific force, its sigma,
    the covariance a rest's own motion adds (calib.rests; None: none), a text per rest saying
    why its sigma was inflated, and the gyro's mean over each. The gyro's data, per method:
    the samples of a separate rest (the bias; None: the longest rest of a recording gives it
    through gyro_bias), the turntable's segments (calib.gyro.turntable), the known-angle turns'
    runs as (accel, gyro) arrays with the rest noise that finds their rests, and a continuous
    stream for the rotation method. A recording gives its one stream instead (recording): the
    gyro's rests, turns and motions are then found in it."""
    means_mps2: np.ndarray
    sigmas_mps2: np.ndarray
    rate_hz: float
    covs: np.ndarray | None = None
    motions_text: list | None = None
    gyro_means_rad_s: np.ndarray | None = None
    rest_gyro_rad_s: np.ndarray | None = None
    turntable_segments: list | None = None
    turn_runs: list | None = None
    turn_noise_mps2: np.ndarray | None = None
    turn_min_still_s: float = 1.0
    rotation: RotationEvidence | None = None
    recording: RecordingEvidence | None = None


# ------------------------------------------------------------------ what comes out
@dataclass
class Calibration:
    """The result of a fit, whoever asked: the accelerometer's fit and how it was chosen, the
    gyro's (or its bias at rest when it was refused, or None when not asked for), the
    g-sensitivity fit and its report, the reason a gyro was refused, and the lines the fit has
    to say, in order."""
    accel: TriadFit
    gyro: TriadFit | None = None
    accel_choice: object | None = None        # calib.acceptance.AccelChoice
    gsens: object | None = None               # calib.gsens.GSensFit applied to the gyro
    gsens_report: dict | None = None
    gyro_refused: str | None = None
    gyro_bias: TriadFit | None = None         # the gyro's bias at rest: what is kept when the gyro is refused
    frame_note: str | None = None             # why the accelerometer stayed in its own frame
    said: list = field(default_factory=list)
    # what the gyro of a recording found in it (Evidence.recording; calib.recording_gyro)
    gyro_scale: float | None = None           # rad/s per unit of the recording's gyro (found by turns if it had none)
    turns: list = field(default_factory=list)  # calib.turns.Turn found between the rests
    gyro_parts: dict = field(default_factory=dict)   # {"fits": {"turns"|"rotation": TriadFit}, "refused": {...: why}}
    gyro_clipping: list = field(default_factory=list)  # the motions where the gyro clipped, as the result keeps them
    detected: tuple | None = None             # (line, °/s): the gyro's full scale found at its clip level

    @property
    def notes(self) -> list[str]:
        """The lines of said that are notes (recording_gyro.Note), in order."""
        return [str(x) for x in self.said if isinstance(x, Note)]

    @property
    def method(self) -> str:
        """"six" or "multi": the accelerometer method whose model was kept."""
        return next(m.name for m in ACCEL_METHOD_LIST if any(f == self.accel.method for f, _ in m.fits))


# ------------------------------------------------------------------ the strategy
def fit(ev: Evidence, *, method: str, gyro: str | None, excess_limit_mps2: float,
        align_frames: bool | None = None, gsens: bool = True, g: float = U.G0_MPS2) -> Calibration:
    """The fit of one board's data (see the module). method: "multi", "six" or "auto" (the
    accelerometer models tried, calib.acceptance.ORDER); gyro: a name of GYRO_METHODS or None;
    excess_limit_mps2: the scatter beyond the noise a linear calibration of this class of sensor
    leaves (the pass tolerance). align_frames: with the turntable, rotate the accelerometer's
    fit into the gyro frame (calib.frames); None: when aligns_frames(method, gyro). gsens: fit the g-sensitivity from the rests' gyro
    means (a recording's gyro fits its own from its rests, calib.recording_gyro). Raises
    FitRefused (a CalibrationError) when no accelerometer model is kept."""
    from imubench.calib.acceptance import fit_accel
    from imubench.calib.gsens import with_zero_force_bias
    if method not in ACCEL_METHODS:
        raise ValueError(f"method must be one of {', '.join(ACCEL_METHODS)}, not {method!r}")
    gm = gyro_method(gyro)
    if align_frames is None:
        align_frames = aligns_frames(method, gyro)
    means = np.asarray(ev.means_mps2, dtype=np.float64)
    sigmas = np.asarray(ev.sigmas_mps2, dtype=np.float64)
    choice = fit_accel(means, sigmas, ev.covs, method, g, excess_limit=excess_limit_mps2,
                       motions_text=ev.motions_text)
    out = Calibration(accel=choice.fit, accel_choice=choice)
    if gm is None:
        return out
    accel = choice.fit
    if ev.rest_gyro_rad_s is not None:
        from imubench.calib.gyro import gyro_bias
        out.gyro_bias = gyro_bias(ev.rest_gyro_rad_s, ev.rate_hz)
    if gsens and ev.gyro_means_rad_s is not None and ev.recording is None:
        out.gsens, out.gsens_report = _gsens(accel, means, np.asarray(ev.gyro_means_rad_s, float), g, out.said)
    try:
        if ev.recording is not None:     # the rests the accelerometer's fit used: the gyro's too
            from imubench.calib.recording_gyro import recording_gyro
            used = [k for k, r in enumerate(choice.rests) if r.use != "left out"]
            gfit = recording_gyro(gm.name, accel, ev.recording, used, means, out)
        else:
            gfit = fit_gyro_method(gm.name, accel, ev, out.gyro_bias, out.gsens, g)
    except CalibrationError as e:
        # a refused gyro never discards the accelerometer: kept with the gyro's bias at rest
        out.gyro_refused = str(e)
        gfit = out.gyro_bias
        out.said.append(f"gyro not calibrated: {out.gyro_refused}")
    if gfit is not None and out.gsens is not None:      # b + G·f: the bias at zero specific force
        gfit = with_zero_force_bias(gfit, out.gsens)
    out.gyro = gfit
    if align_frames and gm.name == "turntable" and gfit is not None and out.gyro_bias is not None:
        out.accel, out.frame_note = _align_frames(accel, gfit, out.gyro_bias, ev, g, out.said)
    return out


def fit_gyro_method(name: str, accel: TriadFit, ev: Evidence, bias: TriadFit | None, gsens=None,
                    g: float = U.G0_MPS2) -> TriadFit:
    """The gyro fit of one method on the evidence gathered for it (bias: from a separate rest)."""
    if name in ("bias", "turntable", "rotation", "turns") and bias is None:
        raise CalibrationError(f"--gyro {name} needs the gyro at rest (the bias): none was recorded")
    if name == "bias":
        return bias
    if name == "turntable":
        if not ev.turntable_segments:
            raise CalibrationError("the turntable method needs a turntable's segments: none were captured")
        return turntable_fit(accel, ev.turntable_segments, bias, gsens, g)
    if name == "rotation":
        return rotation_fit(accel, ev.rotation, bias, ev.rate_hz, gsens, g)
    if name == "turns":
        return known_turns_fit(accel, ev.turn_runs or [], bias, ev.rate_hz, ev.turn_noise_mps2,
                               ev.turn_min_still_s)
    raise CalibrationError(f"--gyro {name}: this method needs a recording's turns and rotations (--from FILE)")


def _gsens(accel: TriadFit, means, gyro_means, g: float, said: list):
    """The gyro's g-sensitivity from the rests' gyro means against their calibrated specific
    force (calib.gsens), or None when the rests cannot separate it. The ADXRS450 has one
    (0.03 °/s/g typical), so it is part of the model whenever it can be fitted: b is then the
    bias at zero specific force and G goes to the device; p_zero says whether these rests alone
    resolve it. Returns (fit or None, the report for the record)."""
    from imubench.calib.gsens import DPS, fit_gsens
    f = accel.correct(means) / g
    try:
        gs = fit_gsens(gyro_means, np.ones_like(gyro_means), f, sigma_from_scatter=True)
    except CalibrationError as e:
        return None, {"applied": False, "why_not": str(e)}
    report = {"applied": True, "resolved": bool(gs.significant), "g_dps_per_g": (gs.g * DPS).tolist(),
              "sigma_dps_per_g": (gs.sigma_g * DPS).tolist(), "p_zero": gs.p_zero, "b_rad_s": gs.b.tolist()}
    said.append(gs.summary())
    return gs, report


def turntable_fit(accel: TriadFit, segments: list, bias: TriadFit, gsens=None, g: float = U.G0_MPS2) -> TriadFit:
    """Gyro M from the turntable segments with b fixed to the rest's bias; with a
    g-sensitivity each segment's reading is taken less G·f (f its calibrated specific force)
    and b is the bias at zero specific force."""
    from imubench.calib import gyro as CG
    from imubench.calib.gsens import zero_force_bias
    if gsens is None:
        return CG.turntable([s[:3] for s in segments], bias=bias)
    segs = [(r, ax, w, None, accel.correct(np.asarray(a_mps2)[None])[0] / g)
            for r, ax, w, _, a_mps2 in segments]
    return CG.turntable(segs, bias=zero_force_bias(gsens, bias), gsens=gsens)


def rotation_fit(accel: TriadFit, rot: RotationEvidence | None, bias: TriadFit, rate_hz: float, gsens=None,
                 g: float = U.G0_MPS2) -> TriadFit:
    """Gyro M from the motions between consecutive rests of one continuous stream; with a
    g-sensitivity the gyro is integrated less G·f(t) (f the calibrated specific force)."""
    from imubench.calib import gyro as CG
    from imubench.calib.gsens import zero_force_bias
    if rot is None:
        raise CalibrationError("the rotation method needs the continuous stream between the rests: none was given")
    if rot.problem:
        raise CalibrationError(rot.problem)
    gyr = np.asarray(rot.gyro_rad_s, dtype=np.float64)
    if gsens is not None:
        gyr = gyr - (accel.correct(rot.accel_mps2) / g) @ gsens.g.T
        bias = zero_force_bias(gsens, bias)
    x = accel.correct(np.asarray(rot.rest_means_mps2, dtype=np.float64))
    dirs = x / np.linalg.norm(x, axis=1)[:, None]
    return CG.rotation_method(gyr, rate_hz, list(rot.intervals), dirs, bias)


def known_turns_fit(accel: TriadFit, runs: list, bias: TriadFit, rate_hz: float, noise_mps2,
                    min_still_s: float) -> TriadFit:
    """Gyro M from known-angle turns, one run (accel, gyro) per board axis: the rests around
    each found by the data (calib.static, calib.turns.split_by_rotation), its turn between them
    (calib.turns)."""
    from imubench.calib.static import detect_static
    from imubench.calib.turns import TURN_DEG, detect_turns, known_angle_turns, split_by_rotation
    turns, missing = [], []
    for k, (acc, gyr) in enumerate(runs):
        iv = detect_static(acc, rate_hz, noise_sigma=None if noise_mps2 is None else np.asarray(noise_mps2),
                           min_duration_s=min_still_s)
        iv = split_by_rotation(acc, gyr, rate_hz, iv, min_duration_s=min_still_s)
        if len(iv) < 2:
            missing.append(f"turn {'XYZ'[k]}: {len(iv)} rest(s) found around it, 2 needed")
            continue
        up = accel.correct(np.array([i.mean for i in iv]))
        found = detect_turns(gyr, rate_hz, iv, up, turn_deg=TURN_DEG)
        turns += found
        if not any(t.usable for t in found):
            missing.append(f"turn {'XYZ'[k]}: no whole turn between two rests of the same attitude")
    return known_angle_turns(turns, bias, noise_density_rad_s_rthz=bias.extra["noise_density_rad_s_rthz"],
                             refused=missing)


def _align_frames(accel: TriadFit, gyro: TriadFit, bias: TriadFit, ev: Evidence, g: float,
                  said: list) -> tuple[TriadFit, str | None]:
    """Multi-position + turntable: rotate the accelerometer's fit into the gyro (board) frame,
    the rotation measured by the gyros between the rests (calib.frames). Returns the fit and,
    when that is impossible, the fit unchanged and the reason."""
    from imubench.calib.frames import align_accel_to_gyro
    try:
        in_accel_frame = rotation_fit(accel, ev.rotation, bias, ev.rate_hz, None, g)
        aligned = align_accel_to_gyro(accel, gyro, in_accel_frame)
    except CalibrationError as e:
        return accel, (f"accelerometer left in its own frame (not aligned to the gyros): {e}; "
                       "strapdown use of both will see that rotation")
    phi = np.degrees(aligned.extra["alignment_rad"])
    said.append(f"accelerometer frame aligned to the gyro turntable axes: rotation "
                f"{np.round(phi, 3).tolist()} ° (about board x, y, z)")
    return aligned, None
