"""Nominal scales of common MEMS IMUs' raw counts, by full-scale setting, from their data sheets
(``--sensor NAME``): the accelerometer's setting is read off the data (the one whose 1 g the
median |a| is nearest, within 15 %), the gyro's is the --gyro-range the user gives (a gyro at
rest does not tell it) unless the sensor has one.

Sources (document number and revision; the sensitivity tables of the "Mechanical
characteristics" / "Gyroscope / Accelerometer specifications" sections):

- MPU-6050: InvenSense MPU-6000 and MPU-6050 Product Specification, PS-MPU-6000A-00, Rev. 3.4
  (2013), §6.1 (gyro 131/65.5/32.8/16.4 LSB/(°/s) at ±250/500/1000/2000 °/s) and §6.2
  (accelerometer 16384/8192/4096/2048 LSB/g at ±2/4/8/16 g).
- MPU-9150: PS-MPU-9150A-00, Rev. 4.3 (2013), §6.1–6.2: the same sensitivities.
- MPU-9250: InvenSense MPU-9250 Product Specification, PS-MPU-9250A-01, Rev. 1.1 (2016), §3.1–3.2:
  the same sensitivities as the MPU-6050.
- ICM-20602: TDK InvenSense ICM-20602 datasheet, DS-000176, Rev. 1.0, §3.1–3.2; ICM-20948: DS-000189,
  Rev. 1.3, §3.1–3.2: the same sensitivities as the MPU-6050.
- BMI160: Bosch Sensortec BMI160 data sheet, BST-BMI160-DS000-07, Rev. 0.8 (2015), §1.1–1.2:
  accelerometer 16384/8192/4096/2048 LSB/g at ±2/4/8/16 g; gyro 262.4/131.2/65.6/32.8/16.4
  LSB/(°/s) at ±125/250/500/1000/2000 °/s.
- LSM6DSO: STMicroelectronics LSM6DSO datasheet, DS12140, Rev. 2, Table 2: 0.061/0.122/0.244/0.488
  mg/LSB at ±2/4/8/16 g and 4.375/8.75/17.50/35/70 mdps/LSB at ±125/250/500/1000/2000 °/s (the
  LSM6DS3/LSM6DSL/LSM6DSM data sheets give the same sensitivities).
- ADXL355 (accelerometer only, 20-bit): Analog Devices ADXL354/ADXL355 data sheet, Rev. A,
  Specifications table: 256000/128000/64000 LSB/g at ±2.048/4.096/8.192 g (3.9/7.8/15.6 µg/LSB).
- ADXRS450 (one gyro axis, Z): Analog Devices ADXRS450 data sheet, Rev. B, Specifications table:
  80 LSB/(°/s), ±300 °/s.

A sensor of one triad is named with another: ``--sensor ADXL355,ADXRS450``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from imubench.recordings import Recording, RecordingError

ACCEL_MATCH = 0.15          # the median |a| within this fraction of a setting's 1 g picks that setting


@dataclass(frozen=True)
class Sensor:
    name: str
    accel: dict          # full scale (g) -> counts per g
    gyro: dict           # full scale (°/s) -> counts per °/s
    source: str


_MPU_A = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
_MPU_G = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
_ST_A = {2: 1000 / 0.061, 4: 1000 / 0.122, 8: 1000 / 0.244, 16: 1000 / 0.488}
_ST_G = {125: 1000 / 4.375, 250: 1000 / 8.75, 500: 1000 / 17.5, 1000: 1000 / 35.0, 2000: 1000 / 70.0}
SENSORS = {s.name: s for s in (
    Sensor("MPU-6050", _MPU_A, _MPU_G, "PS-MPU-6000A-00 Rev. 3.4"),
    Sensor("MPU-9150", _MPU_A, _MPU_G, "PS-MPU-9150A-00 Rev. 4.3"),
    Sensor("MPU-9250", _MPU_A, _MPU_G, "PS-MPU-9250A-01 Rev. 1.1"),
    Sensor("ICM-20602", _MPU_A, _MPU_G, "DS-000176 Rev. 1.0"),
    Sensor("ICM-20948", _MPU_A, _MPU_G, "DS-000189 Rev. 1.3"),
    Sensor("BMI160", _MPU_A, {125: 262.4, 250: 131.2, 500: 65.6, 1000: 32.8, 2000: 16.4},
           "BST-BMI160-DS000-07 Rev. 0.8"),
    Sensor("LSM6DSO", _ST_A, _ST_G, "DS12140 Rev. 2"),
    Sensor("LSM6DS3", _ST_A, _ST_G, "LSM6DSO DS12140 Rev. 2 (same sensitivities)"),
    Sensor("LSM6DSL", _ST_A, _ST_G, "LSM6DSO DS12140 Rev. 2 (same sensitivities)"),
    Sensor("ADXL355", {2.048: 256000.0, 4.096: 128000.0, 8.192: 64000.0}, {}, "ADXL354/ADXL355 data sheet Rev. A"),
    Sensor("ADXRS450", {}, {300: 80.0}, "ADXRS450 data sheet Rev. B"),
)}


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


_BY_KEY = {_key(n): s for n, s in SENSORS.items()}
_BY_KEY.update({"mpu6000": SENSORS["MPU-6050"], "mpu6500": SENSORS["MPU-9250"], "lsm6dsm": SENSORS["LSM6DSL"],
                "mpu9255": SENSORS["MPU-9250"]})


def sensors(spec: str) -> tuple[Sensor | None, Sensor | None]:
    """The sensors of --sensor NAME[,NAME]: (the accelerometer's, the gyro's)."""
    found = []
    for name in str(spec).split(","):
        s = _BY_KEY.get(_key(name))
        if s is None:
            raise RecordingError(f"--sensor {name.strip()!r}: not known; known: {', '.join(SENSORS)} "
                                 "(or give --accel-scale COUNTS_PER_G and --gyro-scale COUNTS_PER_DPS)")
        found.append(s)
    acc = next((s for s in found if s.accel), None)
    gyr = next((s for s in found if s.gyro), None)
    return acc, gyr


def default_units(spec: str, opt: dict, say: list) -> dict:
    """The units a named sensor implies when none are declared: its raw counts."""
    acc, gyr = sensors(spec)
    out = {}
    for key, s in (("accel_unit", acc), ("gyro_unit", gyr)):
        if s is not None and not opt.get(key):
            out[key] = "counts"
    if out:
        what = " and ".join("accelerometer" if k == "accel_unit" else "gyro" for k in out)
        say.append(f"--sensor {spec}: the {what} read as raw counts (--accel-unit/--gyro-unit declare others)")
    return out


def _fmt(d: dict, per: str) -> str:
    """'250|500 (131|65.5 counts per °/s)': the settings and their scales."""
    return ("|".join(f"{k:g}" for k in d) + " (" + "|".join(f"{v:.4g}" for v in d.values()) + f" counts per {per})")


def apply_sensor(rec: Recording, spec: str, gyro_range_dps: float | None = None) -> None:
    """Give rec's raw counts the nominal scales of the named sensor's full-scale settings
    (declared scales win), saying which setting and why, one line each."""
    acc, gyr = sensors(spec)
    unused = [w for w, s, u in (("accelerometer", acc, rec.accel_unit), ("gyro", gyr, rec.gyro_unit))
              if s is not None and u != "counts"]
    if unused:
        rec.notes.append(f"--sensor {spec}: not used for the {' and '.join(unused)} (declared in a unit, not counts)")
    if acc is not None and rec.accel_unit == "counts" and not rec.accel_counts_per_g:
        norm = float(np.median(np.linalg.norm(rec.accel, axis=1)))
        fs, cpg = min(acc.accel.items(), key=lambda kv: abs(norm / kv[1] - 1.0))
        if abs(norm / cpg - 1.0) > ACCEL_MATCH:
            raise RecordingError(f"--sensor {acc.name}: the median |a| is {norm:.6g} counts, 1 g at none of its "
                                 f"settings (±{_fmt(acc.accel, 'g')} g, {acc.source}): check the sensor, or give "
                                 "--accel-scale COUNTS_PER_G")
        rec.accel_counts_per_g = cpg
        rec.options["accel_counts_per_g"] = cpg
        rec.detected.append(f"accelerometer full scale ±{fs:g} g of the {acc.name} ({cpg:.6g} counts per g, "
                            f"{acc.source}): the median |a| is {norm:.6g} counts")
    if gyr is not None and rec.gyro_unit == "counts" and not rec.gyro_counts_per_dps:
        if gyro_range_dps is None and len(gyr.gyro) == 1:
            gyro_range_dps = next(iter(gyr.gyro))
        match = [k for k in gyr.gyro if gyro_range_dps is not None and abs(k - gyro_range_dps) < 0.5]
        if not match:
            said = f"--gyro-range {gyro_range_dps:g} is none of them" if gyro_range_dps is not None else \
                "a gyro at rest does not tell which"
            raise RecordingError(f"--sensor {gyr.name}: its gyro has several full-scale settings and {said}: give "
                                 f"the recording's with --gyro-range {_fmt(gyr.gyro, '°/s')} [{gyr.source}], or "
                                 "--gyro-scale COUNTS_PER_DPS")
        rec.gyro_counts_per_dps = gyr.gyro[match[0]]
        rec.detected.append(f"gyro full scale ±{match[0]:g} °/s of the {gyr.name} ({gyr.gyro[match[0]]:.5g} counts "
                            f"per °/s, {gyr.source})")
        rec.options.setdefault("gyro_range_dps", match[0])
        rec.options["gyro_counts_per_dps"] = gyr.gyro[match[0]]
