"""Allan deviation of a resting IMU and its noise read-offs: pure numpy (and allantools).

    res = allan(gyro_rad_s, fs_hz=100)            # (n, 3) SI rates -> dict per axis "x"/"y"/"z"
    res["x"]["N"], res["x"]["B"], res["x"]["K"]   # white noise, bias instability, rate random walk

Conventions (docs/conventions.md, docs/noise.md): white noise coefficient N with
ADEV(τ) = N/√τ (read at τ = 1 s on the −1/2 line); rate random walk K with ADEV(τ) = K·√(τ/3)
(read at τ = 3 s on the +1/2 line); bias instability B = min ADEV / 0.664.

How the lines are fitted (see docs/noise.md):
  * local log-log slopes between adjacent octave τ;
  * −1/2 region: the longest run of consecutive τ, starting at the first segment (at or
    before the curve's minimum) whose slope is within −1/2 ± 0.15, ending at the first
    segment outside that band. N = weighted mean of log(ADEV·√τ) over it (slope fixed at
    −1/2, weights = equivalent degrees of freedom, i.e. 1/var(log ADEV)).
  * +1/2 region: from the smallest τ after the minimum such that a free weighted log-log fit
    from there to τ_end has slope +1/2 ± 0.15 (at least 3 points), to τ_end = the longest
    τ <= T/8 (T the record length; longer τ have too few independent windows). K = weighted
    mean of log(√(ADEV² − N²/τ)·√(3/τ)) over it: the white part, known from the −1/2 fit, is
    removed so the points near the crossover do not bias K upwards.

The recording is imubench.procedures.allan, the plot and the printed table imubench.results.allan.
"""
from __future__ import annotations

import numpy as np

from imubench.units import G0_MPS2 as G0

RAD2DEG = 180.0 / np.pi


SLOPE_TOL = 0.15


MAX_TAU_FRACTION = 8.0


AXES = ("x", "y", "z")


def require_allantools():
    """allantools, or a one-line error saying how to install it (the allan extra); called
    before a recording starts too, so that hours of samples never wait on a missing package."""
    try:
        import allantools
    except ImportError:
        from imubench.errors import ImubenchError
        raise ImubenchError("the Allan analysis needs allantools, the allan extra: "
                            "pip install 'imubench[allan]' (or pip install allantools)") from None
    return allantools


def _edf_and_ci(taus, devs, slopes_pt, n_freq, fs_hz):
    allantools = require_allantools()
    edfs, lo, hi = [], [], []
    for tau, dev, s in zip(taus, devs, slopes_pt):
        # noise type from the local slope: ADEV ∝ τ^s  <=>  S_y ∝ f^α with α = −2s − 1
        alpha = int(np.clip(np.round(-2.0 * s - 1.0), -2, 0))
        m = int(round(tau * fs_hz))
        try:
            edf = float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n_freq + 1,
                                                 overlapping=True, modified=False))
        except Exception:  # noqa: BLE001 - fall back to the simple estimate
            edf = float(allantools.edf_simple(n_freq + 1, m, alpha))
        edf = max(edf, 1.0)
        a, b = allantools.confidence_interval(dev=dev, edf=edf)
        edfs.append(edf)
        lo.append(float(a))
        hi.append(float(b))
    return np.array(edfs), np.array(lo), np.array(hi)


def _fixed_slope_fit(logtau, logy, w, slope):
    """Weighted mean of the intercept of a line of given slope in log10 space, and its 1σ."""
    c = logy - slope * logtau
    W = np.sum(w)
    c0 = float(np.sum(w * c) / W)
    return c0, float(np.sqrt(1.0 / W))


def _free_slope(logtau, logy, w):
    A = np.vstack([logtau, np.ones_like(logtau)]).T * np.sqrt(w)[:, None]
    coef, *_ = np.linalg.lstsq(A, logy * np.sqrt(w), rcond=None)
    return float(coef[0])


def allan_axis(x: np.ndarray, fs_hz: float) -> dict:
    """Allan analysis of one axis (1-D rate samples in SI at fs_hz)."""
    allantools = require_allantools()
    x = np.asarray(x, dtype=np.float64)
    taus, devs, _errs, ns = allantools.oadev(x, rate=fs_hz, data_type="freq", taus="octave")
    keep = (devs > 0) & (ns >= 1)
    taus, devs, ns = np.asarray(taus)[keep], np.asarray(devs)[keep], np.asarray(ns)[keep]
    if len(taus) < 3:
        raise ValueError(f"too few samples for an Allan analysis ({len(x)})")
    lt, ld = np.log10(taus), np.log10(devs)
    seg = np.diff(ld) / np.diff(lt)                          # slope of segment i -> i+1
    pt = np.empty_like(ld)                                   # slope at each point
    pt[0], pt[-1] = seg[0], seg[-1]
    pt[1:-1] = 0.5 * (seg[:-1] + seg[1:])
    edf, lo, hi = _edf_and_ci(taus, devs, pt, len(x), fs_hz)
    w = 2.0 * edf * np.log(10.0) ** 2                        # 1/var(log10 ADEV) ≈ 2·edf·ln(10)²
    i_min = int(np.argmin(devs))

    # ---- −1/2 line (white noise N)
    ok = np.abs(seg + 0.5) <= SLOPE_TOL
    cand = [i for i in range(min(i_min, len(seg))) if ok[i]] if i_min > 0 else []
    white = {"ok": bool(cand)}
    if cand:
        j0 = cand[0]
        j1 = j0
        while j1 < len(seg) and ok[j1]:
            j1 += 1
        idx = np.arange(j0, j1 + 1)                          # points joined by good segments
    else:                                                    # no −1/2 region: first two points
        idx = np.arange(0, 2)
    c, sc = _fixed_slope_fit(lt[idx], ld[idx], w[idx], -0.5)
    N = 10 ** c
    white.update(N=N, N_rel_1sigma=float(sc * np.log(10)), tau_range=[float(taus[idx[0]]), float(taus[idx[-1]])],
                 n_points=int(len(idx)), free_slope=_free_slope(lt[idx], ld[idx], w[idx]) if len(idx) > 1 else None)

    # ---- +1/2 line (rate random walk K)
    rw = {"ok": False, "K": None}
    # the longest τ are estimated from too few independent windows (their edf estimate is
    # unreliable too): the +1/2 fit uses τ <= T/MAX_TAU_FRACTION only
    last = int(np.searchsorted(taus, len(x) / fs_hz / MAX_TAU_FRACTION, side="right")) - 1
    for j in range(i_min + 1, last - 1):
        s = _free_slope(lt[j:last + 1], ld[j:last + 1], w[j:last + 1])
        if abs(s - 0.5) <= SLOPE_TOL:
            idx = np.arange(j, last + 1)
            var_k = devs[idx] ** 2 - N ** 2 / taus[idx]      # remove the white part (known from N)
            good = var_k > 0
            idx = idx[good]
            if len(idx) == 0:
                break
            yk = 0.5 * np.log10(devs[idx] ** 2 - N ** 2 / taus[idx])
            c, sc = _fixed_slope_fit(lt[idx], yk, w[idx], 0.5)
            K = 10 ** c * np.sqrt(3.0)                       # line K·√(τ/3): value at τ = 3 s is K
            rw = {"ok": True, "K": K, "K_rel_1sigma": float(sc * np.log(10)),
                  "tau_range": [float(taus[idx[0]]), float(taus[idx[-1]])], "n_points": int(len(idx)),
                  "free_slope": s}
            break

    duration_s = len(x) / fs_hz
    last = max(last, 0)
    # ---- read-offs the record cannot support are withheld, with the reason
    if not white["ok"]:
        white["reason"] = (f"no -1/2 slope region before the minimum: N is read from the first two τ "
                           f"({taus[0]:.3g} s, {taus[1]:.3g} s) and is an upper bound")
    B, B_reason = float(devs[i_min] / 0.664), None
    if i_min >= last:
        B, B_reason = None, (f"record too short for bias instability: the deviation is still falling at "
                             f"τ = {taus[last]:.3g} s, the longest τ a {duration_text(duration_s)} record supports "
                             f"(τ ≤ T/{MAX_TAU_FRACTION:g}); its minimum, where B is read, lies beyond: record at least "
                             "10 times longer")
    if not rw["ok"]:
        tail = slice(max(i_min, last - 2), last + 1)
        end_slope = _free_slope(lt[tail], ld[tail], w[tail]) if last - max(i_min, last - 2) >= 1 else None
        if i_min >= last:
            why = "the deviation has not reached its minimum yet"
        elif end_slope is not None:
            why = f"the slope after the minimum is {end_slope:+.2f} (not +1/2 ± {SLOPE_TOL:g})"
        else:
            why = "too few τ after the minimum"
        rw["reason"] = (f"no rate random walk read-off: in τ ≤ T/{MAX_TAU_FRACTION:g} = "
                        f"{duration_s / MAX_TAU_FRACTION:.3g} s {why}; a longer record shows it if it is there")
    return {
        "taus": taus.tolist(), "adev": devs.tolist(), "ci_lo": lo.tolist(), "ci_hi": hi.tolist(),
        "edf": edf.tolist(), "n_pairs": np.asarray(ns).tolist(),
        "N": N, "white": white,
        "B": B, "B_reason": B_reason, "B_tau": float(taus[i_min]),
        "B_adev_ci": [float(lo[i_min]), float(hi[i_min])],
        "K": rw["K"], "K_reason": rw.get("reason"), "rate_rw": rw,
    }


def duration_text(seconds: float) -> str:
    """A record length in the unit a person reads it in: 17 s, 12.5 min, 2.0 h."""
    if seconds < 120:
        return f"{seconds:.3g} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.3g} min"
    return f"{seconds / 3600:.3g} h"


def allan(rates: np.ndarray, fs_hz: float) -> dict:
    """Overlapping Allan deviation (octave τ, 68 % edf confidence intervals) and read-offs
    of each axis of `rates` ((n, 3) in SI: m/s² or rad/s). Returns {"x": {...}, "y": ..., "z": ...,
    "fs_hz": .., "n": .., "duration_s": ..}; each axis: taus, adev, ci_lo, ci_hi, N, B, B_tau, K
    (K None when the recording shows no +1/2 region) and the fit details."""
    r = np.asarray(rates, dtype=np.float64)
    if r.ndim == 1:
        r = r[:, None]
    out = {AXES[k]: allan_axis(r[:, k], fs_hz) for k in range(r.shape[1])}
    out.update(fs_hz=float(fs_hz), n=int(r.shape[0]), duration_s=r.shape[0] / float(fs_hz))
    return out


def usual_units(res_axis: dict, kind: str) -> dict:
    """Read-offs of one axis in the usual units: kind 'accel' (SI m/s²) or 'gyro' (rad/s)."""
    N, B, K = res_axis["N"], res_axis["B"], res_axis["K"]
    if kind == "accel":
        ug = 1e6 / G0
        return {"N_ug_per_rtHz": N * ug, "VRW_m_s_per_rth": N * 60.0, "B_ug": None if B is None else B * ug,
                "K_ug_rtHz": None if K is None else K * ug}
    return {"N_deg_per_rth": N * RAD2DEG * 60.0, "N_deg_s_per_rtHz": N * RAD2DEG,
            "B_deg_h": None if B is None else B * RAD2DEG * 3600.0,
            "K_deg_h_per_rth": None if K is None else K * RAD2DEG * 3600.0 ** 1.5}
