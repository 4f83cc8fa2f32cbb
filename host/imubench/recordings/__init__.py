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
scale in counts per g, or none), gyro rad/s, °/s or raw counts (counts per °/s, or none).
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
           "check_timing", "from_arrays", "read", "FORMATS"]

FORMATS = ("csv", "imutk", "imucal", "npz", "capture", "rosbag")

# canonical unit -> factor to SI (None: raw counts, needs a nominal scale or none)
ACCEL_UNITS = {"mps2": 1.0, "g": G0_MPS2, "mg": G0_MPS2 / 1000.0, "counts": None}
GYRO_UNITS = {"rad_s": 1.0, "dps": math.pi / 180.0, "counts": None}
_ACCEL_ALIASES = {"m/s2": "mps2", "m/s^2": "mps2", "m/s²": "mps2", "ms2": "mps2", "mps2": "mps2",
                  "g": "g", "mg": "mg", "counts": "counts", "raw": "counts", "lsb": "counts", "a.u.": "counts"}
_GYRO_ALIASES = {"rad/s": "rad_s", "rad_s": "rad_s", "rads": "rad_s", "deg/s": "dps", "dps": "dps",
                 "°/s": "dps", "deg_s": "dps", "counts": "counts", "raw": "counts", "lsb": "counts",
                 "a.u.": "counts"}
JITTER_RESAMPLE = 0.1        # a step off the median dt by more than this fraction: resample
GAP_FACTOR = 1.5             # a step longer than this × the median dt is a gap


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
def check_timing(t_s, accel, gyro, *, gap_factor: float = GAP_FACTOR, resample: bool = True):
    """Find and handle what is wrong with a recording's timestamps.

    Returns (t, accel, gyro, fs_hz, breaks, timing): timestamps that go backwards are refused
    (RecordingError naming the row); samples with the same timestamp as the one before are
    dropped (counted); a step longer than gap_factor × the median step (and than the median plus
    6 robust sigmas of the steps, for a jittery clock) is a gap (a break,
    with its length and the samples missing); when steps off the median by more than
    JITTER_RESAMPLE of it remain outside the gaps, each continuous piece is resampled onto a
    uniform grid at the median rate by linear interpolation (numpy.interp) — the integrals of
    the gyro assume uniform samples. timing says all of it (counts, jitter, what was done)."""
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    a = np.asarray(accel, dtype=np.float64)
    g = np.asarray(gyro, dtype=np.float64)
    if len(t) < 3:
        raise RecordingError(f"only {len(t)} samples: a calibration needs minutes of data")
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise RecordingError(f"timestamp of sample {k} is not a number; fix the file")
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        k = int(back[0])
        raise RecordingError(
            f"timestamps go backwards at sample {k + 1} (t = {t[k]:.6f} s, then {t[k + 1]:.6f} s; "
            f"{back.size} time(s) in all): the file is not in time order (merged or restarted logs?); "
            "sort it by time or cut it at the restart")
    dup = np.flatnonzero(dt == 0) + 1
    timing: dict = {"n_read": len(t), "duplicates": int(dup.size)}
    if dup.size:
        keep = np.ones(len(t), bool)
        keep[dup] = False
        same = int(sum(np.array_equal(a[i], a[i - 1]) and np.array_equal(g[i], g[i - 1]) for i in dup))
        timing["duplicates_identical"] = same
        t, a, g = t[keep], a[keep], g[keep]
        dt = np.diff(t)
    med = float(np.median(dt))
    if not med > 0:
        raise RecordingError("the timestamps do not advance (median step 0); check the time column and its unit")
    fs = 1.0 / med
    mad = 1.4826 * float(np.median(np.abs(dt - med)))
    gap_dt = max(gap_factor * med, med + 6.0 * mad)       # jittery clocks: beyond their own spread
    gaps = np.flatnonzero(dt > gap_dt)
    inside = np.ones(len(dt), bool)
    inside[gaps] = False
    dev = np.abs(dt[inside] - med) / med if inside.any() else np.zeros(1)
    jitter = float(np.std(dt[inside]) / med) if inside.any() else 0.0
    timing.update({"median_dt_s": med, "fs_hz": fs, "jitter_rel": jitter,
                   "max_step_dev_rel": float(dev.max()) if dev.size else 0.0,
                   "gaps": [{"index": int(k + 1), "t_s": float(t[k]), "duration_s": float(dt[k]),
                             "missing": int(round(dt[k] / med)) - 1} for k in gaps]})
    breaks = [(int(k + 1), f"gap of {dt[k]:.3f} s ({int(round(dt[k] / med)) - 1} samples missing) at t = {t[k]:.3f} s")
              for k in gaps]
    timing["resampled"] = False
    if resample and dev.size and dev.max() > JITTER_RESAMPLE:
        pieces = np.split(np.arange(len(t)), gaps + 1)
        ts, As, Gs, nb = [], [], [], []
        n0 = 0
        for p in pieces:
            tp = t[p]
            grid = tp[0] + np.arange(int(math.floor((tp[-1] - tp[0]) / med + 1e-9)) + 1) * med
            ts.append(grid)
            As.append(np.column_stack([np.interp(grid, tp, a[p, j]) for j in range(3)]))
            Gs.append(np.column_stack([np.interp(grid, tp, g[p, j]) for j in range(3)]))
            if n0:
                nb.append(n0)
            n0 += len(grid)
        t, a, g = np.concatenate(ts), np.concatenate(As), np.concatenate(Gs)
        breaks = [(i, r) for i, (_, r) in zip(nb, breaks)]
        timing["resampled"] = True
    timing["n_used"] = len(t)
    return t, a, g, fs, breaks, timing


def timing_lines(rec: Recording) -> list[str]:
    """What the timing check found and did, for a person."""
    tm = rec.timing or {}
    out = []
    if not tm:
        return [f"{len(rec)} samples at {rec.fs_hz:g} Hz (declared rate; no timestamps to check)"]
    out.append(f"{tm['n_read']} samples, median step {tm['median_dt_s'] * 1e3:.4g} ms ({tm['fs_hz']:.4g} Hz), "
               f"step jitter {100 * tm['jitter_rel']:.2g} % (largest {100 * tm['max_step_dev_rel']:.2g} % off)")
    if tm.get("duplicates"):
        out.append(f"{tm['duplicates']} samples repeat the timestamp before them "
                   f"({tm.get('duplicates_identical', 0)} identical rows): dropped")
    for gp in tm.get("gaps", [])[:10]:
        out.append(f"gap of {gp['duration_s']:.3f} s at t = {gp['t_s']:.3f} s ({gp['missing']} samples missing): "
                   "a still interval may continue across it; a turn or motion across it is not used for the gyro")
    if len(tm.get("gaps", [])) > 10:
        out.append(f"… {len(tm['gaps']) - 10} more gaps")
    if tm.get("resampled"):
        out.append(f"irregular steps: each continuous piece was resampled to a uniform {tm['fs_hz']:.4g} Hz grid "
                   f"(linear interpolation), {tm['n_used']} samples")
    return out


def from_arrays(accel, gyro, *, t_s=None, rate_hz: float | None = None, accel_unit_name: str = "mps2",
                gyro_unit_name: str = "rad_s", accel_counts_per_g: float | None = None,
                gyro_counts_per_dps: float | None = None, source: str = "arrays", fmt: str = "arrays",
                breaks=(), notes=(), parts=None, device: str | None = None) -> Recording:
    """A Recording from arrays: time from t_s (seconds; checked by check_timing) or from
    rate_hz (uniform samples)."""
    a = np.asarray(accel, dtype=np.float64)
    g = np.asarray(gyro, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or g.shape != a.shape:
        raise RecordingError(f"accelerometer and gyro must be (n, 3) arrays of the same length, got "
                             f"{a.shape} and {g.shape}")
    bad = ~(np.isfinite(a).all(axis=1) & np.isfinite(g).all(axis=1))
    notes = list(notes)
    au, gu = accel_unit(accel_unit_name), gyro_unit(gyro_unit_name)
    for name, v in (("--accel-scale", accel_counts_per_g), ("--gyro-scale", gyro_counts_per_dps)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise RecordingError(f"{name} must be a positive number of counts per unit, got {v}")
    brk = list(breaks)
    if bad.any():
        raise RecordingError(f"{int(bad.sum())} samples hold a missing or non-numeric value (first at sample "
                             f"{int(np.flatnonzero(bad)[0])}); fix or cut the file")
    timing: dict = {}
    t = None
    if t_s is not None:
        t, a, g, fs, tb, timing = check_timing(t_s, a, g)
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
                     device=device)


def read(path, fmt: str | None = None, **options) -> Recording:
    """Read a recording; fmt one of FORMATS, or None to choose by the file (its extension, its
    header). options: see imubench.recordings.readers (units, columns, rate, topic...)."""
    from imubench.recordings import readers
    return readers.read(path, fmt, **options)
