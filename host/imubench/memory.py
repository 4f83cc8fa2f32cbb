"""The memory budget of reading and analysing a recording (issues 36 and 41).

A recording is a normal input at any length the budget holds: 24 h at 200 Hz (17.3 M samples) fits
the default 1 GB. The budget decides, before anything is allocated, how the samples are held and how
they are analysed:

* storage: the six values of a sample as float64 (48 B) when that fits, else float32 (24 B: a
  relative rounding of 6e-8, far below any MEMS noise, and exact for counts up to 2^24); the time
  stamps stay float64 (8 B) either way;
* the Allan deviation: allantools in memory (a float64 copy of an axis and its temporaries,
  ALLAN_IN_MEMORY_BYTES a sample) when that fits beside the storage, else chunked sums over the phase
  (imubench.analysis.allan.oadev_chunked: one float64 column, 8 B a sample);
* the sample limit: the samples whose float32 storage, time stamps and one float64 working column
  (MIN_BYTES_PER_SAMPLE) fit beside the process itself (BASE_BYTES); a file with more is refused before
  any array is allocated, with the budget that would hold it.

No file and no port here: numbers only.
"""
from __future__ import annotations

import re

import numpy as np

#: the default budget: 1 GB (10^9 bytes)
DEFAULT_BUDGET_BYTES = 1_000_000_000
#: what the process takes before any sample: Python, numpy, allantools, matplotlib (measured: ~130 MB)
BASE_BYTES = 150_000_000
#: a float64 working column (the Allan phase, the time steps), per sample
WORK_BYTES = 8
#: float32 values of 6 axes, float64 time, one working column: the least a sample can take
MIN_BYTES_PER_SAMPLE = 6 * 4 + 8 + WORK_BYTES
#: allantools.oadev on one float64 axis in memory: the axis, its mean-free copy, the phase and the
#: temporaries of one τ (d2 - 2·d1 + d0 and its square), per sample
ALLAN_IN_MEMORY_BYTES = 7 * 8
#: the smallest budget accepted: the process itself and a little
MIN_BUDGET_BYTES = 200_000_000

#: what `calibrate --from` takes a sample at its peak (measured: 188 B on a 2 M-sample six-face CSV:
#: the float64 recording, its SI copy and the still detection's blocks); its sample limit is the
#: budget over this
CALIBRATE_BYTES_PER_SAMPLE = 200


class Budget(int):
    """A memory budget in bytes that also states what the analysis after the read takes a sample
    (per_sample, 0: no more than the storage): the sample limit is the budget over the larger."""

    def __new__(cls, value: int, per_sample: int = 0):
        b = super().__new__(cls, value)
        b.per_sample = int(per_sample)
        return b


_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9,
          "kib": 2 ** 10, "mib": 2 ** 20, "gib": 2 ** 30}


def parse_budget(text: str) -> int:
    """'1G', '800MB', '512MiB', '2e9' -> bytes; ValueError with the reason otherwise."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?(?:e[0-9]+)?)\s*([a-z]*)\s*", str(text).lower())
    if not m or m.group(2) not in _UNITS:
        raise ValueError(f"{text!r} is not a size: give e.g. 1G, 800M, 512MiB (bytes without a unit)")
    v = int(float(m.group(1)) * _UNITS[m.group(2)])
    if v < MIN_BUDGET_BYTES:
        raise ValueError(f"{text!r} is less than the {MIN_BUDGET_BYTES / 1e6:.0f} MB the process itself needs")
    return v


def text(budget_bytes: int) -> str:
    """A budget as a person reads it: 1 GB, 300 MB."""
    return f"{budget_bytes / 1e9:.3g} GB" if budget_bytes >= 1e9 else f"{budget_bytes / 1e6:.0f} MB"


def sample_limit(budget_bytes: int | None = None, values: int = 6, with_time: bool = True) -> int:
    """The most samples (of `values` float32 numbers, a float64 time stamp when with_time, one float64
    working column) a budget holds beside the process."""
    b = DEFAULT_BUDGET_BYTES if budget_bytes is None else int(budget_bytes)
    per = max(values * 4 + (8 if with_time else 0) + WORK_BYTES, getattr(budget_bytes, "per_sample", 0))
    return max(0, (b - BASE_BYTES) // per)


def storage_dtype(n: int, budget_bytes: int | None = None, values: int = 6, with_time: bool = True):
    """float64 when n samples of `values` float64 numbers (and their time and one working column) fit
    the budget, else float32; None when not even float32 fits (sample_limit)."""
    b = DEFAULT_BUDGET_BYTES if budget_bytes is None else int(budget_bytes)
    t = 8 if with_time else 0
    if BASE_BYTES + n * max(values * 8 + t + WORK_BYTES, getattr(budget_bytes, "per_sample", 0)) <= b:
        return np.float64
    if n <= sample_limit(budget_bytes, values, with_time):
        return np.float32
    return None


def allan_in_memory(n: int, held_bytes: int, budget_bytes: int | None = None) -> bool:
    """True when allantools' in-memory computation of one axis of n samples fits the budget beside the
    held_bytes the recording takes."""
    b = DEFAULT_BUDGET_BYTES if budget_bytes is None else int(budget_bytes)
    return BASE_BYTES + held_bytes + n * ALLAN_IN_MEMORY_BYTES <= b


def budget_text(budget_bytes: int | None) -> str:
    """'1 GB' for a budget, with what the analysis takes a sample when it states it (Budget)."""
    b = DEFAULT_BUDGET_BYTES if budget_bytes is None else budget_bytes
    per = getattr(b, "per_sample", 0)
    return text(int(b)) + (f" at the {per} B a sample the analysis takes" if per else "")

