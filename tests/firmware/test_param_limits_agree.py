"""Host and device agree on every parameter block: the host's `wire.params.validate` and the
device's `ib_core_check_params` (core.c, built for the host as tests/c/param_check_harness)
are fed the same thousands of blocks (random ones, every limit at, just inside and just outside
its value, singular, ill-conditioned, enormous and tiny matrices, NaN and ±Inf in every
field) and must give the same verdict and the same error code for each."""
from __future__ import annotations

import struct
import subprocess

import numpy as np
import pytest
from conftest import HOST_BUILD, make
from imubench.wire import params as PR
from imubench.wire.protocol_gen import LIMITS, LIMITS_F32, Error, Params

F32 = np.float32
# slots in Params.values(): the matrices, the vectors, the two t_ref, G, the polynomial, the spans
ACCEL_M, ACCEL_B, GYRO_M, GYRO_B = range(0, 9), range(9, 12), range(12, 21), range(21, 24)
A_BTC, A_STC, G_BTC, G_STC = range(24, 27), range(27, 30), range(30, 33), range(33, 36)
T_REF = (36, 37)
GYRO_G = range(40, 49)          # layout 2: after cal_time_unix_s and cal_id
A_C2, A_C3, G_C2, G_C3 = range(49, 52), range(52, 55), range(55, 58), range(58, 61)   # layout 3
A_TMIN, A_TMAX, G_TMIN, G_TMAX = 61, 62, 63, 64                                        # int8, °C
FLOATS = list(range(38)) + list(range(40, 61))
POLY = ((A_C2, "accel_bias_tc2_max_mps2_per_c2"), (A_C3, "accel_bias_tc3_max_mps2_per_c3"),
        (G_C2, "gyro_bias_tc2_max_rad_s_per_c2"), (G_C3, "gyro_bias_tc3_max_rad_s_per_c3"))


@pytest.fixture(scope="module")
def harness():
    make("c-tests")
    return HOST_BUILD / "tests" / "param_check_harness"


def _base() -> list:
    return list(PR.identity().values())


def _f32(x: float) -> float:
    return float(F32(x))


def _up(x: float) -> float:      # the next float32 above / below
    return float(np.nextafter(F32(x), F32(np.inf)))


def _down(x: float) -> float:
    return float(np.nextafter(F32(x), F32(-np.inf)))


def _edges(limit: float) -> list[float]:
    """A limit (as float32), and just inside and outside it, on both signs."""
    v = LIMITS_F32[limit]
    return [s * x for s in (1.0, -1.0) for x in (v, _up(v), _down(v), LIMITS[limit])]


def _blocks() -> list[list]:
    rng = np.random.default_rng(20240611)
    out = []

    def one(**changes):
        v = _base()
        for slot, x in changes.items():
            v[int(slot[1:])] = x
        out.append(v)

    # every limit: at, just inside and just outside, both signs, in every slot it governs
    for m in (ACCEL_M, GYRO_M):
        for k, slot in enumerate(m):
            if k % 4 == 0:
                for x in _edges("m_diag_min") + _edges("m_diag_max"):
                    one(**{f"s{slot}": x})
            else:
                for x in _edges("m_offdiag_max"):
                    one(**{f"s{slot}": x})
    for slots, lim in ((ACCEL_B, "accel_bias_max_mps2"), (GYRO_B, "gyro_bias_max_rad_s"),
                       (A_BTC, "accel_bias_tc_max_mps2_per_c"), (G_BTC, "gyro_bias_tc_max_rad_s_per_c"),
                       (A_STC, "scale_tc_max_per_c"), (G_STC, "scale_tc_max_per_c")):
        for slot in slots:
            for x in _edges(lim):
                one(**{f"s{slot}": x})
    for slot in T_REF:
        for lim in ("t_ref_min_c", "t_ref_max_c"):
            v = LIMITS_F32[lim]
            for x in (v, _up(v), _down(v), LIMITS[lim]):
                one(**{f"s{slot}": x})
    # layout 3: c2, c3 at their limits (span narrowed so that the excursion bound stays inside),
    # the spans around the parts' ranges, empty, reversed, t_ref at and beyond their ends
    for slots, lim in POLY:
        for slot in slots:
            for x in _edges(lim):
                one(**{f"s{slot}": x, "s61": 20, "s62": 30, "s63": 20, "s64": 30})
    for lo_slot, hi_slot, top in ((A_TMIN, A_TMAX, 125), (G_TMIN, G_TMAX, 105)):
        for lo in (-128, -41, -40, -39, 0, 24, 25, 26, 84, 85, 127):
            for hi in (-40, 24, 25, 26, 85, top - 1, top, top + 1, 127):
                one(**{f"s{lo_slot}": lo, f"s{hi_slot}": hi})
        for t_ref in (-40.0, _down(-40.0), _up(-40.0), 10.0, _down(10.0), _up(10.0), 20.0, _up(20.0)):
            one(**{f"s{lo_slot}": 10, f"s{hi_slot}": 20, f"s{36 if lo_slot == A_TMIN else 37}": t_ref})
    # the excursion bound D·(|c1| + D·(|c2| + D·|c3|)) at the bias limit, each order alone, at,
    # just inside and just outside: t_ref at the span's lower end -40, so D = the span's width
    for (c1s, bmax), (c2s, _), (c3s, _) in (((A_BTC, "accel_bias_max_mps2"), POLY[0], POLY[1]),
                                            ((G_BTC, "gyro_bias_max_rad_s"), POLY[2], POLY[3])):
        lo_slot, hi_slot, ref_slot = (A_TMIN, A_TMAX, 36) if c1s is A_BTC else (G_TMIN, G_TMAX, 37)
        b = F32(LIMITS_F32[bmax])
        for order, slots in ((1, c1s), (2, c2s), (3, c3s)):
            for d in (60, 100, 140):
                c = b / F32(d) ** order
                for x in (c, np.nextafter(c, F32(np.inf)), np.nextafter(c, F32(0)), -c):
                    one(**{f"s{slots[order - 1]}": float(x), f"s{lo_slot}": -40, f"s{hi_slot}": -40 + d,
                           f"s{ref_slot}": -40.0})
    # NaN, ±Inf, huge, tiny, subnormal, -0 in every float field
    for slot in FLOATS:
        for x in (float("nan"), float("inf"), -float("inf"), 3.4e38, -3.4e38, 1e30, 1e-30, 1e-45, -0.0, 1e39):
            one(**{f"s{slot}": x})
    # matrices: singular, nearly singular around m_det_min, ill-conditioned around m_cond_max, huge
    for m in (ACCEL_M, GYRO_M):
        mats = [np.zeros(9), np.ones(9), np.array([1, 0, 0, 1, 0, 0, 0, 0, 1.0]),
                np.array([1, 0, 0, 0, 1, 0, 0, 0, 0.0]), np.full(9, 1e20), np.full(9, 1e-20),
                np.eye(3).ravel() * 1e19, np.eye(3).ravel() * 3e38, np.eye(3).ravel() * 1e-3,
                np.array([0.5, -0.19, -0.19, -0.19, 0.5, -0.19, -0.19, -0.19, 0.5]),
                np.array([1.5, 0.2, 0.2, 0.2, 0.5, 0.2, 0.2, 0.2, 1.5]),
                np.array([0.5, 0.2, -0.2, 0.2, 0.5, 0.2, -0.2, 0.2, 0.5])]
        for d in np.geomspace(1e-7, 1e-5, 40):      # determinant crossing m_det_min
            mats.append(np.diag([1.0, 1.0, d]).ravel())
            mats.append(np.diag([d ** (1 / 3)] * 3).ravel())
        # conditioning near 6: diag(1, 1, s) has ||M||·||M⁻¹|| = sqrt((2 + s²)(2 + 1/s²))
        for s in np.linspace(0.30, 0.40, 200):
            mats.append(np.diag([1.0, 1.0, s]).ravel())
        for t in np.linspace(0.17, 0.2, 60):         # off-diagonals pushing the condition up
            mats.append(np.array([0.5, t, t, t, 0.5, t, t, t, 0.5]))
            mats.append(np.array([0.55, -t, t, -t, 0.55, -t, t, -t, 0.55]))
        for mat in mats:
            v = _base()
            for k, slot in enumerate(m):
                v[slot] = float(mat[k])
            out.append(v)
    # random blocks: every field drawn around its limits (about half the blocks valid per field)
    for _ in range(8000):
        v = _base()
        for m in (ACCEL_M, GYRO_M):
            for k, slot in enumerate(m):
                v[slot] = float(rng.uniform(0.45, 1.55) if k % 4 == 0 else rng.uniform(-0.22, 0.22))
        for slots, lim in ((ACCEL_B, "accel_bias_max_mps2"), (GYRO_B, "gyro_bias_max_rad_s"),
                           (A_BTC, "accel_bias_tc_max_mps2_per_c"), (G_BTC, "gyro_bias_tc_max_rad_s_per_c"),
                           (A_STC, "scale_tc_max_per_c"), (G_STC, "scale_tc_max_per_c")):
            for slot in slots:
                v[slot] = float(rng.uniform(-1.02, 1.02) * LIMITS[lim]) if rng.random() < 0.3 else 0.0
        for slot in T_REF:
            v[slot] = float(rng.uniform(-45, 130)) if rng.random() < 0.2 else 25.0
        for slot in GYRO_G:
            lim = LIMITS["gyro_g_max_rad_s_per_mps2"]
            v[slot] = float(rng.uniform(-1.02, 1.02) * lim) if rng.random() < 0.1 else 0.0
            if rng.random() < 0.002:
                v[slot] = float(rng.choice([float("nan"), float("inf"), lim, -lim]))
        for slots, lim in POLY:
            for slot in slots:
                v[slot] = float(rng.uniform(-1.02, 1.02) * LIMITS[lim]) if rng.random() < 0.1 else 0.0
        for lo_slot, hi_slot in ((A_TMIN, A_TMAX), (G_TMIN, G_TMAX)):
            if rng.random() < 0.5:
                lo = int(rng.integers(-45, 60))
                v[lo_slot], v[hi_slot] = lo, int(np.clip(lo + rng.integers(-5, 80), -128, 127))
        if rng.random() < 0.1:                        # some exactly at a limit
            slot = int(rng.choice(FLOATS))
            v[slot] = float(rng.choice([1, -1])) * float(rng.choice(list(LIMITS_F32.values())))
        out.append(v)
    return out


def _host_code(values: list) -> int:
    try:
        PR.validate(Params.from_values(values))
    except PR.InvalidParams as e:
        return int(e.code)
    return int(Error.OK)


def _wire(values: list) -> bytes:
    """The block as the host puts it on the wire: each double rounded to float32 (beyond the
    float32 range: ±inf, which is what a device would be sent)."""
    with np.errstate(all="ignore"):
        floats = np.array(values[:38], dtype=np.float64).astype(np.float32)
        tail = np.array(values[40:61], dtype=np.float64).astype(np.float32)   # G, c2, c3
    return (floats.astype("<f4").tobytes() + struct.pack("<II", *values[38:40]) + tail.astype("<f4").tobytes()
            + struct.pack("<4b", *values[61:65]))


def test_host_and_device_give_the_same_code_for_every_block(harness):
    blocks = _blocks()
    assert len(blocks) > 9000
    wire = [_wire(v) for v in blocks]
    r = subprocess.run([str(harness)], input="\n".join(w.hex() for w in wire) + "\n",
                       capture_output=True, text=True, timeout=120, check=True)
    device = [int(x) for x in r.stdout.split()]
    assert len(device) == len(blocks)
    host = [_host_code(v) for v in blocks]
    codes = {int(c) for c in device}
    # the set exercises every verdict, on both sides of every limit
    assert {Error.OK, Error.PARAM_NOT_FINITE, Error.PARAM_ILL_CONDITIONED, Error.PARAM_OUT_OF_RANGE} <= codes
    differ = [(i, h, d) for i, (h, d) in enumerate(zip(host, device)) if h != d]
    assert not differ, (f"{len(differ)} of {len(blocks)} blocks differ; first: block {differ[0][0]} host "
                        f"{Error(differ[0][1]).name} device {Error(differ[0][2]).name}: "
                        f"{Params.from_values(blocks[differ[0][0]])}")


@pytest.mark.parametrize("field,value", [
    ("accel_m", (1.0, 0.2, 0, 0, 1, 0, 0, 0, 1)),                  # M01 = 0.2
    ("accel_b_mps2", (9.80665, 0.0, 0.0)),
    ("gyro_scale_tc_per_c", (0.001, -0.001, 0.0)),
    ("gyro_b_rad_s", (0.0, -0.5236, 0.0)),
    ("accel_bias_tc_mps2_per_c", (0.0, 0.0, 0.01)),
    ("accel_t_max_c", 125),
    ("gyro_t_min_c", -40),
])
def test_a_block_at_a_documented_limit_is_accepted_by_the_host(field, value):
    """A value equal to its limit is inside it (SPEC.md), on the host as on the device."""
    p = PR.identity()
    setattr(p, field, value)
    PR.validate(p)


@pytest.mark.parametrize("field,value,refused_wide", [
    ("accel_bias_tc2_mps2_per_c2", (0.001, 0.0, 0.0), False), ("accel_bias_tc3_mps2_per_c3", (0.0, -1e-4, 0.0), True),
    ("gyro_bias_tc2_rad_s_per_c2", (0.0, 0.0, 1e-4), False), ("gyro_bias_tc3_rad_s_per_c3", (0.0, 1e-5, 0.0), True),
])
def test_polynomial_coefficients_at_their_limits(field, value, refused_wide):
    """c2, c3 at their limits pass over 15..35 °C; over the default span −40..85 °C (ΔT up to
    65 °C) a c3 at its limit would move the bias beyond the bias limit and is refused."""
    p = PR.identity()
    setattr(p, field, value)
    if refused_wide:
        with pytest.raises(PR.InvalidParams, match="bias polynomial.*may move the bias"):
            PR.validate(p)
    else:
        PR.validate(p)
    p.accel_t_min_c = p.gyro_t_min_c = 15
    p.accel_t_max_c = p.gyro_t_max_c = 35
    PR.validate(p)
