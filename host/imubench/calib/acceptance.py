"""Which accelerometer model the rests carry, which rests it leaves out, and whether it is
better than no calibration at all.

    fit_accel(means, sigmas, covs, method, g, excess_limit)   AccelChoice, or raises FitRefused

The candidates, largest first (docs/calibration.md, "When a fit is accepted"):

    multi-position, 9 parameters   biases, scales and the three non-orthogonality angles, |a| = g
    six-position, 12 parameters    the full matrix and biases, every pose square to gravity
    multi-position, 6 parameters   biases and scales; the angles held at nominal (0)

Each candidate is fitted on every rest, each rest weighted by its noise and its own motion
(calib.rests). A rest whose leave-one-out residual the others cannot explain is left out
(Bonferroni over the rests), one at a time, the worst first. A candidate is kept only when every
parameter it fits is resolved (its sigma within RESOLVED_LIMITS) and it is accepted: on the same
rests it brings |a| closer to g than the nominal model (M = I, b = 0) and its χ²/dof is
consistent with the noise, or its excess over the noise is within `excess_limit` (the scatter a
linear calibration of this class of sensor leaves), stated. The first candidate kept wins;
when none is, FitRefused says why for each and what to record.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special   # χ² and F survival functions: scipy.stats costs far more to import

from imubench.calib import CalibrationError, TriadFit
from imubench.calib import accel as CA

__all__ = ["ALPHA_OUTLIER", "ALPHA_FIT", "MAX_LEFT_OUT_FRACTION", "RESOLVED_LIMITS", "FitRefused",
           "AccelChoice", "RestUse", "fit_accel", "abs_residuals", "excess_sigma"]

# A rest is left out when the others predict it this badly: its leave-one-out χ² has a
# probability below ALPHA_OUTLIER / (number of rests) (Bonferroni: 1 % for the whole recording).
ALPHA_OUTLIER = 0.01
# A fit's χ² is consistent with the noise when its probability is at least this.
ALPHA_FIT = 1e-3
# More rests than this fraction "outlying" is the model not fitting, not the rests: none more
# is left out.
MAX_LEFT_OUT_FRACTION = 0.25
# A fitted parameter is resolved when its 1-sigma is below the error it is there to correct,
# taken as the smallest initial errors MEMS accelerometer data sheets specify, of the order of
# 25 mg offset, 1 % sensitivity and 1 % cross-axis sensitivity: fitting it then gives a smaller
# expected squared error (σ²) than holding it at nominal (the error itself, squared). Biases in
# g, scales dimensionless, angles in rad. A parameter held at nominal is taken to be this size
# in truth (a consider parameter, accel.multi_position's held_sigma).
RESOLVED_LIMITS = {"bias_g": 0.025, "scale": 0.01, "angle_rad": 0.01}
# Six-position takes every face as square to gravity: what its residuals hold beyond the noise is
# the faces' tilt, which it reads as cross-axis terms. A board laid on a table on each face is
# square within about 1°; beyond that the model does not fit the rests.
SIX_TILT_MAX_DEG = 1.0
ANGLES = ("a_yx", "a_zx", "a_zy")


class FitRefused(CalibrationError):
    """No accelerometer model is both resolved by the rests and better than none; the message
    says why for each candidate and what to record. .candidates: the per-candidate reports,
    .rests: the RestUse of every rest as the last candidate saw them."""

    def __init__(self, message: str, candidates: list, rests: list):
        super().__init__(message)
        self.candidates = candidates
        self.rests = rests


@dataclass
class RestUse:
    """How a fit used one rest (index into the means given)."""
    use: str = "used"                 # "used" | "down-weighted" | "left out"
    use_reason: str = ""
    sigma_inflation: float = 1.0      # the sigma the fit used / the rest's noise sigma (≥ 1)
    loo_chi2: float | None = None     # leave-one-out χ² (how far the other rests predict it)
    loo_p: float | None = None


@dataclass
class AccelChoice:
    fit: TriadFit
    model: str                        # e.g. "multi-position, biases and scales"
    held: list                        # parameters held at nominal
    rests: list                       # RestUse per rest given
    summary: str                      # one line for the verdict
    candidates: list = field(default_factory=list)   # per candidate: name, status, reason, numbers


def _multi(hold: tuple) -> tuple:
    free = [a for a in ANGLES if a not in hold]
    what = ("biases, scales and non-orthogonality angles" if not hold else
            "biases and scales" if not free else f"biases, scales and {' and '.join(free)}")
    return (f"multi-position, {what}", "multi", hold)


# kind: (name, method, hold); the levels, largest model first (the models of one level are
# tried together and the best kept of them wins)
_CANDIDATES = {"multi9": _multi(()), "six12": ("six-position, full matrix and biases", "six", ()),
               **{f"multi8-{a}": _multi((a,)) for a in ANGLES},
               **{f"multi7-{a}": _multi(tuple(x for x in ANGLES if x != a)) for a in ANGLES},
               "multi6": _multi(ANGLES)}
_LEVELS_MULTI = (("multi9",), tuple(f"multi8-{a}" for a in ANGLES), tuple(f"multi7-{a}" for a in ANGLES),
                 ("multi6",))
ORDER = {"auto": (_LEVELS_MULTI[0], ("six12",)) + _LEVELS_MULTI[1:], "multi": _LEVELS_MULTI, "six": (("six12",),)}


def abs_residuals(u, sigmas, covs, fit: TriadFit | None, g: float) -> tuple[np.ndarray, np.ndarray]:
    """|x_i| − g and its sigma for means u (m, 3) corrected by fit (None: the nominal model, x =
    u); sigma propagated from diag(sigmas²) + covs through x = M⁻¹(u − b)."""
    u = np.asarray(u, dtype=np.float64)
    minv = np.eye(3) if fit is None else np.linalg.inv(fit.m)
    x = u @ minv.T if fit is None else fit.correct(u)
    nx = np.linalg.norm(x, axis=1)
    v = (x / nx[:, None]) @ minv
    var = np.sum((v * sigmas) ** 2, axis=1)
    if covs is not None:
        var = var + np.einsum("ij,ijk,ik->i", v, covs, v)
    return nx - g, np.sqrt(var)


def excess_sigma(r, s, dof: int) -> float:
    """The extra sigma e, common to every residual, that makes Σ r²/(s² + e²) = dof (0 when χ²
    is already at most dof): the scatter beyond the noise, in the residuals' unit."""
    r, s = np.asarray(r, float).ravel(), np.asarray(s, float).ravel()
    if dof < 1 or np.sum((r / s) ** 2) <= dof:
        return 0.0
    f = lambda e: float(np.sum(r * r / (s * s + e * e))) - dof   # noqa: E731 - decreasing in e
    hi = float(np.sqrt(np.mean(r * r))) * 10 + 1e-300
    return float(optimize.brentq(f, 0.0, hi))


def _outlier_p(q: np.ndarray, chi2: float, dof: int, k: int) -> np.ndarray:
    """Probability of each rest's leave-one-out χ² q_i (k dof). When the other rests' own χ²/dof
    exceeds 1 their scatter, not the sigmas, sets the scale: F(k, dof − k)."""
    p = np.ones(len(q))
    for i, qi in enumerate(q):
        if not math.isfinite(qi):
            continue                  # the others cannot predict it (it alone fixes a parameter)
        c_rest, d_rest = chi2 - qi, dof - k
        if d_rest >= 1 and c_rest / d_rest > 1.0:
            p[i] = float(special.fdtrc(k, d_rest, (qi / k) / (c_rest / d_rest)))
        else:
            p[i] = float(special.chdtrc(k, qi))
    return p


def _run(kind: str, u, sig, covs, g: float, init: TriadFit | None) -> TriadFit:
    name, method, hold = _CANDIDATES[kind]
    if method == "six":
        return CA.six_position(u, sig, g, skip_non_faces=True, covs=covs)
    return CA.multi_position(u, sig, init=init, g=g, covs=covs, hold=hold,
                             held_sigma={n: RESOLVED_LIMITS["angle_rad"] for n in hold})


def _unresolved(fit: TriadFit, g: float) -> list[str]:
    """Fitted parameters whose sigma is above RESOLVED_LIMITS, as 'name σ = x > limit'."""
    lim = RESOLVED_LIMITS
    out = []
    if fit.method == "multi_position":
        sp = fit.extra["sigma_params"]
        for n in fit.extra["params"]:
            if n in fit.extra.get("held", []):
                continue
            if n.startswith("b_"):
                if sp[n] / g > lim["bias_g"]:
                    out.append(f"{n} σ = {sp[n] / g * 1e3:.2g} mg > {lim['bias_g'] * 1e3:g} mg")
            elif n.startswith("s_"):
                if sp[n] > lim["scale"]:
                    out.append(f"{n} σ = {sp[n]:.2g} > {lim['scale']:g}")
            elif sp[n] > lim["angle_rad"]:
                out.append(f"{n} σ = {sp[n] * 1e3:.2g} mrad > {lim['angle_rad'] * 1e3:g} mrad")
        return out
    sm, sb = fit.sigma_m, fit.sigma_b
    for r in range(3):
        for c in range(3):
            limit = lim["scale"] if r == c else lim["angle_rad"]
            if sm[r, c] > limit:
                out.append(f"M{r}{c} σ = {sm[r, c]:.2g} > {limit:g}")
        if sb[r] / g > lim["bias_g"]:
            out.append(f"b_{'xyz'[r]} σ = {sb[r] / g * 1e3:.2g} mg > {lim['bias_g'] * 1e3:g} mg")
    return out


def _inflation(fit: TriadFit, idx: np.ndarray, u, sig, covs, g: float) -> np.ndarray:
    """Per rest in idx: the sigma the fit weighed it by over its noise sigma alone — of |a| for
    the |a| = g model, the largest over the axes for six-position."""
    if covs is None:
        return np.ones(len(idx))
    if fit.method == "multi_position":
        _, s_all = abs_residuals(u[idx], sig[idx], covs[idx], fit, g)
        _, s_noise = abs_residuals(u[idx], sig[idx], None, fit, g)
        return np.maximum(1.0, s_all / s_noise)
    d = np.einsum("ijj->ij", covs[idx])
    return np.maximum(1.0, np.sqrt(np.max((sig[idx] ** 2 + d) / sig[idx] ** 2, axis=1)))


def _try(kind: str, u, sig, covs, g: float, init, excess_limit: float) -> dict:
    """One candidate: fit, leave out outlying rests, judge. A dict with 'status' ("kept",
    "unresolved", "refused", "not observable") and what it found."""
    name, method, hold = _CANDIDATES[kind]
    mg = 1e3 / g
    m = len(u)
    active = np.arange(m)
    left: dict[int, str] = {}
    k = 3 if method == "six" else 1
    try:
        fit = _run(kind, u, sig, covs, g, init)
    except CalibrationError as e:
        return {"kind": kind, "model": name, "status": "not observable", "reason": str(e), "left_out": {}}
    while len(left) < int(MAX_LEFT_OUT_FRACTION * m):
        used = np.asarray(fit.extra.get("used_poses", range(len(active))), dtype=int)
        q = np.asarray(fit.extra["deletion_chi2"], float)
        p = _outlier_p(q, fit.extra["chi2"], fit.dof, k)
        j = int(np.argmin(p))
        if not p[j] < ALPHA_OUTLIER / len(active):
            break
        rest = int(active[used[j]])
        trial = np.delete(active, used[j])
        try:
            fit2 = _run(kind, u[trial], sig[trial], None if covs is None else covs[trial], g, init)
        except CalibrationError:
            break                     # without it the model is not observable: it stays
        left[rest] = (f"the other rests predict it badly: leave-one-out χ² = {q[j]:.3g} for {k} dof, "
                      f"p = {p[j]:.1g} < {ALPHA_OUTLIER:g}/{len(active)} rests")
        active, fit = trial, fit2
    out = {"kind": kind, "model": name, "fit": fit, "active": active, "left_out": left, "held": list(hold)}
    unres = _unresolved(fit, g)
    chi2, dof = fit.extra["chi2"], fit.dof
    out.update(chi2=chi2, dof=dof)
    if unres:
        out.update(status="unresolved", reason="not resolved by the rests: " + "; ".join(unres))
        return out
    ra, sa = abs_residuals(u[active], sig[active], None if covs is None else covs[active], fit, g)
    r0, s0 = abs_residuals(u[active], sig[active], None if covs is None else covs[active], None, g)
    rms_after, rms_before = float(np.sqrt(np.mean(ra ** 2))), float(np.sqrt(np.mean(r0 ** 2)))
    c_after, c_before = float(np.sum((ra / sa) ** 2)), float(np.sum((r0 / s0) ** 2))
    out.update(rms_before=rms_before, rms_after=rms_after, abs_chi2_before=c_before, abs_chi2_after=c_after)
    if not (rms_after <= rms_before and c_after < c_before):
        out.update(status="refused", reason=(
            f"worse than no calibration on the same {len(active)} rests: |a| − g {rms_after * mg:.3g} mg RMS after "
            f"against {rms_before * mg:.3g} mg before (χ² {c_after:.3g} against {c_before:.3g})"))
        return out
    if dof < 1:
        out.update(status="refused", reason=(
            f"as many parameters as rests ({len(active)}): nothing is left to check the fit with"))
        return out
    p_fit = float(special.chdtrc(dof, chi2))
    fit_txt = f"χ²/dof = {chi2 / dof:.3g} for {dof} dof"
    if method == "six":
        res = np.asarray(fit.residuals).ravel()
        su = sig[active][fit.extra["used_poses"]]
        if covs is not None:
            su = np.sqrt(su ** 2 + np.einsum("ijj->ij", covs[active][fit.extra["used_poses"]]))
        tilt = math.degrees(excess_sigma(res, su.ravel(), dof) / g)
        # what |a| = g can check of it (9 of its 12 parameters change |a|)
        d_abs = len(active) - 9
        exc = excess_sigma(ra, sa, d_abs) if d_abs >= 1 else 0.0
        out.update(p_fit=p_fit, excess=exc, face_tilt_deg=tilt)
        if tilt > SIX_TILT_MAX_DEG:
            out.update(status="refused", reason=(
                f"the model does not fit: {fit_txt} (p = {p_fit:.1g}): the faces were {tilt:.2g}° off square beyond "
                f"the noise, more than the {SIX_TILT_MAX_DEG:g}° six-position can take (use poses held on a table, or "
                f"the multi-position fit)"))
        elif d_abs >= 1 and exc > excess_limit:
            out.update(status="refused", reason=(
                f"the model does not fit: |a| − g scatters {exc * mg:.3g} mg beyond the noise over {len(active)} rests, "
                f"more than the {excess_limit * mg:.3g} mg a linear calibration of this class of sensor leaves"))
        elif p_fit >= ALPHA_FIT:
            out.update(status="kept", consistency=f"{fit_txt}, consistent with the rests' noise (p = {p_fit:.2g})")
        else:
            out.update(status="kept", consistency=(
                f"{fit_txt}: the faces were {tilt:.2g}° off square beyond the noise (within {SIX_TILT_MAX_DEG:g}°; "
                f"read as cross-axis terms, and the covariance is scaled by χ²/dof)"
                + (f", |a| − g scatters {exc * mg:.2g} mg beyond the noise" if d_abs >= 1 else "")))
        return out
    res, su = np.asarray(fit.residuals), np.asarray(fit.extra["sigma_r"])
    exc = excess_sigma(res, su, dof)
    out.update(p_fit=p_fit, excess=exc)
    if p_fit >= ALPHA_FIT:
        out.update(status="kept", consistency=f"{fit_txt}, consistent with the rests' noise (p = {p_fit:.2g})")
    elif exc <= excess_limit:
        out.update(status="kept", consistency=(
            f"{fit_txt}: the rests scatter {exc * mg:.2g} mg beyond their noise, within the {excess_limit * mg:.3g} mg a "
            f"linear calibration of this class of sensor leaves (the covariance is scaled by χ²/dof)"))
    else:
        out.update(status="refused", reason=(
            f"the model does not fit: {fit_txt} (p = {p_fit:.1g}), the rests scatter {exc * mg:.3g} mg beyond their "
            f"noise, more than the {excess_limit * mg:.3g} mg a linear calibration of this class of sensor leaves"))
    return out


def _rest_uses(u, sig, covs, motions_text, cand: dict, g: float) -> list[RestUse]:
    m = len(u)
    rests = [RestUse() for _ in range(m)]
    fit = cand.get("fit")
    active = cand.get("active", np.arange(m))
    infl = np.ones(m)
    if fit is not None:
        idx = np.asarray(active)
        infl[idx] = _inflation(fit, idx, u, sig, covs, g)
        if fit.method == "six_position":
            for j in fit.extra["skipped_poses"]:
                rests[int(idx[j])] = RestUse("left out", "not on a face (six-position needs one axis vertical)")
    for i in range(m):
        if i in cand.get("left_out", {}):
            rests[i] = RestUse("left out", cand["left_out"][i], float(max(1.0, infl[i])))
        elif rests[i].use == "left out":
            continue
        elif motions_text and motions_text[i] and infl[i] > 1.01:
            rests[i] = RestUse("down-weighted", f"{motions_text[i]}: σ × {infl[i]:.3g}", float(infl[i]))
        elif motions_text and motions_text[i]:
            rests[i] = RestUse("used", f"{motions_text[i]}: no change to the σ of what the fit uses",
                               float(infl[i]))
        else:
            rests[i] = RestUse("used", "", float(infl[i]))
    return rests


def fit_accel(means, sigmas, covs=None, method: str = "auto", g: float = 9.80665, *,
              excess_limit: float, motions_text: list | None = None) -> AccelChoice:
    """The largest accelerometer model the rests resolve and that is better than none (see the
    module). means, sigmas (m, 3), covs (m, 3, 3) or None: each rest's mean, the sigma of its
    noise and the covariance its motion adds (calib.rests). method: "auto", "multi" or "six"
    (the candidates tried, ORDER). excess_limit: the largest scatter beyond the noise accepted
    (unit of the means). motions_text: per rest, why its sigma was inflated ('' if not).
    Raises FitRefused when no candidate is kept."""
    if method not in ORDER:
        raise ValueError(f"method must be one of {sorted(ORDER)}, not {method!r}")
    u = np.asarray(means, dtype=np.float64)
    sig = np.asarray(sigmas, dtype=np.float64)
    cv = None if covs is None else np.asarray(covs, dtype=np.float64).reshape(len(u), 3, 3)
    init = None
    try:
        init = CA.six_position(u, sig, g, skip_non_faces=True)
    except CalibrationError:
        pass
    cands = []
    last = None
    for level in ORDER[method]:
        tried = [_try(kind, u, sig, cv, g, init, excess_limit) for kind in level]
        cands += tried
        kept = [c for c in tried if c["status"] == "kept"]
        if kept:
            last = min(kept, key=lambda c: c["chi2"] / c["dof"])
            break
    report = [{k: v for k, v in c.items() if k not in ("fit", "active")} | {"left_out": sorted(c["left_out"])}
              for c in cands]
    if last is None:               # the rests as the largest model that could be fitted saw them
        last = next((c for c in cands if "fit" in c), cands[-1])
    rests = _rest_uses(u, sig, cv, motions_text, last, g)
    if last["status"] != "kept":
        lines = "; ".join(f"{c['model']}: {c['reason']}" for c in cands if not c["kind"].startswith(("multi8", "multi7")))
        other = ("--method six with the board square on a table for each face" if method != "six" else
                 "each face square to gravity (a machined cube against a square); held by hand, --method multi")
        raise FitRefused(
            f"no accelerometer model is both resolved by the rests and better than no calibration, so nothing is "
            f"calibrated ({lines}). Next: record more rests, each held still, spread over faces, edges and "
            f"corners (12–26 attitudes, every axis up and down), or {other}", report, rests)
    held = last["held"]
    mg = 1e3 / g
    n_left = len(last["left_out"])
    summary = (f"{last['model']}" + (f" ({', '.join(held)} held at nominal, 0: not resolved by the rests)" if held else "")
               + f"; {last['consistency']}; |a| − g {last['rms_after'] * mg:.3g} mg RMS after, "
               f"{last['rms_before'] * mg:.3g} mg before, on {len(last['active'])} rests"
               + (f" ({n_left} left out)" if n_left else ""))
    fit = last["fit"]
    fit.extra["acceptance"] = {"model": last["model"], "held": held, "chi2": last["chi2"], "dof": last["dof"],
                               "p_fit": last["p_fit"], "excess": last["excess"],
                               "rms_before": last["rms_before"], "rms_after": last["rms_after"],
                               "candidates": report}
    return AccelChoice(fit=fit, model=last["model"], held=held, rests=rests, summary=summary, candidates=report)
