"""The gyro of one continuous recording, found in its data: calib.fit's strategy when the
evidence is a recording (Evidence.recording) rather than a session's separate captures.

A recording has no separate rest and no turntable: the turns are found between its rests
(calib.turns), motions where the gyro clipped are left out (calib.clipping), the bias is the
rests' weighted mean or b of b + G·f when the rests resolve a g-sensitivity (calib.gsens), and
the known-angle turns and the rotation method are combined when both can be used.

Called by calib.fit.fit only (the one front door); nothing here reads a file or prints: what
it has to say goes to Calibration.said (a Note is a line the caller also keeps in the result's
notes), what it found to the Calibration's recording fields.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imubench import units as U
from imubench.calib import CalibrationError, TriadFit, face_of

# a plateau found in the data is a gyro's clip level only at or beyond this rate: no MEMS gyro's range is below
# ±125 °/s, and a slow hand's peak, rounded in a text file, can repeat a value too (calib.clipping)
CLIP_MIN_DPS = 100.0


class Note(str):
    """A line of Calibration.said that is also one of the result's notes (shown as "note: ...")."""


@dataclass
class RecordingEvidence:
    """One recording's continuous stream, as the gyro of calib.fit takes it: the gyro in the
    recording's own unit with its nominal scale (rad/s per unit; None: counts without one, then
    the turns scale it), the accelerometer in m/s², the rests (calib.static.StaticInterval,
    parallel to Evidence.means_mps2), where the stream is not continuous, its named parts (files
    cut around each turn: (name, start, stop)) and what was declared of the turns and the range."""
    gyro: np.ndarray                        # (n, 3), in the recording's unit
    gyro_scale: float | None                # rad/s per unit of `gyro`
    accel_mps2: np.ndarray                  # (n, 3)
    rests: list                             # StaticInterval per rest of Evidence.means_mps2
    rate_hz: float
    breaks: tuple = ()                      # sample indices where the stream is not continuous
    parts: list | None = None               # (name, start, stop) of a file cut into parts
    turn_deg: float = 360.0                 # the known angle of one turn
    angle_sigma_deg: float = 1.0            # hand placement after a turn
    axis_sigma_deg: float = 0.5             # turn axis off the measured vertical
    gyro_range_dps: float | None = None     # the declared range: samples at it are clipped
    range_known: bool = False               # the range is declared (no clip level to report as found)


def check_turn_scale(measured_rad: list[float], turn_rad: float) -> str | None:
    """A warning (never a refusal: the angle of a motion is not known, and returning to an
    attitude by a small motion is normal) when the motions about the vertical between rests of
    the same attitude integrate to a constant multiple of whole turns, as °/s read as rad/s
    (57.3×) or the reverse would; None otherwise."""
    if len(measured_rad) < 2:
        return None
    r = np.abs(np.asarray(measured_rad)) / turn_rad
    med = float(np.median(r))
    for factor, fix in ((180.0 / math.pi, "°/s read as rad/s: declare --gyro-unit dps"),
                        (math.pi / 180.0, "rad/s read as °/s: declare --gyro-unit rad_s")):
        near = np.abs(r / factor - np.round(r / factor)) < 0.1
        if np.all(near & (np.round(r / factor) >= 1)):
            return (f"the motions about the vertical between rests of the same attitude integrate to "
                    f"{', '.join(f'{math.degrees(abs(m)):.0f}°' for m in measured_rad)} (median {med:.3g} turns of "
                    f"{math.degrees(turn_rad):g}°): all {len(r)} are whole turns only if the gyro unit is off by "
                    f"{factor:.4g}× ({fix}); the declared unit is used, as the turns' angles are not known")
    return None


# ------------------------------------------------------------------ clipping
@dataclass
class GyroClipping:
    """The motions between rests where the gyro held its full scale: motion j -> what clipped,
    the rows the result keeps, the lines to say (Notes among them) and the full scale found in
    the data when none was declared ((line, °/s) or None)."""
    motions: dict
    rows: list
    said: list
    detected: tuple | None = None


def clipped_motions(rec: RecordingEvidence, rests: list) -> GyroClipping:
    """The motions between rests where the gyro held its full scale (calib.clipping: a plateau
    at the extreme of the values, or at the declared range), each named in a note; the gyro
    fits leave them out."""
    from imubench.calib.clipping import find_clipping, runs_in
    fs, f_nom = rec.rate_hz, rec.gyro_scale
    said: list = []
    declared = min_level = None
    if f_nom is not None:
        min_level = math.radians(CLIP_MIN_DPS) / f_nom
        if rec.gyro_range_dps is not None:
            declared = math.radians(rec.gyro_range_dps) / f_nom
    elif rec.gyro_range_dps is not None:
        said.append(Note("--gyro-range is in °/s and the gyro is in counts without a nominal scale: clipping is "
                         "found from the data alone"))
    runs = find_clipping(rec.gyro, declared=declared, min_level=min_level or 0.0)

    def level(x: float) -> str:
        return f"{math.degrees(x * f_nom):+.1f} °/s" if f_nom is not None else f"{x:+.6g} counts"
    found = [r for r in runs if r.source != "declared"]
    detected = None
    if found and f_nom is not None and rec.gyro_range_dps is None and not rec.range_known:
        fs_dps = max(abs(math.degrees(r.level * f_nom)) for r in found)     # the sensor's full scale, seen
        line = (f"gyro full scale ±{fs_dps:.4g} °/s from the values' clip level ({sum(r.n for r in found)} "
                f"samples held there in {len(found)} run(s)) (--gyro-range {fs_dps:.4g})")
        detected = (line, float(f"{fs_dps:.4g}"))
        said.append(f"  detected: {line}")
    out: dict[int, str] = {}
    rows: list = []
    for j in range(len(rests) - 1):
        s0, s1 = rests[j].stop - 1, rests[j + 1].start + 1
        inside = runs_in(runs, s0, s1)
        if not inside:
            continue
        parts = []
        for ax in sorted({r.axis for r in inside}):
            rs = [r for r in inside if r.axis == ax]
            parts.append(f"{rs[0].axis_name} at {level(rs[0].level)} for {sum(r.n for r in rs)} samples from "
                         f"{rs[0].start / fs:.2f} s")
        src = "at the declared --gyro-range" if all(r.source == "declared" for r in inside) else \
            "full scale found in the data"
        out[j] = "; ".join(parts) + f" ({src})"
        rows.append({"motion": j, "t_start_s": s0 / fs, "t_stop_s": (s1 - 1) / fs,
                     "axes": [{"axis": r.axis_name, "level": level(r.level), "start": r.start,
                               "samples": r.n, "source": r.source} for r in inside]})
        said.append(Note(f"motion {j} ({s0 / fs:.1f}–{(s1 - 1) / fs:.1f} s) left out of the gyro fit: the gyro "
                         f"clipped, {out[j]}"))
    if out:
        said.append(f"gyro clipped in {len(out)} of {len(rests) - 1} motions: those are left out of the gyro fit")
    return GyroClipping(out, rows, said, detected)


# ------------------------------------------------------------------ the strategy
class _RecordingGyro:
    """One fit of a recording's gyro (state: the evidence, the accelerometer's fit, the
    Calibration the findings go to)."""

    def __init__(self, rec: RecordingEvidence, accel: TriadFit, rests: list, means, out):
        self.rec, self.accel, self.rests, self.out = rec, accel, rests, out
        self.means = np.asarray(means, dtype=np.float64)

    def say(self, line: str) -> None:
        self.out.said.append(line)

    def note(self, line: str) -> None:
        self.out.said.append(Note(line))

    def run(self, method: str) -> TriadFit:
        from imubench.calib import gyro as CG
        from imubench.calib.turns import detect_turns
        rec, accel, keep, out = self.rec, self.accel, self.rests, self.out
        fs, brk = rec.rate_hz, list(rec.breaks)
        acc = rec.accel_mps2
        fg = rec.gyro_scale
        up = accel.correct(self.means)
        up = up / np.linalg.norm(up, axis=1)[:, None]
        clip = clipped_motions(rec, keep)
        out.said.extend(clip.said)
        out.gyro_clipping, out.detected = clip.rows, clip.detected
        clipped = clip.motions
        turn_rad = math.radians(rec.turn_deg)
        longest = max(range(len(keep)), key=lambda k: keep[k].n)
        if fg is None:
            cand = detect_turns(rec.gyro, fs, keep, up, turn_deg=rec.turn_deg, breaks=brk, scale_known=False)
            good = [t for t in cand if t.usable] or [t for t in self._part_turns(rec.gyro, up) if t.usable]
            if not good:
                raise CalibrationError("the gyro is in counts without a nominal scale and the recording has no turn "
                                       "about the vertical between two rests to scale it by: give --gyro-scale "
                                       "COUNTS_PER_DPS (the datasheet's) or record known-angle turns")
            fg = turn_rad / float(np.median([abs(t.measured_rad) for t in good]))
            self.note(f"gyro in counts without a nominal scale: scaled provisionally by the turns "
                      f"({1 / math.degrees(fg):.5g} counts per °/s); M is reported in counts per °/s")
        else:
            cand = detect_turns(rec.gyro * fg, fs, keep, up, turn_deg=rec.turn_deg, breaks=brk, scale_known=False)
            big = [t.measured_rad for t in cand if t.usable]
            big = [m for m in big if abs(m) >= 0.25 * max(np.abs(big))] if big else []
            warn = check_turn_scale(big, turn_rad)
            if warn:
                self.note(warn)
        out.gyro_scale = fg
        gyr = rec.gyro * fg
        bias = CG.gyro_bias(gyr[keep[longest].start:keep[longest].stop], fs)
        out.gyro_bias = bias
        self._acc_g = accel.correct(acc) / U.G0_MPS2           # calibrated specific force per sample, g
        self._f_rest_g = accel.correct(self.means) / U.G0_MPS2
        self.say(f"gyro bias from the longest still interval ({keep[longest].t_start_s:.1f} s, "
                 f"{keep[longest].duration_s:.1f} s)")
        turns = detect_turns(gyr, fs, keep, up, turn_deg=rec.turn_deg, breaks=brk)
        for t in turns:
            if t.usable and t.rest_before in clipped:
                t.usable, t.reason = False, f"the gyro clipped in it, {clipped[t.rest_before]}: turn slower"
        if not any(t.usable for t in turns) and rec.parts:
            turns = self._part_turns(gyr, up)
            if turns:
                self.note(f"no turn with a rest on both sides was found; the file is cut into named parts: the "
                          f"{len(turns)} parts named *_rot are taken as the turns (integrated from cut to cut, "
                          "bias from the still interval of the same attitude)")
        out.turns = turns
        for t in turns:
            if not t.usable:
                self.note(f"{t.label} at {t.start / fs:.1f} s not used: {t.reason}")
        if method == "turntable":
            raise CalibrationError("the turntable method needs a turntable's known rates; from a recording use "
                                   "--gyro turns (known-angle turns) or --gyro rotation")
        if method in ("turns", "rotation", "auto"):
            return self._fit(method, gyr, up, bias, brk, clipped)
        return bias

    def _rotation_bias(self, gyr, bias: TriadFit) -> tuple[np.ndarray, TriadFit]:
        """The gyro series and bias the gyro fits use: b + G·f(t) when the rests resolve a
        g-sensitivity G (calib.gsens, G ≠ 0 at p < 0.01; the series is corrected by G·f, f the calibrated
        specific force in g), else the rests' weighted mean bias (bench/real_data.py: on real
        hand-held recordings one rest's bias is the weak point, the mean of all rests does better)."""
        from imubench.calib import gyro as CG
        from imubench.calib.gsens import DPS, fit_gsens
        from imubench.calib.gyro import _cov12
        keep, fs = self.rests, self.rec.rate_hz
        means = np.array([gyr[i.start:i.stop].mean(axis=0) for i in keep])
        sig = np.array([CG._mean_uncertainty(gyr[i.start:i.stop], min_cluster=max(1, int(round(0.02 * fs))))["sigma"]
                        for i in keep])
        rep = self.out.gsens_report = {"applied": False}
        try:
            gs = fit_gsens(means, sig, self._f_rest_g)
            rep.update(g_dps_per_g=(gs.g * DPS).tolist(), sigma_dps_per_g=(gs.sigma_g * DPS).tolist(),
                       beyond_2sigma=gs.resolved.tolist(), p_zero=gs.p_zero, b_rad_s=gs.b.tolist(),
                       reduced_chi2=gs.extra["reduced_chi2"])
            if gs.significant:
                rep["applied"] = True
                self.say(gs.summary())
                self.note("the rotation method integrates the gyro less the bias b + G·f(t) its g-sensitivity "
                          "predicts (f the calibrated specific force); b is the bias at zero specific force")
                return gyr - self._acc_g @ gs.g.T, TriadFit(
                    method="bias", m=np.eye(3), b=gs.b.copy(), cov=_cov12(b_cov=gs.cov[9:, 9:]),
                    estimated=np.array([False] * 9 + [True] * 3), extra=dict(bias.extra, source="g-sensitivity fit"))
            rep["why_not"] = f"G does not differ from zero (p = {gs.p_zero:.2g} ≥ 0.01)"
        except CalibrationError as e:
            rep["why_not"] = str(e)
        w = 1.0 / sig**2
        b = np.sum(w * means, axis=0) / np.sum(w, axis=0)
        red = np.sum(w * (means - b) ** 2, axis=0) / max(len(keep) - 1, 1)
        sb = np.sqrt(1.0 / np.sum(w, axis=0) * np.maximum(red, 1.0))
        self.note(f"the rotation method's bias: the weighted mean of the {len(keep)} rests' gyro means (g-sensitivity "
                  f"not applied: {rep['why_not']})")
        return gyr, TriadFit(method="bias", m=np.eye(3), b=b, cov=_cov12(b_cov=np.diag(sb**2)),
                             estimated=np.array([False] * 9 + [True] * 3),
                             extra=dict(bias.extra, source="weighted mean of the rests"))

    def _part_turns(self, gyr, up) -> list:
        """Turns from the file's named parts (*_rot), for files cut tightly around each turn."""
        from imubench.calib.turns import turn_in_window
        rec, keep = self.rec, self.rests
        out = []
        for name, s0, s1 in rec.parts or []:
            if not name.endswith("_rot") or s1 - s0 < 3:
                continue
            d = self.accel.correct(rec.accel_mps2[s0:s1].mean(axis=0)[None, :])[0]
            d /= np.linalg.norm(d)
            k = int(np.argmax(up @ d))               # the still interval of the same attitude
            rest = gyr[keep[k].start:keep[k].stop]
            b = rest.mean(axis=0)
            bs = rest.std(axis=0, ddof=1) / math.sqrt(len(rest))
            out.append(turn_in_window(gyr, rec.rate_hz, s0, s1, d, b, bs, turn_deg=rec.turn_deg,
                                      label=f"turn about {face_of(d)} (part {name})"))
        return out

    def _fit(self, method: str, gyr, up, bias, brk, clipped: dict) -> TriadFit:
        from imubench.calib.turns import combine_fits, known_angle_turns
        rec, keep, fs = self.rec, self.rests, self.rec.rate_hz
        fits: dict[str, TriadFit] = {}
        errs: dict[str, CalibrationError] = {}
        u_rot, b_rot = self._rotation_bias(gyr, bias)
        bias = b_rot                    # the bias every gyro fit reports: the rests' mean or b of b + G·f
        try:
            fits["turns"] = known_angle_turns(self.out.turns, bias, noise_density_rad_s_rthz=bias.extra[
                "noise_density_rad_s_rthz"], angle_sigma_deg=rec.angle_sigma_deg, axis_sigma_deg=rec.axis_sigma_deg)
        except CalibrationError as e:
            errs["turns"] = e
        bad = sorted(clipped)
        for j in range(len(keep) - 1):
            inside = [b for b in brk if keep[j].stop - 1 < b <= keep[j + 1].start]
            if inside and j not in clipped:
                bad.append(j)
                self.note(f"motion {j} ({keep[j].stop / fs:.1f}–{keep[j + 1].start / fs:.1f} s) not used by the "
                          f"rotation method: the recording is not continuous inside it (break at sample {inside[0]})")
        try:
            fits["rotation"] = self._rotation_nested(u_rot, up, b_rot, bad)
        except CalibrationError as e:
            if clipped:
                e = type(e)(f"{e} ({len(clipped)} of {len(keep) - 1} motions left out: the gyro clipped in them; "
                            "turn slower than its range)")
            errs["rotation"] = e
        why = {k: str(e) for k, e in errs.items()}
        self.out.gyro_parts = {"fits": dict(fits), "refused": why}
        if method == "auto":
            if not fits:
                raise CalibrationError("neither known-angle turns nor the rotation method could be used: "
                                       + "; ".join(f"{k}: {v}" for k, v in why.items()))
            main = "rotation" if "rotation" in fits else "turns"
            self.say(f"gyro: {' and '.join(sorted(fits))} (--gyro auto: what the recording supports)")
        else:
            main = method
        other = "rotation" if main == "turns" else "turns"
        if main not in fits:
            raise errs[main]
        if other in fits:
            comb = combine_fits(fits["turns"], fits["rotation"])
            self.say(f"gyro: known-angle turns and the rotation method combined "
                     f"({'consistent' if comb.consistent else 'INCONSISTENT'}: χ² = {comb.chi2:.3g} for 9 dof)")
            for n in comb.notes:
                self.note(n)
            return comb.fit
        self.note(f"gyro: the {other} method is not used: {why[other]}")
        return fits[main]

    def _rotation_nested(self, u_rot, up, b_rot, bad) -> TriadFit:
        """The rotation method with every entry of M; where the motions leave entries unresolved
        (σ unbounded or above the limit), again with those held at nominal, while some are
        left to fit: the largest model the motions carry (calib.gyro.rotation_method's hold)."""
        from imubench.calib import gyro as CG
        iv = [(i.start, i.stop) for i in self.rests]
        hold: list[int] = []
        first = None
        while True:
            try:
                fit = CG.rotation_method(u_rot, self.rec.rate_hz, iv, up, b_rot, max_rate_rad_s=None,
                                         exclude_motions=bad, hold=hold)
            except CalibrationError as e:
                entries = getattr(e, "entries", None)
                first = first or e
                if not entries or len(set(hold) | set(entries)) >= 9:
                    raise first from None
                hold = sorted(set(hold) | set(entries))
                continue
            if hold:
                self.note(f"gyro: the rotation method holds {', '.join(fit.extra['held'])} at nominal (their σ "
                          f"would be above {fit.extra['max_sigma']:g}: the motions do not resolve them; fitted with "
                          f"every entry: {first}); the others are fitted, the held ones' possible size carried into "
                          "their σ")
            return fit


def recording_gyro(method: str, accel: TriadFit, rec: RecordingEvidence, used: list[int], means, out) -> TriadFit:
    """The gyro fit of a recording by `method` ("bias", "turns", "rotation", "auto"; "turntable"
    is refused), on the rests the accelerometer's fit used (indices `used` into rec.rests and
    means). Fills out (a calib.fit.Calibration): gyro_bias, gyro_scale, turns, gyro_parts,
    gsens_report, gyro_clipping, detected, said. Raises CalibrationError when it cannot."""
    rests = [rec.rests[k] for k in used]
    return _RecordingGyro(rec, accel, rests, np.asarray(means)[used], out).run(method)
