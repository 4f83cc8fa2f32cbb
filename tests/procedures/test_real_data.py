"""imubench on real data: imucal's public example Ferraris session (tests/data/imucal, MIT).

No ground truth exists for these files: the tests check what the data can decide (the
segmentation against one person's annotation, that the fits succeed with finite sigmas, the
refusal of the multi-position method, imubench's counts fit against imucal's own, rests the fit
did not use) and pin the figures bench/real_data.py prints, so a change in them is seen."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("real_data", ROOT / "bench" / "real_data.py")
real_data = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(real_data)


@pytest.fixture(scope="module")
def si():
    return real_data.si_figures()


@pytest.fixture(scope="module")
def counts():
    return real_data.counts_figures()


def test_the_data_files_are_small_and_licensed():
    d = ROOT / "tests" / "data" / "imucal"
    assert "MIT License" in (d / "LICENSE").read_text()
    assert "mad-lab-fau/imucal" in (d / "README.md").read_text()
    assert sum(p.stat().st_size for p in d.iterdir()) < 300_000
    m = ROOT / "tests" / "data" / "mikoff"
    assert "MIT License" in (m / "LICENSE").read_text() and "mikoff/imu-calib" in (m / "README.md").read_text()
    assert sum(p.stat().st_size for p in m.iterdir()) < 400_000


def test_segmentation_finds_the_six_rests_and_three_turns_without_the_annotation(si):
    r = si["result"]
    assert sorted(set(s["face"] for s in r["segmentation"])) == ["+X", "+Y", "+Z", "-X", "-Y", "-Z"]
    assert len(r["segmentation"]) == 13          # the faces, and the rests before and after each turn
    usable = [t for t in r["turns"] if t["usable"]]
    assert [t["label"] for t in usable] == ["turn about +X", "turn about +Y", "turn about +Z"]
    # compared with imucal's annotation: every section found, each annotated section inside the
    # detected one (the annotation is cut conservatively), ends within 2 s
    ann = r["annotation"]
    assert len(ann) == 9 and all(a["found"] for a in ann)
    assert all(a["annotated_inside_detected"] for a in ann)
    assert max(max(abs(a["start_diff_s"]), abs(a["stop_diff_s"])) for a in ann) < 2.0
    rests = {a["section"]: a for a in ann if a["kind"] == "rest"}
    assert set(rests) == {"x_p", "x_a", "y_p", "y_a", "z_p", "z_a"}


def test_six_position_and_known_angle_fits_succeed_with_sigmas(si):
    fa, r = si["analysis"], si["result"]
    assert fa.accel.method == "six_position" and np.all(fa.accel.sigma_m > 0) and np.all(fa.accel.sigma_m < 2e-3)
    assert np.all(np.isfinite(fa.accel.sigma_b)) and np.all(fa.accel.sigma_b < 0.01)
    # |a| - g per rest: 58 mg RMS before, about 1 mg after; on rests the fit did not use, 1.4 mg
    before = np.array([p["before_g"] for p in r["poses"]])
    after = np.array([p["after_g"] for p in r["poses"]])
    assert 50 < np.sqrt(np.mean((before - 1) ** 2)) * 1e3 < 65
    assert r["accel_rms_after_mg"] < 1.5
    assert si["held_out"]["rms_after_mg"] < 2.0 and len(si["held_out"]["rests"]) == 7
    assert np.all(np.abs(after - 1) < 3e-3)
    g = fa.gyro           # the known-angle turns and the rotation method, combined (consistent)
    assert g.method == "turns+rotation" and np.all(np.isfinite(g.sigma_m)) and np.all(np.diag(g.sigma_m) < 5e-3)
    turns = r["turns"]
    assert [round(t["before_deg"]) for t in turns] == [-370, -354, -359]
    assert all(abs(t["after_deg"] - t["known_deg"]) < 1.5 for t in turns)   # within the hand's placement
    assert "cannot check the fit" in r["gyro_parts"]["fits"]["turns"]["extra"]["warnings"][0]


def test_multi_position_on_six_faces_is_refused_with_the_reason(si):
    assert "6 distinct attitudes" in si["multi_refusal"] and "needs at least 9" in si["multi_refusal"]


def test_the_rotation_method_is_used_on_this_session_though_y_turns_one_way(si):
    """Board Y is turned one way only in this session: with the rest bias known that constrains
    its scale (decided by the σ, not refused by rule), and the result agrees with the turns."""
    parts = si["result"]["gyro_parts"]
    assert parts["refused"] == {}
    rot = parts["fits"]["rotation"]
    assert np.all(np.array(rot["sigma_m"]) < 0.01) and rot["extra"]["reduced_chi2"] > 0
    assert "consistent" in " ".join(si["result"]["notes"]) or si["analysis"].gyro.method == "turns+rotation"


def test_counts_fit_agrees_with_imucals_own_calibration(counts):
    """The counts file, fitted by imubench without any nominal scale, beside imucal's own
    Ferraris calibration of it: the accelerometer's 9 entries and the gyro's scales within 1σ."""
    assert np.abs(counts["z_acc"]).max() < 1.0
    assert np.abs(np.diag(counts["z_gyr"])).max() < 1.0
    # the gyro's cross-axis terms differ by up to ~3σ: imucal also fits a g-sensitivity (K_ga)
    # that moves them; imubench does not
    assert np.abs(counts["z_gyr"]).max() < 3.5
    r = counts["result"]
    assert sorted(s["face"] for s in r["segmentation"]) == ["+X", "+Y", "+Z", "-X", "-Y", "-Z"]
    assert all("(part " in t["label"] for t in r["turns"])   # cut tightly around the turns: taken from the parts


def test_si_and_counts_files_are_not_the_same_calibration_state(si, counts):
    """The issue asked for the SI and counts files' parameters to agree within σ. They do not,
    and cannot: quantities free of any nominal scale (biases in each axis's own scale,
    accelerometer cross-axis terms) differ by 4-100 σ; the gyro's cross-axis terms, whose σ is
    the hand-turn budget, agree within 2.1 σ. The two files are different recordings (102.4 vs
    204.8 Hz, different turn speeds) — documented in docs/calibration.md and bench/real_data.py."""
    x = real_data.si_vs_counts(si, counts)
    assert np.abs(x["accel"]["z_bias"]).min() > 10
    assert np.abs(x["accel"]["z_cross"]).max() > 3.5
    # the SI gyro now also has the rotation method (the counts file cannot: cut at every part), so
    # its cross-axis σ is smaller and the difference reaches ~3σ (g-sensitivity, see above)
    assert np.abs(x["gyro"]["z_cross"]).max() < 3.5


def test_bench_script_prints_the_figures():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "real_data.py"), "--no-publish"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "compared with the annotation" in r.stdout and "imucal's own fit" in r.stdout
    assert r.stdout.strip().splitlines()[-1].startswith('{"si_rests": 13')
    # the figures are deterministic: the tables README and docs/calibration.md show (bench/results) are this run's
    for name in ("real_data", "real_data-gyro"):
        table = (ROOT / "bench" / "results" / f"{name}.md").read_text().split("\n\n", 1)[1]
        assert table in r.stdout, f"bench/real_data.py no longer prints bench/results/{name}.md: run it to publish"


# ------------------------------------------------------------------ issue 26: mikoff's MPU-9150 logs, the gyro
@pytest.fixture(scope="module")
def gyro_rows():
    return dict(real_data.all_recordings())


@pytest.mark.parametrize("name", ["imu0", "imu1"])
def test_mikoff_logs_calibrate_accelerometer_and_gyro_with_a_newcomers_defaults(name):
    """Hand-turned between 22 rests, some axes one way only: once refused by rule, now the
    rotation method fits with σ(M) ≤ 0.0012, next to the recording tool's own scales."""
    from imubench.procedures.from_file import FileAnalysis, FileConfig
    from imubench.recordings import read
    rec = read(real_data._mikoff(f"{name}.log"), rate_hz=100.0, accel_unit="mps2", gyro_unit="rad_s")
    fa = FileAnalysis(rec, FileConfig(), say=lambda s: None)       # the defaults: --gyro auto
    r = fa.run()
    assert r["passed"] and r["accel_rms_after_mg"] < 0.3 and not r["gyro_refused"]
    assert fa.gyro.method == "rotation" and np.all(fa.gyro.sigma_m < 0.0012)
    tool = {"imu0": [0.041, 0.457, 0.826], "imu1": [0.007, 0.26, -0.179]}[name]   # README: s_x, s_y, s_z (%)
    assert np.all(np.abs((np.diag(fa.gyro.m) - 1) * 100 - tool) < 0.35)
    assert "tolerance" in r["tolerance_source"] and r["verdict"].startswith("accelerometer calibrated")


def test_gyro_residual_figures_in_sample_and_held_out(gyro_rows):
    """bench/real_data.py's table: on the hand-held logs the bias of one rest is the weak point
    (the rests' mean does better on held-out motions); G is fitted with σ on every recording
    that has the attitudes, and the counts file (cut at every part) says why it has no figure."""
    for name in ("mikoff imu0 (MPU-9150)", "mikoff imu1 (MPU-9150)"):
        v = gyro_rows[name]["variants"]
        assert v["all rests' mean bias"]["held_out_rms_deg"] < 0.8 * v["one start bias"]["held_out_rms_deg"]
        assert all(c["in_sample_rms_deg"] < 0.3 for c in v.values())
        assert np.array(gyro_rows[name]["G_sigma_dps_per_g"]).max() < 0.01
    assert "held_out_refused" in gyro_rows["imucal Ferraris (SI)"]["variants"]["G"]
    counts = gyro_rows["imucal annotated (counts)"]
    assert counts["motions"] == 0 and "too few for the rotation method" in counts["refused"]
