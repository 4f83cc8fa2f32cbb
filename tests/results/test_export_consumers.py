"""Each export read by its consumer's own parser with the keys and types that consumer's source
requires, then applied the way that consumer's code applies it, and compared with imubench's own
correction (issue 34). The consumers' sources (docs/noise.md, docs/calibration.md):

- OpenVINS  rpng/open_vins ov_msckf/src/core/VioManagerOptions.h (print_and_load_noise,
            print_and_load_state: parse_external("relative_config_imu", "imu0", KEY), all required),
            read with OpenCV's cv::FileStorage (ov_core/src/utils/opencv_yaml_parse.h); applied as
            ov_msckf/src/state/Propagator.cpp predict_and_compute: a_hat = R_ACCtoIMU·Da·(a_m − b_a),
            w_hat = R_GYROtoIMU·Dw·(w_m − b_g − Tg·a_hat), Da, Dw the lower triangle of Ta⁻¹, Tw⁻¹
            for model kalibr / calibrated (State::Dm).
- VINS-Fusion  HKUST-Aerial-Robotics/VINS-Fusion vins_estimator/src/estimator/parameters.cpp
            readParameters (cv::FileStorage, fsSettings["acc_n"] >> ACC_N, ...), applied in
            vins_estimator/src/factor/integration_base.h midPointIntegration: one step adds
            ACC_N²·(dt/2)² to δv's covariance per sample noise and ACC_W²·dt² to the bias.
- imu_utils gaowenliang/imu_utils src/imu_an.cpp writeYAML; gyr_n = getWhiteNoise() = N·√f,
            gyr_w = getBiasInstability() = min ADEV (src/gyr_lib/fitallan_gyr.cpp).
- Kalibr    ethz-asl/kalibr aslam_offline_calibration/kalibr/python/kalibr_imu_camera_calibration/
            IccSensors.py (ScaledMisalignedImu: M lower-triangular, q_gyro_i, A; models of
            kalibr_calibrate_imu_camera --imu-models), read with PyYAML.
- PX4       PX4/PX4-Autopilot src/lib/sensor_calibration/Utilities.cpp FindCurrentCalibrationIndex
            (a slot is used only when CAL_ACCn_ID equals the sensor's device id), Accelerometer.hpp
            Correct: (raw − OFF)∘SCALE; the file in QGroundControl's layout (ParameterManager.cc
            readParametersFromStream: '#' lines skipped, 5 TAB fields).
"""
from __future__ import annotations

import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import yaml
from imu_synth import ferraris_truth

from imubench.calib import TriadFit
from imubench.results import noise_export as NE
from imubench.results import paramfiles as PF

G0 = 9.80665
FS = 200.0                                          # Hz
N_A, K_A, B_A = 1.5e-3, 4e-5, 2e-4                  # m/s²/√Hz, m/s³/√Hz, m/s²
N_G, K_G, B_G = 1.2e-4, 3e-6, 1e-5                  # rad/s/√Hz, rad/s²/√Hz, rad/s


def _res(source="still.csv", name="imu") -> dict:
    """An Allan result (imubench.analysis.allan's dict) with known N, K, B on every axis."""
    def axis(n, k, b):
        return {"N": n, "K": k, "B": b, "taus": [1.0, 100.0], "adev": [n, b * 0.664]}
    return {"source": [source], "device": {"name": name}, "samples": 720000, "rate_hz": FS, "duration_s": 3600.0,
            "accel": {a: axis(N_A, K_A, B_A) for a in "xyz"}, "gyro": {a: axis(N_G, K_G, B_G) for a in "xyz"}}


def _fs(path):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened(), path
    return fs


def _double(node, key) -> float:
    n = node.getNode(key)
    assert not n.empty() and (n.isReal() or n.isInt()), key          # `>> double` of a number
    return n.real()


def _string(node, key) -> str:
    n = node.getNode(key)
    assert not n.empty() and n.isString(), key
    return n.string()


def _mat3(node, key) -> np.ndarray:
    """YamlParser::parse(..., Eigen::Matrix3d&): node[r][c] for r, c < 3."""
    n = node.getNode(key)
    assert not n.empty() and n.isSeq() and n.size() == 3, key
    return np.array([[n.at(r).at(c).real() for c in range(3)] for r in range(3)])


# ------------------------------------------------------------------ 1. OpenVINS
OV_DOUBLES = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
              "accelerometer_random_walk")                                   # print_and_load_noise
OV_MATRICES = ("Tw", "Ta", "R_IMUtoACC", "R_IMUtoGYRO", "Tg")                # print_and_load_state


def _ov_lower(t: np.ndarray) -> np.ndarray:
    """What OpenVINS keeps of T⁻¹ for model kalibr / calibrated: its lower triangle (State::Dm)."""
    return np.tril(np.linalg.inv(t))


def _ov_apply(p: dict, a_m, w_m, b_a=0.0, b_g=0.0):
    """Propagator::predict_and_compute's corrected (a_hat, w_hat), rows of samples."""
    da, dw = _ov_lower(p["Ta"]), _ov_lower(p["Tw"])
    a_hat = (np.asarray(a_m) - b_a) @ da.T @ p["R_IMUtoACC"]                # R_ACCtoIMU = R_IMUtoACCᵀ
    w_hat = (np.asarray(w_m) - b_g - a_hat @ p["Tg"].T) @ dw.T @ p["R_IMUtoGYRO"]
    return a_hat, w_hat


def test_openvins_noise_file_has_every_key_ov_msckf_requires(tmp_path):
    f = NE.write_noise("openvins", tmp_path / "ov.yaml", _res(), topic="/imu0")
    fs = _fs(f)
    imu0 = fs.getNode("imu0")
    assert not imu0.empty()
    p = {k: _double(imu0, k) for k in OV_DOUBLES}
    assert p["accelerometer_noise_density"] == pytest.approx(N_A, rel=1e-5)     # continuous: Qc = σ²/dt
    assert p["gyroscope_random_walk"] == pytest.approx(K_G, rel=1e-5)
    assert _string(imu0, "model") in ("kalibr", "calibrated", "rpng")          # StateOptions::print
    assert _string(imu0, "rostopic") == "/imu0"
    p.update({k: _mat3(imu0, k) for k in OV_MATRICES})
    assert np.all(np.isfinite(np.linalg.inv(p["Tw"]))) and np.all(np.isfinite(np.linalg.inv(p["Ta"])))
    samples = np.random.default_rng(0).normal(0, 5, (200, 3))
    a_hat, w_hat = _ov_apply(p, samples, samples)                   # a calibrated stream goes through unchanged
    np.testing.assert_array_equal(a_hat, samples)
    np.testing.assert_array_equal(w_hat, samples)


# ------------------------------------------------------------------ 2, 3. imu_utils, VINS-Fusion
def test_vins_fusion_gets_a_per_sample_sigma_as_integration_base_uses_it(tmp_path):
    f = NE.write_noise("vins-fusion", tmp_path / "vf.yaml", _res(), topic="/imu0")
    fs = _fs(f)
    v = {k: _double(fs.root(), k) for k in ("acc_n", "gyr_n", "acc_w", "gyr_w", "g_norm")}   # readParameters
    dt = 1.0 / FS
    # integration_base.h: a sample's noise enters with variance ACC_N²; a white density N gives N²/dt
    assert v["acc_n"] ** 2 == pytest.approx(N_A ** 2 / dt, rel=1e-5)
    assert v["gyr_n"] ** 2 == pytest.approx(N_G ** 2 / dt, rel=1e-5)
    # one step adds ACC_W²·dt² to the bias (V.block(9,12) = I·dt); a random walk K adds K²·dt
    assert (v["acc_w"] * dt) ** 2 == pytest.approx(K_A ** 2 * dt, rel=1e-5)
    assert (v["gyr_w"] * dt) ** 2 == pytest.approx(K_G ** 2 * dt, rel=1e-5)
    assert v["g_norm"] == pytest.approx(G0)
    assert "sigma of ONE sample" in f.read_text()


def test_imu_utils_file_holds_what_imu_utils_writes(tmp_path):
    f = NE.write_noise("imu-utils", tmp_path / "iu.yaml", _res(), name="imu")
    fs = _fs(f)
    assert _string(fs.root(), "type") == "IMU" and _string(fs.root(), "name") == "imu"
    for blk, n_key, w_key, n, b in (("Gyr", "gyr_n", "gyr_w", N_G, B_G), ("Acc", "acc_n", "acc_w", N_A, B_A)):
        for ax in ("avg-axis", "x-axis", "y-axis", "z-axis"):
            node = fs.getNode(blk).getNode(ax)
            assert _double(node, n_key) == pytest.approx(n * math.sqrt(FS), rel=1e-5)    # getWhiteNoise: N·√f
            assert _double(node, w_key) == pytest.approx(0.664 * b, rel=1e-5)            # getBiasInstability: min ADEV
    assert "NOT a random walk" in f.read_text()


# ------------------------------------------------------------------ 5. Kalibr intrinsics, read as OpenVINS maps them
KALIBR_MODELS = ("calibrated", "scale-misalignment", "scale-misalignment-size-effect")


def _fit(m, b) -> TriadFit:
    return TriadFit(method="test", m=np.asarray(m, float), b=np.asarray(b, float), cov=np.zeros((12, 12)))


@pytest.fixture(scope="module")
def truth():
    t = ferraris_truth(3)
    return _fit(t["accel_m"], t["accel_b"]), _fit(t["gyro_m"], t["gyro_b"])


def _kalibr(tmp_path, acc, gyr, gsens=None) -> dict:
    f, = PF.write("kalibr", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0,
                  accel_unit="mps2", gyro_unit="rad_s", scaled=True, comment="test", gsens=gsens)
    k = yaml.safe_load(f.read_text())["imu0"]
    assert k["model"] in KALIBR_MODELS
    assert set(k["accelerometers"]) == {"M"} and set(k["gyroscopes"]) == {"M", "A", "C_gyro_i"}
    m_a, m_g = np.array(k["accelerometers"]["M"], float), np.array(k["gyroscopes"]["M"], float)
    c, a = np.array(k["gyroscopes"]["C_gyro_i"], float), np.array(k["gyroscopes"]["A"], float)
    assert np.array_equal(m_a, np.tril(m_a)) and np.array_equal(m_g, np.tril(m_g))   # M_accel_Dv, M_gyro_Dv pattern
    np.testing.assert_allclose(c @ c.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c) == pytest.approx(1.0)
    return {"Ma": m_a, "Mg": m_g, "C": c, "A": a}


def _ours(acc, gyr, ua, ug, gsens=None):
    """imubench's own correction: x = M⁻¹(u − b), ω = M_g⁻¹(u_g − b_g − G·f), f in g."""
    a = acc.correct(ua)
    g = np.zeros((3, 3)) if gsens is None else gsens
    return a, (ug - gyr.b - (a / G0) @ g.T) @ np.linalg.inv(gyr.m).T


def _samples(acc, gyr, gsens=None, n=500):
    rng = np.random.default_rng(11)
    f = rng.normal(0, 12, (n, 3))                     # m/s²
    w = rng.uniform(-np.radians(300), np.radians(300), (n, 3))
    g = np.zeros((3, 3)) if gsens is None else gsens
    return f @ acc.m.T + acc.b, w @ gyr.m.T + (f / G0) @ g.T + gyr.b, f, w


def test_kalibr_intrinsics_hold_our_model_exactly_and_openvins_applies_them_exactly(tmp_path, truth):
    acc, gyr = truth
    k = _kalibr(tmp_path, acc, gyr)
    assert np.count_nonzero(k["A"]) == 0                                     # no g-sensitivity fitted: zeros
    q_a = PF.rq(acc.m)[1]                                                    # the IMU frame: a_i = Q_a·x
    ua, ug, f, w = _samples(acc, gyr)
    # Kalibr's measurement model (addAccelerometerErrorTerms / addGyroscopeErrorTerms), biases ours
    np.testing.assert_allclose((f @ q_a.T) @ k["Ma"].T + acc.b, ua, atol=1e-10)
    np.testing.assert_allclose((w @ q_a.T) @ k["C"].T @ k["Mg"].T + gyr.b, ug, atol=1e-12)
    # OpenVINS' example mapping: Tw ← M, R_IMUtoGYRO ← C_gyro_i, Ta ← M, R_IMUtoACC ← I, Tg ← A
    p = {"Tw": k["Mg"], "R_IMUtoGYRO": k["C"], "Ta": k["Ma"], "R_IMUtoACC": np.eye(3), "Tg": k["A"]}
    a_hat, w_hat = _ov_apply(p, ua, ug, acc.b, gyr.b)
    a_ours, w_ours = _ours(acc, gyr, ua, ug)
    assert np.max(np.abs(a_hat @ q_a - a_ours)) < 1e-9                      # m/s², in our body axes
    assert np.degrees(np.max(np.abs(w_hat @ q_a - w_ours))) < 1e-9          # °/s over ±300 °/s


def test_kalibr_g_sensitivity_is_kalibrs_a(tmp_path, truth):
    acc, gyr = truth
    gsens = np.radians([[0.03, 0.0, 0.0], [0.0, -0.02, 0.01], [0.0, 0.0, 0.04]])     # rad/s per g
    k = _kalibr(tmp_path, acc, gyr, gsens)
    q_a = PF.rq(acc.m)[1]
    ua, ug, f, w = _samples(acc, gyr, gsens)
    f_i, w_i = f @ q_a.T, w @ q_a.T
    # w_meas = M_g·C·w_i + A·C·a_i + b_g: exact
    np.testing.assert_allclose(w_i @ k["C"].T @ k["Mg"].T + f_i @ k["C"].T @ k["A"].T + gyr.b, ug, atol=1e-12)
    # OpenVINS maps Tg ← A and applies it to a_hat in the IMU frame (not C·a_i): the stated small loss
    p = {"Tw": k["Mg"], "R_IMUtoGYRO": k["C"], "Ta": k["Ma"], "R_IMUtoACC": np.eye(3), "Tg": k["A"]}
    _, w_hat = _ov_apply(p, ua, ug, acc.b, gyr.b)
    _, w_ours = _ours(acc, gyr, ua, ug, gsens)
    loss = np.max(np.abs(w_hat @ q_a - w_ours))
    bound = np.linalg.norm(k["A"], 2) * np.linalg.norm(k["C"] - np.eye(3), 2) * np.max(np.linalg.norm(f, axis=1))
    assert loss <= bound * 1.01 + 1e-12


def test_rq_is_exact_and_triangular():
    rng = np.random.default_rng(4)
    for _ in range(50):
        m = np.eye(3) + rng.normal(0, 0.05, (3, 3))
        low, q = PF.rq(m)
        np.testing.assert_allclose(low @ q, m, atol=1e-14)
        assert np.array_equal(low, np.tril(low)) and np.all(np.diag(low) > 0)
        np.testing.assert_allclose(q @ q.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(q) == pytest.approx(1.0)


# ------------------------------------------------------------------ 4. PX4 device ids
def _qgc_rows(text: str) -> dict:
    """readParametersFromStream: '#' lines skipped, 5 TAB fields, else skipped."""
    rows = {}
    for ln in text.splitlines():
        if ln.startswith("#"):
            continue
        f = ln.split("\t")
        assert len(f) == 5, ln                             # a line of ours it would skip: none
        assert f[:2] == ["1", "1"] and f[4] in ("6", "9")
        rows[f[2]] = int(f[3]) if f[4] == "6" else float(f[3])
    return rows


def _px4_correct(p: dict, device_id: int, raw):
    """FindCurrentCalibrationIndex + Accelerometer::Correct: the slot whose CAL_ACCn_ID matches, else Reset()."""
    slot = next((n for n in range(4) if p.get(f"CAL_ACC{n}_ID") == device_id), -1)
    if slot < 0:
        return np.asarray(raw, float)                      # offset 0, scale 1
    off = np.array([p[f"CAL_ACC{slot}_{a}OFF"] for a in "XYZ"])
    scale = np.array([p[f"CAL_ACC{slot}_{a}SCALE"] for a in "XYZ"])
    return (np.asarray(raw, float) - off) * scale


def test_px4_file_with_ids_is_used_by_the_sensor_it_names(tmp_path, truth):
    acc, gyr = truth
    dev_acc, dev_gyro = 1310988, 2163722
    f, = PF.write("px4", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0, accel_unit="mps2",
                  gyro_unit="rad_s", scaled=True, px4_acc_id=dev_acc, px4_gyro_id=dev_gyro)
    p = _qgc_rows(f.read_text())
    assert p["CAL_ACC0_ID"] == dev_acc and p["CAL_GYRO0_ID"] == dev_gyro
    assert p["CAL_ACC0_PRIO"] == -1 and p["CAL_GYRO0_PRIO"] == -1
    assert "NOT USABLE" not in f.read_text()
    ua, _, truth_f, _ = _samples(acc, gyr)
    got = _px4_correct(p, dev_acc, ua)
    # PX4 holds offset and diagonal scale: what it leaves is the cross-axis part, measured here
    diag_only = (ua - acc.b) / np.diag(acc.m)
    np.testing.assert_allclose(got, diag_only, atol=1e-6)
    assert np.max(np.abs(got - acc.correct(ua))) > 0          # the cross-axis terms it cannot hold
    # the gyro: offsets only (Gyroscope::Correct has no scale): the loss the file states bounds the measured one
    _, ug, _, w = _samples(acc, gyr)
    err_dps = np.degrees(np.linalg.norm(ug - [p[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"] - w, axis=1))
    assert np.all(err_dps <= PF.gyro_scale_loss_dps(gyr.m, 1.0) * np.degrees(np.linalg.norm(w, axis=1)) + 1e-9)
    assert f"{PF.gyro_scale_loss_dps(gyr.m, 300.0):.2f} deg/s at 300 deg/s" in f.read_text()
    np.testing.assert_array_equal(_px4_correct(p, 999, ua), ua)     # another sensor: slot not used


def test_px4_file_without_ids_says_it_is_not_usable(tmp_path, truth):
    acc, gyr = truth
    f, = PF.write("px4", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0, accel_unit="mps2",
                  gyro_unit="rad_s", scaled=True)
    text = f.read_text()
    assert "CAL_ACC0_ID" not in _qgc_rows(text)
    head = [ln for ln in text.splitlines() if ln.startswith("#")]
    assert any("NOT USABLE AS IS" in ln and "CAL_ACC0_ID / CAL_GYRO0_ID" in ln for ln in head)
    assert any("listener sensor_accel" in ln and "CAL_ACC0_ID" in ln for ln in head)


def test_calibrate_from_takes_the_px4_ids_and_says_when_they_are_missing(tmp_path):
    from imu_synth import ferraris_session
    ua, ug, _, _ = ferraris_session(fs=100.0, seed=3)
    rec = tmp_path / "rec.csv"
    np.savetxt(rec, np.column_stack([ua, ug]), delimiter=",", header="ax,ay,az,gx,gy,gz", comments="", fmt="%.9g")

    def run(*extra):
        return subprocess.run([sys.executable, "-m", "imubench", "calibrate", "--from", str(rec), "--rate", "100",
                               "--accel-unit", "mps2", "--gyro-unit", "rad_s", "--gyro", "turns", "--export", "px4",
                               "--db", str(tmp_path / "h.sqlite"), *extra], capture_output=True, text=True,
                              cwd=tmp_path, timeout=300, stdin=subprocess.DEVNULL)
    r = run("--dir", "a")
    assert r.returncode == 0, r.stdout + r.stderr
    lines = [ln for ln in r.stdout.splitlines() if "NOT USABLE AS IS" in ln]
    assert len(lines) == 1 and "listener sensor_accel" in lines[0] and "--px4-acc-id" in lines[0]
    r = run("--dir", "b", "--px4-acc-id", "0x140109", "--px4-gyro-id", "2163722")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "NOT USABLE" not in r.stdout
    p = _qgc_rows(next((tmp_path / "b").glob("*.px4.params")).read_text())
    assert p["CAL_ACC0_ID"] == 0x140109 and p["CAL_GYRO0_ID"] == 2163722
    r = run("--dir", "c", "--px4-acc-id", "-5")
    assert r.returncode == 2 and "not a PX4 device id" in r.stderr


# ------------------------------------------------------------------ 7. ArduPilot
def _mavparm(text: str) -> dict:
    """pymavlink mavparm.MAVParmDict.load: '#' lines and blank lines skipped, a line split on ',' or
    white space into NAME VALUE (a third field ignored), anything else a bad line."""
    out = {}
    for ln in text.splitlines():
        ln = ln.strip()
        if not ln or ln[0] == "#":
            continue
        f = ln.replace(",", " ").split()
        assert len(f) >= 2, ln                             # a line of ours it would reject: none
        out[f[0]] = float(f[1])
    return out


def test_ardupilot_file_as_ardupilot_applies_it_with_its_stated_loss(tmp_path, truth):
    acc, gyr = truth
    f, = PF.write("ardupilot", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0,
                  accel_unit="mps2", gyro_unit="rad_s", scaled=True)
    text = f.read_text()
    p = _mavparm(text)
    assert set(p) == {f"INS_{k}_{a}" for k in ("ACCOFFS", "ACCSCAL", "GYROFFS") for a in "XYZ"}
    ua, ug, _, w = _samples(acc, gyr)
    # AP_InertialSensor_Backend::_rotate_and_correct_accel: (raw - offset) * scale; gyro: raw - offset
    got_a = (ua - [p[f"INS_ACCOFFS_{a}"] for a in "XYZ"]) * [p[f"INS_ACCSCAL_{a}"] for a in "XYZ"]
    np.testing.assert_allclose(got_a, (ua - acc.b) / np.diag(acc.m), atol=1e-6)
    got_g = ug - [p[f"INS_GYROFFS_{a}"] for a in "XYZ"]
    # the gyro's scale and cross-axis terms are dropped: the loss the file states bounds the measured one
    err_dps = np.degrees(np.linalg.norm(got_g - w, axis=1))
    rate_dps = np.degrees(np.linalg.norm(w, axis=1))
    bound = PF.gyro_scale_loss_dps(gyr.m, 1.0) * rate_dps
    assert np.all(err_dps <= bound + 1e-9) and np.max(err_dps / bound) > 0.5      # a bound, and a tight one
    line = next(ln for ln in text.splitlines() if "no gyro scale" in ln)
    assert f"{PF.gyro_scale_loss_dps(gyr.m, 300.0):.2f} deg/s at 300 deg/s" in line
    head = " ".join(ln for ln in text.splitlines() if ln.startswith("#"))
    assert "INS_ACC_ID" in head and "INS_GYR_ID" in head and "register_accel" in head
    assert "3D Accel calibration needed" in head


def test_ardupilot_thermal_file_says_enable_then_reboot(tmp_path):
    texts = _thermal_texts("imubench")
    text = texts["ardupilot"]
    p = _mavparm(text)
    assert p["INS_TCAL1_ENABLE"] == 1
    names = [ln.split(",")[0] for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert names[0] == "INS_TCAL1_ENABLE"                    # first, so that a partial load enables it
    head = " ".join(ln for ln in text.splitlines() if ln.startswith("#"))
    assert "INS_TCAL1_ENABLE = 1" in head and "reboot" in head and "load it again" in head


# ------------------------------------------------------------------ the consumers' own code, installed (pyproject [test])
def test_ardupilot_files_through_pymavlinks_own_loader(tmp_path, truth):
    """pymavlink mavparm.MAVParmDict.load (what MAVProxy's `param load` runs): every line of ours it
    reads is a parameter, none is 'Invalid line', and the values are the ones we wrote."""
    from pymavlink import mavparm
    acc, gyr = truth
    f, = PF.write("ardupilot", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0,
                  accel_unit="mps2", gyro_unit="rad_s", scaled=True, comment="board\nINS_ACCSCAL_X,5")
    texts = {"cal": f.read_text(), "thermal": _thermal_texts("warm\nINS_TCAL1_ENABLE,0")["ardupilot"]}
    for key, text in texts.items():
        path = tmp_path / f"{key}.param"
        path.write_text(text)
        p = mavparm.MAVParmDict()
        assert p.load(str(path)) is True
        assert dict(p) == _mavparm(text), key                    # exactly our rows, nothing from a comment
    p = mavparm.MAVParmDict()
    p.load(str(tmp_path / "cal.param"))
    got = (np.asarray(_samples(acc, gyr)[0]) - [p[f"INS_ACCOFFS_{a}"] for a in "XYZ"]) * [p[f"INS_ACCSCAL_{a}"]
                                                                                       for a in "XYZ"]
    np.testing.assert_allclose(got, (_samples(acc, gyr)[0] - acc.b) / np.diag(acc.m), atol=1e-6)


def test_imucal_file_through_imucals_own_loader_and_calibrate(tmp_path, truth):
    """imucal (PyPI) loads our file with its own load_calibration_info and its calibrate() gives
    our correction: accelerometer in m/s², gyro in deg/s (its units), g-sensitivity included."""
    from imucal.management import load_calibration_info
    acc, gyr = truth
    g = np.radians(np.diag([0.03, -0.02, 0.04]))                  # rad/s per g
    f, = PF.write("imucal", tmp_path / "cal", accel=acc, gyro=gyr, accel_factor=1.0, gyro_factor=1.0,
                  accel_unit="mps2", gyro_unit="rad_s", scaled=True, gsens=g, comment='a "name"\n}{')
    cal = load_calibration_info(f)
    ua, ug, f_true, w_true = _samples(acc, gyr, gsens=g)
    a_cal, g_cal = cal.calibrate(ua, ug, acc_unit=cal.from_acc_unit, gyr_unit=cal.from_gyr_unit)
    np.testing.assert_allclose(a_cal, f_true, atol=1e-9)
    np.testing.assert_allclose(g_cal, np.degrees(w_true), atol=1e-7)


# ------------------------------------------------------------------ 8. names through every export
NAMES = ["board\nCBRK_IO_SAFETY,22027\n1\t1\tCBRK_IO_SAFETY\t22027\t6",
         "a\rSM: [1,0,0,0,1,0,0,0,1]\r\nbias: [9,9,9]",
         "x\x0bimu0:\x0c  model: rpng\x85gyr_n: 1\u2028acc_n: 2\u2029",
         "q\"uote'd # not: [a comment] {y: 1} &anchor *ref !!tag |\n---\n...",
         "tab\there\x00\x1b[2J\x07\x7f\x9b\u202e",
         "%YAML:1.0\n---\nimu0:\n  Tw: [[9,9,9],[9,9,9],[9,9,9]]"]


def _not_comments(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]


def _calibration_texts(comment: str, truth) -> dict:
    acc, gyr = truth
    g = np.radians(np.diag([0.03, -0.02, 0.04]))
    return {"ardupilot": PF.ardupilot_text(acc.m, acc.b, gyr.b, comment, gyr.m),
            "kalibr": PF.kalibr_intrinsics_text(acc.m, gyr.m, g, comment),
            "px4": PF.px4_text(acc.m, acc.b, gyr.m, gyr.b, g, comment),
            "px4-ids": PF.px4_text(acc.m, acc.b, gyr.m, gyr.b, g, comment, acc_id=1, gyro_id=2),
            "imu-calib": PF.imu_calib_text(acc.m, acc.b, comment)}


def _noise_texts(name: str) -> dict:
    res = _res(source=f"/data/{name}.csv", name=name)
    return {"kalibr": NE.kalibr_text(res, name), "openvins": NE.openvins_text(res, name),
            "vins-fusion": NE.vins_fusion_text(res, name), "imu-utils": NE.imu_utils_text(res, name)}


def _thermal_texts(comment: str) -> dict:
    from test_warmup import T_REF, _fits_for_export

    from imubench.results import thermal_export as TX
    fits = _fits_for_export(np.random.default_rng(2))
    t_ref = {"accel": T_REF, "gyro": T_REF}
    return {"px4": TX.px4_text(fits, t_ref, "words", comment), "ardupilot": TX.ardupilot_text(fits, t_ref, "words",
                                                                                            comment)}


@pytest.mark.parametrize("name", NAMES)
def test_no_name_becomes_a_line_of_any_export(name, tmp_path, truth):
    from imubench.text import token
    for family, nasty, plain in (
            ("calibration", _calibration_texts(f"imubench from {name}.csv", truth),
             _calibration_texts("imubench from x.csv", truth)),
            ("noise", _noise_texts(name), {k: v for k, v in _noise_texts(token(name)).items()}),
            ("thermal", _thermal_texts(f"imubench from {name}.csv"), _thermal_texts("imubench from x.csv"))):
        for kind, text in nasty.items():
            where = f"{family} {kind}"
            # every line break any consumer knows (str.splitlines knows them all): as many lines as
            # with a plain name, and the lines that are not comments are the same lines
            assert len(text.splitlines()) == len(plain[kind].splitlines()), where
            assert _not_comments(text) == _not_comments(plain[kind]), where
            assert not any(c in text for c in "\r\x00\x0b\x0c\x1b\x85\u2028\u2029\u202e"), where
    # and each consumer's parser reads exactly its keys
    texts = _noise_texts(name)
    for kind, text in texts.items():
        p = tmp_path / f"{kind}.yaml"
        p.write_text(text)
        if kind == "kalibr":
            assert set(yaml.safe_load(text)) == {"rostopic", "update_rate", "accelerometer_noise_density",
                                                 "accelerometer_random_walk", "gyroscope_noise_density",
                                                 "gyroscope_random_walk"}
            continue
        fs = _fs(p)
        root = fs.root()
        keys = set(root.keys())
        if kind == "openvins":
            assert keys == {"imu0"}
            assert _string(root.getNode("imu0"), "model") == "calibrated"
            np.testing.assert_array_equal(_mat3(root.getNode("imu0"), "Tw"), np.eye(3))
        elif kind == "vins-fusion":
            assert keys == {"imu_topic", "acc_n", "gyr_n", "acc_w", "gyr_w", "g_norm"}
        else:
            assert keys == {"type", "name", "Gyr", "Acc"} and _string(root, "name") == token(name)
    cal = _calibration_texts(f"imubench from {name}.csv", truth)
    assert set(_qgc_rows(cal["px4-ids"])) == set(_qgc_rows(_calibration_texts("x", truth)["px4-ids"]))
    assert set(yaml.safe_load(cal["imu-calib"])) == {"SM", "bias"}
    assert set(yaml.safe_load(cal["kalibr"])) == {"imu0"}
