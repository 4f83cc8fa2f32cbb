"""What a recording's own numbers say about what was declared for it, and how its segmentation
compares with a hand annotation (procedures.from_file, procedures.allan).

A declared unit is used; these checks refuse only when the data leave no doubt (|a| at rest far
from 1 g, a gyro at rest beyond any MEMS bias) and otherwise warn with their numbers, never
from motions whose angle is unknown (issue 26; docs/calibration.md, "Any IMU, from a recording").
"""
from __future__ import annotations

import math

import numpy as np

from imubench import units as U
from imubench.recordings import Recording, RecordingError

ACCEL_PLAUSIBLE_G = (0.8, 1.25)          # still |a| in the declared unit, in g
GYRO_REST_MAX_DPS = 20.0                 # a MEMS gyro's bias (zero-rate output) stays below this (MPU-6050: ±20 °/s)
GYRO_REST_REFUSE_DPS = 60.0              # 3× that at rest leaves no doubt: the declared unit is wrong


# ------------------------------------------------------------------ units
def _unit(rec: Recording, k: int) -> str:
    """The declared unit of the accelerometer (k = 0) or gyro (k = 1), as said to a person."""
    return rec.unit_text().split(", ")[k].split(" ", 1)[1]


def check_accel_unit(rec: Recording, still_norm: np.ndarray) -> None:
    """Refuse a declared accelerometer unit the still intervals contradict (|a| far from 1 g)."""
    f = rec.accel_factor()
    if f is None:
        return
    g_read = still_norm * f / U.G0_MPS2
    med = float(np.median(g_read))
    lo, hi = ACCEL_PLAUSIBLE_G
    if lo <= med <= hi:
        return
    raw = float(np.median(still_norm))
    factors = {"mps2": 1.0, "g": U.G0_MPS2, "mg": U.G0_MPS2 / 1000}
    fits = [name for name, fac in factors.items() if lo <= raw * fac / U.G0_MPS2 <= hi]
    hint = (f"read as {fits[0]} they would be {raw * factors[fits[0]] / U.G0_MPS2:.4f} g: "
            f"declare --accel-unit {fits[0]}" if fits else
            f"if these are raw counts, declare --accel-unit counts (and --accel-scale {raw:.0f} counts per g, "
            "or the datasheet's)")
    raise RecordingError(
        f"the declared accelerometer unit ({_unit(rec, 0)}) is implausible: the "
        f"{len(still_norm)} still intervals read |a| = {raw:.6g} in the file (median; range "
        f"{still_norm.min():.6g} … {still_norm.max():.6g}), i.e. {med:.4g} g, far from 1 g; {hint}")


def check_gyro_unit(rec: Recording, rest_rate: np.ndarray, factor: float) -> str | None:
    """A declared gyro unit under which a board at rest would turn: RecordingError when no MEMS
    gyro's bias comes near (≥ GYRO_REST_REFUSE_DPS), a warning (returned) when it is only
    unusual (≥ GYRO_REST_MAX_DPS); None when plausible."""
    dps = float(np.max(np.abs(rest_rate))) * factor * 180.0 / math.pi
    if dps <= GYRO_REST_MAX_DPS:
        return None
    raw = float(np.max(np.abs(rest_rate)))
    hint = ("the data look like °/s: declare --gyro-unit dps" if rec.gyro_unit == "rad_s" and raw < GYRO_REST_MAX_DPS
            else "if these are raw counts, declare --gyro-unit counts (with --gyro-scale COUNTS_PER_DPS if known)")
    text = (f"the declared gyro unit ({_unit(rec, 1)}) is doubtful: at rest (the longest still interval) the gyro "
            f"reads up to {raw:.4g} in the file, i.e. {dps:.4g} °/s")
    if dps >= GYRO_REST_REFUSE_DPS:
        raise RecordingError(f"{text}, beyond {GYRO_REST_REFUSE_DPS:g} °/s, 3× the largest bias MEMS data sheets "
                             f"allow (±{GYRO_REST_MAX_DPS:g} °/s): the unit is wrong; {hint}")
    return (f"{text}, more than a MEMS gyro's bias usually is ({GYRO_REST_MAX_DPS:g} °/s) but possible: the declared "
            f"unit is used; {hint} if that is wrong")


# ------------------------------------------------------------------ segmentation vs annotation
_ANNOT_FACE = {"x_p": "+X", "x_a": "-X", "y_p": "+Y", "y_a": "-Y", "z_p": "+Z", "z_a": "-Z"}


def compare_annotation(parts, intervals, faces, turns, fs_hz: float) -> list[dict]:
    """For each annotated section (imucal's names x_p ... z_a, x_rot ... z_rot), the detected
    still interval (same face, largest overlap) or turn that matches it and the differences of
    their ends in seconds; sections with nothing detected are listed with found False."""
    out = []
    for name, s, e in parts:
        row = {"section": name, "start": s, "stop": e, "found": False}
        if name in _ANNOT_FACE:
            cands = [(min(e, iv.stop) - max(s, iv.start), i) for i, iv in enumerate(intervals)
                     if faces[i] == _ANNOT_FACE[name]]
            cands = [c for c in cands if c[0] > 0]
            if cands:
                _, i = max(cands)
                iv = intervals[i]
                row.update(found=True, kind="rest", detected=[iv.start, iv.stop],
                           start_diff_s=(iv.start - s) / fs_hz, stop_diff_s=(iv.stop - e) / fs_hz,
                           face=faces[i], annotated_inside_detected=iv.start <= s and e <= iv.stop)
        elif name.endswith("_rot"):
            axis = name[0].upper()
            cands = [(min(e, t.stop) - max(s, t.start), i) for i, t in enumerate(turns)
                     if t.label.endswith(axis)]
            cands = [c for c in cands if c[0] > 0]
            if cands:
                _, i = max(cands)
                t = turns[i]
                row.update(found=True, kind="turn", detected=[t.start, t.stop],
                           start_diff_s=(t.start - s) / fs_hz, stop_diff_s=(t.stop - e) / fs_hz,
                           annotated_inside_detected=t.start <= s and e <= t.stop)
        out.append(row)
    return out
