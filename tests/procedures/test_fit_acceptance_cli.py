"""Issue 32 items 1-2 and issue 40 item 5 through the command line, as a user types it:
hand-held recordings (tests/imu_synth.handheld_session) calibrated with the defaults (an accepted
and a refused run in a subprocess; the others through the same entry point, imubench.cli.main,
in-process: tests/inproc.py). Accepted
where the truth is observable, with the scales within 3σ of the truth; refused with the reason
where not; never worse than no calibration on the same rests."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from imu_synth import EDGES_XZ_YZ, FACES6, G0, handheld_session, spread_ups, tilted, write_csv
from imubench.calib.accel import lower_triangular_form

FS = 100.0


def _cli(path, d, *extra):
    return subprocess.run([sys.executable, "-m", "imubench", "calibrate", "--from", str(path), "--dir", str(d),
                           "--accel-unit", "g", "--gyro-unit", "dps", "--db", str(d.parent / f"{d.name}.sqlite"),
                           *extra], capture_output=True, text=True, cwd=d.parent, timeout=300,
                          stdin=subprocess.DEVNULL)


def _main(path, d, monkeypatch, capsys, *extra):
    """_cli's command in this process."""
    from inproc import run_main
    return run_main(["calibrate", "--from", path, "--dir", d, "--accel-unit", "g", "--gyro-unit", "dps", "--db",
                     d.parent / f"{d.name}.sqlite", *extra], monkeypatch, capsys, cwd=d.parent)


def _run(tmp_path, name, ups, *extra, inproc=None, **kw):
    """The recording calibrated by the command line: in a subprocess, or in-process when inproc
    is (monkeypatch, capsys)."""
    ua, ug, truth, _ = handheld_session(ups, fs=FS, **kw)
    p = write_csv(tmp_path / f"{name}.csv", ua / G0, np.degrees(ug), FS)
    r = _cli(p, tmp_path / name, *extra) if inproc is None else _main(p, tmp_path / name, *inproc, *extra)
    assert "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    return r, truth


def _accepted(r, d, truth):
    """The result of an accepted run: exit 0, scales within 3σ of the truth, |a| − g after no
    worse than before on the same rests, every rest named with its use."""
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads((d / "session.json").read_text())["result"]
    a = res["accel"]
    if a["method"] == "multi_position":
        L, _ = lower_triangular_form(truth["accel_m"])
        z = (np.array(a["extra"]["scales"]) - np.diag(L)) / np.array(a["extra"]["sigma_scales"])
    else:
        z = (np.diag(a["m"]) - np.diag(truth["accel_m"])) / np.diag(a["sigma_m"])
    assert np.all(np.abs(z) < 3), z
    before = np.array([p["before_g"] for p in res["poses"]])
    after = np.array([p["after_g"] for p in res["poses"]])
    assert np.sqrt(np.mean((after - 1) ** 2)) <= np.sqrt(np.mean((before - 1) ** 2))
    for rest in res["rests"]:
        assert rest["use"] in ("used", "down-weighted", "left out") and rest["sigma_inflation"] >= 1.0
        assert rest["use"] == "used" or rest["use_reason"]
    return res


def test_hand_held_rests_with_slow_tilts(tmp_path):
    n = 26
    r, truth = _run(tmp_path, "tilts", spread_ups(n), tilt_deg=np.geomspace(0.01, 1.0, n),
                    drift_mg=np.linspace(0.0, 1.0, n), seed=5)
    res = _accepted(r, tmp_path / "tilts", truth)
    assert len(res["rests"]) == n and all(x["use"] != "left out" for x in res["rests"])
    down = [x for x in res["rests"] if x["use"] == "down-weighted"]
    assert len(down) >= 10 and all("moved" in x["use_reason"] and "σ ×" in x["use_reason"] for x in down)
    assert "down-weighted: moved" in r.stdout                       # named in what is printed
    assert res["accel"]["method"] == "multi_position" and not res["accel_held"]


def test_one_rest_per_face(tmp_path, monkeypatch, capsys):
    r, truth = _run(tmp_path, "faces", list(FACES6), seed=5, inproc=(monkeypatch, capsys))
    res = _accepted(r, tmp_path / "faces", truth)
    assert res["accel"]["method"] == "six_position"
    assert "method: six-position (the multi-position fit cannot be used: too few poses" in r.stdout


@pytest.fixture(scope="module")
def six_handheld_ups():
    rng = np.random.default_rng(3)     # each face tilted up to 22°, put down twice about the same way
    return [tilted(f, 3, rng) for f in [tilted(d, 22, rng) for d in FACES6] for _ in range(2)]


def test_six_face_only_hand_held_keeps_biases_and_scales(tmp_path, six_handheld_ups, monkeypatch, capsys):
    r, truth = _run(tmp_path, "six", six_handheld_ups, tilt_deg=0.3, drift_mg=0.2, seed=5, inproc=(monkeypatch, capsys))
    res = _accepted(r, tmp_path / "six", truth)
    assert res["accel_held"] == ["a_yx", "a_zx", "a_zy"]
    assert "a_yx, a_zx, a_zy held at nominal" in res["verdict"]
    assert "held at nominal (not resolved by the rests): a_yx, a_zx, a_zy" in r.stdout       # the table
    six = next(c for c in res["accel_candidates"] if c["kind"] == "six12")
    assert six["status"] in ("refused", "unresolved")


def test_six_face_only_hand_held_with_method_six_is_refused_not_fitted(tmp_path, six_handheld_ups):
    """Issue 32 item 2: six-position on hand-held faces was accepted worse than no calibration."""
    r, _ = _run(tmp_path, "six6", six_handheld_ups, "--method", "six", tilt_deg=0.3, drift_mg=0.2, seed=5)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(err) == 1, r.stdout + r.stderr
    assert "nothing is calibrated" in err[0] and "six-position" in err[0] and "Next:" in err[0]
    assert "PASSED" not in r.stdout


def test_ten_rests_one_per_face_and_four_edges(tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(3)
    ups = [tilted(d, 1.5, rng) for d in list(FACES6) + list(EDGES_XZ_YZ)]
    r, truth = _run(tmp_path, "ten", ups, tilt_deg=0.3, drift_mg=0.2, seed=5, inproc=(monkeypatch, capsys))
    res = _accepted(r, tmp_path / "ten", truth)
    assert res["accel_held"] == ["a_yx"] and "a_yx held at nominal" in res["verdict"]
    assert res["accel_candidates"][0]["kind"] == "multi9" and res["accel_candidates"][0]["status"] != "kept"
    assert len(res["rests"]) == 10


def test_gyro_motions_never_about_z_fit_the_rest_and_hold_its_column(tmp_path, monkeypatch, capsys):
    """Issue 40 item 5 for the gyro: turns about X and Y only leave M's Z column (m02, m12,
    m22) unresolved; the rotation method fits the other six entries and holds those."""
    z, y, x = [0, 0, 1], [0, 1, 0], [1, 0, 0]
    neg = lambda v: [-a for a in v]     # noqa: E731
    ups = [z, y, neg(z), neg(y), z, x, neg(z), neg(x), z, neg(y), neg(z), y, z, neg(x), neg(z), x, z]
    r, truth = _run(tmp_path, "gyro", ups, seed=4, inproc=(monkeypatch, capsys))
    res = _accepted(r, tmp_path / "gyro", truth)
    g = res["gyro"]
    assert g["method"] == "rotation" and g["extra"]["held"] == ["m02", "m12", "m22"]
    assert "m02, m12, m22 held at nominal" in res["verdict"]
    m, sm = np.array(g["m"]), np.array(g["sigma_m"])
    assert np.all(m[:, 2] == np.eye(3)[:, 2]) and np.all(sm[:, 2] > 0)
    assert np.all(np.abs((m - truth["gyro_m"]) / sm)[:, :2] < 3)
