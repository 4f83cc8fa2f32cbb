"""Nominal scaling from raw counts to SI, exactly as docs/conventions.md states it.

These are the datasheet scale factors; calibration (imubench.wire.params) corrects what they
get wrong for a particular part.
"""
from __future__ import annotations

import numpy as np

from imubench.parts_gen import PART_BY_ID, PARTS, PartSpec

G0_MPS2 = 9.80665                       # standard gravity, the product's one value of g
DEG = np.pi / 180.0

# Every accelerometer part's full scales (protocol/parts.toml) are distinct (ADXL355 2/4/8 g,
# ADXL359 10/20/40 g), so a batch's accel_range_g names its sensitivity on its own.
ACCEL_LSB_PER_G = {r.full_scale: r.lsb_per_unit for p in PARTS.values() if p.kind == "accel_triad" for r in p.ranges}
assert len(ACCEL_LSB_PER_G) == sum(len(p.ranges) for p in PARTS.values() if p.kind == "accel_triad"), \
    "two accelerometer parts share a full scale: the range no longer names the sensitivity"
DEFAULT_ACCEL = PARTS["adxl355"]
DEFAULT_GYRO = PARTS["adxrs450"]
GYRO_LSB_PER_DPS = DEFAULT_GYRO.lsb_per_unit()


def part(p) -> PartSpec:
    """A part from its PartSpec, its wire id (info.parts) or its name (any case)."""
    if isinstance(p, PartSpec):
        return p
    if isinstance(p, str):
        try:
            return PARTS[p.lower()]
        except KeyError:
            raise ValueError(f"unknown part {p!r} (known: {', '.join(q.name for q in PARTS.values())})") from None
    try:
        return PART_BY_ID[int(p)]
    except KeyError:
        raise ValueError(f"unknown part id {p}") from None


def accel_counts_to_mps2(counts, range_g) -> np.ndarray:
    """Accelerometer counts (any shape, last axis x/y/z) at range ±range_g to m/s²; range_g may
    be a scalar or an array broadcastable against counts[..., 0]. The sensitivity is the part's
    (protocol/parts.toml) whose range that is; a range no part has is an error, never scaled as
    some other range (the decoder lets no other range through)."""
    r = np.asarray(range_g)
    known = np.isin(r, list(ACCEL_LSB_PER_G))
    if not np.all(known):
        raise ValueError(f"accel_range_g {np.unique(r[~known] if np.ndim(r) else r).tolist()} is no range of "
                         f"an accelerometer part ({', '.join(str(g) for g in sorted(ACCEL_LSB_PER_G))} g)")
    lsb = np.vectorize(ACCEL_LSB_PER_G.__getitem__, otypes=[np.float64])(r) if np.ndim(r) else ACCEL_LSB_PER_G[int(r)]
    if np.ndim(lsb):
        lsb = lsb[..., None]
    return np.asarray(counts, dtype=np.float64) * (G0_MPS2 / lsb)


def gyro_counts_to_rad_s(counts, gyro_part=DEFAULT_GYRO) -> np.ndarray:
    """Gyro rate counts to rad/s at the part's scale (ADXRS450, ADXRS453: 80 LSB per °/s)."""
    return np.asarray(counts, dtype=np.float64) * (DEG / part(gyro_part).lsb_per_unit())


ACCEL_PART_OF_RANGE = {r.full_scale: p for p in PARTS.values() if p.kind == "accel_triad" for r in p.ranges}


def accel_temp_counts_to_c(counts, accel_part=DEFAULT_ACCEL, range_g=None) -> np.ndarray:
    """Accelerometer 12-bit temperature (ADXL355: 1885 LSB at 25 °C, ADXL359: 1852; −9.05 LSB/°C).
    With range_g (a batch's accel_range_g, scalar or per element of counts) the part is the one
    that range belongs to: a block carries its part that way."""
    c = np.asarray(counts, dtype=np.float64)
    if range_g is None:
        p = part(accel_part)
        return p.temp_ref_c + (c - p.temp_offset_counts) / p.temp_lsb_per_c
    r = np.broadcast_to(np.asarray(range_g), c.shape)
    off = np.vectorize(lambda g: ACCEL_PART_OF_RANGE[int(g)].temp_offset_counts, otypes=[np.float64])(r)
    p = DEFAULT_ACCEL   # every accelerometer part: 25 °C reference, −9.05 LSB/°C (asserted below)
    return p.temp_ref_c + (c - off) / p.temp_lsb_per_c


assert len({(p.temp_ref_c, p.temp_lsb_per_c) for p in ACCEL_PART_OF_RANGE.values()}) == 1


def gyro_temp_counts_to_c(raw10, gyro_part=DEFAULT_GYRO) -> np.ndarray:
    """Gyro temperature: signed 10-bit TEM >> 6, 5 LSB/°C, 0 at 45 °C (ADXRS450, ADXRS453)."""
    p = part(gyro_part)
    return p.temp_ref_c + (np.asarray(raw10, dtype=np.float64) - p.temp_offset_counts) / p.temp_lsb_per_c


def mps2_to_mg(x) -> np.ndarray:
    return np.asarray(x) / G0_MPS2 * 1000.0


def rad_s_to_dps(x) -> np.ndarray:
    return np.asarray(x) / DEG
