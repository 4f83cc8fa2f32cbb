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

How the deviation is computed (imubench.memory decides, by the memory budget): allantools.oadev on a
float64 copy of each axis when that fits, else oadev_chunked, the same estimator (NIST SP 1065, Riley,
"Handbook of Frequency Stability Analysis", 2008, eq. 11) from the same phase (the mean-free cumulative
sum, as allantools' frequency2phase) with each τ's sum of squared second differences taken a block at a
time: one float64 column of the recording's length, whatever its length. The two agree to rounding
(1e-12 relative; tests/procedures/test_allan_stream.py).

The recording is imubench.procedures.allan, the plot and the printed table imubench.results.allan.
"""
from __future__ import annotations

import math

import numpy as np

from imubench import memory

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


#: samples of a block in the chunked sums
BLOCK = 1 << 20


def oadev_chunked(y: np.ndarray, fs_hz: float, factor: float = 1.0, block: int = BLOCK):
    """(taus, adev, n) of the overlapping Allan deviation of the rates factor·y at octave τ (1, 2, 4 ...
    samples), as allantools.oadev(factor·y, rate=fs_hz, data_type="freq", taus="octave") gives them,
    holding one float64 column (the phase) and blocks of `block` samples: y may be float32, or a
    strided column of the recording. The phase is the cumulative sum of the mean-free rates (a block at
    a time, carried: the same sums as one cumulative sum) times the step; σ²(mτ₀) = Σ (x[i+2m] − 2x[i+m]
    + x[i])² / (2 (N−2m) (mτ₀)²) summed a block at a time."""
    y = np.asarray(y).reshape(-1)
    n = len(y)
    if n < 3:
        raise ValueError(f"too few samples for an Allan analysis ({n})")
    dt = 1.0 / float(fs_hz)

    def rates(i, j):
        r = y[i:j].astype(np.float64)
        return r * factor if factor != 1.0 else r
    mean = math.fsum(float(np.sum(rates(i, i + block))) for i in range(0, n, block)) / n
    x = np.empty(n + 1)
    x[0] = 0.0
    carry = 0.0
    for i in range(0, n, block):
        j = min(n, i + block)
        r = rates(i, j)
        r -= mean
        r[0] += carry
        np.cumsum(r, out=x[i + 1:j + 1])
        carry = float(x[j])
    x[1:] *= dt
    N = n + 1
    taus, devs, ns = [], [], []
    for k in range(int(math.floor(math.log2(N))) + 1):
        m = 2 ** k
        count = N - 2 * m
        if m >= N or count <= 1:
            continue
        parts = []
        for i in range(0, count, block):
            j = min(count, i + block)
            v = x[i + 2 * m:j + 2 * m] - 2 * x[i + m:j + m]
            v += x[i:j]
            parts.append(float(np.dot(v, v)))
        taus.append(m * dt)
        devs.append(math.sqrt(math.fsum(parts) / (2.0 * count)) / m * fs_hz)
        ns.append(count)
    return np.array(taus), np.array(devs), np.array(ns, dtype=float)


def oadev_in_memory(y: np.ndarray, fs_hz: float, factor: float = 1.0):
    """(taus, adev, n) from allantools.oadev on a float64 copy of factor·y (octave τ)."""
    allantools = require_allantools()
    x = np.asarray(y, dtype=np.float64)
    if factor != 1.0:
        x = x * factor
    taus, devs, _errs, ns = allantools.oadev(x, rate=fs_hz, data_type="freq", taus="octave")
    return np.asarray(taus), np.asarray(devs), np.asarray(ns)


def allan_axis(x: np.ndarray, fs_hz: float, factor: float = 1.0, chunked: bool = False) -> dict:
    """Allan analysis of one axis (1-D rate samples at fs_hz, in SI once multiplied by factor):
    allantools in memory, or chunked sums (oadev_chunked) when chunked."""
    n = len(x)
    taus, devs, ns = (oadev_chunked if chunked else oadev_in_memory)(x, fs_hz, factor)
    return _readoffs(taus, devs, ns, n, fs_hz)


def _readoffs(taus, devs, ns, n: int, fs_hz: float) -> dict:
    """The read-offs N, B, K of an Allan curve of n samples (see the module's doc)."""
    keep = (devs > 0) & (ns >= 1)
    taus, devs, ns = np.asarray(taus)[keep], np.asarray(devs)[keep], np.asarray(ns)[keep]
    if len(taus) < 3:
        if not np.any(np.asarray(devs) > 0):
            raise ValueError("its samples do not vary (every one the same value): there is no noise to analyse; "
                             "is the column a constant, or the sensor's output stuck?")
        raise ValueError(f"too few samples for an Allan analysis ({n})")
    lt, ld = np.log10(taus), np.log10(devs)
    seg = np.diff(ld) / np.diff(lt)                          # slope of segment i -> i+1
    pt = np.empty_like(ld)                                   # slope at each point
    pt[0], pt[-1] = seg[0], seg[-1]
    pt[1:-1] = 0.5 * (seg[:-1] + seg[1:])
    edf, lo, hi = _edf_and_ci(taus, devs, pt, n, fs_hz)
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
    last = int(np.searchsorted(taus, n / fs_hz / MAX_TAU_FRACTION, side="right")) - 1
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

    duration_s = n / fs_hz
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


def allan(rates: np.ndarray, fs_hz: float, factor: float = 1.0, memory_budget: int | None = None,
          held_bytes: int | None = None) -> dict:
    """Overlapping Allan deviation (octave τ, 68 % edf confidence intervals) and read-offs
    of each axis of `rates` ((n, 3), in SI once multiplied by factor: m/s² or rad/s; float64 or
    float32, never copied whole). Returns {"x": {...}, "y": ..., "z": ..., "fs_hz": .., "n": ..,
    "duration_s": .., "method": ..}; each axis: taus, adev, ci_lo, ci_hi, N, B, B_tau, K (K None when
    the recording shows no +1/2 region) and the fit details. The method is allantools in memory when a
    float64 axis and its temporaries fit the memory budget (imubench.memory, default 1 GB) beside
    held_bytes (what the caller holds: the recording; default rates' own size), else chunked sums."""
    r = np.asarray(rates)
    if r.dtype not in (np.float32, np.float64):
        r = r.astype(np.float64)
    if r.ndim == 1:
        r = r[:, None]
    n = int(r.shape[0])
    held = r.nbytes if held_bytes is None else int(held_bytes)
    chunked = not memory.allan_in_memory(n, held, memory_budget)
    out = {}
    for k in range(r.shape[1]):
        try:
            out[AXES[k]] = allan_axis(r[:, k], fs_hz, factor, chunked)
        except ValueError as e:
            raise ValueError(f"axis {AXES[k]}: {e}") from None
    out.update(fs_hz=float(fs_hz), n=n, duration_s=n / float(fs_hz),
               method=("chunked sums over the phase, one float64 column (the memory budget of "
                       f"{memory.text(memory_budget or memory.DEFAULT_BUDGET_BYTES)} holds no in-memory copy)"
                       if chunked else "allantools.oadev in memory"))
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
