"""Recordings of any 6-axis IMU, read from files: the arrays the calibration engine needs, with
their units declared and their timing checked.

    rec = read("log.csv", accel_unit="g", gyro_unit="dps", time_column="t", time_unit="ms")
    acc_mps2, gyr_rad_s = rec.accel_mps2(), rec.gyro_rad_s()

`Recording` holds the samples as read (in the declared units), the sample rate, where the
recording is not continuous (`breaks`: gaps, cut points) and what the reader did (`notes`).
The readers (imubench.recordings.readers) cover CSV with a header, imu_tk's ASCII files,
imucal's CSV layouts, our own captures (`imubench decode --npz`, a session's capture-N.bin)
and ROS 1/2 bags with sensor_msgs/Imu (the optional `rosbags` library).

Units are declared, never guessed: accelerometer m/s², g, mg or raw counts (with a nominal
scale in counts per g, from a named sensor's data sheet (recordings.sensors), or none), gyro
rad/s, °/s or raw counts (counts per °/s, or none). Raw counts stored unsigned are found by
their values and their offset subtracted (unsigned_offset). What a reader settles without
being told is said (Recording.detected) and kept as the options that read the file again
(Recording.options, command_options).
A declared unit that the data contradict is refused by the caller that can see it
(imubench.procedures.from_file: |a| of the still intervals far from 1 g).

This package reads files; the algorithms (imubench.calib, imubench.analysis) never do.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from imubench.errors import ImubenchError
from imubench.units import G0_MPS2

__all__ = ["Recording", "RecordingError", "ACCEL_UNITS", "GYRO_UNITS", "accel_unit", "gyro_unit",
           "check_timing", "from_arrays", "read", "FORMATS", "unsigned_offset", "command_options", "command_line", "timing_lines"]

FORMATS = ("csv", "imutk", "imucal", "npz", "capture", "rosbag")

# canonical unit -> factor to SI (None: raw counts, needs a nominal scale or none)
ACCEL_UNITS = {"mps2": 1.0, "g": G0_MPS2, "mg": G0_MPS2 / 1000.0, "counts": None}
GYRO_UNITS = {"rad_s": 1.0, "dps": math.pi / 180.0, "counts": None}
_ACCEL_ALIASES = {"m/s2": "mps2", "m/s^2": "mps2", "m/s²": "mps2", "ms2": "mps2", "mps2": "mps2",
                  "g": "g", "mg": "mg", "counts": "counts", "raw": "counts", "lsb": "counts", "a.u.": "counts"}
_GYRO_ALIASES = {"rad/s": "rad_s", "rad_s": "rad_s", "rads": "rad_s", "deg/s": "dps", "dps": "dps",
                 "°/s": "dps", "deg_s": "dps", "counts": "counts", "raw": "counts", "lsb": "counts",
                 "a.u.": "counts"}
JITTER_RESAMPLE = 0.1        # a step off the mean step by more than this fraction: resample
GAP_FACTOR = 1.5             # a step longer than this × the nominal step may be a gap (_gaps decides)
GAP_WINDOW = 25              # samples each side compared to tell a gap from a jittery clock's long step


class RecordingError(ImubenchError, ValueError):
    """A file that cannot be read as a recording; the message says what and what to do."""


def accel_unit(name: str) -> str:
    """The canonical accelerometer unit of a name (m/s2, g, mg, counts, ...)."""
    u = _ACCEL_ALIASES.get(str(name).strip().lower())
    if u is None:
        raise RecordingError(f"unknown accelerometer unit {name!r}; use one of mps2 (m/s²), g, mg, counts")
    return u


def gyro_unit(name: str) -> str:
    """The canonical gyro unit of a name (rad/s, deg/s, counts, ...)."""
    u = _GYRO_ALIASES.get(str(name).strip().lower())
    if u is None:
        raise RecordingError(f"unknown gyro unit {name!r}; use one of rad_s (rad/s), dps (°/s), counts")
    return u


@dataclass
class Recording:
    """Samples of one IMU, in the units declared. accel, gyro: (n, 3) float64; fs_hz: the
    sample rate (from the timestamps' median step, or declared); t_s: the time of each sample
    in seconds (None when only a rate was given); breaks: (index, why) where the samples
    before and after index are not continuous in time; parts: (name, start, stop) sections
    named in the file (an annotation, imucal's cut parts) — never used to find the poses."""
    accel: np.ndarray
    gyro: np.ndarray
    fs_hz: float
    accel_unit: str = "mps2"
    gyro_unit: str = "rad_s"
    t_s: np.ndarray | None = None
    accel_counts_per_g: float | None = None      # nominal scale of raw accelerometer counts
    gyro_counts_per_dps: float | None = None     # nominal scale of raw gyro counts
    source: str = ""
    fmt: str = ""
    breaks: list = field(default_factory=list)   # [(index, reason)]
    notes: list = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    parts: list | None = None
    device: str | None = None                    # a name for the IMU, when the file has one
    detected: list = field(default_factory=list)  # what the reader settled without being told, one line each
    options: dict = field(default_factory=dict)   # read() options that read the file again the same way

    def __len__(self) -> int:
        return len(self.accel)

    @property
    def duration_s(self) -> float:
        return len(self) / self.fs_hz

    @property
    def accel_scaled(self) -> bool:
        """False for raw counts without a nominal scale (the fit then reports counts per g)."""
        return self.accel_unit != "counts" or bool(self.accel_counts_per_g)

    @property
    def gyro_scaled(self) -> bool:
        return self.gyro_unit != "counts" or bool(self.gyro_counts_per_dps)

    def accel_factor(self) -> float | None:
        """m/s² per unit of the data (None: counts without a nominal scale)."""
        if self.accel_unit == "counts":
            return G0_MPS2 / self.accel_counts_per_g if self.accel_counts_per_g else None
        return ACCEL_UNITS[self.accel_unit]

    def gyro_factor(self) -> float | None:
        """rad/s per unit of the data (None: counts without a nominal scale)."""
        if self.gyro_unit == "counts":
            return math.pi / 180.0 / self.gyro_counts_per_dps if self.gyro_counts_per_dps else None
        return GYRO_UNITS[self.gyro_unit]

    def accel_mps2(self, factor: float | None = None) -> np.ndarray:
        """The accelerometer in m/s² (nominal scaling; `factor` m/s² per count for raw counts
        without a declared scale)."""
        f = self.accel_factor() or factor
        if f is None:
            raise RecordingError("the accelerometer is in raw counts without a nominal scale: give "
                                 "--accel-scale COUNTS_PER_G, or let the fit report counts per g")
        return self.accel * f

    def gyro_rad_s(self, factor: float | None = None) -> np.ndarray:
        f = self.gyro_factor() or factor
        if f is None:
            raise RecordingError("the gyro is in raw counts without a nominal scale: give "
                                 "--gyro-scale COUNTS_PER_DPS, or let the fit report counts per °/s")
        return self.gyro * f

    def unit_text(self) -> str:
        def one(u, scale, per):
            if u != "counts":
                return {"mps2": "m/s²", "g": "g", "mg": "mg", "rad_s": "rad/s", "dps": "°/s"}[u]
            return f"counts ({scale:g} per {per})" if scale else "counts (no nominal scale)"
        return (f"accelerometer {one(self.accel_unit, self.accel_counts_per_g, 'g')}, "
                f"gyro {one(self.gyro_unit, self.gyro_counts_per_dps, '°/s')}")


# ------------------------------------------------------------------ timing
def _diffs(t: np.ndarray):
    """(start, steps) of the time steps t[k+1] − t[k], a block at a time (steps[j] is step start + j)."""
    for i in range(0, len(t) - 1, BLOCK):
        yield i, np.diff(t[i:i + BLOCK + 1])


def _nominal_step(t: np.ndarray, buf: np.ndarray | None = None) -> float:
    """The clock's nominal step: the median over the recording of the mean step of GAP_WINDOW
    consecutive steps (a jittery clock's long and short steps average out; a few gaps do not
    move the median). From the time stamps a block at a time into one working array (buf, reused
    when given)."""
    n = len(t) - 1
    w = min(GAP_WINDOW, n)
    m = n - w + 1
    out = buf[:m] if buf is not None and len(buf) >= m else np.empty(m)
    for i in range(0, m, BLOCK):
        j = min(m, i + BLOCK)
        np.subtract(t[i + w:j + w], t[i:j], out=out[i:j])
    out /= w
    return float(np.median(out, overwrite_input=True))


def _gaps(t: np.ndarray, long: np.ndarray, step: float) -> tuple[list, int]:
    """(gaps [(k, missing)], long steps that are jitter): a step k longer than gap_factor × step is
    a gap only when the clock's phase (t − i·step) after it stays ahead of its phase before it by
    half a step or more, compared as medians over GAP_WINDOW samples each side (up to the next long
    step): samples are missing. A long step the next ones make up for (a logging PC's late stamp,
    then an early one) is jitter, and the samples on both sides are continuous. long: the indices of
    the steps longer than gap_factor × step."""
    if not long.size:
        return [], 0

    def phase(lo, hi):
        return t[lo:hi] - t[0] - np.arange(lo, hi) * step
    out = []
    bounds = np.concatenate([[-1], long, [len(t) - 1]])
    for j, k in enumerate(long):
        lo = max(bounds[j] + 1, k - GAP_WINDOW + 1)
        hi = min(bounds[j + 2] + 1, k + 1 + GAP_WINDOW)
        shift = float(np.median(phase(k + 1, hi)) - np.median(phase(lo, k + 1)))
        missing = int(round(shift / step))
        if missing >= 1:
            out.append((int(k), missing))
    return out, int(long.size - len(out))


def check_timing(t_s, accel, gyro, *, gap_factor: float = GAP_FACTOR, resample: bool = True,
                 in_place: bool = False):
    """Find and handle what is wrong with a recording's timestamps.

    Returns (t, accel, gyro, fs_hz, breaks, timing): timestamps that go backwards are refused
    (RecordingError naming the row); samples with the same timestamp as the one before are
    dropped (counted); a step longer than gap_factor × the clock's nominal step is a gap (a break,
    with its length and the samples missing) only when the time stamps after it stay ahead of
    the sample count (_gaps: a jittery clock's long steps, made up by the next ones, are not
    gaps). The rate is the measured mean (the mean step outside the gaps), the jitter the RMS of
    the steps about it. When steps off the mean by more than JITTER_RESAMPLE of it remain, each
    continuous piece is resampled onto a uniform grid at the mean rate by linear interpolation
    (numpy.interp) between the time stamps: the gyro's integrals (which assume uniform samples)
    then integrate over the time stamps the file has. timing says all of it (counts, jitter,
    what was done).

    Memory: the checks go a block at a time; dropping repeated samples and resampling write the result
    over the arrays given when in_place (a reader's own arrays, never the caller's: from_arrays
    copy=False), else into one new set of arrays of the result's length; either way no mask or index
    array of the recording's length, and resampling in place keeps aside only the original samples
    the grid still needs after overwriting them (a block and the clock's lead on the grid)."""
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    a, g = _floats(accel), _floats(gyro)
    if len(t) < 3:
        raise RecordingError(f"only {len(t)} samples: a calibration needs minutes of data")
    for i in range(0, len(t), BLOCK):
        fin = np.isfinite(t[i:i + BLOCK])
        if not fin.all():
            k = i + int(np.flatnonzero(~fin)[0])
            raise RecordingError(f"timestamp of sample {k} is not a number; fix the file")
    back, first_back, ndup = 0, None, 0
    for i, d in _diffs(t):
        neg = np.flatnonzero(d < 0)
        if neg.size:
            back += neg.size
            first_back = first_back if first_back is not None else i + int(neg[0])
        ndup += int(np.count_nonzero(d == 0))
    if back:
        k = first_back
        raise RecordingError(
            f"timestamps go backwards at sample {k + 1} (t = {t[k]:.6f} s, then {t[k + 1]:.6f} s; "
            f"{back} time(s) in all): the file is not in time order (merged or restarted logs?); "
            "sort it by time or cut it at the restart")
    timing: dict = {"n_read": len(t), "duplicates": ndup}
    if ndup:
        t, a, g, timing["duplicates_identical"] = _drop_repeats(t, a, g, len(t) - ndup, in_place)
    if len(t) < 3:
        raise RecordingError("the timestamps do not advance (median step 0); check the time column and its unit")
    buf = np.diff(t)                                   # the one working array of the recording's length
    median_dt = float(np.median(buf, overwrite_input=True))
    if not median_dt > 0:
        raise RecordingError("the timestamps do not advance (median step 0); check the time column and its unit")
    step = _nominal_step(t, buf)
    del buf
    long = np.concatenate([np.flatnonzero(d > gap_factor * step) + i for i, d in _diffs(t)])
    found, jitter_long = _gaps(t, long, step)
    del long
    gaps = np.array([k for k, _ in found], dtype=np.int64)
    # the steps outside the gaps: count, sum, min, max, then the spread about their mean (two passes)
    total, count, lo, hi = [], 0, np.inf, -np.inf
    for i, d in _diffs(t):
        d = _outside(d, i, gaps)
        if d.size:
            total.append(float(np.sum(d)))
            count += d.size
            lo, hi = min(lo, float(d.min())), max(hi, float(d.max()))
    mean = math.fsum(total) / count if count else step
    if not count:
        lo = hi = mean
    sq = math.fsum(float(np.sum((_outside(d, i, gaps) - mean) ** 2)) for i, d in _diffs(t))
    std = math.sqrt(sq / count) if count else 0.0
    fs = 1.0 / mean
    dev_max = max(abs(hi - mean), abs(mean - lo)) / mean
    dt_at = {int(k): float(t[k + 1] - t[k]) for k, _ in found}
    timing.update({"median_dt_s": median_dt, "mean_dt_s": mean, "fs_hz": fs,
                   "jitter_rel": float(std / mean), "jitter_s": float(std),
                   "min_dt_s": float(lo), "max_dt_s": float(hi),
                   "max_step_dev_rel": float(dev_max), "long_steps_jitter": jitter_long,
                   "gaps": [{"index": int(k + 1), "t_s": float(t[k]), "duration_s": dt_at[k],
                             "missing": m} for k, m in found]})
    breaks = [(int(k + 1), f"gap of {dt_at[k]:.3f} s ({m} samples missing) at t = {t[k]:.3f} s") for k, m in found]
    timing["resampled"] = False
    if resample and dev_max > JITTER_RESAMPLE:
        t, a, g, nb = _resample(t, a, g, gaps, mean, in_place or ndup > 0)
        breaks = [(i, r) for i, (_, r) in zip(nb, breaks)]
        timing["resampled"] = True
    timing["n_used"] = len(t)
    return t, a, g, fs, breaks, timing


#: rows a time the repeats are dropped and the grid interpolated (their copies: a few MB)
STEP_ROWS = 1 << 18


def _drop_repeats(t, a, g, m: int, in_place: bool):
    """(t, a, g, identical) without the samples whose time stamp repeats the one before (m remain): written
    over t, a, g from the start when in_place (the rows kept move down; the result is views of their first
    m rows), else into new arrays of m rows; a block at a time. identical: the dropped samples whose values
    repeat the sample before them too."""
    n = len(t)
    if in_place:
        t2, a2, g2 = t, a, g
    else:
        t2, a2, g2 = np.empty(m), np.empty((m, a.shape[1]), a.dtype), np.empty((m, g.shape[1]), g.dtype)
    w, same = 0, 0
    prev = None                                   # the original row before the block: (t, a, g)
    for i in range(0, n, STEP_ROWS):
        j = min(n, i + STEP_ROWS)
        tb, ab, gb = t[i:j].copy(), a[i:j].copy(), g[i:j].copy()
        rep = np.empty(j - i, bool)
        rep[1:] = tb[1:] == tb[:-1]
        rep[0] = prev is not None and tb[0] == prev[0]
        if rep.any():
            k = np.flatnonzero(rep)
            pa = np.concatenate([prev[1][None], ab[:-1]]) if prev is not None else np.concatenate([ab[:1], ab[:-1]])
            pg = np.concatenate([prev[2][None], gb[:-1]]) if prev is not None else np.concatenate([gb[:1], gb[:-1]])
            same += int(np.count_nonzero(np.all(ab[k] == pa[k], axis=1) & np.all(gb[k] == pg[k], axis=1)))
        prev = (tb[-1], ab[-1].copy(), gb[-1].copy())
        keep = ~rep
        c = int(np.count_nonzero(keep))
        t2[w:w + c], a2[w:w + c], g2[w:w + c] = tb[keep], ab[keep], gb[keep]
        w += c
    return t2[:m], a2[:m], g2[:m], same


def _resample(t, a, g, gaps, mean: float, in_place: bool):
    """(t, a, g, piece_starts) of check_timing's resampling: each continuous piece (between the gaps)
    onto a uniform grid from its first time stamp at the mean step, linear interpolation (numpy.interp)
    between the time stamps, the values kept in their floating type; piece_starts: the first row of
    each piece after the first. A block of grid points at a time; in_place: written over t, a, g (the
    grid has at most as many points as the samples: each piece's span over the mean step, floored),
    keeping aside the original rows the grid still needs after it has written over them."""
    n = len(t)
    bounds = [0] + [int(k) + 1 for k in gaps] + [n]
    spans = [(p0, p1, float(t[p0]), int(math.floor((t[p1 - 1] - t[p0]) / mean + 1e-9)) + 1)
             for p0, p1 in zip(bounds[:-1], bounds[1:])]
    m = sum(s[3] for s in spans)
    if in_place and m > n:                       # never with the mean step of the pieces; rounding aside
        in_place = False
    if in_place:
        to, ao, go = t, a, g
    else:
        to, ao, go = np.empty(m), np.empty((m, a.shape[1]), a.dtype), np.empty((m, g.shape[1]), g.dtype)
    w = 0                                        # rows written
    s_lo, st, sa, sg = 0, t[:0].copy(), a[:0].copy(), g[:0].copy()   # original rows s_lo.. kept aside

    def search(x: float, hi: int, side: str) -> int:
        """The index of x in the original time stamps (sorted) up to row hi: those kept aside (rows s_lo
        to w, the rows the grid still needs after overwriting them), then those still in place."""
        if not in_place:
            return int(np.searchsorted(t[:hi], x, side))
        k = int(np.searchsorted(st, x, side)) if len(st) else 0
        if k < len(st):
            return s_lo + k
        return w + int(np.searchsorted(t[w:hi], x, side))

    def rows(r0: int, r1: int):
        """The original rows r0..r1-1: kept aside below w, still in place from w."""
        if not in_place or r0 >= w:
            return t[r0:r1].copy(), a[r0:r1].astype(np.float64), g[r0:r1].astype(np.float64)
        k0, k1 = r0 - s_lo, min(r1, w) - s_lo
        parts = [(st[k0:k1], sa[k0:k1], sg[k0:k1])]
        if r1 > w:
            parts.append((t[w:r1], a[w:r1], g[w:r1]))
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]).astype(np.float64),
                np.concatenate([p[2] for p in parts]).astype(np.float64))
    starts = []
    for p0, p1, t0, count in spans:
        if w:
            starts.append(w)
        for k0 in range(0, count, STEP_ROWS):
            k1 = min(count, k0 + STEP_ROWS)
            grid = t0 + np.arange(k0, k1) * mean
            lo = max(p0, search(grid[0], p1, "right") - 1)
            hi = min(p1, search(grid[-1], p1, "left") + 1)
            tp, av, gv = rows(lo, hi)
            ab = np.column_stack([np.interp(grid, tp, av[:, j]) for j in range(av.shape[1])]).astype(a.dtype, copy=False)
            gb = np.column_stack([np.interp(grid, tp, gv[:, j]) for j in range(gv.shape[1])]).astype(g.dtype, copy=False)
            del tp, av, gv
            o1 = w + len(grid)
            if in_place:   # the grid's rows lo.. are needed later: keep aside those it overwrites now
                if len(st) and s_lo < lo:                  # (the kept rows are s_lo..w-1, when any)
                    k = min(len(st), lo - s_lo)
                    st, sa, sg = st[k:], sa[k:], sg[k:]
                    s_lo += k
                r0 = max(w, lo)
                if o1 > r0:
                    if not len(st):
                        s_lo = r0
                    st, sa, sg = (np.concatenate([st, t[r0:o1]]), np.concatenate([sa, a[r0:o1]]),
                                  np.concatenate([sg, g[r0:o1]]))
            to[w:o1], ao[w:o1], go[w:o1] = grid, ab, gb
            w = o1
    return to[:m], ao[:m], go[:m], starts


def _outside(d: np.ndarray, start: int, gaps: np.ndarray) -> np.ndarray:
    """The steps of a block (step start + j) that are not gaps."""
    inside = gaps[(gaps >= start) & (gaps < start + len(d))]
    return np.delete(d, inside - start) if inside.size else d


#: samples whose values are integers in [0, 2^n) for one of these n are looked at as unsigned counts
UNSIGNED_BITS = (12, 16, 24, 32)


def unsigned_offset(x) -> tuple[int, int] | None:
    """(2^(n−1), n) when x ((n, 3) samples) holds signed counts stored unsigned: every value an
    integer in [0, 2^n), the largest 2^(n−1) or more (which no signed n-bit value is) and every
    axis's median within 60 % of 2^(n−1) of it (a signed reading's zero: a MEMS axis at rest
    reads within ±1 g of 0, and its full scale is at least ±2 g); else None."""
    v = _floats(x)
    if not v.size or v.min() < 0 or v.max() < 2 ** (UNSIGNED_BITS[0] - 1):
        return None
    if not all(np.array_equal(b, np.round(b)) for b in (v[i:i + BLOCK] for i in range(0, len(v), BLOCK))):
        return None
    n = next((b for b in UNSIGNED_BITS if v.max() < 2 ** b), None)
    if n is None or v.max() < 2 ** (n - 1):
        return None
    half = 2 ** (n - 1)
    med = _medians(v)
    return (half, n) if np.all(np.abs(med - half) <= 0.6 * half) else None


def _medians(v: np.ndarray) -> np.ndarray:
    """The median of each column (one column copied at a time)."""
    return np.array([np.median(v[:, j]) for j in range(v.shape[1])]) if v.ndim == 2 else np.median(v, axis=0)


def _offset(v: np.ndarray, declared, unit: str, what: str, flag: str, detected: list, options: dict,
            copy: bool = True) -> np.ndarray:
    """v less its offset: declared (--accel-offset / --gyro-offset, 0 for none), else 2^(n−1) when
    the values are unsigned counts (unsigned_offset), said in one line; unsigned counts under a
    physical unit are refused (the unit is wrong, and a scale cannot stand in for an offset)."""
    if declared is not None:
        if not math.isfinite(declared):
            raise RecordingError(f"--{flag}-offset must be a number of counts, got {declared}")
        return _minus(v, declared, copy) if declared else v
    found = unsigned_offset(v)
    if found is None:
        return v
    half, n = found
    med = ", ".join(f"{m:.0f}" for m in _medians(v))
    seen = f"every value an integer in 0..{2 ** n - 1}, axis medians {med}"
    if unit != "counts":
        raise RecordingError(f"the {what} holds unsigned {n}-bit counts centred on {half} ({seen}), not {unit}: "
                             f"declare --{flag}-unit counts (and --{flag}-scale or --sensor NAME for its scale); "
                             f"{half} is then subtracted (--{flag}-offset N declares another offset)")
    detected.append(f"{what}: unsigned {n}-bit counts centred on {half} ({seen}): {half} subtracted "
                    f"(--{flag}-offset {half}; --{flag}-offset 0 keeps the values as they are)")
    options[f"{flag}_offset"] = half
    return _minus(v, half, copy)


def _minus(v: np.ndarray, offset: float, copy: bool) -> np.ndarray:
    """v − offset, in place when v is the caller's to give away (copy False)."""
    if copy:
        return v - offset
    v -= offset
    return v


#: a value beyond this in any unit (m/s², g, mg, rad/s, °/s, counts of a 32-bit register) is no
#: sensor's reading
ABSURD = 1e12
#: samples looked at a time by the checks (no temporaries the size of the recording)
BLOCK = 1 << 20


def _floats(x) -> np.ndarray:
    """x as a float array: float32 and float64 kept as they are, anything else float64."""
    a = np.asarray(x)
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)


def _check_values(a: np.ndarray, g: np.ndarray) -> None:
    """Refuse samples holding a missing, non-finite or absurd value, naming the first (a block at a time)."""
    count, first = 0, None
    for i in range(0, len(a), BLOCK):
        with np.errstate(invalid="ignore"):
            bad = ~(np.isfinite(a[i:i + BLOCK]).all(axis=1) & np.isfinite(g[i:i + BLOCK]).all(axis=1))
        if bad.any():
            count += int(bad.sum())
            first = first if first is not None else i + int(np.flatnonzero(bad)[0])
    if count:
        raise RecordingError(f"{count} samples hold a missing or non-numeric value (first at sample {first}); "
                             "fix or cut the file")
    for i in range(0, len(a), BLOCK):
        big = (np.abs(a[i:i + BLOCK]) > ABSURD).any(axis=1) | (np.abs(g[i:i + BLOCK]) > ABSURD).any(axis=1)
        if big.any():
            k = i + int(np.flatnonzero(big)[0])
            v = max(np.abs(a[k]).max(), np.abs(g[k]).max())
            raise RecordingError(f"sample {k} holds {v:.3g}, beyond any sensor's range (|x| > {ABSURD:.0e}); "
                                 "fix or cut the file")


def from_arrays(accel, gyro, *, t_s=None, rate_hz: float | None = None, accel_unit_name: str = "mps2",
                gyro_unit_name: str = "rad_s", accel_counts_per_g: float | None = None,
                gyro_counts_per_dps: float | None = None, source: str = "arrays", fmt: str = "arrays",
                breaks=(), notes=(), parts=None, device: str | None = None, accel_offset: float | None = None,
                gyro_offset: float | None = None, detected=(), options: dict | None = None,
                copy: bool = True) -> Recording:
    """A Recording from arrays: time from t_s (seconds; checked by check_timing) or from
    rate_hz (uniform samples). accel_offset, gyro_offset: counts subtracted (None: 2^(n−1) when
    the values are unsigned counts, see unsigned_offset; 0: none). detected, options: what the
    reader settled (one line each) and the options that read the file again the same way. The arrays
    keep their floating type (float32 from a reader under a small memory budget, imubench.memory);
    copy=False: they are the caller's to give away (a reader's own), and an offset is subtracted in
    place."""
    a, g = _floats(accel), _floats(gyro)
    if a.ndim != 2 or a.shape[1] != 3 or g.shape != a.shape:
        raise RecordingError(f"accelerometer and gyro must be (n, 3) arrays of the same length, got "
                             f"{a.shape} and {g.shape}")
    notes = list(notes)
    au, gu = accel_unit(accel_unit_name), gyro_unit(gyro_unit_name)
    for name, v in (("--accel-scale", accel_counts_per_g), ("--gyro-scale", gyro_counts_per_dps)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise RecordingError(f"{name} must be a positive number of counts per unit, got {v}")
    brk = list(breaks)
    _check_values(a, g)
    detected, options = list(detected), dict(options or {})
    a = _offset(a, accel_offset, au, "accelerometer", "accel", detected, options, copy)
    g = _offset(g, gyro_offset, gu, "gyro", "gyro", detected, options, copy)
    timing: dict = {}
    t = None
    if t_s is not None:
        t, a, g, fs, tb, timing = check_timing(t_s, a, g, in_place=not copy)
        brk = sorted(brk + tb)
        if rate_hz:
            notes.append(f"--rate {rate_hz:g} ignored: the file has timestamps ({fs:.4g} Hz)")
    elif rate_hz:
        fs = float(rate_hz)
    else:
        raise RecordingError("no time: the file has no time column; give --rate HZ (samples per second)")
    if not (math.isfinite(fs) and fs > 0):
        raise RecordingError(f"sample rate must be positive, got {fs}")
    return Recording(accel=a, gyro=g, fs_hz=fs, accel_unit=au, gyro_unit=gu, t_s=t,
                     accel_counts_per_g=accel_counts_per_g if au == "counts" else None,
                     gyro_counts_per_dps=gyro_counts_per_dps if gu == "counts" else None,
                     source=source, fmt=fmt, breaks=brk, notes=notes, timing=timing, parts=parts,
                     device=device, detected=detected, options=options)


def read(path, fmt: str | None = None, **options) -> Recording:
    """Read a recording; fmt one of FORMATS, or None to choose by the file (its extension, its
    header). options: see imubench.recordings.readers (units, columns, rate, topic...)."""
    from imubench.recordings import readers
    return readers.read(path, fmt, **options)


# said back (recordings.restate), importable from here as before
from imubench.recordings.restate import command_line, command_options, timing_lines  # noqa: E402
