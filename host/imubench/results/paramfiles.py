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
- ``kalibr``   Kalibr's IMU intrinsics (its imu-*.yaml output, IccSensors.py ScaledMisalignedImu,
               model ``scale-misalignment``): a_meas = M_a·a_i + b, ω_meas = M_g·C_gyro_i·ω_i +
               A·C_gyro_i·a_i + b, with Kalibr's M lower-triangular. Our full M = L·Q (RQ, ``rq``):
               the IMU frame i is the accelerometer's triangle frame, a_i = Q_a·x (Q_a is a rotation
               of our body axes, which Kalibr keeps in its camera-IMU extrinsics), accelerometers
               M = L_a, and M_g·Q_aᵀ = L_g·C_gyro_i gives gyroscopes M = L_g and C_gyro_i. A = G/g0
               in (rad/s)/(m/s²) taken into the same frames (zero when G was not fitted). The
               product is exact: read as OpenVINS maps it (Tw ← M, R_IMUtoGYRO ← C_gyro_i,
               Ta ← M) the lower triangle it keeps of Tw⁻¹, Ta⁻¹ is the whole inverse.
- ``px4``      PX4's CAL_ACC0_* and CAL_GYRO0_* in QGroundControl's parameter file layout: corrected
               = (raw − OFF)·SCALE per axis (m/s², rad/s): OFF = b, SCALE = 1/M_ii; PX4 has no
               cross-axis terms, no gyro scale and no g-sensitivity: the file says what it drops.
               PX4 uses a slot only when its CAL_ACC0_ID / CAL_GYRO0_ID equals the sensor's device
               id (sensor_calibration/Utilities.cpp FindCurrentCalibrationIndex): with the ids given
               (``px4_acc_id``, ``px4_gyro_id``) they are written with CAL_*0_PRIO = -1 (PX4's
               default priority); without, the file says in its header that it is not usable as is.
- ``imu-calib`` ROS imu_calib's YAML (dpkoch/imu_calib): corrected = SM·raw − bias, accelerometer
               only: SM = M⁻¹ (row-major, 9), bias = M⁻¹·b (m/s²).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from imubench.results.atomic import write_json_atomic, write_text_atomic
from imubench.results.exports import names
from imubench.text import comment as comment_line
from imubench.units import G0_MPS2

WRITERS = names("calibration")                                        # the export registry's (results.exports)
SI_WRITERS = ("params", "ardupilot", "kalibr", "px4", "imu-calib")     # need a declared nominal scale


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


AP_ID_HOW = ("ArduPilot counts INS_ACCOFFS/INS_ACCSCAL as this sensor's calibration only when the INS_ACC_ID it has "
             "stored equals the id of the accelerometer it detects (AP_InertialSensor::register_accel sets "
             "_accel_id_ok; a mismatch or none stored fails accel_calibrated_ok_all, pre-arm '3D Accel "
             "calibration needed'; INS_GYR_ID likewise for the gyro). This file does not set "
             "them: load it into the vehicle whose INS_ACC_ID / INS_GYR_ID already name this sensor (check with "
             "`param show INS_ACC_ID` in MAVProxy or the Full Parameter List), and record in the board's axes")


def gyro_scale_loss_dps(gyro_m, rate_dps: float) -> float:
    """The largest rate error (°/s) a firmware without gyro scale and cross-axis terms makes at
    rate_dps: corrected = raw − offset = M_g·ω, so the error is (M_g − I)·ω, at most the largest
    singular value of M_g − I times the rate."""
    g = np.asarray(gyro_m, float)
    return float(np.linalg.norm(g - np.eye(3), 2)) * rate_dps


def ardupilot_text(acc_m, acc_b_mps2, gyro_b_rad_s=None, comment: str = "", gyro_m=None) -> str:
    m = np.asarray(acc_m, float)
    scale = 1.0 / np.diag(m)
    off = np.asarray(acc_b_mps2, float)
    dropped = m - np.diag(np.diag(m))
    worst = float(np.max(np.abs(dropped)))
    # the largest |a| error the dropped cross-axis terms make at 1 g, over the six faces
    err_mg = max(float(np.linalg.norm(np.linalg.inv(np.diag(np.diag(m))) @ (m @ e) - e)) for e in np.eye(3)) * 1e3
    lines = [comment_line(comment or "imubench calibration"),      # a comment stays one line
             "# ArduPilot: corrected = INS_ACCSCAL * (raw - INS_ACCOFFS), per axis, m/s² (AP_InertialSensor)",
             f"# ArduPilot has no cross-axis terms: dropped off-diagonal of M up to {worst:.2e} "
             f"(≈ {err_mg:.2f} mg at 1 g); frame: the axes of the recording (ArduPilot applies these after "
             "rotating the sensor into the autopilot board's axes, before AHRS_ORIENTATION: record in those axes)",
             *[comment_line(part) for part in _wrap(f"Before loading: {AP_ID_HOW}.")]]
    if gyro_b_rad_s is not None and gyro_m is not None:
        g = np.asarray(gyro_m, float)
        lines += [comment_line(
            "ArduPilot has no gyro scale and no gyro cross-axis terms (corrected = raw - INS_GYROFFS): dropped "
            f"M_g diagonal {', '.join(f'{v:.6f}' for v in np.diag(g))}, off-diagonal up to "
            f"{float(np.max(np.abs(g - np.diag(np.diag(g))))):.2e}; the rate error this leaves is up to "
            f"{gyro_scale_loss_dps(g, 100.0):.2f} deg/s at 100 deg/s and {gyro_scale_loss_dps(g, 300.0):.2f} deg/s "
            "at 300 deg/s")]
    for i, ax in enumerate("XYZ"):
        lines.append(f"INS_ACCOFFS_{ax},{off[i]:.9g}")
    for i, ax in enumerate("XYZ"):
        lines.append(f"INS_ACCSCAL_{ax},{scale[i]:.9g}")
    if gyro_b_rad_s is not None:
        lines.append("# INS_GYROFFS_*: rad/s; ArduPilot re-measures them at boot when INS_GYR_CAL = 1")
        for i, ax in enumerate("XYZ"):
            lines.append(f"INS_GYROFFS_{ax},{float(gyro_b_rad_s[i]):.9g}")
    return "\n".join(lines) + "\n"


def _wrap(text: str, width: int = 110) -> list[str]:
    """A long comment as several lines (each becomes its own comment line)."""
    import textwrap
    return textwrap.wrap(text, width, break_long_words=False, break_on_hyphens=False) or [""]


def _yaml_matrix(m, indent: str) -> str:
    return "\n".join(f"{indent}- [{', '.join(f'{v:.12g}' for v in row)}]" for row in np.asarray(m, float))


def rq(m) -> tuple[np.ndarray, np.ndarray]:
    """(L, Q) with L·Q = m, L lower-triangular with a positive diagonal, Q a rotation (det +1;
    for det m < 0 the last diagonal element of L is negative)."""
    q1, r1 = np.linalg.qr(np.asarray(m, float).T)          # mᵀ = q1·r1  →  m = r1ᵀ·q1ᵀ
    low, q = r1.T, q1.T
    d = np.sign(np.diag(low))
    d[d == 0] = 1.0
    low, q = low * d, d[:, None] * q                       # L·D, D·Q: the same product, diag(L) > 0
    if np.linalg.det(q) < 0:
        low[:, 2], q[2] = -low[:, 2], -q[2]
    return np.tril(low), q


def kalibr_intrinsics(acc_m, gyro_m, gsens_rad_s_per_g=None) -> dict:
    """Kalibr's lower-triangular form of our model (module docstring): {'Ma', 'Mg', 'C_gyro_i', 'A',
    'Q_a'} with Q_a the rotation of the IMU frame from our body axes (a_i = Q_a·x)."""
    la, qa = rq(acc_m)
    lg, c = rq(np.asarray(gyro_m, float) @ qa.T)
    g = np.zeros((3, 3)) if gsens_rad_s_per_g is None else np.asarray(gsens_rad_s_per_g, float) / G0_MPS2
    # u_g = M_g·ω + (G/g0)·f = L_g·C·ω_i + (G/g0)·Q_aᵀ·f_i, and Kalibr's term is A·(C·f_i)
    return {"Ma": la, "Mg": lg, "C_gyro_i": c, "A": g @ qa.T @ c.T, "Q_a": qa}


def kalibr_intrinsics_text(acc_m, gyro_m, gsens_rad_s_per_g=None, comment: str = "") -> str:
    """Kalibr's imu-*.yaml intrinsics block (imu0: model, accelerometers: M, gyroscopes: M, A, C_gyro_i)."""
    k = kalibr_intrinsics(acc_m, gyro_m, gsens_rad_s_per_g)
    lines = [comment_line(comment or "imubench calibration"),
             "# Kalibr scale-misalignment (IccSensors.py): a_meas = M_a*a_i + b_a;",
             "# w_meas = M_g*C_gyro_i*w_i + A*C_gyro_i*a_i + b_g (SI), M_a and M_g lower-triangular.",
             "# imubench's full M = L*Q: accelerometers M = L_a, gyroscopes M, C_gyro_i from M_g*Q_a^T; exact.",
             "# The IMU frame i is rotated from imubench's body axes: a_i = Q_a*a_body (Kalibr estimates this",
             "# rotation with the camera-IMU extrinsics). Q_a, rows:",
             *[comment_line(" ".join(f"{v:.12g}" for v in row)) for row in k["Q_a"]],
             "# A: gyro g-sensitivity, (rad/s)/(m/s^2) in the gyro frame"
             + (" (zeros: none was fitted)." if gsens_rad_s_per_g is None else "."),
             "# Biases are not in this file (estimated online by Kalibr and OpenVINS).",
             "imu0:", "  model: scale-misalignment", "  accelerometers:", "    M:", _yaml_matrix(k["Ma"], "      "),
             "  gyroscopes:", "    M:", _yaml_matrix(k["Mg"], "      "), "    A:", _yaml_matrix(k["A"], "      "),
             "    C_gyro_i:", _yaml_matrix(k["C_gyro_i"], "      ")]
    return "\n".join(lines) + "\n"


PX4_ID_HOW = ("find the ids with `listener sensor_accel` / `listener sensor_gyro` (device_id) in the PX4 shell, or "
              "read CAL_ACC0_ID / CAL_GYRO0_ID of the vehicle's current parameters, and give them as "
              "--px4-acc-id / --px4-gyro-id")


def px4_missing_ids(acc_id, gyro_id, with_gyro: bool) -> list[str]:
    """The CAL_*0_ID a .px4.params file lacks (it is then not usable as is)."""
    return ([] if acc_id is not None else ["CAL_ACC0_ID"]) + ([] if gyro_id is not None or not with_gyro
                                                               else ["CAL_GYRO0_ID"])


def px4_text(acc_m, acc_b_mps2, gyro_m=None, gyro_b_rad_s=None, gsens=None, comment: str = "",
             acc_id: int | None = None, gyro_id: int | None = None) -> str:
    """PX4's CAL_ACC0_* / CAL_GYRO0_* as a QGroundControl parameter file (tab separated); acc_id,
    gyro_id: the PX4 device ids of the sensors (CAL_ACC0_ID, CAL_GYRO0_ID)."""
    m = np.asarray(acc_m, float)
    dropped = float(np.max(np.abs(m - np.diag(np.diag(m)))))
    missing = px4_missing_ids(acc_id, gyro_id, gyro_b_rad_s is not None)
    rows = [comment_line(comment or "imubench calibration")]
    if missing:
        rows += [comment_line(f"NOT USABLE AS IS: no {' / '.join(missing)}. PX4 uses a calibration slot only when its "
                              "id equals the sensor's device id (FindCurrentCalibrationIndex); otherwise it loads "
                              "these values and ignores them."),
                 comment_line(f"To fix: {PX4_ID_HOW}.")]
    rows += [
            "# PX4 (src/modules/sensors): corrected = (raw - CAL_*_OFF) * CAL_*_SCALE per axis; offsets in m/s^2 "
            "and rad/s.",
            f"# PX4 cannot hold: the accelerometer's cross-axis terms (off-diagonal of M, up to {dropped:.2e}, dropped)"]
    if gyro_m is not None:
        g = np.asarray(gyro_m, float)
        rows.append(f"# and the gyro's scale and cross-axis terms (M_g diagonal {', '.join(f'{v:.6f}' for v in np.diag(g))}"
                    f", off-diagonal up to {float(np.max(np.abs(g - np.diag(np.diag(g))))):.2e}: PX4 has no gyro scale)")
        rows.append(f"#   the rate error this leaves: up to {gyro_scale_loss_dps(g, 100.0):.2f} deg/s at 100 deg/s, "
                    f"{gyro_scale_loss_dps(g, 300.0):.2f} deg/s at 300 deg/s")
    if gsens is not None:
        rows.append("# and the gyro g-sensitivity G (PX4 has none): its bias is the one at zero specific force")
    rows += ["# Onboard parameters for Vehicle 1", "#", "# Vehicle-Id Component-Id Name Value Type"]
    ints = [] if acc_id is None else [("CAL_ACC0_ID", acc_id), ("CAL_ACC0_PRIO", -1)]
    if gyro_b_rad_s is not None and gyro_id is not None:
        ints += [("CAL_GYRO0_ID", gyro_id), ("CAL_GYRO0_PRIO", -1)]
    if ints:
        rows.append("# CAL_*0_PRIO = -1: PX4's default priority (50 internal, 75 external sensor); 0 would disable it")
    vals = [(f"CAL_ACC0_{ax}OFF", float(acc_b_mps2[i])) for i, ax in enumerate("XYZ")]
    vals += [(f"CAL_ACC0_{ax}SCALE", 1.0 / float(m[i, i])) for i, ax in enumerate("XYZ")]
    if gyro_b_rad_s is not None:
        vals += [(f"CAL_GYRO0_{ax}OFF", float(gyro_b_rad_s[i])) for i, ax in enumerate("XYZ")]
    rows += [f"1\t1\t{name}\t{int(v)}\t6" for name, v in ints]            # MAV_PARAM_TYPE_INT32
    rows += [f"1\t1\t{name}\t{v:.9g}\t9" for name, v in vals]            # MAV_PARAM_TYPE_REAL32
    return "\n".join(rows) + "\n"


def imu_calib_text(acc_m, acc_b_mps2, comment: str = "") -> str:
    """ROS imu_calib's calibration YAML: corrected = SM·raw − bias (accelerometer)."""
    sm = np.linalg.inv(np.asarray(acc_m, float))
    bias = sm @ np.asarray(acc_b_mps2, float)
    return (comment_line(comment or "imubench calibration") + "\n"
            + "# ROS imu_calib (dpkoch): corrected = SM*raw - bias, accelerometer, m/s^2; SM row-major.\n"
            + f"SM: [{', '.join(f'{v:.12g}' for v in sm.ravel())}]\n"
            + f"bias: [{', '.join(f'{v:.12g}' for v in bias)}]\n")


def write(kind: str, prefix: Path, *, accel, gyro=None, accel_factor: float, gyro_factor: float | None,
          accel_unit: str, gyro_unit: str, scaled: bool, params=None, comment: str = "",
          gsens=None, px4_acc_id: int | None = None, px4_gyro_id: int | None = None) -> list[Path]:
    """Write one layout; prefix is the path without extension (the file names are the export
    registry's, results.exports). accel, gyro: TriadFit in SI (or None); accel_factor /
    gyro_factor: SI per unit of the recording; scaled: whether the recording's unit had a declared
    nominal scale (ours and ArduPilot's need one); params: the parameter block for 'params'. Each
    file is stamped with what it holds, cannot hold and leaves to do (exports.stamp). Returns the
    files written."""
    from imubench.results import exports as X
    prefix = Path(prefix)
    if kind not in WRITERS:
        raise ValueError(f"unknown writer {kind!r}; one of {', '.join(WRITERS)}")
    fmt = X.get("calibration", kind)
    paths = [prefix.parent / n for n in X.file_names("calibration", kind, prefix.name)]

    def put(path: Path, text: str) -> Path:
        return write_text_atomic(path, X.stamp(text, fmt))
    if kind == "params":
        from imubench.wire import params as PR
        return [write_json_atomic(paths[0], PR.to_json(params))]
    if kind == "ardupilot":
        return [put(paths[0], ardupilot_text(accel.m, accel.b, None if gyro is None else gyro.b, comment,
                                             None if gyro is None else gyro.m))]
    if kind == "kalibr":
        return [put(paths[0], kalibr_intrinsics_text(accel.m, np.eye(3) if gyro is None else gyro.m, gsens, comment))]
    if kind == "px4":
        return [put(paths[0], px4_text(accel.m, accel.b, None if gyro is None else gyro.m,
                                       None if gyro is None else gyro.b, gsens, comment, px4_acc_id, px4_gyro_id))]
    if kind == "imu-calib":
        return [put(paths[0], imu_calib_text(accel.m, accel.b, comment))]
    am, ab = raw_model(accel.m, accel.b, accel_factor)
    if kind == "imutk":
        out = [write_text_atomic(paths[0], imutk_text(am, ab))]
        if gyro is not None and gyro_factor:
            gm, gb = raw_model(gyro.m, gyro.b, gyro_factor)
            out.append(write_text_atomic(paths[1], imutk_text(gm, gb)))
        return out
    # imucal: gyro out in deg/s
    if gyro is not None and gyro_factor:
        gm, gb = raw_model(gyro.m, gyro.b, gyro_factor)
        gm = gm * (math.pi / 180.0)
    else:
        gm, gb = np.eye(3), np.zeros(3)
    units = {"mps2": "m/s^2", "g": "g", "mg": "mg", "counts": "a.u.", "rad_s": "rad/s", "dps": "deg/s"}
    d = imucal_dict(am, ab, gm, gb, units.get(accel_unit, accel_unit), units.get(gyro_unit, gyro_unit), comment)
    if gsens is not None and gyro_factor:   # imucal's K_ga: raw gyro units per (m/s²) of calibrated acceleration
        d["K_ga"] = (np.asarray(gsens, float) / 9.80665 / gyro_factor).tolist()
    return [put(paths[0], json.dumps(d, indent=4) + "\n")]
