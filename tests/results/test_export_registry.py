"""One export registry (issue 34, item 9): every format, its consumer, file name and what it cannot
hold in one place (imubench.results.exports), one option syntax in every command, every file
saying what it holds, leaves out and leaves to do in its consumer's comment syntax, and no name
(a device's, a recording's, a topic) becoming a line of the consumer's through any export."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from imu_synth import ferraris_truth

from imubench.calib import TriadFit
from imubench.cli.main import build_parser
from imubench.procedures.export_files import write_calibration
from imubench.results import exports as X
from imubench.results import noise_export as NE
from imubench.results import paramfiles as PF
from imubench.results import thermal_export as TX


def test_every_format_is_described_once_and_the_writers_use_the_registrys_names():
    seen = set()
    for f in X.FORMATS:
        assert (f.family, f.name) not in seen
        seen.add((f.family, f.name))
        assert f.family in X.FAMILIES and f.consumer and f.source and f.files and f.holds and f.cannot_hold
        assert f.comments in ("#", "json", "")
    assert PF.WRITERS == X.names("calibration") and NE.NOISE_WRITERS == X.names("noise")
    assert TX.KINDS == X.names("thermal") and X.names("session") == ("json", "junit")
    # every calibration file name is distinct (a station writes them all side by side)
    names = [n for k in X.names("calibration") for n in X.file_names("calibration", k, "p")]
    assert len(names) == len(set(names))


@pytest.mark.parametrize("argv, dest, want", [
    (["calibrate", "--export", "px4,kalibr", "--export", "imucal", "--export", "px4"], "export",
     ("px4", "kalibr", "imucal")),
    (["calibrate", "--export", "params , IMU-CALIB"], "export", ("params", "imu-calib")),
    (["allan", "--export", "kalibr", "--export", "openvins,vins-fusion,imu-utils"], "export",
     ("kalibr", "openvins", "vins-fusion", "imu-utils")),
    (["thermal", "--export", "px4", "--export", "ardupilot"], "export", ("px4", "ardupilot")),
    (["thermal", "--export", "px4,ardupilot"], "export", ("px4", "ardupilot")),
    (["history", "--export", "S1", "--format", "json,junit"], "format", ("json", "junit")),
    (["history", "--export", "S1", "--format", "junit", "--format", "json"], "format", ("junit", "json")),
    (["calibrate"], "export", ()),
])
def test_one_option_syntax_everywhere(argv, dest, want):
    a = build_parser().parse_args(argv)
    assert getattr(a, dest) == want


@pytest.mark.parametrize("cmd, flag, bad", [("calibrate", "--export", "px4,ardupilot-thermal"),
                                            ("allan", "--export", "kalibr,px4"),
                                            ("thermal", "--export", "kalibr"),
                                            ("history", "--format", "xml")])
def test_an_unknown_format_is_one_line_naming_the_familys_formats(cmd, flag, bad, capsys):
    from imubench.cli import main as imubench
    extra = ["--export", "S1"] if cmd == "history" else []
    assert imubench([cmd, *extra, flag, bad]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "unknown format" in err and "Traceback" not in err
    family = {"calibrate": "calibration", "allan": "noise", "thermal": "thermal", "history": "session"}[cmd]
    assert ", ".join(X.names(family)) in err


@pytest.fixture(scope="module")
def truth():
    t = ferraris_truth(3)

    def fit(m, b):
        return TriadFit(method="t", m=np.asarray(m, float), b=np.asarray(b, float), cov=np.zeros((12, 12)))
    return fit(t["accel_m"], t["accel_b"]), fit(t["gyro_m"], t["gyro_b"])


def _result(acc, gyr) -> dict:
    """A session's result record as results.record keeps it (fit_dict: M, b in SI)."""
    return {"accel": {"m": acc.m.tolist(), "b_mps2": acc.b.tolist()}, "gyro": {"m": gyr.m.tolist(),
            "b_rad_s": gyr.b.tolist()}, "gsens": {"applied": True, "g_dps_per_g": (np.eye(3) * 0.03).tolist()},
            "finished": "2026-01-01T00:00:00+00:00"}


def test_a_session_result_writes_every_format_and_each_file_says_what_it_is(tmp_path, truth):
    acc, gyr = truth
    files = write_calibration(X.names("calibration"), tmp_path, _result(acc, gyr), name="ABC123",
                                comment="imubench calibration of ABC123", px4_acc_id=1310988, px4_gyro_id=2163722)
    assert set(files) == set(X.names("calibration"))
    for kind, paths in files.items():
        fmt = X.get("calibration", kind)
        assert [p.rsplit("/", 1)[-1] for p in paths] == X.file_names("calibration", kind, "calibration-ABC123")[
            :len(paths)]
        text = open(paths[0]).read()
        if fmt.comments == "#":                 # in the consumer's own comment syntax, before its keys
            lines = text.splitlines()
            assert any(ln.startswith("# Holds: ") for ln in lines)
            assert any(ln.startswith("# Cannot hold (left out): ") for ln in lines)
            assert any(ln.startswith("# You must still: ") for ln in lines)
        elif fmt.comments == "json":
            c = json.loads(text)["comment"]
            assert "Holds:" in c and "Cannot hold" in c and "You must still" in c
    index = (tmp_path / "exports-calibration.txt").read_text()       # also for imu_tk and the params JSON
    assert all(f"{k}: " in index for k in X.names("calibration")) and "cannot hold:" in index
    # what the consumers read is the calibration itself: Kalibr's M = L·Q, PX4's with its ids, imucal's K·R
    k = yaml.safe_load(open(files["kalibr"][0]).read())["imu0"]
    la, qa = PF.rq(acc.m)
    np.testing.assert_allclose(np.array(k["accelerometers"]["M"]) @ qa, acc.m, atol=1e-10)
    px4 = {ln.split("\t")[2]: float(ln.split("\t")[3]) for ln in open(files["px4"][0]).read().splitlines()
           if not ln.startswith("#")}
    assert px4["CAL_ACC0_ID"] == 1310988 and px4["CAL_ACC0_XOFF"] == pytest.approx(acc.b[0], abs=1e-8)
    d = json.loads(open(files["imucal"][0]).read())
    np.testing.assert_allclose(np.array(d["K_a"]) @ np.array(d["R_a"]), acc.m, atol=1e-12)
    params = json.loads(open(files["params"][0]).read())
    np.testing.assert_allclose(params["accel_m"], acc.m.ravel(), atol=1e-6)


def test_the_stamp_keeps_opencvs_first_line_and_every_key(tmp_path):
    from test_export_consumers import _res
    for kind in X.names("noise"):
        path = NE.write_noise(kind, tmp_path / f"{kind}.yaml", _res())
        text = path.read_text()
        plain = NE.__dict__[{"kalibr": "kalibr_text", "openvins": "openvins_text", "vins-fusion": "vins_fusion_text",
                             "imu-utils": "imu_utils_text"}[kind]](_res(), "/imu0" if kind != "imu-utils" else "imu")
        assert text.splitlines()[0] == plain.splitlines()[0]                  # %YAML:1.0 stays first
        keep = [ln for ln in text.splitlines() if not ln.startswith("#")]
        assert keep == [ln for ln in plain.splitlines() if not ln.startswith("#")]
        assert "# Holds: " in text and "# You must still: " in text


# ------------------------------------------------------------------ fuzz: names through every export, on disk
NAMES = ["board\nCBRK_IO_SAFETY,22027\n1\t1\tCBRK_IO_SAFETY\t22027\t6",
         "a\rSM: [1,0,0,0,1,0,0,0,1]\r\nbias: [9,9,9]",
         "x\x0bimu0:\x0c  model: rpng\x85gyr_n: 1\u2028acc_n: 2\u2029",
         "q\"uote'd # not: [a comment] {y: 1} &anchor *ref !!tag |\n---\n...",
         "tab\there\x00\x1b[2J\x07\x7f\x9b\u202e",
         "%YAML:1.0\n---\nimu0:\n  Tw: [[9,9,9],[9,9,9],[9,9,9]]",
         "<testcase name='x'/>&amp;]]>\x01"]
BREAKS = "\r\x00\x0b\x0c\x1b\x85\u2028\u2029\u202e"


def _lines_not_comments(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]


_FITS: dict = {}


def _thermal_fits():
    """The warm-up fits of test_warmup, fitted once for every name (a second of cross-validation)."""
    if not _FITS:
        from test_warmup import _fits_for_export
        _FITS["fits"] = _fits_for_export(np.random.default_rng(2))
    return _FITS["fits"]


def _all_files(tmp_path, name: str, truth) -> dict:
    """Every export of every family written to disk the way the commands write them, with name in
    every place a name goes (the device name, the comment, the topic, the file name)."""
    from test_export_consumers import _res
    from test_warmup import T_REF
    acc, gyr = truth
    out = {}
    d = tmp_path / "cal"
    for kind, paths in write_calibration(X.names("calibration"), d, _result(acc, gyr), name=name,
                                           comment=f"imubench calibration of {name}", px4_acc_id=5,
                                           px4_gyro_id=6).items():
        for i, p in enumerate(paths):
            out[f"calibration {kind} {i}"] = open(p).read()
    out["calibration index"] = (d / "exports-calibration.txt").read_text()
    res = _res(source=f"/data/{name}.csv", name=name)
    for kind, p in NE.write_noise_files(X.names("noise"), tmp_path / "noise", res, topic=name, name=name).items():
        out[f"noise {kind}"] = open(p).read()
    fits = _thermal_fits()
    (tmp_path / "thermal").mkdir(parents=True)
    files = TX.write_exports(tmp_path / "thermal", {k: (fits, name) for k in TX.KINDS},
                             {"accel": T_REF, "gyro": T_REF}, TX.KINDS, comment=f"imubench from {name}.csv")
    for kind, paths in files.items():
        out[f"thermal {kind}"] = paths[0].read_text()
    return out


@pytest.mark.parametrize("name", NAMES)
def test_no_name_becomes_a_line_of_any_export_on_disk(name, tmp_path, truth):
    nasty = _all_files(tmp_path / "n", name, truth)
    plain = _all_files(tmp_path / "p", "x", truth)
    assert set(nasty) == set(plain)
    for key, text in nasty.items():
        if key.startswith(("calibration imucal", "calibration params")):
            json.loads(text)                                          # JSON escapes what it quotes
            continue
        assert len(text.splitlines()) == len(plain[key].splitlines()), key
        assert len(_lines_not_comments(text)) == len(_lines_not_comments(plain[key])), key
        assert not any(c in text for c in BREAKS), key
        if "index" not in key and "imutk" not in key:
            # the lines a consumer reads are the plain file's, but for the name made a token (topic, name)
            from imubench.text import token
            a = [ln.replace(token(name), "x") for ln in _lines_not_comments(text)]
            assert a == _lines_not_comments(plain[key]), key


def test_no_name_breaks_a_session_record(tmp_path):
    """history --export: the session's free text (station, operator, failure) in JSON and JUnit XML."""
    from imubench.results.export import junit_xml, session_json
    for name in NAMES:
        run = {"run_id": 1, "session_id": name, "station_id": name, "operator": name, "fixture": name,
               "slot": 1, "port": name, "mcu_uid": name, "passed": False, "failure": name, "failed_stage": name,
               "started_utc": "2026-01-01T00:00:00", "finished_utc": "2026-01-01T00:01:00",
               "measurements": [{"name": "accel_norm_rms_mg", "value": 0.5, "unit": "mg", "low": None,
                                 "high": 1.0, "passed": True}]}
        d = json.loads(session_json([run]))
        assert d["station_id"] == name and d["boards"][0]["failure"]["reason"] == name
        root = ET.fromstring(junit_xml([run]).split("\n", 1)[1])
        assert len(root.findall("testsuite")) == 1 and len(root.find("testsuite").findall("testcase")) == 2
