"""The one front door of a fit (calib.fit, issue 35): one list of gyro methods for every
caller, one strategy, one result type."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import imubench.station

from imu_synth import G0, handheld_session, spread_ups
from imubench.calib.fit import (ACCEL_METHOD_LIST, GYRO_METHODS, Calibration, Evidence, Note, RecordingEvidence,
                                RotationEvidence, fit, fit_text, gyro_method)
from imubench.calib.static import detect_static

FS = 100.0


def test_every_caller_takes_its_gyro_methods_from_the_one_list():
    from imubench.cli.calibrate import GYRO_METHODS as cli_methods
    from imubench.cli.main import build_parser
    from imubench.procedures.from_file import GYRO_FILE_METHODS
    from imubench.station.runner import GYRO_METHODS as station_methods
    names = [m.name for m in GYRO_METHODS]
    assert len(set(names)) == len(names)
    assert tuple(cli_methods) == tuple(names)
    gyro_opt = next(a for a in build_parser()._subparsers._group_actions[0].choices["calibrate"]._actions
                    if a.dest == "gyro")
    assert tuple(gyro_opt.choices) == tuple(names)
    assert set(station_methods) == {m.name for m in GYRO_METHODS if m.live}
    assert set(GYRO_FILE_METHODS) == {m.name for m in GYRO_METHODS if m.recording}
    assert "turntable" not in GYRO_FILE_METHODS and "auto" not in station_methods
    page = (Path(imubench.station.__file__).parent / "static" / "station.html").read_text()
    select = re.search(r'<select name="gyro">(.*?)</select>', page, re.S).group(1)
    assert sorted(re.findall(r'<option value="([^"]+)"', select)) == sorted(station_methods)   # the page offers them all
    assert gyro_method("none") is None and gyro_method(None) is None
    with pytest.raises(ValueError, match="unknown gyro method 'spin': one of turntable, rotation"):
        gyro_method("spin")


def test_what_a_session_captures_is_the_strategys_to_say():
    from imubench.calib.fit import data_needed
    assert data_needed("multi", "rotation") == {"rest", "stream"}
    assert data_needed("six", "turntable") == {"rest", "turntable"}
    assert data_needed("multi", "turntable") == {"rest", "turntable", "stream"}    # the frames aligned on it
    assert data_needed("multi", "turns") == {"rest", "turns"} and data_needed("six", "bias") == {"rest"}
    assert data_needed("multi", None) == data_needed("multi", "none") == frozenset()
    src = (Path(imubench.station.__file__).parents[1] / "procedures" / "session.py").read_text()
    assert 'cfg.gyro == "' not in src            # the session asks the strategy, it keeps no list of its own


def test_the_accelerometer_methods_and_the_reports_words_come_from_the_same_lists():
    from imubench.cli.calibrate import METHODS as cli_accel
    from imubench.results.calibration import _method
    from imubench.station.runner import METHODS as station_accel
    live = tuple(m.name for m in ACCEL_METHOD_LIST if m.live)
    assert tuple(cli_accel) == live == ("multi", "six") and tuple(station_accel) == live
    page = (Path(imubench.station.__file__).parent / "static" / "station.html").read_text()
    select = re.search(r'<select name="method"[^>]*>(.*?)</select>', page, re.S).group(1)
    assert sorted(re.findall(r'<option value="([^"]+)"', select)) == sorted(live)
    # every fit a method gives has the report's words, and the record's text of a method is the list's
    fits = [f for m in ACCEL_METHOD_LIST + GYRO_METHODS for f, _ in m.fits]
    assert set(fits) >= {"six_position", "multi_position", "turntable", "rotation", "turns", "bias", "turns+rotation"}
    assert all(fit_text(f) != f for f in fits) and fit_text("allan") == "allan"
    assert fit_text("turns+rotation").startswith("known-angle turns and the rotation method")
    assert _method({"method": "six"}) == "six-position" and _method({"method": "odd"}) == "odd"
    src = (Path(imubench.station.__file__).parents[1] / "results" / "report.py").read_text()
    assert "six_position\"" not in src and "FIT_METHODS" not in src     # no second copy of the texts


def _evidence(seed=3):
    ua, ug, truth, _ = handheld_session(spread_ups(14), fs=FS, seed=seed, rest_s=3.0)
    ivs = detect_static(ua, FS)
    means = np.array([i.mean for i in ivs])
    sig = np.array([i.sigma_mean for i in ivs])
    longest = max(ivs, key=lambda i: i.n)
    rot = RotationEvidence(accel_mps2=ua, gyro_rad_s=ug, intervals=[(i.start, i.stop) for i in ivs],
                           rest_means_mps2=means)
    ev = Evidence(means_mps2=means, sigmas_mps2=sig, rate_hz=FS,
                  gyro_means_rad_s=np.array([ug[i.start:i.stop].mean(axis=0) for i in ivs]),
                  rest_gyro_rad_s=ug[longest.start:longest.stop], rotation=rot)
    ev.recording_parts = (ua, ug, ivs)
    return ev, truth


def _as_recording(ev: Evidence, gyro_scale=1.0) -> Evidence:
    """The same data as one recording's stream: the gyro's rests and turns found in it by fit."""
    ua, ug, ivs = ev.recording_parts
    rec = RecordingEvidence(gyro=ug / gyro_scale, gyro_scale=gyro_scale, accel_mps2=ua, rests=list(ivs), rate_hz=FS)
    return Evidence(means_mps2=ev.means_mps2, sigmas_mps2=ev.sigmas_mps2, rate_hz=FS, recording=rec)


def test_a_recording_is_fitted_by_the_same_front_door():
    ev, truth = _evidence()
    cal = fit(_as_recording(ev, gyro_scale=np.radians(1.0)), method="multi", gyro="auto",
              excess_limit_mps2=1e-3 * G0, gsens=False)
    assert isinstance(cal, Calibration) and cal.gyro_refused is None
    assert cal.gyro.method in ("rotation", "turns+rotation") and "rotation" in cal.gyro_parts["fits"]
    assert np.max(np.abs(np.diag(cal.gyro.m) - np.diag(truth["gyro_m"]))) < 0.01
    assert cal.gyro_scale == pytest.approx(np.radians(1.0))      # the recording's own unit, °/s here
    assert cal.gyro_bias is not None and cal.gsens_report is not None and "applied" in cal.gsens_report
    assert any(line.startswith("gyro bias from the longest still interval") for line in cal.said)
    assert cal.notes and all(isinstance(n, str) and not isinstance(n, Note) for n in cal.notes)
    assert [str(x) for x in cal.said if isinstance(x, Note)] == cal.notes
    bias = fit(_as_recording(ev), method="multi", gyro="bias", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert bias.gyro.method == "bias" and not bias.gyro_parts
    table = fit(_as_recording(ev), method="multi", gyro="turntable", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert table.gyro_refused.startswith("the turntable method needs a turntable's known rates; from a recording")
    assert table.gyro.method == "bias" and np.allclose(table.accel.m, cal.accel.m, atol=1e-3)


def test_one_fit_gives_the_accelerometer_and_the_gyro_of_a_recording():
    ev, truth = _evidence()
    cal = fit(ev, method="multi", gyro="rotation", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert isinstance(cal, Calibration) and cal.gyro_refused is None and cal.method == "multi"
    assert cal.accel_choice is not None and cal.accel.method == "multi_position"
    assert np.max(np.abs(cal.accel.b - truth["accel_b"])) < 0.01            # m/s²
    assert cal.gyro.method == "rotation"
    assert np.max(np.abs(np.diag(cal.gyro.m) - np.diag(truth["gyro_m"]))) < 0.01


def test_a_refused_gyro_keeps_the_accelerometer_and_the_bias_at_rest():
    ev, _ = _evidence()
    ev.rotation = RotationEvidence(problem="stream 1 has gaps (12 samples lost)")
    ok = fit(ev, method="multi", gyro="bias", excess_limit_mps2=1e-3 * G0, gsens=False)
    cal = fit(ev, method="multi", gyro="rotation", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert cal.gyro_refused == "stream 1 has gaps (12 samples lost)"
    assert cal.said == ["gyro not calibrated: stream 1 has gaps (12 samples lost)"]
    assert cal.gyro.method == "bias" and np.allclose(cal.gyro.b, ok.gyro.b)
    assert np.allclose(cal.accel.m, ok.accel.m)
    turntable = fit(ev, method="multi", gyro="turntable", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert "needs a turntable's segments" in turntable.gyro_refused
    auto = fit(ev, method="multi", gyro="auto", excess_limit_mps2=1e-3 * G0, gsens=False)
    assert "needs a recording's turns and rotations" in auto.gyro_refused
    assert fit(ev, method="multi", gyro="none", excess_limit_mps2=1e-3 * G0).gyro is None


def test_bad_method_names_are_refused_in_one_line():
    ev, _ = _evidence()
    with pytest.raises(ValueError, match="method must be one of multi, six, auto, not 'seven'"):
        fit(ev, method="seven", gyro=None, excess_limit_mps2=1e-3 * G0)
    with pytest.raises(ValueError, match="unknown gyro method 'spin'"):
        fit(ev, method="multi", gyro="spin", excess_limit_mps2=1e-3 * G0)
