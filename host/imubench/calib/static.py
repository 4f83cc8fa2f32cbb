"""Static-interval detection from the data itself (imu_tk style), with thresholds derived from
the measured noise, never fixed in m/s².

Everything here works in the unit of the data it is given (m/s², counts, g): noise, thresholds
and means come back in that unit. docs/calibration.md ("Static detection") explains the method.

    rest_noise(acc, fs_hz)                    per-axis noise sigma of the quietest part
    detect_static(acc, fs_hz, ...)            the still intervals (StaticIntervals, a list)
    require_static(intervals, n_needed)       raises NotEnoughStatic, explaining what to do
    interval_stats(samples)                   mean, std, sigma of the mean (correlated noise)

The live detector of a session (StillnessDetector: moving / settling / still, block by block)
is calib.stillness, on the same thresholds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special   # the χ² distribution functions: scipy.stats costs ~3x its import time

from imubench.calib import CalibrationError

__all__ = [
    "StaticInterval", "StaticIntervals", "NotEnoughStatic",
    "rest_noise", "detect_static", "require_static", "interval_stats", "window_length",
    "noise_floor", "moving_variance", "sigma_of_mean", "k_min_for_window", "K_GRID",
]

# Candidate threshold factors k (window std / rest noise sigma), as imu_tk's 2..10, finer.
K_GRID = tuple(np.round(np.arange(2.0, 10.0001, 0.5), 2))
# A window is still when its variance is below k² × the rest variance. k never goes below the
# level a still window of w samples exceeds with probability ALPHA_STILL per axis (chi-square).
ALPHA_STILL = 1e-6
# Floor of the noise sigma, relative to the median |a| of the recording (1 µg for data in g):
# keeps the thresholds finite for a noise-free (simulated) sensor, well below the ADXL355's
# per-sample noise at any rate (≥ 100 µg at 20 Hz).
REL_SIGMA_FLOOR = 1e-6
# An interval whose first and last thirds differ by more than this many sigmas of their
# difference is not clean (it contains motion, or two poses merged across a gentle move).
DRIFT_Z_MAX = 8.0
# Auto k: the smallest k whose clean still time is at least this fraction of the best k's.
CLEAN_TIME_FRACTION = 0.97


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def window_length(window_s: float, fs_hz: float) -> int:
    """Samples in a centred window of window_s seconds: odd, at least 3."""
    if not (fs_hz > 0 and window_s > 0):
        raise ValueError(f"need fs_hz > 0 and window_s > 0 (got {fs_hz}, {window_s})")
    w = int(round(window_s * fs_hz))
    w = max(3, w)
    return w if w % 2 == 1 else w + 1


def _as_samples(acc) -> np.ndarray:
    a = np.asarray(acc, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"expected samples of shape (n, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("samples contain NaN or inf")
    return a


def _block(a, i: int, j: int) -> np.ndarray:
    """Rows i..j-1 of an array, or of rows handed out a block at a time (.rows: calib.still_blocks)."""
    return a.rows(i, j) if hasattr(a, "rows") else a[i:j]


def _scale_of(a: np.ndarray) -> float:
    """Typical magnitude of the data (median |a|; for an accelerometer at rest, g in the data's
    unit). Falls back to the largest absolute value for data near zero."""
    norms = np.empty(len(a))                 # a block at a time: no (n, 3) temporary
    for i in range(0, len(a), VAR_BLOCK_ROWS):
        norms[i:i + VAR_BLOCK_ROWS] = np.linalg.norm(_block(a, i, i + VAR_BLOCK_ROWS), axis=1)
    s = float(np.median(norms, overwrite_input=True)) if len(a) else 0.0
    del norms
    if not s > 0:
        s = max((float(np.max(np.abs(_block(a, i, i + VAR_BLOCK_ROWS)))) for i in range(0, len(a), VAR_BLOCK_ROWS)),
                default=0.0)
    return s if s > 0 else 1.0


def noise_floor(acc) -> np.ndarray:
    """The smallest noise sigma the thresholds use, per axis: REL_SIGMA_FLOOR × the median |a|,
    or the quantisation noise (LSB/√12) when the data are visibly quantised, whichever is
    larger. Keeps a noise-free recording usable."""
    a = _as_samples(acc)
    return _noise_floor(a, _scale_of(a))


def _noise_floor(a, scale: float) -> np.ndarray:
    """noise_floor of samples a (an array, or rows handed out a block at a time, whose .sorted(j) is a
    column sorted in its stored type) whose median |a| is scale."""
    floor = REL_SIGMA_FLOOR * scale
    out = np.full(3, floor)
    for j in range(3):
        u = a.sorted(j) if hasattr(a, "rows") else np.sort(a[:, j])   # the smallest step between distinct
        steps = [d[d > 0] for d in (np.diff(np.asarray(u[i:i + VAR_BLOCK_ROWS + 1], dtype=np.float64))  # values,
                                    for i in range(0, max(len(u) - 1, 0), VAR_BLOCK_ROWS))]   # a block at a time
        steps = [float(d.min()) for d in steps if d.size]
        del u
        if steps:
            lsb = min(steps)
            # only a real quantisation step counts (float data have tiny spurious steps)
            if lsb > floor:
                out[j] = max(out[j], lsb / math.sqrt(12.0))
    return out


def _window_sums(y: np.ndarray, w: int) -> np.ndarray:
    """Sums of y over windows of w consecutive rows, for every start 0..len(y)-w, computed from
    prefix sums restarted every w rows, so rounding stays local (no error accumulated over a
    long recording). y: (L, c)."""
    L, c = y.shape
    nwin = L - w + 1
    if nwin <= 0:
        return np.zeros((0, c))
    nb = -(-L // w) + 1                       # blocks, plus one of zeros
    yp = np.zeros((nb * w, c))
    yp[:L] = y
    blk = yp.reshape(nb, w, c)
    pre = np.cumsum(blk, axis=1)                         # inclusive prefix within a block
    suf = np.cumsum(blk[:, ::-1], axis=1)[:, ::-1]       # inclusive suffix within a block
    # window starting at (b, t): suffix of block b from t, plus prefix of block b+1 up to t-1
    nxt = np.zeros_like(pre)
    nxt[:-1, 1:] = pre[1:, :-1]
    return (suf + nxt).reshape(nb * w, c)[:nwin]


def _column_medians(a) -> np.ndarray:
    """The median of each column as float64 (np.median of the column); of rows handed out a block
    at a time (.rows, .median), each column's own median, one column at a time."""
    if hasattr(a, "rows"):
        return np.array([a.median(j) for j in range(a.shape[1])], dtype=np.float64)
    return np.array([np.median(a[:, j]) for j in range(a.shape[1])], dtype=np.float64)


#: window starts computed at a time by moving_variance (rounded to a multiple of the window): its
#: temporaries are a few arrays of this many rows, not of the recording's length
VAR_BLOCK_ROWS = 1 << 16


def _variance_blocks(a, w: int, centred: bool = True, ref: np.ndarray | None = None):
    """(start, variances) of moving_variance a block of window starts at a time. Each block starts at a
    multiple of w, where _window_sums restarts its prefix sums, so its sums are those of the whole
    recording at once, bit for bit. a: an array, or rows handed out a block at a time (calib.still_blocks
    .Scaled: a recording's stored values in SI, never copied whole); ref: the column medians (the
    values are taken about them), when the caller has them."""
    if not hasattr(a, "rows"):
        a = np.asarray(a)
    n, c = a.shape
    if ref is None:
        ref = _column_medians(a) if n else np.zeros(c)
    h = w // 2 if centred else 0
    L = n + 2 * h
    nwin = L - w + 1
    step = w * max(1, VAR_BLOCK_ROWS // w)
    for s in range(0, max(nwin, 0), step):
        e = min(nwin, s + step)
        p0, p1 = s, e + w - 1                    # rows of the padded recording the windows s..e-1 cover
        dp = np.zeros((p1 - p0, c))
        lo, hi = max(p0, h), min(p1, h + n)
        if hi > lo:
            np.subtract(_block(a, lo - h, hi - h), ref, out=dp[lo - p0:hi - p0])
        s1 = _window_sums(dp, w)[:e - s]
        s2 = _window_sums(dp * dp, w)[:e - s]
        if centred:
            ones = np.zeros((p1 - p0, 1))
            ones[lo - p0:hi - p0] = 1.0
            cnt = _window_sums(ones, w)[:e - s]
        else:
            cnt = np.full((e - s, 1), float(w))
        mean = s1 / cnt
        var = (s2 - cnt * mean * mean) / np.maximum(cnt - 1.0, 1.0)
        yield s, np.clip(var, 0.0, None)


def moving_variance(a: np.ndarray, w: int, centred: bool = True) -> np.ndarray:
    """Per-axis variance (ddof=1) over a window of w samples. centred: a window centred on each
    sample, truncated at the ends of the recording; otherwise trailing windows (the sample and
    the w-1 before it), only where complete: output length len(a) - w + 1. Computed a block of
    VAR_BLOCK_ROWS at a time (_variance_blocks): the output and a few block-sized temporaries."""
    a = np.asarray(a)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    n = max(len(a) + 2 * (w // 2 if centred else 0) - w + 1, 0)     # len(a) (+1 for an even centred window)
    out = np.empty((n, a.shape[1]))
    for s, v in _variance_blocks(a, w, centred):
        out[s:s + len(v)] = v
    return out


#: an interval longer than this (samples) has its autocorrelation summed over segments of this length
#: (lags up to a quarter of it): the FFT of a day at 200 Hz would take gigabytes, and Sokal's window
#: stops far below 2^18 lags for any still IMU
TAU_SEGMENT = 1 << 21


def _tau_int(x: np.ndarray) -> np.ndarray:
    """Integrated autocorrelation time per column (1 for white noise), Sokal's automatic
    window (the sum of autocorrelations stops at the smallest lag M ≥ 5·τ(M)). Floored at 1."""
    n, c = x.shape
    if n < 16:
        return np.ones(c)
    mean = x.mean(axis=0)
    seg = min(n, TAU_SEGMENT)                  # a long interval: the autocorrelation summed over segments
    nfft = 1 << int(math.ceil(math.log2(2 * seg)))
    out = np.ones(c)
    for j in range(c):                         # a column at a time: the FFT's arrays for one axis only
        acf = 0.0
        for i in range(0, n - seg + 1, seg):
            f = np.fft.rfft(x[i:i + seg, j] - mean[j], n=nfft)
            acf = acf + np.fft.irfft(f * np.conj(f), n=nfft)[: seg // 4 + 1]
            del f
        if acf[0] <= 0:
            continue
        rho = acf / acf[0]
        tau = 2.0 * np.cumsum(rho) - 1.0          # tau(M) = 1 + 2 Σ_{k=1..M} rho_k
        m = np.arange(len(rho))
        ok = np.nonzero(m >= 5.0 * tau)[0]
        t = tau[ok[0]] if len(ok) else tau[-1]
        out[j] = max(1.0, float(t))
    return out


def interval_stats(samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, std, sigma_mean) per axis of still samples (n, 3). sigma_mean is the 1-sigma
    uncertainty of the mean: std·√(τ/n) with τ the integrated autocorrelation time of the
    samples (τ = 1 for white noise; a low-pass filtered or drifting signal has τ > 1), never
    less than std/√n."""
    x = _as_samples(samples)
    n = len(x)
    if n < 2:
        raise ValueError("need at least 2 samples")
    mean = x.mean(axis=0)
    std = x.std(axis=0, ddof=1)
    tau = _tau_int(x)
    return mean, std, std * np.sqrt(tau / n)


def sigma_of_mean(x) -> float:
    """1-sigma uncertainty of the mean of one series x (n,): std·√(τ/n), τ the integrated
    autocorrelation time (as interval_stats), never less than std/√n."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 1)
    n = len(x)
    if n < 2:
        raise ValueError("need at least 2 samples")
    return float(x.std(ddof=1) * math.sqrt(_tau_int(x)[0] / n))


# --------------------------------------------------------------------------------------------
# noise
# --------------------------------------------------------------------------------------------

def rest_noise(acc, fs_hz: float, window_s: float = 0.5, quantile: float = 0.1) -> np.ndarray:
    """Per-axis noise sigma of the quietest part of a recording.

    The recording is cut into non-overlapping windows of window_s. A first estimate is the
    `quantile` (default the 10th percentile) of the windows' standard deviations divided by the
    same quantile of a window std of Gaussian noise (√(χ²_q(w−1)/(w−1))): it is right as long
    as more than `quantile` of the recording is still. Then the variances of all windows
    consistent with that noise (below its 99.9 % chi-square point) are pooled, and divided by
    the mean of a chi-square truncated there: a far less noisy estimate than one quantile (it
    uses every still window), still unbiased. Works at any rate; a recording shorter than two
    windows gives its plain std."""
    return _rest_noise(_as_samples(acc), fs_hz, window_s, quantile)


def _rest_noise(a, fs_hz: float, window_s: float, quantile: float) -> np.ndarray:
    """rest_noise of samples a: an array, or rows handed out a block at a time (.rows)."""
    w = max(3, int(round(window_s * fs_hz)))
    nw = len(a) // w
    if nw < 2:
        return _block(a, 0, len(a)).std(axis=0, ddof=1) if len(a) > 1 else np.zeros(3)
    nu = w - 1
    v = np.empty((nw, 3))                                # (nw, 3), a few thousand windows at a time
    step = max(1, VAR_BLOCK_ROWS // w)
    for i in range(0, nw, step):
        k = min(nw, i + step)
        v[i:k] = _block(a, i * w, k * w).reshape(k - i, w, 3).var(axis=1, ddof=1)
    q = float(np.clip(quantile, 0.01, 0.5))
    s0 = np.quantile(np.sqrt(v), q, axis=0) / math.sqrt(2.0 * special.gammaincinv(nu / 2.0, q) / nu)
    cut = 2.0 * special.gammaincinv(nu / 2.0, 0.999) / nu   # χ²_ν's 0.999 quantile / ν, in units of sigma²
    # E[X | X ≤ c] for X = χ²_ν/ν: P(χ²_{ν+2} ≤ νc) / P(χ²_ν ≤ νc)
    trunc = special.chdtr(nu + 2, nu * cut) / special.chdtr(nu, nu * cut)
    out = np.empty(3)
    for j in range(3):
        sel = v[:, j] <= cut * s0[j] ** 2
        out[j] = math.sqrt(v[sel, j].mean() / trunc) if sel.any() and s0[j] > 0 else s0[j]
    return out


def k_min_for_window(w: int) -> float:
    """The smallest sensible k for a window of w samples: the window std of still Gaussian
    noise exceeds k·sigma with probability ALPHA_STILL per axis. ≈ 2 for w = 11, 1.4 for 51."""
    return math.sqrt(special.chdtri(w - 1, ALPHA_STILL) / (w - 1))


# --------------------------------------------------------------------------------------------
# detection
# --------------------------------------------------------------------------------------------

@dataclass
class StaticInterval:
    """One still interval: samples start..stop-1 of the recording."""
    start: int
    stop: int                     # exclusive
    n: int
    mean: np.ndarray              # (3,) in the data's unit
    std: np.ndarray               # (3,) sample std (ddof=1)
    sigma_mean: np.ndarray        # (3,) 1-sigma uncertainty of the mean (correlated noise included)
    fs_hz: float = float("nan")
    drift_z: float = 0.0          # max over axes: |mean(first third) − mean(last third)| in sigmas

    @property
    def duration_s(self) -> float:
        return self.n / self.fs_hz

    @property
    def t_start_s(self) -> float:
        return self.start / self.fs_hz

    @property
    def clean(self) -> bool:
        """False when the interval's mean moved within it (motion or a merge of two poses)."""
        return self.drift_z <= DRIFT_Z_MAX


class StaticIntervals(list):
    """The result of detect_static: a list of StaticInterval, plus how they were found (what
    require_static / NotEnoughStatic need to explain a shortfall)."""

    def __init__(self, items=(), *, fs_hz: float, window_s: float, min_duration_s: float,
                 k: float, noise_sigma: np.ndarray, scale: float, n_samples: int,
                 short: list[tuple[int, int]] | None = None, k_auto: bool = False):
        super().__init__(items)
        self.fs_hz = fs_hz
        self.window_s = window_s
        self.min_duration_s = min_duration_s
        self.k = k
        self.k_auto = k_auto
        self.noise_sigma = np.asarray(noise_sigma, dtype=np.float64)   # as used (floored)
        self.scale = scale                   # median |a| of the recording
        self.n_samples = n_samples
        self.short = short or []             # still runs dropped as shorter than min_duration_s

    @property
    def threshold_sigma(self) -> np.ndarray:
        """Per axis: the window std above which a window counts as moving."""
        return self.k * self.noise_sigma


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of the runs of True in a boolean array."""
    if not mask.any():
        return []
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    starts = np.nonzero(d == 1)[0]
    stops = np.nonzero(d == -1)[0]
    return list(zip(starts.tolist(), stops.tolist()))


def _intervals_for_k(ratio: np.ndarray, k: float, n: int, h: int, min_n: int):
    """Trimmed still runs for one k: (kept, short). Edges next to motion are trimmed by h
    samples (half a window); the ends of the recording are not."""
    return _trim_runs(_runs(ratio <= k * k), n, h, min_n)


def _trim_runs(runs, n: int, h: int, min_n: int):
    """(kept, short) of still runs [start, stop): trimmed by h at edges next to motion, kept when
    min_n samples remain."""
    kept, short = [], []
    for s, e in runs:
        s2 = s + h if s > 0 else s
        e2 = e - h if e < n else e
        if e2 - s2 >= min_n:
            kept.append((s2, e2))
        elif e2 > s2:
            short.append((s2, e2))
    return kept, short


def _drift_z(a: np.ndarray, s: int, e: int, sig_floor: np.ndarray) -> float:
    """|mean(first third) − mean(last third)| over its 1-sigma (from the interval's own std,
    floored), max over axes."""
    n = e - s
    if n < 6:
        return 0.0
    t = n // 3
    x = a[s:e]
    d = np.abs(x[:t].mean(axis=0) - x[-t:].mean(axis=0))
    sd = np.maximum(x.std(axis=0, ddof=1), sig_floor)
    return float(np.max(d / (sd * math.sqrt(2.0 / t))))


def detect_static(acc, fs_hz: float, noise_sigma=None, window_s: float = 0.5,
                  min_duration_s: float = 1.0, k: float | None = None) -> StaticIntervals:
    """Still intervals of a recording acc (n, 3) sampled at fs_hz.

    A sample is still when the variance over a centred window of window_s, on every axis, is
    at most k² × the rest variance (noise_sigma², from rest_noise when not given, floored by
    noise_floor). Each still run is trimmed by half a window at both ends (not at the ends of
    the recording) and kept when at least min_duration_s remain; runs separated by motion are
    never merged. With k None it is chosen from K_GRID (≥ k_min_for_window): the smallest k
    whose clean still time (intervals whose mean did not move within them) is within 3 % of
    the best k's — see docs/calibration.md. Returns a StaticIntervals (a list)."""
    a = _as_samples(acc)
    n = len(a)
    w = window_length(window_s, fs_hz)
    h = w // 2
    min_n = max(2, int(math.ceil(min_duration_s * fs_hz - 1e-9)))
    scale = _scale_of(a) if n else 1.0
    if noise_sigma is None:
        sigma = rest_noise(a, fs_hz, window_s) if n >= 2 else np.zeros(3)
    else:
        sigma = np.broadcast_to(np.asarray(noise_sigma, dtype=np.float64), (3,)).copy()
    sigma = np.maximum(sigma, noise_floor(a) if n else REL_SIGMA_FLOOR)

    common = dict(fs_hz=fs_hz, window_s=window_s, min_duration_s=min_duration_s,
                  noise_sigma=sigma, scale=scale, n_samples=n)
    if n < 2:
        return StaticIntervals([], k=float(k or K_GRID[0]), **common)

    ratio = np.empty(n + 2 * h - w + 1)     # the largest variance / rest variance of the axes, a block at a time
    for s0, var in _variance_blocks(a, w, centred=True):
        ratio[s0:s0 + len(var)] = np.max(var / sigma**2, axis=1)

    if k is not None:
        kept, short = _intervals_for_k(ratio, float(k), n, h, min_n)
        k_used, k_auto = float(k), False
    else:
        kmin = k_min_for_window(w)
        grid = [kk for kk in K_GRID if kk >= kmin - 1e-9] or [K_GRID[-1]]
        cand = []
        for kk in grid:
            kept_k, short_k = _intervals_for_k(ratio, kk, n, h, min_n)
            clean_n = sum(e - s for s, e in kept_k if _drift_z(a, s, e, sigma) <= DRIFT_Z_MAX)
            cand.append((kk, clean_n, kept_k, short_k))
        best = max(c[1] for c in cand)
        if best > 0:
            pick = next(c for c in cand if c[1] >= CLEAN_TIME_FRACTION * best)
        else:        # nothing still at any k: report the most permissive attempt
            pick = max(cand, key=lambda c: (len(c[2]), len(c[3]), c[0]))
        k_used, _, kept, short = pick
        k_auto = True

    out = []
    for s, e in kept:
        mean, std, sig = interval_stats(a[s:e])
        out.append(StaticInterval(start=s, stop=e, n=e - s, mean=mean, std=std, sigma_mean=sig,
                                  fs_hz=fs_hz, drift_z=_drift_z(a, s, e, sigma)))
    return StaticIntervals(out, k=k_used, k_auto=k_auto, short=short, **common)


# --------------------------------------------------------------------------------------------
# not enough
# --------------------------------------------------------------------------------------------

class NotEnoughStatic(CalibrationError):
    """Fewer still intervals than the calibration needs. The message says how many were found,
    how long each was, the threshold relative to the noise, and what to do."""

    def __init__(self, message: str, *, found: int, needed: int, durations_s: list[float],
                 short_s: list[float], k: float | None, noise_sigma: np.ndarray | None,
                 hold_s: float):
        super().__init__(message)
        self.found = found
        self.needed = needed
        self.durations_s = durations_s
        self.short_s = short_s
        self.k = k
        self.noise_sigma = noise_sigma
        self.hold_s = hold_s          # how long to hold each pose


def _fmt_list(xs, fmt="{:.1f}", limit=12) -> str:
    xs = list(xs)
    body = ", ".join(fmt.format(x) for x in xs[:limit])
    return body + (f", … ({len(xs) - limit} more)" if len(xs) > limit else "")


def require_static(intervals, n_needed: int, what: str = "poses", *,
                   fs_hz: float | None = None, min_duration_s: float | None = None) -> list:
    """Return `intervals` if there are at least n_needed of them, else raise NotEnoughStatic.
    Best given the StaticIntervals of detect_static (it carries the threshold and the dropped
    short runs); a plain list works too (fs_hz / min_duration_s then say what they can)."""
    ivs = list(intervals)
    if len(ivs) >= n_needed:
        return intervals
    fs = getattr(intervals, "fs_hz", fs_hz)
    if fs is None and ivs:
        fs = ivs[0].fs_hz
    min_d = getattr(intervals, "min_duration_s", min_duration_s)
    window_s = getattr(intervals, "window_s", None)
    k = getattr(intervals, "k", None)
    sigma = getattr(intervals, "noise_sigma", None)
    scale = getattr(intervals, "scale", None)
    short = getattr(intervals, "short", [])

    def dur(nsamp):
        return nsamp / fs if fs else float("nan")

    durations = [dur(iv.n) for iv in ivs]
    short_s = [dur(e - s) for s, e in short]
    win = window_s if window_s else 0.0
    # a hold loses about a window at each end (the centred window, then half a window trimmed)
    hold_s = (min_d or 1.0) + 2.0 * win + 1.0

    lines = [f"not enough still {what}: found {len(ivs)} still interval"
             f"{'' if len(ivs) == 1 else 's'}, {n_needed} needed."]
    if ivs:
        lines.append(f"Still intervals kept (s): {_fmt_list(durations)}.")
    if short_s:
        lines.append(f"{len(short_s)} shorter still stretch{'' if len(short_s) == 1 else 'es'} "
                     f"dropped as under {min_d:.1f} s: {_fmt_list(sorted(short_s, reverse=True), '{:.2f}')} s.")
    if k is not None and sigma is not None and window_s is not None:
        rel = ""
        if scale:
            rel_ug = np.asarray(sigma) / scale * 1e6
            rel = f" = {_fmt_list(rel_ug, '{:.0f}')} µg if |a| at rest is 1 g"
        auto = "chosen automatically" if getattr(intervals, "k_auto", False) else "given"
        lines.append(
            f"A {window_s:.2f} s window counted as still when its standard deviation stayed "
            f"below k = {k:.1f} ({auto}) × the rest noise on every axis; rest noise σ = "
            f"{_fmt_list(sigma, '{:.3g}')} (x, y, z, in the data's unit{rel}).")
    lines.append(
        f"What to do: hold each pose at least {hold_s:.0f} s without touching the board "
        f"(the detection gives up about {win:.2f} s at each end of a hold, and "
        f"{min_d or 1.0:.1f} s must remain); move between poses in one clear motion; put the "
        f"board on a firm surface away "
        f"from fans, vibration and cables that pull on it. If the board was held still and "
        f"intervals were still dropped, the rest noise was measured on a quieter stretch than "
        f"the poses: record a longer rest at the start, or pass a larger k.")
    raise NotEnoughStatic(" ".join(lines), found=len(ivs), needed=n_needed, durations_s=durations,
                          short_s=short_s, k=k, noise_sigma=sigma, hold_s=hold_s)
