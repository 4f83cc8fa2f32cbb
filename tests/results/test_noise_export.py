"""`imubench allan --from FILE` on a long still recording of any IMU, and the noise files it
writes for the estimators (issue 26), read back the way each consumer parses them: Kalibr's
imu.yaml with PyYAML (Kalibr's own loader), OpenVINS' and VINS-Fusion's OpenCV FileStorage YAML
(`%YAML:1.0` first, then YAML; PyYAML reads the rest), imu_utils' output likewise."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

FS, T = 100.0, 900.0
NA, NG = 2.0e-3, 2.0e-4                # m/s²/√Hz, rad/s/√Hz: white noise densities of the record
KG = 3.0e-5                            # rad/s²/√Hz: a gyro bias random walk the record can show


@pytest.fixture(scope="module")
def still(tmp_path_factory) -> Path:
    rng = np.random.default_rng(7)
    n = int(FS * T)
    acc = np.array([0.05, -0.03, 9.81]) + rng.normal(0, NA * np.sqrt(FS), (n, 3))
    gyr = (np.array([0.01, -0.02, 0.005]) + rng.normal(0, NG * np.sqrt(FS), (n, 3))
           + np.cumsum(rng.normal(0, KG / np.sqrt(FS), (n, 3)), axis=0))
    p = tmp_path_factory.mktemp("still") / "still.txt"
    np.savetxt(p, np.column_stack([acc, gyr]), fmt="%.7g")          # no header, 6 columns (mikoff's layout)
    return p


def _allan(args, cwd):
    return subprocess.run([sys.executable, "-m", "imubench", "allan", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=180, stdin=subprocess.DEVNULL)


def _opencv_yaml(path: Path) -> dict:
    text = path.read_text()
    assert text.startswith("%YAML:1.0\n")                   # OpenCV FileStorage's header
    return yaml.safe_load(text.split("\n", 1)[1])


@pytest.fixture(scope="module")
def exported(still, tmp_path_factory):
    d = tmp_path_factory.mktemp("allan")
    r = _allan(["--from", str(still), "--rate", "100", "--accel-unit", "mps2", "--gyro-unit", "rad_s", "--out", "out",
                "--export", "kalibr", "--export", "openvins", "--export", "vins-fusion", "--export", "imu-utils",
                "--imu-topic", "/my/imu"], d)
    assert r.returncode == 0, r.stdout + r.stderr
    return d / "out", r.stdout


def test_allan_from_a_headerless_file_reads_the_noise(exported):
    out, stdout = exported
    assert "no header row: 6 columns read as ax ay az gx gy gz" in stdout
    assert "90000 samples at 100 Hz" in stdout
    assert (out / "allan.json").is_file() and (out / "allan_gyro.png").is_file()


def test_kalibr_imu_yaml_as_kalibr_reads_it(exported):
    out, _ = exported
    d = yaml.safe_load((out / "kalibr-imu.yaml").read_text())
    assert set(d) == {"rostopic", "update_rate", "accelerometer_noise_density", "accelerometer_random_walk",
                      "gyroscope_noise_density", "gyroscope_random_walk"}
    assert d["rostopic"] == "/my/imu" and d["update_rate"] == 100
    assert all(isinstance(d[k], float) for k in d if k not in ("rostopic", "update_rate"))
    # continuous-time densities in SI (not per-sample sigma, not °/h): the record's own
    assert d["accelerometer_noise_density"] == pytest.approx(NA, rel=0.06)
    assert d["gyroscope_noise_density"] == pytest.approx(NG, rel=0.06)
    assert 0.3 * KG < d["gyroscope_random_walk"] < 3 * KG
    text = (out / "kalibr-imu.yaml").read_text()
    assert "worst axis" in text and "kalibr issue #663" in text and "Not applied" in text


def test_openvins_and_vins_fusion_files_as_opencv_reads_them(exported):
    out, _ = exported
    ov = _opencv_yaml(out / "openvins-kalibr_imu_chain.yaml")["imu0"]
    assert np.array(ov["T_i_b"]).shape == (4, 4) and np.allclose(ov["T_i_b"], np.eye(4))
    for k in ("accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density",
              "gyroscope_random_walk", "rostopic", "time_offset", "update_rate", "model"):
        assert k in ov
    assert ov["model"] == "calibrated" and ov["update_rate"] == 100
    assert ov["gyroscope_noise_density"] == pytest.approx(NG, rel=0.06)
    vf = _opencv_yaml(out / "vins-fusion-imu.yaml")
    assert set(vf) == {"imu_topic", "acc_n", "gyr_n", "acc_w", "gyr_w", "g_norm"}
    # VINS-Fusion's acc_n, gyr_n are the σ of one sample (integration_base.h): N·√f, the record's own σ
    assert vf["acc_n"] == pytest.approx(NA * np.sqrt(FS), rel=0.06) and vf["gyr_n"] == pytest.approx(NG * np.sqrt(FS), rel=0.06)
    assert vf["g_norm"] == pytest.approx(9.80665) and vf["imu_topic"] == "/my/imu"


def test_imu_utils_file_keeps_imu_utils_meaning(exported):
    out, _ = exported
    d = _opencv_yaml(out / "imu_utils.yaml")
    assert d["type"] == "IMU"
    for key, n_key, w_key, n_true in (("Gyr", "gyr_n", "gyr_w", NG), ("Acc", "acc_n", "acc_w", NA)):
        blk = d[key]
        assert set(blk) == {"unit", "avg-axis", "x-axis", "y-axis", "z-axis"}
        assert blk["avg-axis"][n_key] == pytest.approx(n_true * np.sqrt(FS), rel=0.06)   # imu_utils: N·√f
        assert isinstance(blk["x-axis"][w_key], float)        # the Allan minimum (0.664·B), or .nan when withheld
    assert "NOT a random walk" in (out / "imu_utils.yaml").read_text()


def test_allan_from_refuses_a_unit_the_data_contradict_and_stray_options(still, tmp_path):
    r = _allan(["--from", str(still), "--rate", "100", "--accel-unit", "g", "--gyro-unit", "rad_s", "--out", "o"],
               tmp_path)
    assert r.returncode == 1 and "declared accelerometer unit (g) is implausible" in r.stderr
    assert "Traceback" not in r.stderr
    r = _allan(["--topic", "/imu", "--duration", "1m"], tmp_path)
    assert r.returncode == 2 and "--topic goes with --from FILE" in r.stderr
    r = _allan(["--export", "kalibr,nope", "--duration", "1m"], tmp_path)      # --export goes with a device too
    assert r.returncode == 2 and "unknown format 'nope'; one of kalibr, openvins, vins-fusion, imu-utils" in r.stderr


# ------------------------------------------------------------------ the calibration in Kalibr's, PX4's, imu_calib's files
@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    from imu_synth import ferraris_session

    from imubench.procedures.from_file import FileAnalysis, FileConfig
    from imubench.recordings import from_arrays
    ua, ug, truth, _ = ferraris_session(fs=100.0, seed=3)
    rec = from_arrays(ua, ug, rate_hz=100.0, accel_unit_name="mps2", gyro_unit_name="rad_s")
    fa = FileAnalysis(rec, FileConfig(gyro="turns"), say=lambda s: None)
    fa.run()
    return fa, ua, tmp_path_factory.mktemp("cal")


def _write(kind, fa, d, gsens=None):
    from imubench.results import paramfiles
    return paramfiles.write(kind, d / "cal", accel=fa.accel, gyro=fa.gyro, accel_factor=1.0, gyro_factor=1.0,
                            accel_unit="mps2", gyro_unit="rad_s", scaled=True, comment="test", gsens=gsens)


def test_kalibr_intrinsics_read_back_with_and_without_g(calibration):
    fa, _, d = calibration
    f, = _write("kalibr", fa, d)
    k = yaml.safe_load(f.read_text())["imu0"]
    assert k["model"] == "scale-misalignment" and np.count_nonzero(k["gyroscopes"]["A"]) == 0
    la = np.array(k["accelerometers"]["M"])
    assert np.array_equal(la, np.tril(la))                                 # Kalibr's lower-triangular M
    lg, c = np.array(k["gyroscopes"]["M"]), np.array(k["gyroscopes"]["C_gyro_i"])
    from imubench.results.paramfiles import rq
    qa = rq(fa.accel.m)[1]
    assert np.allclose(la @ qa, fa.accel.m) and np.allclose(lg @ c @ qa, fa.gyro.m)   # the products are ours
    g = np.radians([[0.03, 0, 0], [0, -0.02, 0.01], [0, 0, 0.04]])        # rad/s per g
    f, = _write("kalibr", fa, d, gsens=g)
    k = yaml.safe_load(f.read_text())["imu0"]
    assert k["model"] == "scale-misalignment"
    c = np.array(k["gyroscopes"]["C_gyro_i"])
    assert np.allclose(np.array(k["gyroscopes"]["A"]) @ c @ qa, g / 9.80665)   # (rad/s)/(m/s²), Kalibr's unit


def test_imu_calib_yaml_reproduces_our_correction(calibration):
    fa, ua, d = calibration
    f, = _write("imu-calib", fa, d)
    c = yaml.safe_load(f.read_text())
    sm, bias = np.array(c["SM"], float).reshape(3, 3), np.array(c["bias"], float)
    assert len(c["SM"]) == 9 and len(c["bias"]) == 3
    raw = ua[:500]
    np.testing.assert_allclose(raw @ sm.T - bias, fa.accel.correct(raw), atol=1e-9)   # corrected = SM·raw − bias


def test_px4_params_as_qgroundcontrol_reads_them(calibration):
    fa, ua, d = calibration
    f, = _write("px4", fa, d, gsens=np.zeros((3, 3)))
    rows = [ln.split("\t") for ln in f.read_text().splitlines() if ln and not ln.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] and r[4] == "9" for r in rows)
    p = {r[2]: float(r[3]) for r in rows}
    assert set(p) == {f"CAL_ACC0_{a}{k}" for a in "XYZ" for k in ("OFF", "SCALE")} | {f"CAL_GYRO0_{a}OFF" for a in "XYZ"}
    off = np.array([p[f"CAL_ACC0_{a}OFF"] for a in "XYZ"])
    scale = np.array([p[f"CAL_ACC0_{a}SCALE"] for a in "XYZ"])
    assert np.allclose(off, fa.accel.b) and np.allclose(scale, 1 / np.diag(fa.accel.m))
    text = f.read_text()
    assert "PX4 cannot hold" in text and "cross-axis" in text and "no gyro scale" in text and "g-sensitivity" in text
