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

ROOT = Path(__file__).resolve().parent.parent
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
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "real_data.py")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "compared with the annotation" in r.stdout and "imucal's own fit" in r.stdout
    assert r.stdout.strip().splitlines()[-1].startswith('{"si_rests": 13')
