"""Calibrating from a recording (imubench calibrate --from; imubench.recordings,
imubench.procedures.from_file, imubench.results.paramfiles): every format with a small file made
here, units declared and refused, gaps, duplicates and irregular time, the writers' layouts,
the command line end to end and the guided session's known-angle turn step."""
from __future__ import annotations

import json
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imu_synth import G0, ferraris_session, write_csv
from imubench.procedures.from_file import FileAnalysis, FileConfig
from imubench.recordings import RecordingError, from_arrays, read
from imubench.results import paramfiles

FS = 100.0


@pytest.fixture(scope="module")
def session():
    ua, ug, truth, events = ferraris_session(fs=FS, seed=2)
    return ua, ug, truth, events


def _check_truth(fa: FileAnalysis, truth, gyro=True):
    za = (fa.accel.m - truth["accel_m"]) / fa.accel.sigma_m
    assert np.abs(za).max() < 5, za
    assert np.all(np.abs(fa.accel.b - truth["accel_b"]) < 5 * fa.accel.sigma_b + 1e-4)
    if gyro:
        zg = (fa.gyro.m - truth["gyro_m"]) / fa.gyro.sigma_m
        assert np.abs(zg).max() < 3, zg


def _analyse(rec, **cfg):
    fa = FileAnalysis(rec, FileConfig(**{"gyro": "turns", **cfg}), say=lambda s: None)
    return fa, fa.run()


# ------------------------------------------------------------------ formats
def test_csv_by_common_names_with_time_in_ms(session, tmp_path):
    ua, ug, truth, _ = session
    p = write_csv(tmp_path / "log.csv", ua / G0, np.degrees(ug), FS)
    rec = read(p, accel_unit="g", gyro_unit="dps")
    assert rec.fmt == "csv" and abs(rec.fs_hz - FS) < 1e-6
    assert any("columns found by name" in n for n in rec.notes)
    assert any("time unit ms from the column name" in n for n in rec.notes)
    fa, res = _analyse(rec)
    _check_truth(fa, truth)
    assert [t["label"] for t in res["turns"]] == ["turn about +X", "turn about +Y", "turn about +Z"]
    assert sorted(set(fa.faces)) == ["+X", "+Y", "+Z", "-X", "-Y", "-Z"]
    # a better declared hand (a stop to turn against) gives smaller sigmas, in proportion
    fa2, _ = _analyse(rec, angle_sigma_deg=0.25)
    sig = [np.diag(np.array(f.gyro_parts["fits"]["turns"]["sigma_m"])) for f in (fa, fa2)]
    assert np.allclose(sig[1] / sig[0], 0.25, rtol=0.05)


def test_csv_columns_mapped_by_option_and_by_profile(session, tmp_path):
    ua, ug, truth, _ = session
    hdr = ("Time", "Acc1", "Acc2", "Acc3", "Rot1", "Rot2", "Rot3")
    p = write_csv(tmp_path / "vendor.csv", ua, ug, FS, header=hdr, t=np.arange(len(ua)) / FS)
    with pytest.raises(RecordingError, match="no accel columns found.*--columns"):
        read(p, accel_unit="mps2", gyro_unit="rad_s")
    cols = {"ax": "Acc1", "ay": "Acc2", "az": "Acc3", "gx": "Rot1", "gy": "Rot2", "gz": "Rot3"}
    # a time column in seconds at 100 Hz: only s makes its steps an IMU's rate (detected and said)
    found = read(p, columns=cols, time_column="Time", accel_unit="mps2", gyro_unit="rad_s")
    assert found.options["time_unit"] == "s" and found.fs_hz == pytest.approx(FS)
    rec = read(p, columns=cols, time_column="Time", time_unit="s", accel_unit="mps2", gyro_unit="rad_s")
    assert np.array_equal(found.t_s, rec.t_s)
    _check_truth(_analyse(rec)[0], truth)
    from imubench.recordings.readers import load_profile
    prof = tmp_path / "vendor.toml"
    prof.write_text('[columns]\nax = "Acc1"\nay = "Acc2"\naz = "Acc3"\ngx = "Rot1"\ngy = "Rot2"\ngz = "Rot3"\n'
                    't = "Time"\n[units]\naccel = "mps2"\ngyro = "rad_s"\ntime = "s"\n')
    rec2 = read(p, **load_profile(prof))
    assert np.array_equal(rec2.accel, rec.accel)
    prof.write_text('colums = 1\n')
    with pytest.raises(RecordingError, match="unknown key.*colums"):
        load_profile(prof)


def test_imutk_two_files(session, tmp_path):
    ua, ug, truth, _ = session
    t = np.arange(len(ua)) / FS
    counts_per_g, counts_per_dps = 16384.0, 131.0
    np.savetxt(tmp_path / "acc.mat", np.column_stack([t, np.round(ua / G0 * counts_per_g)]), fmt="%.9g")
    np.savetxt(tmp_path / "gyro.mat", np.column_stack([t, np.round(np.degrees(ug) * counts_per_dps)]), fmt="%.9g")
    # the pair is found by name beside the accelerometer's file, and said so; without it, asked for
    found = read(tmp_path / "acc.mat", accel_unit="counts", gyro_unit="counts", accel_counts_per_g=counts_per_g,
                 gyro_counts_per_dps=counts_per_dps)
    assert found.fmt == "imutk" and any("the gyro file gyro.mat beside it" in d for d in found.detected)
    (tmp_path / "gyro.mat").rename(tmp_path / "rates.mat")
    with pytest.raises(RecordingError, match="give the gyro file with --gyro-file"):
        read(tmp_path / "acc.mat", "imutk", accel_unit="counts", gyro_unit="counts")
    (tmp_path / "rates.mat").rename(tmp_path / "gyro.mat")
    rec = read(tmp_path / "acc.mat", "imutk", gyro_file=tmp_path / "gyro.mat", accel_unit="counts",
               gyro_unit="counts", accel_counts_per_g=counts_per_g, gyro_counts_per_dps=counts_per_dps)
    fa, _ = _analyse(rec)
    _check_truth(fa, truth)


def test_counts_without_a_scale_report_counts_per_unit(session, tmp_path):
    ua, ug, truth, _ = session
    cpg, cpd = 4096.0, 32.8
    rec = from_arrays(ua / G0 * cpg, np.degrees(ug) * cpd, rate_hz=FS, accel_unit_name="counts",
                      gyro_unit_name="counts")
    fa, res = _analyse(rec)
    m_counts = np.asarray(res["accel_counts_per_g"])
    assert np.allclose(m_counts, truth["accel_m"] * cpg, rtol=0, atol=5 * fa.accel.sigma_m.max() * cpg)
    g_counts = np.asarray(res["gyro_counts_per_dps"])
    assert np.allclose(g_counts, truth["gyro_m"] * cpd, atol=3 * fa.gyro.sigma_m.max() * cpd)


def test_imucal_layout(session, tmp_path):
    ua, ug, truth, _ = session
    p = tmp_path / "imucal.csv"
    np.savetxt(p, np.column_stack([np.arange(len(ua)), np.degrees(ug), ua]), delimiter=",",
               header="n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z", comments="", fmt="%.9g")
    with pytest.raises(RecordingError, match="--rate"):
        read(p, accel_unit="mps2", gyro_unit="dps")
    rec = read(p, rate_hz=FS, accel_unit="mps2", gyro_unit="dps")
    assert rec.fmt == "imucal"
    _check_truth(_analyse(rec)[0], truth)


def test_our_npz(session, tmp_path):
    ua, ug, truth, _ = session
    p = tmp_path / "decoded.npz"
    np.savez_compressed(p, t_us=(np.arange(len(ua)) * 1e6 / FS).astype(np.int64), sample_index=np.arange(len(ua)),
                        status=np.zeros(len(ua), np.uint8), accel_mps2=ua, rate_rad_s=ug)
    rec = read(p)
    assert rec.fmt == "npz" and rec.accel_unit == "mps2" and rec.gyro_unit == "rad_s"
    _check_truth(_analyse(rec)[0], truth)
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(RecordingError, match="accel_mps2"):
        read(tmp_path / "other.npz")


def _write_bag(path: Path, ua, ug, ros1: bool, topic="/imu/data", extra_topic=None):
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    imu_t = "sensor_msgs/msg/Imu"

    def msg(i):
        ns = int(round(i * 1e9 / FS)) + 1_700_000_000 * 10**9
        hk = {"stamp": T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), "frame_id": "imu"}
        if ros1:
            hk["seq"] = i
        v3 = T["geometry_msgs/msg/Vector3"]
        return T[imu_t](header=T["std_msgs/msg/Header"](**hk), orientation=T["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
            angular_velocity=v3(x=float(ug[i, 0]), y=float(ug[i, 1]), z=float(ug[i, 2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=v3(x=float(ua[i, 0]), y=float(ua[i, 1]), z=float(ua[i, 2])),
            linear_acceleration_covariance=np.zeros(9)), ns
    if ros1:
        from rosbags.rosbag1 import Writer
        ser = ts.serialize_ros1
        w = Writer(path)
    else:
        from rosbags.rosbag2 import Writer
        ser = ts.serialize_cdr
        w = Writer(path, version=8)
    with w:
        conn = w.add_connection(topic, imu_t, typestore=ts)
        conn2 = w.add_connection(extra_topic, imu_t, typestore=ts) if extra_topic else None
        for i in range(len(ua)):
            m, ns = msg(i)
            w.write(conn, ns, ser(m, imu_t))
            if conn2 is not None and i < 10:
                w.write(conn2, ns, ser(m, imu_t))
    return path


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_rosbag(session, tmp_path, ros1):
    ua, ug, truth, _ = session
    p = _write_bag(tmp_path / ("imu.bag" if ros1 else "imu_bag2"), ua, ug, ros1)
    rec = read(p)
    assert rec.fmt == "rosbag" and abs(rec.fs_hz - FS) < 1e-3
    _check_truth(_analyse(rec)[0], truth)
    p2 = _write_bag(tmp_path / ("two.bag" if ros1 else "two_bag2"), ua[:50], ug[:50], ros1, extra_topic="/imu2")
    with pytest.raises(RecordingError, match="several sensor_msgs/Imu topics.*--topic"):
        read(p2)
    assert len(read(p2, topic="/imu2")) == 10


def test_rosbag_without_the_extra_says_how_to_install(tmp_path, monkeypatch):
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n")
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)      # import fails as if not installed
    with pytest.raises(RecordingError, match=r"pip install 'imubench\[rosbag\]'"):
        read(tmp_path / "x.bag")


def test_turns_and_rotation_method_combined_when_both_are_present():
    ua, ug, truth, _ = ferraris_session(fs=FS, seed=5, both_ways=True)
    rec = from_arrays(ua, ug, rate_hz=FS)
    fa, res = _analyse(rec)
    parts = res["gyro_parts"]
    assert set(parts["fits"]) == {"turns", "rotation"} and not parts["refused"]
    assert fa.gyro.method == "turns+rotation" and fa.gyro.extra["consistent"]
    turns_sigma = np.asarray(parts["fits"]["turns"]["sigma_m"])
    assert np.all(fa.gyro.sigma_m <= turns_sigma + 1e-12)       # the combination is at least as good
    assert np.abs((fa.gyro.m - truth["gyro_m"]) / fa.gyro.sigma_m).max() < 4
    # asked for the rotation method, the turns join in the same way
    fa2, _ = _analyse(rec, gyro="rotation")
    assert fa2.gyro.method == "turns+rotation" and np.allclose(fa2.gyro.m, fa.gyro.m)


def test_multi_position_from_a_file_with_edges_and_corners():
    ua, ug, truth, _ = ferraris_session(fs=FS, seed=7, edges=True)
    fa, res = _analyse(from_arrays(ua, ug, rate_hz=FS), method="multi")
    assert fa.accel.method == "multi_position"
    # multi-position's frame: M = L·Q, lower triangular; compare what |a| = g can see
    from imubench.calib.accel import lower_triangular_form
    l_true, _ = lower_triangular_form(truth["accel_m"])
    est = fa.accel.m
    assert np.abs(est - l_true).max() < 5 * np.nanmax(fa.accel.sigma_m) + 1e-4
    assert res["accel_rms_after_mg"] < 0.5


# ------------------------------------------------------------------ units
def test_implausible_units_are_refused_with_the_numbers(session):
    ua, ug, _, _ = session
    rec = from_arrays(ua, np.degrees(ug), rate_hz=FS, accel_unit_name="g", gyro_unit_name="dps")
    with pytest.raises(RecordingError, match=r"implausible.*9\.8.*g, far from 1 g.*declare --accel-unit mps2"):
        _analyse(rec)
    # a gyro unit that only looks wrong: used, with a warning and its numbers; the accelerometer result stands
    rec = from_arrays(ua, np.degrees(ug), rate_hz=FS, accel_unit_name="mps2", gyro_unit_name="rad_s")
    fa, res = _analyse(rec)
    assert any("declared gyro unit (rad/s) is doubtful" in n and "°/s" in n and "the declared unit is used" in n
               for n in res["notes"])
    assert res["passed"] and res["gyro_refused"] and res["verdict"].startswith("accelerometer calibrated")
    assert "gyro not:" in res["verdict"]
    # rates at rest no MEMS gyro's bias reaches leave no doubt: the gyro is refused, the accelerometer kept
    rec = from_arrays(ua, np.degrees(ug) + 3.0, rate_hz=FS, accel_unit_name="mps2", gyro_unit_name="rad_s")
    fa, res = _analyse(rec)
    assert "the unit is wrong" in res["gyro_refused"] and "--gyro-unit dps" in res["gyro_refused"]
    assert res["gyro"] is None and res["passed"] and res["accel"]["m"]


# ------------------------------------------------------------------ timing
def test_gap_inside_a_turn_makes_it_unusable_with_the_reason(session):
    ua, ug, truth, events = session
    t = np.arange(len(ua)) / FS
    turn_x = [e for e in events if e[0] == "rot"][-3]            # the turn about X
    mid = (turn_x[1] + turn_x[2]) // 2
    keep = np.ones(len(ua), bool)
    keep[mid:mid + 20] = False
    rec = from_arrays(ua[keep], ug[keep], t_s=t[keep])
    assert rec.timing["gaps"][0]["missing"] == 20
    fa = FileAnalysis(rec, FileConfig(gyro="turns"), say=lambda s: None)
    res = fa.run()            # the gyro's turns are refused; the accelerometer's result is kept
    assert re.search(r"turn about \+X.*not continuous inside the turn", res["gyro_refused"])
    assert res["gyro"]["method"] == "bias" and res["passed"]
    assert res["verdict"].startswith("accelerometer calibrated") and "gyro not: known-angle turns" in res["verdict"]
    # the same gap inside a rest changes nothing that matters
    rest = [e for e in events if e[0] == "rest"][1]
    keep = np.ones(len(ua), bool)
    keep[rest[1] + 150:rest[1] + 170] = False
    fa, res = _analyse(from_arrays(ua[keep], ug[keep], t_s=t[keep]))
    _check_truth(fa, truth)


def test_duplicates_dropped_backwards_refused_jitter_resampled(session):
    ua, ug, truth, _ = session
    t = np.arange(len(ua)) / FS
    idx = np.sort(np.concatenate([np.arange(len(ua)), [100, 2000, 2000]]))
    rec = from_arrays(ua[idx], ug[idx], t_s=t[idx])
    assert rec.timing["duplicates"] == 3 and rec.timing["duplicates_identical"] == 3 and len(rec) == len(ua)
    tb = t.copy()
    tb[500] = tb[498]
    with pytest.raises(RecordingError, match="backwards at sample 500"):
        from_arrays(ua, ug, t_s=tb)
    tj = t + np.random.default_rng(1).uniform(-0.3, 0.3, len(t)) / FS
    rec = from_arrays(ua, ug, t_s=tj)
    assert rec.timing["resampled"] and rec.timing["jitter_rel"] > 0.1
    _check_truth(_analyse(rec)[0], truth, gyro=False)


# ------------------------------------------------------------------ writers
def test_writers_express_the_same_calibration(session, tmp_path):
    ua, ug, truth, _ = session
    fa, _ = _analyse(from_arrays(ua / G0 * 4096, np.degrees(ug), rate_hz=FS, accel_unit_name="counts",
                                 gyro_unit_name="dps", accel_counts_per_g=4096))
    u_raw = np.array([[100.0, -4000.0, 250.0]])                 # counts
    x_ours = fa.accel.correct(u_raw * fa.fa)                  # m/s²
    (acc_file,) = [p for p in paramfiles.write("imutk", tmp_path / "c", accel=fa.accel, gyro=None, accel_factor=fa.fa,
                                           gyro_factor=None, accel_unit="counts", gyro_unit="dps", scaled=True)]
    tm, km, bv = paramfiles.read_imutk_text(acc_file.read_text())
    assert np.allclose(np.diag(tm), 1.0)
    assert np.allclose((tm @ km @ (u_raw[0] - bv)), x_ours[0])
    (js,) = paramfiles.write("imucal", tmp_path / "c", accel=fa.accel, gyro=fa.gyro, accel_factor=fa.fa,
                         gyro_factor=fa.fg, accel_unit="counts", gyro_unit="dps", scaled=True)
    d = json.loads(js.read_text())
    assert d["cal_type"] == "Ferraris" and d["_format_version"] == "2.0.0" and d["from_acc_unit"] == "a.u."
    ka, ra = np.array(d["K_a"]), np.array(d["R_a"])
    assert np.allclose(np.linalg.norm(ra, axis=1), 1.0)
    assert np.allclose(np.linalg.inv(ra) @ np.linalg.inv(ka) @ (u_raw[0] - d["b_a"]), x_ours[0])
    w_dps = np.array([10.0, -20.0, 30.0])
    x_g = np.degrees(fa.gyro.correct(np.radians(w_dps)[None, :])[0])
    kg, rg = np.array(d["K_g"]), np.array(d["R_g"])
    assert np.allclose(np.linalg.inv(rg) @ np.linalg.inv(kg) @ (w_dps - d["b_g"]), x_g)
    (ap,) = paramfiles.write("ardupilot", tmp_path / "c", accel=fa.accel, gyro=fa.gyro, accel_factor=fa.fa,
                         gyro_factor=fa.fg, accel_unit="counts", gyro_unit="dps", scaled=True)
    vals = dict(ln.split(",") for ln in ap.read_text().splitlines() if not ln.startswith("#"))
    assert np.allclose([float(vals[f"INS_ACCOFFS_{a}"]) for a in "XYZ"], fa.accel.b)
    assert np.allclose([float(vals[f"INS_ACCSCAL_{a}"]) for a in "XYZ"], 1 / np.diag(fa.accel.m))
    assert "no cross-axis terms" in ap.read_text()
    from imubench.procedures.writeback import params_from_fits
    from imubench.wire import params as PR
    (pp,) = paramfiles.write("params", tmp_path / "c", accel=fa.accel, gyro=fa.gyro, accel_factor=fa.fa,
                         gyro_factor=fa.fg, accel_unit="counts", gyro_unit="dps", scaled=True,
                         params=params_from_fits(fa.accel, fa.gyro, PR.identity(), 0))
    p = PR.from_json(json.loads(pp.read_text()))
    PR.validate(p)
    assert np.allclose(PR.correct(PR.accel(p), u_raw * fa.fa), x_ours, atol=1e-5)


# ------------------------------------------------------------------ the command line
def _cli(args, cwd: Path, timeout=180):
    return subprocess.run([sys.executable, "-m", "imubench", "calibrate", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, stdin=subprocess.DEVNULL)


def _main(args, cwd: Path, monkeypatch, capsys, command="calibrate"):
    """_cli's command through the same entry point (imubench.cli.main) in this process: for runs
    whose behaviour a subprocess run in this module also shows (tests/inproc.py)."""
    from inproc import run_main
    return run_main([command, *args], monkeypatch, capsys, cwd=cwd)


def test_cli_end_to_end(session, tmp_path, monkeypatch, capsys):
    ua, ug, truth, _ = session
    p = write_csv(tmp_path / "board7.csv", ua / G0, np.degrees(ug), FS)
    db = tmp_path / "h.sqlite"
    r = _cli(["--from", str(p), "--accel-unit", "g", "--gyro-unit", "dps", "--gyro", "turns", "--dir", "out",
              "--db", str(db), "--device", "board 7", "--export", "imutk,imucal", "--export",
              "ardupilot", "--export", "params", "--tolerance-mg", "2"], tmp_path)
    out = r.stdout
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Traceback" not in out + r.stderr and r.stderr == ""
    lines = out.splitlines()
    assert lines[0].startswith(f"recording: {p} (csv), 7500 samples at 100 Hz (75.0 s); accelerometer g, gyro °/s")
    assert "still intervals: 12 found by the data" in out
    # no --method: six faces (6 distinct attitudes) cannot feed the 9-parameter |a| = g fit, so six is chosen
    assert "method: six-position (the multi-position fit cannot be used: too few poses: 12 given, 6 distinct" in out
    assert json.loads((tmp_path / "out" / "session.json").read_text())["config"]["method"] == "six"
    assert "turn about +X" in out and "turn about +Y" in out and "turn about +Z" in out
    assert "gyro (turns+rotation):" in out and "known-angle turns and the rotation method combined (consistent" in out
    assert "recorded in the history as run 1" in out
    assert lines[-1] == "calibration PASSED (fitted from a file; nothing is written to a device)"
    d = tmp_path / "out"
    for f in ("session.json", "residuals.png", "segmentation.png", "report.html", "calibration-board_7_acc.calib",
              "calibration-board_7_gyro.calib", "calibration-board_7.imucal.json",
              "calibration-board_7.ardupilot.param", "calibration-board_7.params.json", "exports-calibration.txt"):
        assert (d / f).is_file(), f
    index = (d / "exports-calibration.txt").read_text()          # imu_tk's and our JSON take no comments
    assert "imutk: calibration-board_7_acc.calib, calibration-board_7_gyro.calib" in index
    assert "params: calibration-board_7.params.json" in index and "cannot hold: the gyro g-sensitivity" in index
    html = (d / "report.html").read_text()
    assert "<h3>Recording</h3>" in html and "known-angle turns" in html and "data:image/png;base64" in html
    with sqlite3.connect(db) as con:
        (n, method), = con.execute("SELECT count(*), gyro_method FROM runs").fetchall()
    assert n == 1 and method == "turns"
    # the report command reads the directory like any session's (as typed: tests/results/test_report.py)
    r2 = _main([d, "--out", tmp_path / "r.html"], tmp_path, monkeypatch, capsys, command="report")
    assert r2.returncode == 0 and (tmp_path / "r.html").is_file(), r2.stderr


@pytest.mark.parametrize("args,code,needle", [
    (["--accel-unit", "g"], 1, "does not say its units: give --gyro-unit"),
    (["--accel-unit", "mps2", "--gyro-unit", "dps"], 1, "implausible"),
    (["--accel-unit", "furlongs", "--gyro-unit", "dps"], 1, "unknown accelerometer unit 'furlongs'"),
    (["--accel-unit", "g", "--gyro-unit", "dps", "--port", "socket://127.0.0.1:1"], 2, "--from and --port exclude"),
    (["--accel-unit", "g", "--gyro-unit", "dps", "--gyro", "turntable"], 2, "--gyro turntable needs a turntable"),
])
def test_cli_mistakes_give_one_line(session, tmp_path, args, code, needle, monkeypatch, capsys):
    ua, ug, _, _ = session
    p = write_csv(tmp_path / "log.csv", ua / G0, np.degrees(ug), FS)
    argv = ["--from", str(p), "--dir", "o", "--db", str(tmp_path / "h.sqlite"), *args]
    # the first as typed (a subprocess); the others through the same entry point in-process
    r = _cli(argv, tmp_path) if args == ["--accel-unit", "g"] else _main(argv, tmp_path, monkeypatch, capsys)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == code and len(err) == 1 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    assert err[0].startswith("imubench calibrate: error: ") and needle in err[0], err[0]


def test_cli_names_the_formats_and_writers_of_the_library_without_importing_it():
    """Every command's parser is built at start-up: the --from options must not load the readers."""
    import imubench.cli.calibrate as C
    from imubench.recordings import FORMATS
    assert C.FORMATS == FORMATS and C.WRITERS == paramfiles.WRITERS
    r = subprocess.run([sys.executable, "-c", "import sys, importlib; importlib.import_module("
                        "'imubench.cli.main').build_parser(); print('imubench.recordings' in sys.modules "
                        "or 'imubench.results.paramfiles' in sys.modules or 'scipy' in sys.modules)"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stdout + r.stderr


def test_cli_file_options_without_from_are_refused(tmp_path):
    r = _cli(["--accel-unit", "g", "--sim"], tmp_path)
    assert r.returncode == 2 and "--accel-unit goes with --from FILE" in r.stderr


# ------------------------------------------------------------------ the guided session
def test_guided_session_known_angle_turns_on_the_virtual_bench(tmp_path):
    from imubench.device.link import Device
    from imubench.device.sim import VirtualBench
    from imubench.procedures.session import SessionConfig, SimPresenter, run_session
    said = []
    with VirtualBench(speed=40.0, seed=3, truth="random") as vb:
        ui = SimPresenter(vb, seed=3, quiet=True)
        ui.say = said.append
        with Device.open(vb.port_url, timeout=5.0) as dev:
            # no pose timeout, as `imubench calibrate` runs a person's session (it crashed the turn step)
            result, _ = run_session(dev, tmp_path / "s", SessionConfig(gyro="turns", write=False, pose_timeout_s=None),
                                    ui)
        truth = vb.get_truth()
    assert sum("turns the board 360°" in s for s in said) == 3
    g = result["gyro"]
    assert g["method"] == "turns"
    m_true = np.array([gg["sens"] for gg in truth["gyro"]])
    err = np.abs(np.asarray(g["m"]) - m_true) / np.asarray(g["sigma_m"])
    assert err.max() < 3, err
    # the session's own capture, calibrated from the file: the same poses, the same turns
    rec = read(tmp_path / "s" / "capture-1.bin")
    assert rec.fmt == "capture" and rec.accel_unit == "mps2" and abs(rec.fs_hz - 500) < 1
    fa, res = _analyse(rec)
    assert [t["label"] for t in res["turns"] if t["usable"]] == ["turn about +X", "turn about +Y", "turn about +Z"]
    # the file's known-angle turns are the session's turns: the same fit
    assert np.abs(np.asarray(fa.gyro_parts["fits"]["turns"]["m"]) - np.asarray(g["m"])).max() < 1e-3
    # and what it reports, the turns combined with the rotation method, is right within its sigma
    # (inflated by chi2/9 when the two disagree: a loaded run once gave the rotation method's X column
    # 0.05 off while the turns were right)
    assert np.all(np.abs(fa.gyro.m - m_true) < 4 * fa.gyro.sigma_m + 1e-4), (fa.gyro.m - m_true, fa.gyro.sigma_m)
    # the file's accelerometer fit uses longer rests (and those around the turns) than the session's 2 s
    # holds: it is at least as close to the truth as the session's, at the session's sigma
    a_true = np.asarray(truth["accel"]["m"])
    sig_session = np.asarray(result["accel"]["sigma_m"])
    assert np.abs(fa.accel.m - a_true).max() < 4 * sig_session.max()


# ------------------------------------------------------------------ issue 26: other people's recordings
def test_headerless_table_read_by_position(session, tmp_path):
    """A log of six numbers a line and no header (mikoff/imu-calib's .log): read by position,
    found as csv from its content whatever its extension, and said so."""
    ua, ug, truth, _ = session
    p = tmp_path / "imu0.log"
    np.savetxt(p, np.column_stack([ua, ug]), fmt="%.6f", delimiter=" ")
    rec = read(p, rate_hz=FS, accel_unit="mps2", gyro_unit="rad_s")
    assert rec.fmt == "csv" and np.allclose(rec.accel, ua, atol=1e-6) and np.allclose(rec.gyro, ug, atol=1e-6)
    assert any("no header row: 6 columns read as ax ay az gx gy gz" in n for n in rec.notes)
    # the columns in another order, by 1-based position
    q = tmp_path / "swapped.txt"
    np.savetxt(q, np.column_stack([ug, ua]), fmt="%.6f")
    rec2 = read(q, rate_hz=FS, accel_unit="mps2", gyro_unit="rad_s",
                columns={"gx": "1", "gy": "2", "gz": "3", "ax": "4", "ay": "5", "az": "6"})
    assert np.allclose(rec2.accel, ua, atol=1e-6)
    with pytest.raises(RecordingError, match="no header row: map the columns by position"):
        read(q, rate_hz=FS, accel_unit="mps2", gyro_unit="rad_s", columns={"ax": "AccX"})


def test_explicit_gyro_method_refused_keeps_the_accelerometer_and_exits_1(session, tmp_path, monkeypatch, capsys):
    """--gyro rotation on a recording whose motions cannot give it: the accelerometer's result is
    printed, kept in session.json and the history, exported; the verdict says why; exit 1."""
    ua, ug, _, events = session
    rests = [e for e in events if e[0] == "rest"]
    cut = rests[5][2]                         # the six faces: five motions, fewer than the method needs
    p = write_csv(tmp_path / "short.csv", ua[:cut] / G0, np.degrees(ug[:cut]), FS)
    db = tmp_path / "h.sqlite"
    r = _main(["--from", str(p), "--accel-unit", "g", "--gyro-unit", "dps", "--gyro", "rotation", "--method", "six",
               "--dir", "out", "--db", str(db), "--export", "imucal"], tmp_path, monkeypatch, capsys)
    if "not enough still poses" in r.stderr:
        pytest.fail("the synthetic session's first rests are not six faces: " + r.stderr)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert "verdict: accelerometer calibrated" in r.stdout and "gyro not: rotation_method:" in r.stdout
    assert "calibration PARTIAL" in r.stdout
    assert "--gyro rotation was refused" in r.stderr and "the accelerometer result is kept" in r.stderr
    state = json.loads((tmp_path / "out" / "session.json").read_text())
    assert state["result"]["accel"]["m"] and state["result"]["gyro_refused"].startswith("rotation_method:")
    assert list((tmp_path / "out").glob("*.imucal.json"))
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT count(*) FROM runs").fetchone()[0] == 1


def test_live_six_with_rotation_is_refused_before_capture(tmp_path, monkeypatch, capsys):
    r = _main(["--sim", "--method", "six", "--gyro", "rotation", "--dir", "s", "--db", str(tmp_path / "h.sqlite")],
              tmp_path, monkeypatch, capsys)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "6 attitudes give 5 motion(s)" in r.stderr and "nothing was captured" in r.stderr
    assert not (tmp_path / "s").exists()


# ------------------------------------------------------------------ issue 32: clipping, evidence, README's command
CLIP_FS = 100.0
THIRD = tuple(range(2, 18, 3))                  # 6 of the 18 motions faster than the gyro's ±250 °/s


@pytest.mark.parametrize("declared", [None, 250.0], ids=["found-in-the-data", "declared-range"])
def test_gyro_clipped_in_a_third_of_its_motions_leaves_them_out(declared):
    """Clipped motions are found by default (a plateau at the extreme of the values) or at the
    declared --gyro-range, named, left out of the gyro fit; the rest still calibrate it."""
    from imu_synth import clipped_gyro_session
    ua, ug, truth, _ = clipped_gyro_session(THIRD, range_dps=250.0, fs=CLIP_FS, seed=0)
    assert np.sum(np.abs(np.degrees(ug)) >= 250.0 - 1e-9) > 100           # the synthetic gyro did clip
    said = []
    fa = FileAnalysis(from_arrays(ua, ug, rate_hz=CLIP_FS), FileConfig(gyro_range_dps=declared), say=said.append)
    res = fa.run()
    assert res["gyro_refused"] is None and fa.gyro.method == "rotation"
    assert [m["motion"] for m in res["clipping"]["gyro"]] == list(THIRD)
    src = "declared" if declared else "data"
    for m in res["clipping"]["gyro"]:
        assert {a["source"] for a in m["axes"]} == {src} and all(a["level"] in ("+250.0 °/s", "-250.0 °/s")
                                                                for a in m["axes"])
    named = [n for n in res["notes"] if "left out of the gyro fit: the gyro clipped" in n]
    assert len(named) == len(THIRD) and re.search(r"motion 2 \(\d+\.\d–\d+\.\d s\) left out .* X at \+250\.0 °/s "
                                                  r"for \d+ samples from \d+\.\d\d s", named[0]), named
    assert "gyro clipped in 6 of 18 motions: those are left out of the gyro fit" in said
    # a full scale found in the data is said once, as the option that declares it (issue 40, item 6)
    det = [d for d in res["source"]["detected"] if d.startswith("gyro full scale")]
    if declared is None:
        assert len(det) == 1 and det[0].startswith("gyro full scale ±250 °/s from the values' clip level")
        assert "--gyro-range 250" in det[0] and res["source"]["options"][-2:] == ["--gyro-range", "250"]
    else:
        assert not det
    z = (fa.gyro.m - truth["gyro_m"]) / fa.gyro.sigma_m
    assert np.abs(z).max() < 3, z
    # without leaving them out, the same motions spoil the fit: the check is what makes it work
    from imubench.calib import gyro as CG
    keep = fa.intervals
    up = fa.accel.correct(np.array([i.mean for i in keep]))
    with pytest.raises(CG.CalibrationError, match="does not explain the gravity directions"):
        CG.rotation_method(ug, CLIP_FS, [(i.start, i.stop) for i in keep], up, fa.gyro.b, max_rate_rad_s=None)


def test_known_angle_turns_where_the_gyro_clipped_are_not_used_and_say_why():
    ua, ug, _, _ = ferraris_session(fs=FS, seed=2)             # its turns peak at 180 °/s
    r = np.radians(150.0)
    fa, res = _analyse(from_arrays(ua, np.clip(ug, -r, r), rate_hz=FS))
    assert [t["label"] for t in res["turns"]] == ["turn about +X", "turn about +Y", "turn about +Z"]
    for t, ax in zip(res["turns"], "XYZ"):
        assert not t["usable"] and re.match(rf"the gyro clipped in it, {ax} at \+150\.0 °/s for \d+ samples from "
                                            r"\d+\.\d\d s \(full scale found in the data\): turn slower", t["reason"])
    assert res["gyro_refused"].startswith("known-angle turns: 0 usable turn(s)") and res["passed"]


def test_gyro_clipped_in_nearly_all_motions_is_refused_with_the_reason():
    from imu_synth import clipped_gyro_session
    fast = tuple(j for j in range(18) if j not in (0, 6, 12))
    ua, ug, _, _ = clipped_gyro_session(fast, fs=CLIP_FS, seed=0)
    fa, res = _analyse(from_arrays(ua, ug, rate_hz=CLIP_FS), gyro="auto")
    assert len(res["clipping"]["gyro"]) == 15
    assert re.search(r"rotation_method: 3 motion\(s\) .* at least 6 are needed.*\(15 of 18 motions left out: the gyro "
                     r"clipped in them; turn slower than its range\)", res["gyro_refused"]), res["gyro_refused"]
    assert res["passed"] and res["gyro"]["method"] == "bias"           # the accelerometer and the bias stand
    assert "gyro not:" in res["verdict"] and "clipped" in res["verdict"]


def test_accelerometer_rest_at_full_scale_is_left_out_and_named():
    """Rests where the accelerometer sat at its full scale (here Z, clipped just under the +Z
    rests' reading) are left out of the fit and named; the other attitudes still calibrate it."""
    from imubench.calib.accel import lower_triangular_form
    ua, ug, truth, _ = ferraris_session(fs=FS, seed=7, edges=True)
    ua_c = ua.copy()
    ua_c[:, 2] = np.minimum(ua[:, 2], ua[:300, 2].mean() - 0.002 * G0)
    fa = FileAnalysis(from_arrays(ua_c, ug, rate_hz=FS), FileConfig(gyro=None, method="multi"), say=lambda s: None)
    res = fa.run()
    left = [r for r in res["rests"] if r["use"] == "left out"]
    assert len(left) >= 3 and {r["face"] for r in left} == {"+Z"}
    assert all(re.match(r"clipped: accelerometer Z held at \+0\.98\d+ g \(its full scale, found in the data\)",
                        r["use_reason"]) for r in left), left
    assert not any(r["face"] == "+Z" and r["use"] == "used" for r in res["rests"])
    assert len(res["clipping"]["accel"]) == len(left)
    l_true, _ = lower_triangular_form(truth["accel_m"])
    assert np.abs(fa.accel.m - l_true).max() < 5 * np.nanmax(fa.accel.sigma_m) + 1e-4
    assert res["passed"]


def _few_faces_file(tmp_path):
    """A recording whose rests show four faces: the six-position fit is refused."""
    from imu_synth import clipped_gyro_session
    ua, ug, _, events = clipped_gyro_session((), fs=CLIP_FS, seed=0)
    cut = [e for e in events if e[0] == "rest"][6][2]
    p = tmp_path / "few_faces.csv"
    np.savetxt(p, np.column_stack([ua[:cut], ug[:cut]]), delimiter=",", header="acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z",
               comments="", fmt="%.9g")
    return p


def test_a_refused_accelerometer_leaves_its_evidence(tmp_path, monkeypatch, capsys):
    """A refusal writes the folder: the segmentation plot, the rests table (CSV and README) and
    the reason, and says where; the error is still one line."""
    p = _few_faces_file(tmp_path)
    r = _cli(["--from", str(p), "--accel-unit", "mps2", "--gyro-unit", "rad_s", "--rate", "100", "--dir", "out",
              "--db", str(tmp_path / "h.sqlite")], tmp_path)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(err) == 1 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    assert "missing faces: -X, -Z" in err[0]
    d = tmp_path / "out"
    assert f"refused; what was found is in {Path('out')}: segmentation.png" in r.stdout
    assert (d / "segmentation.png").stat().st_size > 10_000 and not (d / "session.json").exists()
    import csv
    rows = list(csv.DictReader((d / "rests.csv").open()))
    assert [row["index"] for row in rows] == [str(k) for k in range(7)]
    assert [row["face"] for row in rows] == ["+Z", "-Y", "+Z", "+Y", "+Z", "+X", "+Z"]
    assert all(row["use"] in ("used", "down-weighted", "left out") for row in rows)
    assert abs(float(rows[0]["mean_z_g"]) - 1.0) < 0.02 and float(rows[0]["duration_s"]) > 1.0
    readme = (d / "README.md").read_text()
    reason = err[0].split("error: calibration failed: ", 1)[1].split("; see docs/")[0]
    assert f"**REFUSED:** {reason}" in readme
    assert "imubench calibrate --from" in readme and rests_header() in readme
    # the same folder again: refused, nothing overwritten
    r2 = _main(["--from", str(p), "--accel-unit", "mps2", "--gyro-unit", "rad_s", "--rate", "100", "--dir", "out",
                "--db", str(tmp_path / "h.sqlite")], tmp_path, monkeypatch, capsys)
    assert r2.returncode == 1 and "already holds a session" in r2.stderr


def rests_header() -> str:
    return "rests found by the data (σ: the 1σ of each mean; σ ×: its inflation in the fit):"


def test_readme_first_command_without_dir_from_an_empty_folder(tmp_path):
    """Issue 32 item 6: `calibrate --from FILE --accel-unit mps2 --gyro-unit rad_s --rate 100`,
    no --dir: it ran into a NameError. Now it names its folder after the file and leaves the
    evidence there, accepted (here: the gyro clipped in a third of its motions, left out)."""
    from imu_synth import clipped_gyro_session
    ua, ug, _, _ = clipped_gyro_session(THIRD, fs=CLIP_FS, seed=0)
    data = tmp_path / "data"
    data.mkdir()
    p = data / "myimu.csv"
    np.savetxt(p, np.column_stack([ua, ug]), delimiter=",", header="acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z",
               comments="", fmt="%.9g")
    work = tmp_path / "empty"
    work.mkdir()
    r = subprocess.run([sys.executable, "-m", "imubench", "calibrate", "--from", str(p), "--accel-unit", "mps2",
                        "--gyro-unit", "rad_s", "--rate", "100"], capture_output=True, text=True, cwd=work,
                       timeout=180, stdin=subprocess.DEVNULL, env={**__import__("os").environ,
                                                                   "IMUBENCH_DB": str(tmp_path / "h.sqlite")})
    assert r.returncode == 0 and r.stderr == "", r.stdout + r.stderr
    (d,) = list(work.glob("imubench-file-myimu-*"))
    for f in ("session.json", "segmentation.png", "rests.csv", "README.md", "report.html"):
        assert (d / f).is_file(), f
    assert "gyro clipped in 6 of 18 motions" in r.stdout and "rests: 19 used, 0 down-weighted, 0 left out" in r.stdout
    state = json.loads((d / "session.json").read_text())["result"]
    assert [m["motion"] for m in state["clipping"]["gyro"]] == list(THIRD) and len(state["rests"]) == 19
    assert "## Clipping" in (d / "README.md").read_text() and rests_header() in (d / "report.html").read_text()
