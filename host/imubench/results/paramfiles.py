"""A calibration written in other tools' layouts (docs/calibration.md, "Writing the result").

Our model (docs/conventions.md), u the measurement in the recording's own unit converted to SI
by its declared nominal scale, x the truth in SI:

    u = M·x + b          x = M⁻¹·(u − b)

Expressed in the recording's own unit (raw counts, g, °/s, ...: `factor` = SI per unit), the
same calibration is u_raw = M_raw·x + b_raw with M_raw = M / factor, b_raw = b / factor. Each
writer maps that onto its tool's equation:

- ``params``   our parameter file: the JSON of the device's parameter block (Params fields,
               imubench.wire.params.to_json), M and b in SI; needs a declared nominal scale.
- ``imutk``    imu_tk's CalibratedTriad text (Tedaldi et al. 2014): x = T·K·(u_raw − B) with T
               unit-diagonal, K diagonal: K = diag(M_raw⁻¹), T = M_raw⁻¹·K⁻¹, B = b_raw. Files
               PREFIX_acc.calib and PREFIX_gyro.calib: T (3 rows), blank, K (3 rows), blank, B
               (3 rows), as imu_tk's CalibratedTriad_::save writes and ::load reads them.
- ``imucal``   imucal's FerrarisCalibrationInfo JSON (format 2.0.0): x = R⁻¹·K⁻¹·(u_raw − b), K
               diagonal, R with unit rows: K = diag(|row_i of M_raw|), R = K⁻¹·M_raw; accelerometer
               out in m/s², gyro out in deg/s (imucal's units), K_ga = 0 (not estimated here).
- ``ardupilot`` ArduPilot's INS_ACCOFFS_* and INS_ACCSCAL_* (and INS_GYROFFS_*): corrected =
               scale ∘ (raw − offset), element-wise, in m/s² (rad/s): offset = b, scale_i = 1/M_ii.
               ArduPilot's model has no cross-axis terms: the off-diagonal of M is dropped, and
               the file says how large the dropped terms are.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from imubench.results.atomic import write_json_atomic, write_text_atomic
from imubench.text import one_line

WRITERS = ("params", "imutk", "imucal", "ardupilot")


def raw_model(m, b, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """(M_raw, b_raw) of u_raw = M_raw·x + b_raw from the SI model and SI per raw unit."""
    return np.asarray(m, float) / factor, np.asarray(b, float) / factor


def imutk_decompose(m_raw) -> tuple[np.ndarray, np.ndarray]:
    """(T, K) with T·K = M_raw⁻¹, T unit-diagonal, K diagonal."""
    inv = np.linalg.inv(np.asarray(m_raw, float))
    k = np.diag(np.diag(inv))
    return inv @ np.linalg.inv(k), k


def _eigen_rows(a) -> str:
    a = np.atleast_2d(np.asarray(a, float))
    return "\n".join(" ".join(f"{v:.12g}" for v in row) for row in a)


def imutk_text(m_raw, b_raw) -> str:
    t, k = imutk_decompose(m_raw)
    return f"{_eigen_rows(t)}\n\n{_eigen_rows(k)}\n\n{_eigen_rows(np.asarray(b_raw, float)[:, None])}\n\n"


def read_imutk_text(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, K, B) from imu_tk's .calib text (21 numbers), as CalibratedTriad_::load reads them."""
    v = np.array(text.split(), dtype=float)
    if v.size != 21:
        raise ValueError(f"imu_tk .calib holds 21 numbers, got {v.size}")
    return v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:]


def imucal_decompose(m_raw) -> tuple[np.ndarray, np.ndarray]:
    """(K, R) with K·R = M_raw, K diagonal positive, R with unit rows."""
    m = np.asarray(m_raw, float)
    k = np.diag(np.linalg.norm(m, axis=1))
    return k, np.linalg.inv(k) @ m


def imucal_dict(acc_m_raw, acc_b_raw, gyr_m_raw_per_dps, gyr_b_raw, from_acc_unit: str, from_gyr_unit: str,
                comment: str = "") -> dict:
    ka, ra = imucal_decompose(acc_m_raw)
    kg, rg = imucal_decompose(gyr_m_raw_per_dps)
    return {"acc_unit": "m/s^2", "gyr_unit": "deg/s", "from_acc_unit": from_acc_unit, "from_gyr_unit": from_gyr_unit,
            "comment": comment, "K_a": ka.tolist(), "R_a": ra.tolist(), "b_a": np.asarray(acc_b_raw, float).tolist(),
            "K_g": kg.tolist(), "R_g": rg.tolist(), "K_ga": np.zeros((3, 3)).tolist(),
            "b_g": np.asarray(gyr_b_raw, float).tolist(), "cal_type": "Ferraris", "_format_version": "2.0.0"}


def ardupilot_text(acc_m, acc_b_mps2, gyro_b_rad_s=None, comment: str = "") -> str:
    m = np.asarray(acc_m, float)
    scale = 1.0 / np.diag(m)
    off = np.asarray(acc_b_mps2, float)
    dropped = m - np.diag(np.diag(m))
    worst = float(np.max(np.abs(dropped)))
    # the largest |a| error the dropped cross-axis terms make at 1 g, over the six faces
    err_mg = max(float(np.linalg.norm(np.linalg.inv(np.diag(np.diag(m))) @ (m @ e) - e)) for e in np.eye(3)) * 1e3
    lines = [f"# {one_line(comment)}" if comment else "# imubench calibration",      # a comment stays one line
             "# ArduPilot: corrected = INS_ACCSCAL * (raw - INS_ACCOFFS), per axis, m/s² (AP_InertialSensor)",
             f"# ArduPilot has no cross-axis terms: dropped off-diagonal of M up to {worst:.2e} "
             f"(≈ {err_mg:.2f} mg at 1 g); frame: the axes of the recording (ArduPilot applies these after "
             "rotating the sensor into the autopilot board's axes, before AHRS_ORIENTATION: record in those axes)"]
    for i, ax in enumerate("XYZ"):
        lines.append(f"INS_ACCOFFS_{ax},{off[i]:.9g}")
    for i, ax in enumerate("XYZ"):
        lines.append(f"INS_ACCSCAL_{ax},{scale[i]:.9g}")
    if gyro_b_rad_s is not None:
        lines.append("# INS_GYROFFS_*: rad/s; ArduPilot re-measures them at boot when INS_GYR_CAL = 1")
        for i, ax in enumerate("XYZ"):
            lines.append(f"INS_GYROFFS_{ax},{float(gyro_b_rad_s[i]):.9g}")
    return "\n".join(lines) + "\n"


def write(kind: str, prefix: Path, *, accel, gyro=None, accel_factor: float, gyro_factor: float | None,
          accel_unit: str, gyro_unit: str, scaled: bool, params=None, comment: str = "") -> list[Path]:
    """Write one layout; prefix is the path without extension. accel, gyro: TriadFit in SI (or
    None); accel_factor / gyro_factor: SI per unit of the recording; scaled: whether the
    recording's unit had a declared nominal scale (ours and ArduPilot's need one); params:
    the parameter block for 'params'. Returns the files written."""
    prefix = Path(prefix)
    if kind not in WRITERS:
        raise ValueError(f"unknown writer {kind!r}; one of {', '.join(WRITERS)}")
    if kind == "params":
        from imubench.wire import params as PR
        return [write_json_atomic(prefix.with_suffix(".params.json"), PR.to_json(params))]
    if kind == "ardupilot":
        return [write_text_atomic(prefix.with_suffix(".ardupilot.param"),
                                  ardupilot_text(accel.m, accel.b, None if gyro is None else gyro.b, comment))]
    am, ab = raw_model(accel.m, accel.b, accel_factor)
    if kind == "imutk":
        out = [write_text_atomic(Path(f"{prefix}_acc.calib"), imutk_text(am, ab))]
        if gyro is not None and gyro_factor:
            gm, gb = raw_model(gyro.m, gyro.b, gyro_factor)
            out.append(write_text_atomic(Path(f"{prefix}_gyro.calib"), imutk_text(gm, gb)))
        return out
    # imucal: gyro out in deg/s
    if gyro is not None and gyro_factor:
        gm, gb = raw_model(gyro.m, gyro.b, gyro_factor)
        gm = gm * (math.pi / 180.0)
    else:
        gm, gb = np.eye(3), np.zeros(3)
    units = {"mps2": "m/s^2", "g": "g", "mg": "mg", "counts": "a.u.", "rad_s": "rad/s", "dps": "deg/s"}
    d = imucal_dict(am, ab, gm, gb, units.get(accel_unit, accel_unit), units.get(gyro_unit, gyro_unit), comment)
    path = prefix.with_suffix(".imucal.json")
    write_text_atomic(path, json.dumps(d, indent=4) + "\n")
    return [path]
