"""Many boards on one fixture (imubench.procedures.fixture) on the virtual bench: several
virtual devices, each with its own random truth and serial numbers, on one virtual plate;
a healthy set, a board that loses its link half-way, boards with a faulted gyro (before the
session and in the middle of it) among healthy ones; the per-board records in the history."""
from __future__ import annotations

import hashlib
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench.cli import main as imubench
from imubench.device.link import Device
from imubench.device.sim import VirtualBench
from imubench.procedures.fixture import FixtureRun, Plate, Station
from imubench.procedures.schedule import Need
from imubench.procedures.session import SessionConfig
from imubench.procedures.virtual import PlatePresenter
from imubench.results.calibration import truth_in_fit_frame
from imubench.results.history import History
from imubench.wire import params as PR
from imubench.wire.protocol_gen import ParamsWhich


def _benches(n: int, seed0: int, speed: float = 0) -> list[VirtualBench]:
    out = []
    try:
        for k in range(n):
            vb = VirtualBench(speed=speed, seed=seed0 + k, truth="random")
            vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)      # a fixed truth
            out.append(vb)
    except BaseException:
        for vb in out:
            vb.close()
        raise
    return out


def _run(benches, tmp_path, on_event=None, **kw):
    events = []

    def ev(st):
        events.append(st)
        if on_event is not None:
            on_event(st)
    # 100 Hz rather than the default 500, and a plate turning at 360 °/s rather than 90: what
    # these tests prove (each board its own fit, a fault stays its board's) depends on neither;
    # the defaults (500 Hz, the CLI's plate) run end to end in
    # test_cli_station_session_on_virtual_devices and the one-board session below; so do the
    # per-board residual plots (asserted there), which these tests do not look at
    run = FixtureRun([vb.port_url for vb in benches], tmp_path / "station", SessionConfig(rate_hz=100),
                     PlatePresenter(benches, quiet=True, rate_dps=360.0), station=Station("S-test", "ana", "plate-3"),
                     db=str(tmp_path / "line.sqlite"), on_event=ev, link_timeout_s=kw.pop("link_timeout_s", 3.0),
                     say=lambda s: None, plots=kw.pop("plots", False), **kw)
    return run, run.run(), events


def test_a_healthy_set_each_board_fitted_on_its_own(tmp_path):
    benches = _benches(3, 301)
    try:
        _, res, events = _run(benches, tmp_path)
        truths = [vb.get_truth() for vb in benches]
        actives = []
        for vb in benches:
            with Device.open(vb.port_url, timeout=5.0) as dev:
                actives.append(dev.get_params(ParamsWhich.ACTIVE).params)
    finally:
        for vb in benches:
            vb.close()
    assert [b.state for b in res.boards] == ["passed"] * 3, [b.reason for b in res.boards]
    uids = [b.uid for b in res.boards]
    assert len(set(uids)) == 3
    sns = [tuple(res.results[s]["device"]["gyro_sn"]) for s in (1, 2, 3)]
    assert len(set(sns)) == 3                                   # each virtual device its own serial numbers
    for slot, truth, active in zip((1, 2, 3), truths, actives):
        rec = res.results[slot]
        t = truth_in_fit_frame(rec, truth)
        m, sm = np.array(rec["accel"]["m"]), np.array(rec["accel"]["sigma_m"])
        est = sm > 0
        assert np.all(np.abs((m - t["accel_m"])[est] / sm[est]) < 4.0)           # its own truth, not another's
        assert np.all(np.abs((np.array(rec["accel"]["b_mps2"]) - t["accel_b_mps2"])
                             / np.array(rec["accel"]["sigma_b_mps2"])) < 4.0)
        assert rec["written"] and rec["verified"]
        assert rec["params_after"] == PR.to_json(active)         # what the device holds now
        assert rec["params_before"]["accel_m"] == [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
        host_and_path = rec["capture"]["uri"].removeprefix("file://")     # file://HOST/abs/path
        cap = Path("/" + host_and_path.split("/", 1)[1])
        assert hashlib.sha256(cap.read_bytes()).hexdigest() == rec["capture"]["sha256"]
        assert all(m["passed"] for m in rec["measurements"])
        assert {m["name"] for m in rec["measurements"]} >= {"accel_norm_rms_mg", "params_written", "samples_lost"}
    # the truths differ between boards by much more than the fits' sigma: the fits are not shared
    b1, b2 = (np.array(res.results[s]["accel"]["b_mps2"]) for s in (1, 2))
    assert np.abs(b1 - b2).max() > 100 * max(res.results[1]["accel"]["sigma_b_mps2"])
    stages = [[e["stage"] for e in events if e["slot"] == s] for s in (1, 2, 3)]
    for st in stages:
        seen = list(dict.fromkeys(st))
        assert seen == ["connect", "health", "rest", "poses", "fit", "write", "verify", "done"], seen
    # one record per board, with the station, the session and the slot
    with History(tmp_path / "line.sqlite", readonly=True) as h:
        runs = h.session_runs(res.session_id)
    assert [(r["slot"], r["mcu_uid"], r["station_id"], r["operator"], r["fixture"]) for r in runs] == \
        [(s, u, "S-test", "ana", "plate-3") for s, u in zip((1, 2, 3), uids)]
    assert all(r["passed"] and r["host_version"] for r in runs)
    station = json.loads((tmp_path / "station" / "station.json").read_text())
    assert station["finished"] and [b["state"] for b in station["boards"]] == ["passed"] * 3


def test_a_board_losing_its_link_half_way_does_not_stop_the_others(tmp_path):
    benches = _benches(3, 311)
    cut = threading.Event()

    def on_event(st):           # board 2's link goes silent when the plate presents the third attitude
        if st["slot"] == 2 and st["message"].startswith("[3/6]") and not cut.is_set():
            cut.set()
            benches[1].inject("link_drop", count=10**9)
    try:
        _, res, _ = _run(benches, tmp_path, on_event=on_event)
    finally:
        for vb in benches:
            vb.close()
    assert cut.is_set()
    states = {b.slot: (b.state, b.stage) for b in res.boards}
    assert states == {1: ("passed", "done"), 2: ("failed", "link"), 3: ("passed", "done")}, \
        [b.reason for b in res.boards]
    assert "link lost: no data from the device for 3 s" in res.boards[1].reason
    rec2 = res.results[2]
    assert rec2["failure"]["stage"] == "link" and rec2["device"]["mcu_uid"] == res.boards[1].uid
    assert rec2["capture"]["sha256"] is not None           # what it sent before is kept and hashed
    assert res.results[1]["verified"] and res.results[3]["verified"]
    with History(tmp_path / "line.sqlite", readonly=True) as h:
        (f,) = h.failures()
        assert f["slot"] == 2 and f["failed_stage"] == "link" and "link lost" in f["failure"]
        assert h.yield_table("station")[0]["passed"] == 2
    assert imubench(["history", "--db", str(tmp_path / "line.sqlite"), "--failed"]) == 0


def test_faulted_gyros_among_healthy_boards(tmp_path):
    """Slot 2's gyro Y is faulted before the session (the health check refuses it), slot 3's
    gyro Z faults while the poses are captured (its samples are flagged bad); slots 1 and 4
    are calibrated as if nothing happened."""
    benches = _benches(4, 321)
    benches[1].inject("gyro_fault_bits", sensor="gyro_y", bits=0x10, persistent=True)
    hit = threading.Event()

    def on_event(st):
        if st["slot"] == 3 and st["message"].startswith("[2/6]") and not hit.is_set():
            hit.set()
            benches[2].inject("gyro_fault_bits", sensor="gyro_z", bits=0x10, persistent=True)
    try:
        _, res, _ = _run(benches, tmp_path, on_event=on_event)
    finally:
        for vb in benches:
            vb.close()
    states = {b.slot: (b.state, b.stage) for b in res.boards}
    assert states == {1: ("passed", "done"), 2: ("failed", "health"), 3: ("failed", "sensor"),
                      4: ("passed", "done")}, [b.reason for b in res.boards]
    assert "refusing to calibrate on faulted data" in res.boards[1].reason
    assert "gyro Z flagged bad during capture" in res.boards[2].reason
    for slot in (2, 3):
        assert res.results[slot]["written"] is False and res.results[slot]["params_after"] is None
    with History(tmp_path / "line.sqlite", readonly=True) as h:
        fails = {f["slot"]: f for f in h.failures()}
    assert set(fails) == {2, 3} and fails[2]["mcu_uid"] == res.boards[1].uid


# ------------------------------------------------------------------ the plate, without devices
class _Mover:
    def __init__(self):
        self.moves = []

    def present_pose(self, name, direction, index, total):
        self.moves.append(name)

    def present_turn(self, axis, rate, dur):
        self.moves.append(("turn", rate))


def test_the_plate_moves_once_when_every_live_board_asked_and_stops_waiting_for_a_board_that_left():
    mover = _Mover()
    plate = Plate(mover, [1, 2, 3])
    done = []

    def board(slot, poses, leave_after=None):
        for i, p in enumerate(poses):
            if leave_after is not None and i == leave_after:
                plate.leave(slot)
                return
            plate.request(slot, Need("verify", (p,)), {p: (p, None, i, len(poses))})
            done.append((slot, p))
        plate.leave(slot)
    ts = [threading.Thread(target=board, args=(1, ["a", "b", "c"])),
          threading.Thread(target=board, args=(2, ["a", "b", "c"], 1)),
          threading.Thread(target=board, args=(3, ["a", "b", "c"]))]
    for t in ts:
        t.start()
    for t in ts:
        t.join(10)
    assert not any(t.is_alive() for t in ts)
    assert mover.moves == ["a", "b", "c"]                      # each attitude presented once
    assert sorted(done) == sorted([(1, "a"), (1, "b"), (1, "c"), (2, "a"), (3, "a"), (3, "b"), (3, "c")])


# ------------------------------------------------------------------ command line
def test_cli_station_session_on_virtual_devices(tmp_path, capsys):
    db = tmp_path / "line.sqlite"
    assert imubench(["calibrate", "--sim", "--sim-boards", "2", "--sim-seed", "41", "--dir", str(tmp_path / "st"),
                     "--db", str(db), "--station", "S9", "--operator", "bo", "--fixture", "plate-1",
                     "--export", "px4,kalibr", "--export", "imucal", "--px4-acc-id", "1310988",
                     "--px4-gyro-id", "2163722"]) == 0
    out = capsys.readouterr().out
    # every board's result in the files its consumers read (issue 34): one set per slot, named by its UID
    for slot in (1, 2):
        d = tmp_path / "st" / f"slot-{slot}"
        (px4,) = d.glob("calibration-*.px4.params")
        rows = {ln.split("\t")[2]: ln.split("\t")[3] for ln in px4.read_text().splitlines() if not ln.startswith("#")}
        assert rows["CAL_ACC0_ID"] == "1310988" and rows["CAL_GYRO0_ID"] == "2163722"
        assert len(list(d.glob("calibration-*.kalibr-imu.yaml"))) == 1 and len(list(d.glob("calibration-*.imucal.json"))) == 1
        assert (d / "exports-calibration.txt").is_file()
        assert (d / "residuals.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"      # each board's residual plot
    assert "NOT USABLE" not in out
    table = [ln for ln in out.splitlines() if ln.strip()[:1].isdigit() and "PASSED" in ln]
    assert len(table) == 2 and all("written and verified" in ln for ln in table)
    assert "2 of 2 boards passed" in out
    sid = next(ln.split()[2].rstrip(":") for ln in out.splitlines() if ln.startswith("station session "))
    assert imubench(["history", "--db", str(db), "--export", sid, "--format", "junit",
                     "--out", str(tmp_path / "s.xml")]) == 0
    import xml.etree.ElementTree as ET
    root = ET.parse(tmp_path / "s.xml").getroot()
    assert len(root.findall("testsuite")) == 2 and root.get("failures") == "0" and int(root.get("tests")) >= 10
    # both formats at once (the registry's option syntax): one file each in the directory
    assert imubench(["history", "--db", str(db), "--export", sid, "--format", "json,junit",
                     "--out", str(tmp_path / "both")]) == 0
    assert sorted(p.name for p in (tmp_path / "both").iterdir()) == sorted(
        [f"session-{sid}.json", f"session-{sid}.junit.xml"])


@pytest.mark.parametrize("args, words", [
    (["--sim-boards", "2"], "--sim-boards goes with --sim"),
    (["--port", "socket://127.0.0.1:1", "--port", "socket://127.0.0.1:2", "--resume", "."], "holds no station session"),
    (["--sim", "--sim-boards", "2", "--port", "socket://127.0.0.1:1"], "exclude each other"),
    (["--port", "socket://127.0.0.1:1", "--port", "socket://127.0.0.1:1"], "given twice"),
    (["--sim", "--sim-boards", "0"], "give 1 to 64"),
])
def test_cli_station_usage_errors(args, words, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert imubench(["calibrate", *args]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_cli_station_file(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('station = "S1"\nportz = ["/dev/ttyUSB0"]\n')
    assert imubench(["calibrate", "--station-file", str(bad)]) == 2
    assert "unknown key portz" in capsys.readouterr().err
    bad.write_text('ports = "/dev/ttyUSB0"\n')
    assert imubench(["calibrate", "--station-file", str(bad)]) == 2
    assert "ports must be a list" in capsys.readouterr().err
    # two ports where no device answers: each board fails at connect, and is recorded so
    good = tmp_path / "station.toml"
    good.write_text(f'station = "S3"\noperator = "cy"\nfixture = "plate-9"\ndb = "{tmp_path / "l.sqlite"}"\n'
                    'ports = ["socket://127.0.0.1:1", "socket://127.0.0.1:2"]\n')
    assert imubench(["calibrate", "--station-file", str(good), "--dir", str(tmp_path / "st")]) == 1
    cap = capsys.readouterr()
    assert "2 of 2 boards failed: slot 1 at connect; slot 2 at connect" in cap.err
    assert len(cap.err.strip().splitlines()) == 1 and "Traceback" not in cap.err
    assert "no answer from the device on socket://127.0.0.1:2" in cap.out
    with History(tmp_path / "l.sqlite", readonly=True) as h:
        runs = {r["slot"]: r for r in h.failures()}
    assert set(runs) == {1, 2}
    assert all(r["mcu_uid"] is None and r["station_id"] == "S3" and r["operator"] == "cy" and
               r["fixture"] == "plate-9" and r["failed_stage"] == "connect" for r in runs.values())


def test_a_one_board_session_records_the_production_fields_too(tmp_path, capsys):
    db = tmp_path / "one.sqlite"
    assert imubench(["calibrate", "--sim", "--sim-seed", "61", "--dir", str(tmp_path / "s"), "--db", str(db),
                     "--station", "S5", "--operator", "di", "--fixture", "cube-2",
                     "--export", "params,px4", "--export", "ardupilot"]) == 0
    out = capsys.readouterr().out
    assert "px4: NOT USABLE AS IS, no CAL_ACC0_ID / CAL_GYRO0_ID" in out       # no ids given: said, with how
    assert "listener sensor_accel" in out
    with History(db, readonly=True) as h:
        (dev,) = h.devices()
        (run,) = h.runs(dev["mcu_uid"])
    assert (run["station_id"], run["operator"], run["fixture"], run["slot"]) == ("S5", "di", "cube-2", 1)
    assert run["host_version"] and run["params_before"]["accel_m"] == [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    assert run["params_after"]["accel_m"] != run["params_before"]["accel_m"]          # what was written
    cap = tmp_path / "s" / "capture-1.bin"
    assert run["capture_sha256"] == hashlib.sha256(cap.read_bytes()).hexdigest()
    assert run["capture_uri"].endswith(str(cap.resolve()))
    assert {m["name"] for m in run["measurements"]} >= {"accel_norm_rms_mg", "params_written"}
    # the live session's files (issue 34): our parameter file is the block written to the device
    uid = dev["mcu_uid"]
    params = json.loads((tmp_path / "s" / f"calibration-{uid}.params.json").read_text())
    assert params == run["params_after"]
    ap = (tmp_path / "s" / f"calibration-{uid}.ardupilot.param").read_text()
    vals = {ln.split(",")[0]: float(ln.split(",")[1]) for ln in ap.splitlines() if ln and not ln.startswith("#")}
    m = np.array(run["params_after"]["accel_m"]).reshape(3, 3)
    np.testing.assert_allclose([vals[f"INS_ACCSCAL_{a}"] for a in "XYZ"], 1.0 / np.diag(m), rtol=1e-7)
    assert "INS_ACC_ID" in ap and "# Holds: " in ap


def test_a_board_still_needing_an_attitude_is_served_before_another_boards_verification():
    """Issue 24: slot 1 went on to verification while slot 2 still needed an attitude; the
    plate presents slot 2's attitude first (slot 1 waits, visibly), then the verification."""
    mover, waits = _Mover(), []
    plate = Plate(mover, [1, 2], on_wait=lambda s, t: waits.append((s, t)))
    got = {}

    def slot2():
        got[2] = plate.request(2, Need("pose", ("+Y-Z edge", "-X-Z edge")), {"+Y-Z edge": ("+Y-Z edge", None),
                                                                            "-X-Z edge": ("-X-Z edge", None)})
        plate.leave(2)
    t = threading.Thread(target=slot2)
    t.start()
    got[1] = plate.request(1, Need("verify", ("+Z up (level)",)), {"+Z up (level)": ("+Z up (level)", None, 0, 3)})
    t.join(5)
    assert not t.is_alive()
    assert mover.moves == ["+Y-Z edge", "+Z up (level)"] and got == {1: "+Z up (level)", 2: "+Y-Z edge"}
    assert any(s == 1 and t and "waits for slot 2 to come to verification" in t and "deadline 300 s device time" in t
               for s, t in waits)
    assert waits[-1] == (1, None) or (1, None) in waits          # no longer waiting once served


def test_a_refused_fit_fails_that_board_only(tmp_path, monkeypatch):
    """The fit of slot 2 is refused (here: the fit says its poses cannot constrain the model);
    slot 1 is written and verified, slot 2 is recorded as failed at fit, nothing written to it."""
    import imubench.calib.accel as CA
    from imubench.calib import CalibrationError
    real = CA.six_position

    def six_position(*a, **k):
        if threading.current_thread().name == "board-2":
            raise CalibrationError("the poses do not constrain the scale of Y (test)")
        return real(*a, **k)
    monkeypatch.setattr(CA, "six_position", six_position)
    benches = _benches(2, 331)
    try:
        _, res, _ = _run(benches, tmp_path)
        with Device.open(benches[1].port_url, timeout=5.0) as dev:
            untouched = PR.is_factory(dev.get_params(ParamsWhich.ACTIVE).params)
    finally:
        for vb in benches:
            vb.close()
    assert [(b.state, b.stage) for b in res.boards] == [("passed", "done"), ("failed", "fit")]
    # the acceptance rules (calib.fit) name the model refused and why, in one line
    assert res.boards[1].reason.startswith("fit refused: no accelerometer model is both resolved by the rests")
    assert "six-position, full matrix and biases: the poses do not constrain the scale of Y (test)" in res.boards[1].reason
    assert untouched and res.results[2]["written"] is False


def test_a_station_name_with_escapes_reaches_the_terminal_escaped(tmp_path, capsys):
    """issue 36: a --station value with ESC and BEL was printed raw by the multi-board summary
    (an ESC ] 0 ; ... BEL retitles the terminal, ESC [ 2 J clears it)."""
    good = tmp_path / "station.toml"
    good.write_text(f'db = "{tmp_path / "l.sqlite"}"\nports = ["socket://127.0.0.1:1", "socket://127.0.0.1:2"]\n')
    evil = "S\x1b]0;owned\x07\x1b[2J\r\u202eX"
    assert imubench(["calibrate", "--station-file", str(good), "--station", evil, "--dir", str(tmp_path / "st")]) == 1
    cap = capsys.readouterr()
    for stream in (cap.out, cap.err):
        assert not any(c in stream for c in "\x1b\x07\r\u202e"), repr(stream[:300])
    assert "station S\\x1b]0;owned\\x07\\x1b[2J\\r\\u202eX, session directory" in cap.out
    assert "--export $'S\\x1b]0;owned" in cap.out


def test_a_terminal_gets_no_control_characters_whatever_a_command_forgets(monkeypatch):
    """The last guard (text.SafeTerminal): on a terminal every write is made printable; a
    pipe or a file is left alone (a CSV's CR LF)."""
    import io
    import sys as _sys

    from imubench.text import SafeTerminal, guard_terminal

    class Tty(io.StringIO):
        def isatty(self):
            return True
    tty, pipe = Tty(), io.StringIO()
    monkeypatch.setattr(_sys, "stdout", tty)
    monkeypatch.setattr(_sys, "stderr", pipe)
    guard_terminal(_sys)
    assert isinstance(_sys.stdout, SafeTerminal) and _sys.stderr is pipe
    print("name \x1b[31mred\x07\ttab", "a,b\r", sep="\n")
    _sys.stderr.write("a,b\r\n")
    assert tty.getvalue() == "name \\x1b[31mred\\x07\ttab\na,b\\r\n" and pipe.getvalue() == "a,b\r\n"
    guard_terminal(_sys)                        # not wrapped twice
    assert _sys.stdout._stream is tty


def test_a_printed_command_reads_back_as_the_same_text_in_bash():
    import subprocess

    from imubench.text import shell_word
    for s in ("S9-20261128T074142Z-dcab08", "a b", "S\x1b]0;o\x07\x1b[2J\r\u202eX'q\\z\n"):
        w = shell_word(s)
        assert not any(c in w for c in "\x1b\x07\r\n\u202e")
        assert subprocess.run(["bash", "-c", "printf %s " + w], capture_output=True).stdout == s.encode()
