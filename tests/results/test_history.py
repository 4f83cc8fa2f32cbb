"""The calibration history database and `imubench history` (main_history)."""
from __future__ import annotations

import copy
import json
import math
import sqlite3

import numpy as np
import pytest
from imubench.cli import main as imubench
from imubench.cli.history_text import format_device_report
from imubench.results import history as H
from imubench.results.history import (
    AmbiguousDevice,
    History,
    SchemaError,
    UnknownDevice,
)

G0 = 9.80665
UID_A = "0123456789ABCDEF01234567"      # upper-case hex, as imubench.wire.ids writes it
UID_B = "0123FFFF89ABCDEF01234567"
UID_C = "FEDCBA9876543210FEDCBA98"


def make_result(uid=UID_A, started="2026-11-22T06:40:00+00:00", accel_b_mps2=(0.01, -0.02, 0.03),
                sigma_b_mps2=2e-5, accel_scale=(250e-6, -310e-6, 80e-6), gyro=True, gyro_sn=(1001, 1002, 1003),
                note="bench A", passed=True):
    m = np.eye(3) + np.diag(accel_scale)
    m[0, 1], m[1, 2], m[2, 0] = 120e-6, -15e-6, -400e-6     # largest cross-axis: M[z,x]
    return {
        "schema": 1,
        "device": {"mcu_uid": uid, "board": "SIM", "fw_version": "0.2.0", "fw_build": "sim-0.1.0",
                   "parts": ["ADXL355", "ADXRS450", "ADXRS450", "ADXRS453"],
                   "accel_ids": [173, 29, 237, 1], "gyro_pid": [20993, 20993, 20994], "gyro_sn": list(gyro_sn)},
        "started": started, "finished": started[:11] + "07:05:00+00:00",
        "method": "six", "gyro_method": "turntable" if gyro else None,
        "accel": {"m": m.tolist(), "b_mps2": list(accel_b_mps2), "sigma_m": np.full((3, 3), 3e-6).tolist(),
                  "sigma_b_mps2": [sigma_b_mps2] * 3, "residual_rms_mps2": 1e-4, "extra": {"iterations": 4}},
        "gyro": {"m": (np.eye(3) * (1 + 500e-6)).tolist(), "b_rad_s": [1e-3, -2e-3, 5e-4],
                 "sigma_m": np.full((3, 3), 1e-5).tolist(), "sigma_b_rad_s": [1e-5] * 3, "residual_rms": 2e-4,
                 "extra": {}} if gyro else None,
        "poses": [{"name": n, "n": 2000, "before_g": 1.0 + 0.01 * (i + 1), "after_g": 1.0 + 1e-5 * (i - 2),
                   "sigma_g": 2e-5, "temp_c": 25.1}
                  for i, n in enumerate(["+X up", "-X up", "+Y up", "-Y up", "+Z up (level)", "-Z up"])],
        "temperature_c": {"accel": 25.0, "gyro": [25.2, 25.1, 25.3]},
        "tolerances": {"accel_rms_mg": 1.0, "verify_mg": 2.0},
        "passed": passed, "written": True, "verified": True,
        "verification": [{"name": "+Z up (level)", "after_g": 1.00001}],
        "note": note, "capture_dir": "/tmp/session-1",
    }


@pytest.fixture
def db(tmp_path):
    return tmp_path / "history.sqlite"


def test_record_runs_round_trip(db):
    r = make_result()
    with History(db) as h:
        run_id = h.record(r)
        runs = h.runs(UID_A)
        devs = h.devices()
    assert len(runs) == 1
    got = runs[0]
    assert got["run_id"] == run_id
    assert got["record"] == r                           # the whole record, unchanged
    assert got["mcu_uid"] == UID_A and got["board"] == "SIM"
    for k in ("started", "finished", "method", "gyro_method", "poses", "verification", "tolerances",
              "passed", "written", "verified", "note", "capture_dir"):
        assert got[k] == r[k], k
    for k in ("m", "b_mps2", "sigma_m", "sigma_b_mps2", "residual_rms_mps2"):
        assert got["accel"][k] == r["accel"][k], k
    for k in ("m", "b_rad_s", "sigma_m", "sigma_b_rad_s", "residual_rms"):
        assert got["gyro"][k] == r["gyro"][k], k
    assert got["temperature_c"] == r["temperature_c"]
    assert got["fw_version"] == "0.2.0" and got["fw_build"] == "sim-0.1.0"
    assert got["gyro_sn"] == [1001, 1002, 1003]
    assert devs == [{
        "mcu_uid": UID_A, "board": "SIM", "parts": ["ADXL355", "ADXRS450", "ADXRS450", "ADXRS453"],
        "accel_ids": [173, 29, 237, 1], "gyro_pid": [20993, 20993, 20994],
        "gyro_sn": [1001, 1002, 1003], "first_seen": "2026-11-22T06:40:00.000000+00:00",
        "last_seen": "2026-11-22T06:40:00.000000+00:00", "runs": 1,
        "last_run": {"started": "2026-11-22T06:40:00.000000+00:00", "method": "six", "gyro_method": "turntable",
                     "passed": True, "written": True, "verified": True}}]


def test_the_file_is_sqlite_in_wal_with_a_schema_version(db):
    with History(db) as h:
        h.record(make_result())
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert con.execute("SELECT version FROM schema_version").fetchall() == [(H.SCHEMA_VERSION,)]
    cols = {r[1] for r in con.execute("PRAGMA table_info(runs)")}
    assert {"device_id", "started", "finished", "method", "gyro_method", "accel_m", "accel_sigma_b_mps2",
            "gyro_b_rad_s", "accel_residual_rms_mps2", "poses", "temp_accel_c", "temp_gyro_c", "fw_version",
            "fw_build", "passed", "written", "verified", "note", "record"} <= cols
    con.close()


def test_gyro_may_be_absent(db):
    with History(db) as h:
        h.record(make_result(gyro=False))
        (run,) = h.runs(UID_A)
    assert run["gyro"] is None and run["gyro_method"] is None


def test_lookup_by_uid_prefix_and_serial(db):
    with History(db) as h:
        h.record(make_result(UID_A, gyro_sn=(0x1001, 0x1002, 0x1003)))
        h.record(make_result(UID_C.lower(), gyro_sn=(0x2001, 0x2002, 0x2003)))   # as older sessions wrote it
        assert h.resolve(UID_A) == UID_A
        assert h.resolve(UID_A.lower()) == UID_A         # any case
        assert h.resolve("01234") == UID_A
        assert h.resolve("fedc") == UID_C
        assert h.resolve("00001002") == UID_A            # a gyro serial number, as `imubench info` prints it
        assert h.resolve("2003") == UID_C
        assert h.resolve("0x2001") == UID_C              # ... with 0x
        assert h.resolve("fedc:ba98") == UID_C           # separators do not matter
        assert [r["mcu_uid"] for r in h.runs("2001")] == [UID_C]
        with pytest.raises(UnknownDevice, match="not an identifier"):
            h.resolve("B559-FCF4-X")                     # not hex: says what an identifier looks like
        with pytest.raises(UnknownDevice, match="at least 4 hex digits"):
            h.resolve("012")
        with pytest.raises(UnknownDevice, match="no device 'abcd'"):
            h.resolve("abcd")
        with pytest.raises(UnknownDevice):
            h.runs("99999")


def test_a_serial_from_an_earlier_run_still_finds_the_device(db):
    with History(db) as h:
        h.record(make_result(gyro_sn=(0x1001, 0x1002, 0x1003)))
        h.record(make_result(started="2026-12-01T08:00:00+00:00", gyro_sn=(0x1001, 0x5555, 0x1003)))   # gyro Y replaced
        assert h.devices()[0]["gyro_sn"] == [0x1001, 0x5555, 0x1003]
        assert h.resolve("5555") == UID_A
        assert h.resolve("1002") == UID_A


def test_ambiguous_prefix_lists_the_matches(db):
    with History(db) as h:
        h.record(make_result(UID_A))
        h.record(make_result(UID_B, gyro_sn=(7, 8, 9)))
        with pytest.raises(AmbiguousDevice) as e:
            h.runs("0123")
        assert e.value.matches == [UID_A, UID_B]
        assert UID_A in str(e.value) and UID_B in str(e.value)
        assert h.resolve("01234") == UID_A and h.resolve("0123f") == UID_B


@pytest.mark.parametrize("path, key", [
    (("device", "mcu_uid"), "device.mcu_uid"),
    (("accel", "sigma_m"), "accel.sigma_m"),
    (("accel", "residual_rms_mps2"), "accel.residual_rms_mps2"),
    (("gyro", "b_rad_s"), "gyro.b_rad_s"),
    (("poses",), "poses"),
    (("started",), "started"),
    (("passed",), "passed"),
    (("gyro_method",), "gyro_method"),
])
def test_missing_keys_are_named_and_nothing_is_stored(db, path, key):
    r = make_result()
    d = r
    for p in path[:-1]:
        d = d[p]
    del d[path[-1]]
    with History(db) as h:
        with pytest.raises(ValueError, match=r"missing .*" + key.replace(".", r"\.")):
            h.record(r)
        assert h.devices() == [] and h.count_runs() == 0


def test_several_missing_keys_are_all_named(db):
    r = make_result()
    del r["accel"]["m"], r["device"]["board"], r["finished"]
    with History(db) as h, pytest.raises(ValueError) as e:
        h.record(r)
    for k in ("accel.m", "device.board", "finished"):
        assert k in str(e.value)


@pytest.mark.parametrize("mutate, words", [
    (lambda r: r["accel"].__setitem__("m", [[1, 0, 0], [0, 1, 0]]), "accel.m must be 3x3"),
    (lambda r: r["accel"].__setitem__("b_mps2", [0.0, float("nan"), 0.0]), "accel.b_mps2 must be 3 finite"),
    (lambda r: r["device"].__setitem__("mcu_uid", "xyz"), "24 hex digits"),
    (lambda r: r.__setitem__("started", "yesterday"), "ISO 8601"),
    (lambda r: r.__setitem__("schema", 3), "schema"),
    (lambda r: r.__setitem__("poses", []), "non-empty"),
])
def test_malformed_records_are_refused(db, mutate, words):
    r = make_result()
    mutate(r)
    with History(db) as h:
        with pytest.raises(ValueError, match=words):
            h.record(r)
        assert h.count_runs() == 0


def test_a_failure_inside_the_transaction_leaves_nothing(db, monkeypatch):
    with History(db) as h:
        def boom(*a, **k):
            raise RuntimeError("power cut")
        monkeypatch.setattr(h, "_insert_run", boom)
        with pytest.raises(RuntimeError):
            h.record(make_result())
        monkeypatch.undo()
        assert h.devices() == [] and h.count_runs() == 0      # the device row was rolled back too
        h.record(make_result())
        assert h.count_runs() == 1


def test_recording_twice_is_idempotent_and_a_conflict_is_refused(db):
    r = make_result()
    with History(db) as h:
        a = h.record(r)
        assert h.record(copy.deepcopy(r)) == a
        other = make_result(note="something else")
        with pytest.raises(ValueError, match="already has a different run"):
            h.record(other)
        assert h.count_runs() == 1


def test_record_once_says_whether_the_run_is_new(db):
    r = make_result() | {"session_started": "2026-11-22T06:30:00+00:00"}
    with History(db) as h:
        rid, new = h.record_once(r)
        assert new is True
        assert h.record_once(json.loads(json.dumps(r))) == (rid, False)     # as read back from session.json
        edited = copy.deepcopy(r) | {"note": "edited"}
        with pytest.raises(ValueError, match="of the same session"):
            h.record_once(edited)
        assert h.count_runs() == 1


def test_two_devices_and_time_order(db):
    with History(db) as h:
        h.record(make_result(UID_A, started="2026-12-01T08:00:00+00:00", note="second"))
        h.record(make_result(UID_A, started="2026-11-22T06:40:00+00:00", note="first"))
        # 2026-12-01T09:30+02:00 is 07:30 UTC: before the 08:00 UTC run, after the first
        h.record(make_result(UID_A, started="2026-12-01T09:30:00+02:00", note="middle"))
        h.record(make_result(UID_C, started="2026-11-30T10:00:00+00:00", gyro_sn=(1, 2, 3)))
        assert [r["note"] for r in h.runs(UID_A)] == ["first", "middle", "second"]
        assert len(h.runs(UID_C)) == 1
        devs = {d["mcu_uid"]: d for d in h.devices()}
    assert devs[UID_A]["runs"] == 3 and devs[UID_C]["runs"] == 1
    assert devs[UID_A]["first_seen"].startswith("2026-11-22T06:40")
    assert devs[UID_A]["last_seen"].startswith("2026-12-01T08:00")


def test_a_reader_is_not_blocked_by_an_open_write(db):
    with History(db) as w:
        w.record(make_result())
        with w._write() as con:                     # a session in the middle of recording
            con.exec_driver_sql("UPDATE runs SET note = 'changing'")
            with History(db, readonly=True, timeout_s=0.5) as r:
                assert r.runs(UID_A)[0]["note"] == "bench A"     # the last committed state
        with History(db, readonly=True) as r:
            assert r.runs(UID_A)[0]["note"] == "changing"


def test_newer_schema_is_refused(db, capsys):
    with History(db) as h:
        h.record(make_result())
    con = sqlite3.connect(db)
    con.execute("UPDATE schema_version SET version = ?", (H.SCHEMA_VERSION + 1,))
    con.commit()
    con.close()
    with pytest.raises(SchemaError, match="newer imubench"):
        History(db)
    with pytest.raises(SchemaError, match="newer imubench"):
        History(db, readonly=True)
    assert imubench(["history", "--db", str(db)]) == 1
    assert "newer imubench" in capsys.readouterr().err


def test_default_path_is_in_the_user_data_dir(tmp_path, monkeypatch):
    import platformdirs
    monkeypatch.setattr(platformdirs, "user_data_dir", lambda app: str(tmp_path / "data" / app))
    assert H.default_path() == tmp_path / "data" / "imubench" / "history.sqlite"
    with History() as h:
        h.record(make_result())
    assert (tmp_path / "data" / "imubench" / "history.sqlite").is_file()


# ------------------------------------------------------------------ drift
def _series(db, z_bias_steps_sigma, sigma=2e-5):
    """Runs whose accel Z bias moves by the given multiples of the per-run sigma."""
    with History(db) as h:
        z = 0.03
        for i, step in enumerate([0.0, *z_bias_steps_sigma]):
            z += step * sigma
            h.record(make_result(started=f"2026-11-{10 + i:02d}T08:00:00+00:00", accel_b_mps2=(0.01, -0.02, z),
                                 sigma_b_mps2=sigma))


def test_a_real_bias_step_is_flagged(db):
    # combined sigma of a step is sqrt(2)·sigma: a 5-sigma-of-the-difference step is 5·sqrt(2)·sigma
    _series(db, [0.4, 5.0 * math.sqrt(2), -0.6])
    with History(db, readonly=True) as h:
        rep = H.device_report(h, UID_A)
    dz = rep["drift"]["quantities"]["accel_bias_mg"]["axes"]["z"]
    assert [s["flagged"] for s in dz["steps"]] == [False, True, False]
    assert dz["steps"][1]["n_sigma"] == pytest.approx(5.0, rel=1e-6)
    assert dz["steps"][1]["change"] == pytest.approx(5.0 * math.sqrt(2) * 2e-5 / G0 * 1000)
    assert dz["first_last"]["flagged"]
    flagged = {(f["quantity"], f["axis"], f["from"], f["to"]) for f in rep["drift"]["flagged"]}
    assert flagged == {("accel_bias_mg", "z", 2, 3), ("accel_bias_mg", "z", 1, 4)}


def test_noise_only_changes_are_not_flagged(db):
    _series(db, [0.9, -1.7, 2.1, -0.4, 1.3])        # each below 3 combined sigmas (~4.24 sigma)
    with History(db, readonly=True) as h:
        rep = H.device_report(h, UID_A)
    assert rep["drift"]["flagged"] == []
    assert len(rep["drift"]["quantities"]["accel_bias_mg"]["axes"]["z"]["steps"]) == 5


def test_parameters_not_estimated_are_left_out_of_drift(db):
    a = make_result(started="2026-11-10T08:00:00+00:00")
    b = make_result(started="2026-11-11T08:00:00+00:00")
    b["gyro_method"] = "bias"
    b["gyro"]["m"] = np.eye(3).tolist()                               # the bias method does not fit M
    b["gyro"]["sigma_m"] = [[None] * 3] * 3
    with History(db) as h:
        h.record(a)
        h.record(b)
        rep = H.device_report(h, UID_A)
    q = rep["drift"]["quantities"]
    assert q["gyro_scale_ppm"]["axes"]["x"]["steps"] == []          # 500 ppm -> 0 is not a drift
    assert len(q["gyro_bias_dps"]["axes"]["x"]["steps"]) == 1
    assert rep["drift"]["flagged"] == []
    text = format_device_report(rep)
    assert "+0.0 (not estimated)" in text
    assert "gyro scale [ppm]: fewer than two runs estimated it" in text


# ------------------------------------------------------------------ CLI
def test_cli_lists_devices(db, capsys):
    with History(db) as h:
        h.record(make_result(UID_A))
        h.record(make_result(UID_A, started="2026-12-01T08:00:00+00:00", passed=False))
        h.record(make_result(UID_C, gyro_sn=(1, 2, 3)))
    assert imubench(["history", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    line_a = next(ln for ln in out.splitlines() if ln.startswith(UID_A))
    assert "SIM" in line_a and " 2 " in line_a and "2026-12-01 08:00 UTC" in line_a and "FAILED" in line_a
    assert any(ln.startswith(UID_C) and "2026-11-22 06:40 UTC" in ln for ln in out.splitlines())
    assert imubench(["history", "--db", str(db), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert {d["mcu_uid"]: d["runs"] for d in data["devices"]} == {UID_A: 2, UID_C: 1}


def test_cli_device_report_numbers(db, capsys):
    _series(db, [0.3, 5.0 * math.sqrt(2)])
    assert imubench(["history", "--db", str(db), "0123456"]) == 0
    out = capsys.readouterr().out
    # accel bias 0.01 m/s² = 1.0197 mg ± 2e-5 m/s² = 0.0020 mg; scale 250 ppm ± 3 ppm
    assert "X +1.0197 ± 0.0020" in out and "Y -2.0394 ± 0.0020" in out
    assert "X +250.0 ± 3.0" in out and "Y -310.0 ± 3.0" in out and "Z +80.0 ± 3.0" in out
    assert "largest M[z,x] = -400.0 ± 3.0 ppm" in out
    # gyro bias 1e-3 rad/s = 0.05730 °/s ± 1e-5 rad/s = 0.00057 °/s; scale 500 ppm ± 10
    assert "X +0.05730 ± 0.00057" in out and "X +500 ± 10 " in out        # to the precision of its sigma
    assert "accel 25.0 °C, gyro X/Y/Z 25.2/25.1/25.3 °C" in out
    assert "passed yes, written yes, verified yes" in out and "bench A" in out
    assert out.count("method six, gyro turntable") == 3
    step2 = next(ln for ln in out.splitlines() if ln.strip().startswith("run 2 -> 3"))
    assert "DRIFT" in step2 and f"+{5 * math.sqrt(2) * 2e-5 / G0 * 1000:.4f} ± 0.0029 DRIFT" in step2
    step1 = next(ln for ln in out.splitlines() if ln.strip().startswith("run 1 -> 2"))
    assert "DRIFT" not in step1
    assert "first -> last (1 -> 3)" in out
    assert "accel bias Z run 2 -> 3" in out and "(5.0σ)" in out

    assert imubench(["history", "--db", str(db), "0123456", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["device"]["mcu_uid"] == UID_A
    assert [r["index"] for r in data["runs"]] == [1, 2, 3]
    r0 = data["runs"][0]
    assert r0["accel"]["bias_mg"][0] == pytest.approx(1.0197162, rel=1e-6)
    assert r0["accel"]["scale_error_ppm"] == pytest.approx([250.0, -310.0, 80.0])
    assert r0["accel"]["cross_axis"]["term"] == "M[z,x]"
    assert r0["gyro"]["bias_dps"][0] == pytest.approx(math.degrees(1e-3))
    assert r0["temperature_c"] == {"accel": 25.0, "gyro": [25.2, 25.1, 25.3]}
    assert [(f["quantity"], f["axis"], f["from"], f["to"]) for f in data["drift"]["flagged"]] == \
        [("accel_bias_mg", "z", 2, 3), ("accel_bias_mg", "z", 1, 3)]


def test_cli_json_is_strict_json_with_unestimated_sigmas(db, capsys):
    r = make_result()
    r["gyro"]["sigma_m"] = [[float("nan")] * 3] * 3
    with History(db) as h:
        h.record(r)
    assert imubench(["history", "--db", str(db), UID_A, "--json"]) == 0
    text = capsys.readouterr().out
    assert "NaN" not in text
    assert json.loads(text)["runs"][0]["gyro"]["scale_error_sigma_ppm"] == [None, None, None]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("imubench history: error: "), err
    return err


def test_cli_errors_are_one_line_exit_1(db, tmp_path, capsys):
    """A device or database that is not there is a failure (exit 1), named in one line."""
    with History(db) as h:
        h.record(make_result())
    assert imubench(["history", "--db", str(db), "beef"]) == 1
    assert "no device 'beef'" in _one_error_line(capsys)
    assert imubench(["history", "--db", str(tmp_path / "nope.sqlite")]) == 1
    assert "no history database" in _one_error_line(capsys)
    assert not (tmp_path / "nope.sqlite").exists()              # reading never creates a database
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database" * 100)
    assert imubench(["history", "--db", str(junk)]) == 1
    assert "cannot read" in _one_error_line(capsys)
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t (x)")
    con.commit()
    con.close()
    assert imubench(["history", "--db", str(other)]) == 1
    assert "not an imubench history" in _one_error_line(capsys)


def test_cli_without_a_database_yet(tmp_path, monkeypatch, capsys):
    import platformdirs
    monkeypatch.setattr(platformdirs, "user_data_dir", lambda app: str(tmp_path / app))
    assert imubench(["history", ]) == 0
    assert "no calibrations recorded yet" in capsys.readouterr().out
    assert not (tmp_path / "imubench").exists()
