"""Nominal scaling from raw counts to SI, exactly as docs/conventions.md states it.

These are the datasheet scale factors; calibration (imubench.wire.params) corrects what they
get wrong for a particular part.
"""
from __future__ import annotations

import numpy as np

G0_MPS2 = 9.80665                       # standard gravity, the product's one value of g
ACCEL_LSB_PER_G = {2: 256000.0, 4: 128000.0, 8: 64000.0}
GYRO_LSB_PER_DPS = 80.0
DEG = np.pi / 180.0


def accel_counts_to_mps2(counts, range_g) -> np.ndarray:
    """ADXL355 counts (any shape, last axis x/y/z) at range ±range_g to m/s²; range_g may be
    a scalar or an array broadcastable against counts[..., 0]. A range other than 2, 4 or 8 g is
    an error, never scaled as some other range (the decoder lets no other range through)."""
    r = np.asarray(range_g)
    known = (r == 2) | (r == 4) | (r == 8)
    if not np.all(known):
        raise ValueError(f"accel_range_g {np.unique(r[~known] if np.ndim(r) else r).tolist()} is not 2, 4 or 8 g")
    lsb = np.where(r == 8, 64000.0, np.where(r == 4, 128000.0, 256000.0))
    if np.ndim(lsb):
        lsb = lsb[..., None]
    return np.asarray(counts, dtype=np.float64) * (G0_MPS2 / lsb)


def gyro_counts_to_rad_s(counts) -> np.ndarray:
    """ADXRS450 rate counts to rad/s (80 LSB per °/s)."""
    return np.asarray(counts, dtype=np.float64) * (DEG / GYRO_LSB_PER_DPS)


def accel_temp_counts_to_c(counts) -> np.ndarray:
    """ADXL355 12-bit temperature: 1885 LSB at 25 °C, −9.05 LSB/°C."""
    return 25.0 + (np.asarray(counts, dtype=np.float64) - 1885.0) / -9.05


def gyro_temp_counts_to_c(raw10) -> np.ndarray:
    """ADXRS450 temperature: signed 10-bit TEM >> 6, 5 LSB/°C, 0 at 45 °C."""
    return 45.0 + np.asarray(raw10, dtype=np.float64) / 5.0


def mps2_to_mg(x) -> np.ndarray:
    return np.asarray(x) / G0_MPS2 * 1000.0


def rad_s_to_dps(x) -> np.ndarray:
    return np.asarray(x) / DEG
