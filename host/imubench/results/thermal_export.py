"""A warm-up's temperature terms as autopilot parameter files, beside the other exports
(results.paramfiles): what each firmware evaluates, read from its source, and what it cannot hold.

PX4 (src/modules/temperature_compensation/TemperatureCompensation.cpp, calc_thermal_offsets_3D;
applied in src/lib/sensor_calibration as corrected = (raw − thermal_offset − CAL_*_OFF)·scale):

    ΔT = clamp(T, TMIN, TMAX) − TREF       offset_i = X0_i + X1_i·ΔT + X2_i·ΔT² + X3_i·ΔT³

per sensor (TC_A0_* the accelerometer, TC_G0_* the gyro), m/s² and rad/s, T the sensor's one
temperature. We write X0 = 0 and TREF = our t_ref: the offset at t_ref stays in CAL_ACC0_xOFF /
CAL_GYRO0_xOFF (`imubench calibrate --export px4`). TC_*0_ID must be the PX4 device id of the
sensor (we cannot know it: 0 is written, to be replaced). TC_A_ENABLE / TC_G_ENABLE = 1.

ArduPilot (libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp, TCal::correct_sensor;
applied before INS_ACCOFFS / INS_ACCSCAL in AP_InertialSensor_Backend::_rotate_and_correct_*):

    T' = clamp(T, TMIN, TMAX), Tc = clamp(CALTEMP, TMIN, TMAX)
    v −= p(T' − 35) − p(Tc − 35),   p(d) = (c1 + (c2 + c3·d)·d)·d · 1e-6

with a fixed reference of 35 °C (TEMP_REFERENCE), no constant term, the parameters c_k stored
×1e6 (INS_TCAL1_ACCk_*, INS_TCAL1_GYRk_*, k = 1..3), one temperature per IMU for both its
accelerometer and its gyro, m/s² and rad/s. We re-expand our polynomial about 35 °C (exactly)
and write INS_ACC1_CALTEMP = INS_GYR1_CALTEMP = t_ref, the temperature our offsets belong to
(ArduPilot's own accelerometer calibration and boot gyro calibration overwrite them with theirs,
which keeps the correction right: it is relative to CALTEMP).

Neither holds scale temperature terms, nor a temperature per gyro axis: the files say which
temperature their coefficients are fitted against and what they drop.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench.analysis.thermal_poly import AxisFit, shift_poly
from imubench.results.atomic import write_text_atomic
from imubench.results.exports import names
from imubench.text import comment as comment_line
from imubench.wire.board_parts import DEFAULT as DEFAULT_PARTS
from imubench.wire.board_parts import BoardParts

KINDS = names("thermal")          # the export registry's (results.exports)
AP_TREF_C = 35.0          # ArduPilot's TEMP_REFERENCE
AP_SCALE = 1e6            # ArduPilot's SCALE_FACTOR



def _coef(a: AxisFit) -> np.ndarray:
    c = np.array([a.bias.coef[i] if i <= a.bias.order else 0.0 for i in range(4)], float)
    c[0] = 0.0
    return c


def _span(axes) -> tuple[float, float]:
    s = np.array([a.bias.span_c for a in axes], float)
    return math.ceil(s[:, 0].max() * 10 - 1e-9) / 10, math.floor(s[:, 1].min() * 10 + 1e-9) / 10


def _orders(axes) -> str:
    return "/".join(str(a.bias.order) for a in axes)


def _dropped(fits: dict) -> list[str]:
    out = []
    for k, a in enumerate(fits["accel"]):
        if a.scale_tc_per_c is not None:
            out.append(f"accel {'xyz'[k]} scale temperature term {a.scale_tc_per_c * 1e6:+.1f} ppm/degC (dropped)")
        out += [u for u in a.undetermined]
    return out


def px4_text(fits: dict, t_ref: dict, gyro_temp: str, comment: str = "", parts: BoardParts = DEFAULT_PARTS) -> str:
    """QGroundControl parameter file (tab separated) with TC_A0_* and TC_G0_*; parts: the board's,
    named with the temperatures."""
    rows = [comment_line(comment or "imubench warm-up temperature calibration"),
            "# PX4 temperature_compensation: offset = X0 + X1*dT + X2*dT^2 + X3*dT^3, dT = clamp(T, TMIN, TMAX) - TREF;",
            "# corrected = (raw - offset - CAL_*_OFF) * CAL_*_SCALE; m/s^2 (TC_A0) and rad/s (TC_G0).",
            "# X0 = 0: the offset at TREF stays in CAL_ACC0_xOFF / CAL_GYRO0_xOFF (imubench calibrate --export px4).",
            "# TC_A0_ID / TC_G0_ID: replace 0 with the PX4 device id of the sensor (CAL_ACC0_ID / CAL_GYRO0_ID).",
            f"# TC_A0: against the {parts.accel.name} temperature. TC_G0: PX4 has one temperature per gyro sensor; "
            "ours are three",
            comment_line(f"{parts.gyro_words} gyros: these coefficients are fitted against {gyro_temp}, the temperature "
                         "the driver must report."),
            "# PX4 holds: a bias polynomial of order <= 3 per axis about TREF, clamped to TMIN..TMAX, one per sensor;",
            f"# ours: orders accel {_orders(fits['accel'])}, gyro {_orders(fits['gyro'])} (x/y/z).",
            "# PX4 cannot hold: scale temperature terms, a temperature per gyro axis."]
    rows += [comment_line(d) for d in _dropped(fits)]
    rows += ["# Onboard parameters for Vehicle 1", "#", "# Vehicle-Id Component-Id Name Value Type"]
    vals = [("TC_A_ENABLE", 1, 6), ("TC_G_ENABLE", 1, 6)]
    for pre, triad in (("TC_A0", "accel"), ("TC_G0", "gyro")):
        axes = fits[triad]
        lo, hi = _span(axes)
        vals += [(f"{pre}_ID", 0, 6), (f"{pre}_TMIN", lo, 9), (f"{pre}_TMAX", hi, 9), (f"{pre}_TREF", t_ref[triad], 9)]
        c = np.array([_coef(a) for a in axes])
        for j in range(4):
            vals += [(f"{pre}_X{j}_{i}", float(c[i, j]), 9) for i in range(3)]
    rows += [f"1\t1\t{n}\t{v:d}\t{t}" if t == 6 else f"1\t1\t{n}\t{v:.9g}\t{t}" for n, v, t in vals]
    return "\n".join(rows) + "\n"


def ardupilot_text(fits: dict, t_ref: dict, imu_temp: str, comment: str = "") -> str:
    """Mission Planner parameter file (NAME,VALUE) with INS_TCAL1_* and the calibration temperatures."""
    lines = [comment_line(comment or "imubench warm-up temperature calibration"),
             "# ArduPilot TCal: v -= p(clamp(T,TMIN,TMAX)-35) - p(clamp(CALTEMP,TMIN,TMAX)-35),",
             "# p(d) = (c1 + (c2 + c3*d)*d)*d * 1e-6, c_k = INS_TCAL1_ACCk_* / INS_TCAL1_GYRk_*; m/s^2 and rad/s;",
             "# applied before INS_ACCOFFS/INS_ACCSCAL (INS_GYROFFS). Our polynomial re-expanded about 35 degC;",
             "# CALTEMP = our t_ref (the temperature our offsets belong to).",
             comment_line(f"ArduPilot has one temperature per IMU for accelerometer and gyro: these are fitted "
                          f"against {imu_temp}."),
             "# ArduPilot holds: a bias polynomial of order <= 3 per axis about 35 degC without its constant term,",
             f"# clamped to one TMIN..TMAX per IMU; ours: orders accel {_orders(fits['accel'])}, gyro {_orders(fits['gyro'])}.",
             "# ArduPilot cannot hold: scale temperature terms, a temperature per gyro axis, a constant term.",
             "# LOAD IN TWO STEPS: the INS_TCAL1_* parameters exist only once INS_TCAL1_ENABLE = 1 and the board has",
             "# rebooted (AP_Param enable flag). Load this file, reboot the autopilot, then load it again: the first",
             "# load sets INS_TCAL1_ENABLE and the second the coefficients (until then they are refused as unknown).",
             "# INS_ACC_ID / INS_GYR_ID on the vehicle must name this IMU (the calibration of another is not used)."]
    lines += [comment_line(d) for d in _dropped(fits)]
    lo = max(_span(fits["accel"])[0], _span(fits["gyro"])[0])
    hi = min(_span(fits["accel"])[1], _span(fits["gyro"])[1])
    lines += ["INS_TCAL1_ENABLE,1", f"INS_TCAL1_TMIN,{lo:.2f}", f"INS_TCAL1_TMAX,{hi:.2f}"]
    for triad, name in (("accel", "ACC"), ("gyro", "GYR")):
        c = np.array([shift_poly(_coef(a), t_ref[triad], AP_TREF_C) for a in fits[triad]]) * AP_SCALE
        for k in range(1, 4):
            for i, ax in enumerate("XYZ"):
                lines.append(f"INS_TCAL1_{name}{k}_{ax},{c[i, k]:.9g}")
    lines += [f"INS_ACC1_CALTEMP,{t_ref['accel']:.2f}", f"INS_GYR1_CALTEMP,{t_ref['gyro']:.2f}"]
    return "\n".join(lines) + "\n"


def write_exports(out_dir, fits_by_kind: dict, t_ref: dict, kinds, comment: str = "",
                  prefix: str = "warmup", parts: BoardParts = DEFAULT_PARTS) -> dict:
    """Write the asked files into out_dir: fits_by_kind[kind] = (fits, temperature words) with the
    gyro fitted against the temperature that firmware uses; parts: the board's (named in the
    files). Returns {kind: [path]}."""
    from imubench.results import exports as X
    out = {}
    for kind in kinds:
        fits, temp = fits_by_kind[kind]
        path = Path(out_dir) / X.file_names("thermal", kind, prefix)[0]
        text = (px4_text(fits, t_ref, temp, comment, parts) if kind == "px4" else
                ardupilot_text(fits, t_ref, temp, comment))
        out[kind] = [write_text_atomic(path, X.stamp(text, X.get("thermal", kind)))]
    if out:
        X.write_index(out_dir, "thermal", out, comment or "warm-up temperature calibration")
    return out


# ------------------------------------------------------------------ reading back, as the consumer evaluates
def read_px4(text: str) -> dict:
    vals = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        parts = line.split("\t")
        vals[parts[2]] = float(parts[3])
    return vals


def px4_offset(vals: dict, pre: str, temp_c: float) -> np.ndarray:
    """PX4's calc_thermal_offsets_3D for one temperature."""
    t = vals[f"{pre}_TMAX"] if temp_c > vals[f"{pre}_TMAX"] else vals[f"{pre}_TMIN"] if temp_c < vals[f"{pre}_TMIN"] else temp_c
    d = t - vals[f"{pre}_TREF"]
    return np.array([vals[f"{pre}_X0_{i}"] + vals[f"{pre}_X1_{i}"] * d + vals[f"{pre}_X2_{i}"] * d * d
                     + vals[f"{pre}_X3_{i}"] * d ** 3 for i in range(3)])


def read_ardupilot(text: str) -> dict:
    vals = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        k, v = line.split(",")
        vals[k] = float(v)
    return vals


def ardupilot_correction(vals: dict, name: str, temp_c: float) -> np.ndarray:
    """What ArduPilot's TCal::correct_sensor subtracts at temp_c (name: ACC or GYR)."""
    lo, hi = vals["INS_TCAL1_TMIN"], vals["INS_TCAL1_TMAX"]
    cal = vals[f"INS_{name}1_CALTEMP"]
    c = np.array([[vals[f"INS_TCAL1_{name}{k}_{ax}"] for ax in "XYZ"] for k in (1, 2, 3)])

    def p(d):
        return (c[0] + (c[1] + c[2] * d) * d) * d * 1e-6
    return p(min(max(temp_c, lo), hi) - AP_TREF_C) - p(min(max(cal, lo), hi) - AP_TREF_C)
