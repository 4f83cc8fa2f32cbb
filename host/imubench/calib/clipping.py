"""Clipping: samples a sensor held at its full scale, found in the data.

A MEMS gyro turned faster than its range reports its full-scale value for as long as the rate
stays beyond it: the series shows a plateau, several consecutive samples at one value, at the
extreme of the axis's values. The integral over such a motion misses the rotation beyond full
scale, so the motion cannot feed a gyro fit. An accelerometer rest at full scale (a range set
too small, an offset) reads the clip level instead of its specific force.

    find_clipping(x, declared=..., ...)     the runs of clipped samples, per axis and sign
    runs_in(runs, start, stop)              the runs that touch samples start..stop-1

How a plateau is found (docs/calibration.md, "Clipping"):

* declared range R (e.g. --gyro-range): every sample with |x| ≥ (1 − DECLARED_REL) · R is
  clipped (the user named the level; one sample at it is enough);
* from the data alone, per axis and sign: the extreme value E of the axis (its max, its min) is
  a clip level when at least MIN_RUN consecutive samples lie within a quantum of E (the step
  between the axis's distinct values near E: one count of a raw series, the rounding of a text
  file), E is far from the axis's median (at least a quarter of the axis's span), |E| is at least
  min_level (for a gyro, 100 °/s: no MEMS gyro has a range below ±125 °/s, so a slow hand's
  rounded peak is not mistaken for a clip), the values pile up at E (more samples at E than at
  the next value inward: the tail of noise thins out towards its extreme, a clip collects it)
  and the other axes are not constant over the run (a noise-free simulation repeats values
  for other reasons). Noise makes equal consecutive values at an unclipped peak improbable; a
  saturated converter repeats its code exactly.

Everything here is numpy on arrays in the caller's unit; nothing touches a file or a port.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ClipRun", "find_clipping", "runs_in", "MIN_RUN", "DECLARED_REL"]

MIN_RUN = 3              # consecutive samples at the extreme that make a plateau
DECLARED_REL = 0.01      # a declared range is reached within 1 % (full scales are nominal: ±250 °/s is 250.1)
_AXES = "XYZ"


@dataclass(frozen=True)
class ClipRun:
    """Samples start..stop-1 of one axis held at the clip level."""
    axis: int               # 0, 1, 2 (X, Y, Z)
    start: int
    stop: int               # exclusive
    level: float            # the clip level, signed, in the data's unit
    source: str             # "declared" (at the given range) or "data" (a plateau at the extreme)

    @property
    def n(self) -> int:
        return self.stop - self.start

    @property
    def axis_name(self) -> str:
        return _AXES[self.axis]


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _quantum(x: np.ndarray, extreme: float) -> float:
    """The step between distinct values next to the extreme (the series' resolution there),
    never below a relative 1e-9 of |extreme| (floats written by a program)."""
    near = np.unique(x[np.abs(x - extreme) <= 0.05 * max(abs(extreme), 1e-300)])
    steps = np.diff(near)
    steps = steps[steps > 0]
    q = float(steps.min()) if steps.size else 0.0
    return max(q * 0.5, 1e-9 * abs(extreme))


def find_clipping(x, *, declared: float | None = None, min_level: float = 0.0,
                  min_run: int = MIN_RUN) -> list[ClipRun]:
    """The clipped runs of an (n, 3) series, in time order.

    declared: the sensor's range (same unit as x), when known; samples at or beyond it
    (within DECLARED_REL) are clipped. Without it, a plateau of at least min_run consecutive
    samples at an axis's extreme value, with |value| ≥ min_level and at least a quarter of the axis's
    span away from its median, is a clip (module docstring). Both are applied when declared
    is given (a sensor that clips below its nominal range is still found)."""
    u = np.asarray(x, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3:
        raise ValueError(f"expected samples of shape (n, 3), got {u.shape}")
    out: list[ClipRun] = []
    for k in range(3):
        col = u[:, k]
        if not len(col):
            continue
        found = np.zeros(len(col), bool)
        if declared is not None and declared > 0:
            level = (1.0 - DECLARED_REL) * float(declared)
            for sign in (1.0, -1.0):
                for s, e in _runs(sign * col >= level):
                    out.append(ClipRun(k, s, e, sign * float(declared), "declared"))
                    found[s:e] = True
        med = float(np.median(col))
        span = float(col.max() - col.min())
        for ext in (float(col.max()), float(col.min())):
            if abs(ext - med) < 0.25 * span or abs(ext) < min_level or span == 0.0:
                continue
            q = _quantum(col, ext)
            at = np.abs(col - ext) <= q
            inward = col[~at] if ext > med else -col[~at]
            nxt = inward.max() if inward.size else None
            n_next = int(np.sum(np.abs((col if ext > med else -col) - nxt) <= q)) if nxt is not None else 0
            if int(at.sum()) <= n_next:
                continue
            others = [j for j in range(3) if j != k]
            for s, e in _runs(at):
                if e - s >= min_run and not found[s:e].all() and np.ptp(u[s:e][:, others], axis=0).max() > 0:
                    out.append(ClipRun(k, s, e, ext, "data"))
    out.sort(key=lambda r: (r.start, r.axis))
    return out


def runs_in(runs, start: int, stop: int) -> list[ClipRun]:
    """The runs that overlap samples start..stop-1."""
    return [r for r in runs if r.start < stop and r.stop > start]
