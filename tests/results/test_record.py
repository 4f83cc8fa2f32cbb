"""The calibration record (results/record.py): one structure, one schema, one validation, one
verdict rule, one JSON conversion, one clock."""
from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pytest
from imubench.calib import TriadFit
from imubench.results.record import RECORD_SCHEMA, CalibrationRecord, now_utc, verdict


def _fit(method="six_position"):
    return TriadFit(method=method, m=np.eye(3) * 1.001, b=np.array([0.01, -0.02, 0.03]),
                    cov=np.eye(12) * 1e-8, residual_rms=np.float64(2e-4),
                    extra={"n": np.int64(6), "dirs": np.ones((2, 3))})


def _record(rms_mg=0.4, **kw):
    return CalibrationRecord.from_fit(
        device={"mcu_uid": "0123456789ABCDEF01234567", "board": "SIM", "fw_version": "1.0", "fw_build": "x"},
        started=now_utc(), method="six", gyro_method="bias", accel=_fit(), gyro=_fit("bias"),
        poses=[{"name": "+Z up", "n": 100, "before_g": 1.001, "after_g": 1.0}],
        tolerances={"accel_rms_mg": 1.0, "verify_mg": 2.0}, accel_rms_after_mg=np.float64(rms_mg), **kw)


def test_the_record_is_plain_json_with_one_schema_and_round_trips():
    rec = _record(sections={"source": {"path": "x.csv"}})
    d = rec.to_json()
    assert d["schema"] == RECORD_SCHEMA == 2
    assert json.loads(json.dumps(d)) == d                       # nothing numpy left
    assert d["accel"]["extra"]["n"] == 6 and d["accel"]["residual_rms_mps2"] == pytest.approx(2e-4)
    assert d["source"] == {"path": "x.csv"} and "failure" not in d
    back = CalibrationRecord.from_json(d)
    assert back.to_json() == d and back.sections == {"source": {"path": "x.csv"}}


def test_the_fit_passes_by_its_tolerance_and_the_run_by_the_one_verdict():
    assert _record(0.4).passed and not _record(1.5).passed
    ok = _record(0.4).to_json()
    assert verdict(ok, write_requested=False) == (True, [])
    assert verdict(ok, write_requested=True) == (False, ["written parameters not verified"])
    assert verdict(ok | {"verified": True}, write_requested=True) == (True, [])
    bad, why = verdict(_record(1.5).to_json(), write_requested=False)
    assert not bad and why == ["fit out of tolerance: |a| − g RMS 1.500 mg > 1 mg"]
    meas = [{"name": "accel_rms_after", "value": 3.0, "unit": "mg", "passed": False}]
    assert verdict(ok | {"measurements": meas}, False) == (False, ["accel_rms_after = 3 mg outside its limit"])
    failed = ok | {"failure": {"stage": "write", "reason": "link lost"}}
    assert verdict(failed, False) == (False, ["failed at write: link lost"])


def test_a_malformed_record_is_refused_naming_what_is_wrong():
    d = _record().to_json()
    d["accel"]["m"] = [[1, 2], [3, 4]]
    del d["finished"]
    with pytest.raises(ValueError, match="missing finished.*accel.m must be 3x3"):
        CalibrationRecord.from_json(d)


def test_one_clock_utc_with_microseconds():
    t = dt.datetime.fromisoformat(now_utc())
    assert t.utcoffset() == dt.timedelta(0) and abs((dt.datetime.now(dt.timezone.utc) - t).total_seconds()) < 5
    assert len(now_utc().split(".")[1]) == len("000000+00:00")
