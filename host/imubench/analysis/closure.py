"""The closure check of one recording: apply a calibration to raw samples exactly as the device
does, and integrate the closed path three ways (nominal scaling, calibrated, calibrated with
the gyro bias zeroed at the start rest). Pure numpy: a SampleBlock and Params in, numbers out.

The integration itself (motion window, levelling, strapdown, noise floor) is
imubench.analysis.strapdown; recording a path on a device is imubench.procedures.closure.
docs/closure.md describes the method and its numbers.
"""
from __future__ import annotations

import numpy as np

from imubench import units as U
from imubench.analysis.strapdown import (
    ClosureError,
    motion_window,
    noise_floor,
    strapdown,
)
from imubench.wire import params as PR
from imubench.wire.decoder import SampleBlock
from imubench.wire.protocol_gen import Params

G0 = U.G0_MPS2


def _temperatures(block: SampleBlock) -> tuple[np.ndarray, np.ndarray]:
    return (U.accel_temp_counts_to_c(block.accel_temp_counts, range_g=block.accel_range_g), U.gyro_temp_counts_to_c(block.gyro_temp_counts))


def corrected(block: SampleBlock, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """(accel m/s², rate rad/s) of a RAW block with params applied on the host, exactly as
    the device applies them (imubench.wire.params.correct, per-sample sensor temperatures)."""
    acc, gyr = block.si()
    ta, tg = _temperatures(block)
    a = PR.correct(PR.accel(params), acc, ta)
    return a, PR.correct(PR.gyro(params), gyr, tg, accel_mps2=a)     # the gyro's G·a, as the device


def closure_from_block(block: SampleBlock, params: Params, rest_s: float = 2.0, g_mps2: float = G0,
                       align_s: float | None = None, window: tuple[int, int] | None = None) -> dict:
    """The closure check of one raw recording: still for rest_s at the start, a closed path,
    still at the end. Integrates it over the same motion window (detected on the calibrated
    data unless given) as "before" (nominal scaling: no calibration), "after" (params applied)
    and "after_rest_bias" (params applied, and the gyro bias the calibrated gyros still show
    at the start rest removed, as navigation does at every power-up). Returns those three
    Integrations, "gyro_bias_at_rest_rad_s" (what the calibrated gyros read at rest: the bias
    change since the calibration), "window", "noise_floor", "improvement" (before / after)."""
    if block is None or block.calibrated:
        raise ClosureError("the closure check needs a RAW recording (it applies the calibration itself)")
    si = np.diff(block.sample_index)
    if len(si) and (si != 1).any():
        lost = int((si[si > 1] - 1).sum())
        raise ClosureError(f"{lost} samples were lost in the recording ({int((si != 1).sum())} gaps); "
                           "an integration across a gap is meaningless: record again (lower --rate?)")
    bad = int(np.count_nonzero(block.status))
    if bad:
        raise ClosureError(f"{bad} samples carry sensor fault bits; fix the sensors and record again")
    t = block.t_us.astype(np.float64) * 1e-6
    fs = (len(t) - 1) / (t[-1] - t[0])
    acc_b, gyr_b = block.si()
    acc_a, gyr_a = corrected(block, params)
    i0, i1 = window if window is not None else motion_window(t, acc_a, gyr_a, rest_s)
    align_n = int(round((align_s if align_s is not None else 0.8 * rest_s) * fs))
    before = strapdown(t, acc_b, gyr_b, i0, i1, align_n, g_mps2, "before calibration (nominal scaling)")
    after = strapdown(t, acc_a, gyr_a, i0, i1, align_n, g_mps2, "after calibration")
    # the gyro bias moves between power-ups and with time (bias repeatability, random walk):
    # navigation re-measures it at rest before moving; so does this third integration
    a0 = max(0, i0 - align_n + 1)
    rest_bias = gyr_a[a0:i0 + 1].mean(axis=0)
    after_zb = strapdown(t, acc_a, gyr_a - rest_bias, i0, i1, align_n, g_mps2,
                         "after, gyro bias zeroed at rest")
    rest_n = int(np.searchsorted(t, t[0] + rest_s))
    floor = noise_floor(acc_a[:rest_n], gyr_a[:rest_n], fs, t[i1] - t[i0], align_n, g_mps2)
    return {"before": before, "after": after, "after_rest_bias": after_zb,
            "gyro_bias_at_rest_rad_s": rest_bias.tolist(),
            "window": {"i0": int(i0), "i1": int(i1), "t0_s": float(t[i0]), "t1_s": float(t[i1]),
                       "duration_s": float(t[i1] - t[i0]), "fs_hz": float(fs), "samples": int(i1 - i0 + 1)},
            "noise_floor": floor,
            "improvement": before.distance_m / max(after.distance_m, 1e-12)}
