"""calib.clipping: samples held at full scale, found in the data or at a declared range."""
from __future__ import annotations

import numpy as np

from imubench.calib.clipping import find_clipping, runs_in


def test_a_plateau_at_the_extreme_is_a_clip_a_peak_is_not():
    """calib.clipping: a plateau at the extreme is a clip; a noisy or a slow, rounded peak is not."""
    rng = np.random.default_rng(4)
    t = np.arange(400) / 100.0
    peak = 300.0 * np.exp(-((t - 2.0) / 0.3) ** 2)
    x = np.column_stack([peak, np.zeros_like(t), np.zeros_like(t)]) + rng.normal(0, 0.05, (400, 3))
    assert find_clipping(x, min_level=100.0) == []                       # noisy, unclipped
    runs = find_clipping(np.clip(x, -250.0, 250.0), min_level=100.0)
    assert [(r.axis_name, r.level, r.source) for r in runs] == [("X", 250.0, "data")] and runs[0].n > 10
    slow = np.round(x * [0.4, 1, 1], 1)                                 # a slow 120 °/s peak written to 0.1 °/s
    assert find_clipping(slow, min_level=100.0) == []
    declared = find_clipping(x, declared=200.0)
    assert declared and all(r.source == "declared" and r.level == 200.0 for r in declared[:1])


def test_a_declared_range_marks_every_sample_at_it_and_runs_in_finds_them_by_window():
    x = np.zeros((100, 3))
    x[40:43, 1] = -250.2                  # a full scale is nominal: ±250 °/s reads 250.1
    x[70, 2] = 248.0                      # within 1 % of the range: at it
    x[80, 2] = 240.0                      # below: not
    runs = find_clipping(x, declared=250.0)
    assert [(r.axis_name, r.start, r.stop, r.level) for r in runs] == [("Y", 40, 43, -250.0), ("Z", 70, 71, 250.0)]
    assert runs_in(runs, 0, 41) == runs[:1] and runs_in(runs, 43, 70) == [] and runs_in(runs, 60, 100) == runs[1:]


def test_a_noise_free_series_is_not_taken_for_clipping():
    """A simulation without noise holds values for other reasons: only a plateau that the other
    axes' noise runs through counts."""
    x = np.zeros((300, 3))
    x[100:200, 0] = np.minimum(300.0 * np.sin(np.linspace(0, np.pi, 100)), 250.0)   # a turn held at 250
    assert find_clipping(x, min_level=100.0) == []
    x[:, 1:] = np.random.default_rng(0).normal(0, 0.05, (300, 2))
    (r,) = find_clipping(x, min_level=100.0)
    assert r.axis_name == "X" and r.level == 250.0 and r.source == "data" and 100 < r.start < r.stop < 200
