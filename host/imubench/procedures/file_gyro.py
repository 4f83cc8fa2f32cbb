"""The gyro of a recording (`imubench calibrate --from`): what the data hold of it, found there.

A recording has no separate rest and no turntable: the turns are found between its rests
(calib.turns), motions where the gyro clipped are left out (calib.clipping), the bias is the
rests' weighted mean or b of b + G·f when the rests resolve a g-sensitivity (calib.gsens), and
the known-angle turns and the rotation method are combined when both can be used. FileGyro is a
part of procedures.from_file.FileAnalysis (its state: the recording, the notes, the clipping);
calib.fit.fit calls its _gyro as the recording's gyro_fitter.
"""
from __future__ import annotations

import math

import numpy as np

from imubench import units as U
from imubench.calib import CalibrationError, TriadFit
from imubench.procedures.recording_checks import check_turn_scale, face_of
from imubench.results.record import fit_dict

# a plateau found in the data is a gyro's clip level only at or beyond this rate: no MEMS gyro's range is below
# ±125 °/s, and a slow hand's peak, rounded in a text file, can repeat a value too (calib.clipping)
CLIP_MIN_DPS = 100.0


class FileGyro:
    """The gyro half of a recording's analysis (a mixin of FileAnalysis)."""

    def _gyro(self, rec, cfg, fs, keep, acc, means, accel) -> TriadFit:
        from imubench.calib import gyro as CG
        from imubench.calib.turns import detect_turns
        brk = [b for b, _ in rec.breaks]
        fg = rec.gyro_factor()
        up = accel.correct(means)
        up = up / np.linalg.norm(up, axis=1)[:, None]
        clipped = self._clipped_motions(keep)
        turn_rad = math.radians(cfg.turn_deg)
        longest = max(range(len(keep)), key=lambda k: keep[k].n)
        if fg is None:
            cand = detect_turns(rec.gyro, fs, keep, up, turn_deg=cfg.turn_deg, breaks=brk, scale_known=False)
            good = [t for t in cand if t.usable] or [t for t in self._part_turns(rec.gyro, acc, keep, up, accel)
                                                     if t.usable]
            if not good:
                raise CalibrationError("the gyro is in counts without a nominal scale and the recording has no turn "
                                       "about the vertical between two rests to scale it by: give --gyro-scale "
                                       "COUNTS_PER_DPS (the datasheet's) or record known-angle turns")
            fg = turn_rad / float(np.median([abs(t.measured_rad) for t in good]))
            self._note(f"gyro in counts without a nominal scale: scaled provisionally by the turns "
                       f"({1 / math.degrees(fg):.5g} counts per °/s); M is reported in counts per °/s")
        else:
            cand = detect_turns(rec.gyro * fg, fs, keep, up, turn_deg=cfg.turn_deg, breaks=brk,
                                scale_known=False)
            big = [t.measured_rad for t in cand if t.usable]
            big = [m for m in big if abs(m) >= 0.25 * max(np.abs(big))] if big else []
            warn = check_turn_scale(big, turn_rad, rec)
            if warn:
                self._note(warn)
        self.fg = fg
        gyr = rec.gyro * fg
        self.rest_index = longest
        bias = CG.gyro_bias(gyr[keep[longest].start:keep[longest].stop], fs) if cfg.gyro else None
        self._bias = bias
        self._acc_g = accel.correct(acc) / U.G0_MPS2           # calibrated specific force per sample, g
        self._f_rest_g = accel.correct(means) / U.G0_MPS2
        if bias is not None:
            self.say(f"gyro bias from the longest still interval ({keep[longest].t_start_s:.1f} s, "
                     f"{keep[longest].duration_s:.1f} s)")
        self.turns = detect_turns(gyr, fs, keep, up, turn_deg=cfg.turn_deg, breaks=brk)
        for t in self.turns:
            if t.usable and t.rest_before in clipped:
                t.usable, t.reason = False, f"the gyro clipped in it, {clipped[t.rest_before]}: turn slower"
        if not any(t.usable for t in self.turns) and rec.parts:
            self.turns = self._part_turns(gyr, acc, keep, up, accel)
            if self.turns:
                self._note(f"no turn with a rest on both sides was found; the file is cut into named parts: the "
                           f"{len(self.turns)} parts named *_rot are taken as the turns (integrated from cut to cut, "
                           "bias from the still interval of the same attitude)")
        for t in self.turns:
            if not t.usable:
                self._note(f"{t.label} at {t.start / fs:.1f} s not used: {t.reason}")
        if cfg.gyro == "turntable":
            raise CalibrationError("the turntable method needs a turntable's known rates; from a recording use "
                                   "--gyro turns (known-angle turns) or --gyro rotation")
        if cfg.gyro in ("turns", "rotation", "auto"):
            return self._gyro_fit(gyr, fs, keep, up, bias, brk, clipped)
        return bias

    def _clipped_motions(self, keep) -> dict[int, str]:
        """The motions between rests where the gyro held its full scale (calib.clipping: a plateau
        at the extreme of the values, or at the declared --gyro-range): motion j -> what clipped,
        each named in a note; the gyro fits leave them out."""
        from imubench.calib.clipping import find_clipping, runs_in
        rec, fs = self.rec, self.rec.fs_hz
        f_nom = rec.gyro_factor()                 # rad/s per file unit (None: counts without a scale)
        declared = min_level = None
        if f_nom is not None:
            min_level = math.radians(CLIP_MIN_DPS) / f_nom
            if self.cfg.gyro_range_dps is not None:
                declared = math.radians(self.cfg.gyro_range_dps) / f_nom
        elif self.cfg.gyro_range_dps is not None:
            self._note("--gyro-range is in °/s and the gyro is in counts without a nominal scale: clipping is found "
                       "from the data alone")
        runs = find_clipping(rec.gyro, declared=declared, min_level=min_level or 0.0)

        def level(x: float) -> str:
            return f"{math.degrees(x * f_nom):+.1f} °/s" if f_nom is not None else f"{x:+.6g} counts"
        found = [r for r in runs if r.source != "declared"]
        if found and f_nom is not None and self.cfg.gyro_range_dps is None and "gyro_range_dps" not in rec.options:
            fs_dps = max(abs(math.degrees(r.level * f_nom)) for r in found)     # the sensor's full scale, seen
            line = (f"gyro full scale ±{fs_dps:.4g} °/s from the values' clip level ({sum(r.n for r in found)} "
                    f"samples held there in {len(found)} run(s)) (--gyro-range {fs_dps:.4g})")
            rec.detected.append(line)
            rec.options["gyro_range_dps"] = float(f"{fs_dps:.4g}")
            self.say(f"  detected: {line}")
        out: dict[int, str] = {}
        for j in range(len(keep) - 1):
            s0, s1 = keep[j].stop - 1, keep[j + 1].start + 1
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
            self.clipping["gyro"].append({"motion": j, "t_start_s": s0 / fs, "t_stop_s": (s1 - 1) / fs,
                                          "axes": [{"axis": r.axis_name, "level": level(r.level), "start": r.start,
                                                    "samples": r.n, "source": r.source} for r in inside]})
            self._note(f"motion {j} ({s0 / fs:.1f}–{(s1 - 1) / fs:.1f} s) left out of the gyro fit: the gyro clipped, "
                       f"{out[j]}")
        if out:
            self.say(f"gyro clipped in {len(out)} of {len(keep) - 1} motions: those are left out of the gyro fit")
        return out

    def _rotation_bias(self, gyr, fs, keep, bias: TriadFit) -> tuple[np.ndarray, TriadFit]:
        """The gyro series and bias the gyro fits use: b + G·f(t) when the rests resolve a
        g-sensitivity G (calib.gsens, G ≠ 0 at p < 0.01; the series is corrected by G·f, f the calibrated
        specific force in g), else the rests' weighted mean bias (bench/real_data.py: on real
        hand-held recordings one rest's bias is the weak point, the mean of all rests does better)."""
        from imubench.calib import gyro as CG
        from imubench.calib.gsens import DPS, fit_gsens
        from imubench.calib.gyro import _cov12
        means = np.array([gyr[i.start:i.stop].mean(axis=0) for i in keep])
        sig = np.array([CG._mean_uncertainty(gyr[i.start:i.stop], min_cluster=max(1, int(round(0.02 * fs))))["sigma"]
                        for i in keep])
        self.gsens = {"applied": False}
        try:
            gs = fit_gsens(means, sig, self._f_rest_g)
            self.gsens.update(g_dps_per_g=(gs.g * DPS).tolist(), sigma_dps_per_g=(gs.sigma_g * DPS).tolist(),
                              beyond_2sigma=gs.resolved.tolist(), p_zero=gs.p_zero, b_rad_s=gs.b.tolist(),
                              reduced_chi2=gs.extra["reduced_chi2"])
            if gs.significant:
                self.gsens["applied"] = True
                self.say(gs.summary())
                self._note("the rotation method integrates the gyro less the bias b + G·f(t) its g-sensitivity "
                           "predicts (f the calibrated specific force); b is the bias at zero specific force")
                return gyr - self._acc_g @ gs.g.T, TriadFit(
                    method="bias", m=np.eye(3), b=gs.b.copy(), cov=_cov12(b_cov=gs.cov[9:, 9:]),
                    estimated=np.array([False] * 9 + [True] * 3), extra=dict(bias.extra, source="g-sensitivity fit"))
            self.gsens["why_not"] = f"G does not differ from zero (p = {gs.p_zero:.2g} ≥ 0.01)"
        except CalibrationError as e:
            self.gsens["why_not"] = str(e)
        w = 1.0 / sig**2
        b = np.sum(w * means, axis=0) / np.sum(w, axis=0)
        red = np.sum(w * (means - b) ** 2, axis=0) / max(len(keep) - 1, 1)
        sb = np.sqrt(1.0 / np.sum(w, axis=0) * np.maximum(red, 1.0))
        self._note(f"the rotation method's bias: the weighted mean of the {len(keep)} rests' gyro means (g-sensitivity "
                   f"not applied: {self.gsens['why_not']})")
        return gyr, TriadFit(method="bias", m=np.eye(3), b=b, cov=_cov12(b_cov=np.diag(sb**2)),
                             estimated=np.array([False] * 9 + [True] * 3),
                             extra=dict(bias.extra, source="weighted mean of the rests"))

    def _part_turns(self, gyr, acc, keep, up, accel) -> list:
        """Turns from the file's named parts (*_rot), for files cut tightly around each turn."""
        from imubench.calib.turns import turn_in_window
        out = []
        fs = self.rec.fs_hz
        for name, s0, s1 in self.rec.parts or []:
            if not name.endswith("_rot") or s1 - s0 < 3:
                continue
            d = accel.correct(acc[s0:s1].mean(axis=0)[None, :])[0]
            d /= np.linalg.norm(d)
            k = int(np.argmax(up @ d))               # the still interval of the same attitude
            rest = gyr[keep[k].start:keep[k].stop]
            b = rest.mean(axis=0)
            bs = rest.std(axis=0, ddof=1) / math.sqrt(len(rest))
            out.append(turn_in_window(gyr, fs, s0, s1, d, b, bs, turn_deg=self.cfg.turn_deg,
                                      label=f"turn about {face_of(d)} (part {name})"))
        return out

    def _gyro_fit(self, gyr, fs, keep, up, bias, brk, clipped: dict) -> TriadFit:
        from imubench.calib.turns import combine_fits, known_angle_turns
        cfg = self.cfg
        fits: dict[str, TriadFit] = {}
        errs: dict[str, CalibrationError] = {}
        u_rot, b_rot = self._rotation_bias(gyr, fs, keep, bias)
        bias = b_rot                    # the bias every gyro fit reports: the rests' mean or b of b + G·f
        try:
            fits["turns"] = known_angle_turns(self.turns, bias, noise_density_rad_s_rthz=bias.extra[
                "noise_density_rad_s_rthz"], angle_sigma_deg=cfg.angle_sigma_deg, axis_sigma_deg=cfg.axis_sigma_deg)
        except CalibrationError as e:
            errs["turns"] = e
        bad = sorted(clipped)
        for j in range(len(keep) - 1):
            inside = [b for b in brk if keep[j].stop - 1 < b <= keep[j + 1].start]
            if inside and j not in clipped:
                bad.append(j)
                self._note(f"motion {j} ({keep[j].stop / fs:.1f}–{keep[j + 1].start / fs:.1f} s) not used by the "
                           f"rotation method: the recording is not continuous inside it (break at sample {inside[0]})")
        try:
            fits["rotation"] = self._rotation_nested(u_rot, fs, keep, up, b_rot, bad)
        except CalibrationError as e:
            if clipped:
                e = type(e)(f"{e} ({len(clipped)} of {len(keep) - 1} motions left out: the gyro clipped in them; "
                            "turn slower than its range)")
            errs["rotation"] = e
        why = {k: str(e) for k, e in errs.items()}
        self.gyro_parts = {"fits": {k: fit_dict(v, "rad_s") for k, v in fits.items()}, "refused": why}
        if cfg.gyro == "auto":
            if not fits:
                raise CalibrationError("neither known-angle turns nor the rotation method could be used: "
                                       + "; ".join(f"{k}: {v}" for k, v in why.items()))
            main = "rotation" if "rotation" in fits else "turns"
            self.say(f"gyro: {' and '.join(sorted(fits))} (--gyro auto: what the recording supports)")
        else:
            main = cfg.gyro
        other = "rotation" if main == "turns" else "turns"
        if main not in fits:
            raise errs[main]
        if other in fits:
            comb = combine_fits(fits["turns"], fits["rotation"])
            self.say(f"gyro: known-angle turns and the rotation method combined "
                     f"({'consistent' if comb.consistent else 'INCONSISTENT'}: χ² = {comb.chi2:.3g} for 9 dof)")
            for n in comb.notes:
                self._note(n)
            return comb.fit
        self._note(f"gyro: the {other} method is not used: {why[other]}")
        return fits[main]

    def _rotation_nested(self, u_rot, fs, keep, up, b_rot, bad) -> TriadFit:
        """The rotation method with every entry of M; where the motions leave entries unresolved
        (σ unbounded or above the limit), again with those held at nominal, while some are
        left to fit: the largest model the motions carry (calib.gyro.rotation_method's hold)."""
        from imubench.calib import gyro as CG
        iv = [(i.start, i.stop) for i in keep]
        hold: list[int] = []
        first = None
        while True:
            try:
                fit = CG.rotation_method(u_rot, fs, iv, up, b_rot, max_rate_rad_s=None, exclude_motions=bad,
                                         hold=hold)
            except CalibrationError as e:
                entries = getattr(e, "entries", None)
                first = first or e
                if not entries or len(set(hold) | set(entries)) >= 9:
                    raise first from None
                hold = sorted(set(hold) | set(entries))
                continue
            if hold:
                self._note(f"gyro: the rotation method holds {', '.join(fit.extra['held'])} at nominal (their σ "
                           f"would be above {fit.extra['max_sigma']:g}: the motions do not resolve them; fitted with "
                           f"every entry: {first}); the others are fitted, the held ones' possible size carried into "
                           "their σ")
            return fit
