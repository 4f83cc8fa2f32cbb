"""The still search of calib.static and calib.turns a block at a time, on a recording's stored arrays
(issue 41): what `allan --from` runs on a recording whose float64 SI copies do not fit the memory
budget (imubench.memory.still_in_memory).

    src = Scaled(rec.accel, m_s2_per_unit)          # rows in SI, never copied whole
    pieces = still_pieces(Scaled(rec.accel, fa), Scaled(rec.gyro, fg), fs_hz)

still_pieces gives the pieces calib.turns.split_by_rotation gives after calib.static.detect_static
(its automatic threshold, window_s and min_duration_s), as (start, stop) pairs: the same pieces, found
from the same numbers. The SI values are made as the in-memory search makes them (stored values ×
factor, in the stored type, then float64), a block of rows at a time; the median, the moving variance,
the rest noise and the noise floor are the in-memory functions of calib.static, handed the blocks
(bit for bit the same); the runs of each threshold are followed across blocks instead of from one
array of the recording's length; each run's drift (calib.static._drift_z) is computed as the
in-memory one up to EXACT_ROWS samples and from block sums beyond (the same to rounding, 1e-13).
What it holds beside the recording: one working column of 8 B a sample at a time (the norms for
the median |a|, a sorted column for the noise floor, a column for a median) and 1 B a sample for the
gyro's moving mask; the rest is blocks of calib.static.VAR_BLOCK_ROWS rows.

Numbers only: no file, no port.
"""
from __future__ import annotations

import math

import numpy as np

from imubench.calib import static

#: a run up to this many samples (22 min at 200 Hz) has its drift computed as calib.static._drift_z
#: does, from one
#: float64 copy of its rows (a few of 24 B a sample: 20 MB at most); a longer one from block sums
EXACT_ROWS = 1 << 18


class Scaled:
    """Rows of a stored (n, 3) array (float32 or float64, any strides) in SI: the values × factor
    computed in the stored type (as `stored * factor` is), handed out as float64 a block at a time."""

    def __init__(self, x: np.ndarray, factor: float = 1.0):
        self.x, self.f = x, float(factor)

    @property
    def shape(self) -> tuple[int, int]:
        return self.x.shape

    def __len__(self) -> int:
        return len(self.x)

    def rows(self, i: int, j: int) -> np.ndarray:
        return np.asarray(self.x[i:j] * self.f, dtype=np.float64)

    def column(self, j: int, i0: int = 0, i1: int | None = None) -> np.ndarray:
        """Column j of rows i0..i1-1 in SI, in the stored type (one copy of its length)."""
        return self.x[i0:i1, j] * self.f

    def sorted(self, j: int) -> np.ndarray:
        """Column j in SI sorted, in the stored type (the float64 values are its values, exactly)."""
        c = self.column(j)
        c.sort()
        return c

    def median(self, j: int, i0: int = 0, i1: int | None = None) -> float:
        """np.median of column j (rows i0..i1-1) of the float64 SI values, from one copy in the stored
        type: the same middle element(s), averaged in float64 as np.median averages them."""
        c = self.column(j, i0, i1)
        n = len(c)
        if n == 0:
            return float("nan")
        h = n // 2
        if n % 2:
            c.partition(h)
            return float(np.float64(c[h]))
        c.partition([h - 1, h])
        return float(np.mean(np.array([c[h - 1], c[h]], dtype=np.float64)))


def _runs_blocks(blocks, ks, n: int) -> dict:
    """{k: [(start, stop)]}: the runs of ratio <= k² for each k of ks, from the ratio a block at a
    time ((start, ratio) pairs in order, covering 0..n-1), as calib.static._runs of the whole."""
    out = {k: [] for k in ks}
    open_at = {k: None for k in ks}
    for s0, r in blocks:
        for k in ks:
            m = r <= k * k
            x = np.empty(len(m) + 1, np.int8)
            x[0] = open_at[k] is not None
            x[1:] = m
            d = np.diff(x)
            starts = (np.flatnonzero(d == 1) + s0).tolist()
            stops = (np.flatnonzero(d == -1) + s0).tolist()
            if open_at[k] is not None:
                starts.insert(0, open_at[k])
            if len(starts) > len(stops):
                open_at[k] = starts.pop()
            else:
                open_at[k] = None
            out[k].extend(zip(starts, stops))
    for k in ks:
        if open_at[k] is not None:
            out[k].append((open_at[k], n))
    return out


def _drift_z(src: Scaled, s: int, e: int, sig_floor: np.ndarray, block: int) -> float:
    """calib.static._drift_z of rows s..e-1: from one copy up to EXACT_ROWS, else from block sums."""
    n = e - s
    if n <= EXACT_ROWS:
        return static._drift_z(src.rows(s, e), 0, n, sig_floor)
    t = n // 3

    def total(i0, i1, mean=None):
        parts = []
        for i in range(i0, i1, block):
            x = src.rows(i, min(i1, i + block))
            if mean is not None:
                x -= mean
                x *= x
            parts.append(x.sum(axis=0))
        return np.array([math.fsum(p[j] for p in parts) for j in range(3)])
    mean_all = total(s, e) / n
    d = np.abs(total(s, s + t) / t - total(e - t, e) / t)
    sd = np.maximum(np.sqrt(total(s, e, mean=mean_all) / (n - 1)), sig_floor)
    return float(np.max(d / (sd * math.sqrt(2.0 / t))))


def detect_static_runs(acc: Scaled, fs_hz: float, window_s: float = 0.5, min_duration_s: float = 1.0) -> list:
    """The (start, stop) of the still intervals calib.static.detect_static(acc, fs_hz, window_s=...,
    min_duration_s=...) finds with its automatic k, a block at a time."""
    n = len(acc)
    if n < 2:
        return []
    w = static.window_length(window_s, fs_hz)
    h = w // 2
    min_n = max(2, int(math.ceil(min_duration_s * fs_hz - 1e-9)))
    scale = static._scale_of(acc)
    sigma = static._rest_noise(acc, fs_hz, window_s, 0.1)
    sigma = np.maximum(sigma, static._noise_floor(acc, scale))
    kmin = static.k_min_for_window(w)
    grid = [kk for kk in static.K_GRID if kk >= kmin - 1e-9] or [static.K_GRID[-1]]
    ref = static._column_medians(acc)
    nr = n + 2 * h - w + 1

    def ratios():
        for s0, var in static._variance_blocks(acc, w, centred=True, ref=ref):
            yield s0, np.max(var / sigma**2, axis=1)
    runs = _runs_blocks(ratios(), grid, nr)
    block = static.VAR_BLOCK_ROWS
    drift: dict = {}
    cand = []
    for kk in grid:
        kept_k, short_k = static._trim_runs(runs[kk], n, h, min_n)
        clean_n = 0
        for s, e in kept_k:
            if (s, e) not in drift:
                drift[s, e] = _drift_z(acc, s, e, sigma, block)
            if drift[s, e] <= static.DRIFT_Z_MAX:
                clean_n += e - s
        cand.append((kk, clean_n, kept_k, short_k))
    best = max(c[1] for c in cand)
    if best > 0:
        pick = next(c for c in cand if c[1] >= static.CLEAN_TIME_FRACTION * best)
    else:
        pick = max(cand, key=lambda c: (len(c[2]), len(c[3]), c[0]))
    return list(pick[2])


def split_by_rotation_runs(gyro: Scaled, fs_hz: float, intervals, *, moving_dps: float = 5.0,
                           min_duration_s: float = 1.0, guard_s: float = 0.25) -> list:
    """The (start, stop) of the pieces calib.turns.split_by_rotation(acc, gyro, fs_hz, intervals) gives
    (gyro in rad/s), a block at a time: each interval cut where the rate departs from its median by
    more than moving_dps, ± guard_s (a 1 B a sample mask, dilated by scipy.ndimage.maximum_filter1d:
    the same samples as split_by_rotation's convolution with a box)."""
    from scipy.ndimage import maximum_filter1d
    thr = math.radians(moving_dps)
    guard = int(round(guard_s * fs_hz))
    min_n = max(2, int(math.ceil(min_duration_s * fs_hz)))
    block = static.VAR_BLOCK_ROWS
    out = []
    for s, e in intervals:
        med = np.array([gyro.median(j, s, e) for j in range(3)], dtype=np.float64)
        moving = np.empty(e - s, bool)
        for i in range(s, e, block):
            j = min(e, i + block)
            moving[i - s:j - s] = np.max(np.abs(gyro.rows(i, j) - med), axis=1) > thr
        if not moving.any():
            out.append((s, e))
            continue
        if guard:
            moving = maximum_filter1d(moving.view(np.uint8), size=2 * guard + 1, mode="constant", cval=0) > 0
        edges = np.flatnonzero(np.diff(np.concatenate([[1], moving.astype(np.int8), [1]])))
        del moving
        for s0, s1 in zip(edges[::2].tolist(), edges[1::2].tolist()):
            if s1 - s0 >= min_n:
                out.append((s + s0, s + s1))
    return out


def still_pieces(acc: Scaled, gyro: Scaled, fs_hz: float, window_s: float = 0.5,
                 min_duration_s: float = 1.0) -> list:
    """(start, stop) of the pieces split_by_rotation(detect_static(acc)) gives, a block at a time."""
    ivs = detect_static_runs(acc, fs_hz, window_s, min_duration_s)
    return split_by_rotation_runs(gyro, fs_hz, ivs, min_duration_s=min_duration_s)
