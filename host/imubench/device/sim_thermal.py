"""The virtual device's thermal truth as numbers: what the sensor models' bias is at given die
temperatures, on the warming or the cooling branch (firmware/boards/sim/models; docs/simulator.md).

Pure (no process, no port): tests and benchmarks evaluate the truth curves with it, from the
dict `VirtualBench.get_truth()` returns.

Per accelerometer axis k (m/s^2) and per gyro (rad/s), about the truth's 25 degC reference,
dT = T - 25 with T the sensor's own die temperature (ADXL355 for the three accelerometer axes,
each ADXRS450's own for its axis):

    bias_k(T) = b_k + c1_k dT + c2_k dT^2 + c3_k dT^3 + hysteresis_k * h,

h = +1 on the warming branch (the die warmed by more than the dead band hysteresis_width_c since
it last cooled), -1 on the cooling branch. The bias random walk and the gyros' g-sensitivity
(which depends on the attitude) are not included; the accelerometer's bias is the one of its
model u = M f + b (in counts' frame, before M^-1).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

__all__ = ["DIES", "T_REF_C", "truth_bias", "thermal_terms"]

T_REF_C = 25.0                                  # the models' reference temperature
DIES = ("accel", "gyro_x", "gyro_y", "gyro_z")  # order of die temperatures everywhere


def _vec3(d: Mapping[str, Any], key: str) -> np.ndarray:
    v = d.get(key, 0.0)
    a = np.asarray(v, dtype=float)
    return np.full(3, float(a)) if a.ndim == 0 else a.reshape(3)


def thermal_terms(truth: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The truth's bias terms as arrays, accelerometer axes then gyros X, Y, Z (6 entries each):
    b, c1, c2, c3, hysteresis, hysteresis_width_c (accelerometer in m/s^2 per degC^n, gyros in
    rad/s per degC^n)."""
    acc = truth["accel"]
    gyr = truth["gyro"]
    if isinstance(gyr, Mapping):
        gyr = [gyr[a] for a in ("x", "y", "z")]
    if len(gyr) != 3:
        raise ValueError("the truth needs three gyros (x, y, z)")

    def g(key: str) -> np.ndarray:
        return np.array([float(x.get(key, 0.0)) for x in gyr])

    return {
        "b": np.concatenate([_vec3(acc, "bias_mps2"), g("bias_rad_s")]),
        "c1": np.concatenate([_vec3(acc, "bias_tc"), g("bias_tempco_rad_s_per_c")]),
        "c2": np.concatenate([_vec3(acc, "bias_tc2"), g("bias_tc2")]),
        "c3": np.concatenate([_vec3(acc, "bias_tc3"), g("bias_tc3")]),
        "hysteresis": np.concatenate([_vec3(acc, "hysteresis"), g("hysteresis")]),
        "hysteresis_width_c": np.concatenate([_vec3(acc, "hysteresis_width_c"), g("hysteresis_width_c")]),
    }


def truth_bias(truth: Mapping[str, Any], temps_c, warming: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The true bias at die temperatures temps_c ((n, 4) or (4,): ADXL355, gyro X, Y, Z, degC)
    on the warming (h = +1) or the cooling (h = -1) branch.

    truth: `VirtualBench.get_truth()` (keys "accel" and "gyro"). Returns (accel_bias_mps2 (n, 3),
    gyro_bias_rad_s (n, 3)); the accelerometer's three axes all use the ADXL355 die (column 0),
    gyro k uses column 1 + k."""
    t = np.asarray(temps_c, dtype=float)
    if t.ndim == 1:
        t = t.reshape(1, -1)
    if t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"temps_c must have 4 columns (ADXL355, gyro X, Y, Z), got shape {np.shape(temps_c)}")
    p = thermal_terms(truth)
    per_axis = np.concatenate([np.repeat(t[:, :1], 3, axis=1), t[:, 1:]], axis=1)   # (n, 6)
    d = per_axis - T_REF_C
    h = 1.0 if warming else -1.0
    bias = p["b"] + d * (p["c1"] + d * (p["c2"] + d * p["c3"])) + h * p["hysteresis"]
    return bias[:, :3], bias[:, 3:]
