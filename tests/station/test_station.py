"""The pieces of the person's session without a browser: attitudes in words and pictures, live
detection, any order with a hint and no timeout, adaptive capture, the station's ownership and
its errors (tests/station/test_station_browser.py drives the whole page in chromium)."""
from __future__ import annotations

import json
import urllib.error
import urllib.request
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from imubench.calib.accel import POSE_PLAN
from imubench.procedures.poses import Targets, detect_attitude, pose_words
from imubench.results.boardpic import board_rotation, board_svg, board_text
from imubench.station.runner import Station, StationError
from imubench.station.state import StationState


def test_attitudes_in_words_a_person_understands():
    assert pose_words([0, 0, 1]) == "Z up, board level"
    assert pose_words([1, 0, 0]) == "X up, connector to the floor"
    assert pose_words([-1, 0, 0]) == "X down, connector up"
    assert pose_words([0, 0, -1]) == "Z down, board upside down"
    assert pose_words(np.array([1, 0, -1]) / np.sqrt(2)) == "X up, Z down (45° on an edge, Y level)"
    assert pose_words(np.array([1, -1, 1]) / np.sqrt(3)).startswith("X and Z up, Y down (on a corner")
    # every planned attitude has its own words
    assert len({pose_words(p.vector) for p in POSE_PLAN}) == len(POSE_PLAN)


def test_detection_names_the_nearest_planned_attitude_within_tolerance():
    plan = [(p.name, p.vector) for p in POSE_PLAN]
    tilt = np.radians(10.0)
    k, ang = detect_attitude([np.sin(tilt), 0, np.cos(tilt)], plan)       # a hand, 10° off level
    assert plan[k][0] == "+Z up (level)" and ang == pytest.approx(10.0, abs=1e-6)
    between = np.radians(22.5)                                            # half-way to the +X+Z edge
    k, ang = detect_attitude([np.sin(between), 0, np.cos(between)], plan)
    assert k is None and ang == pytest.approx(22.5, abs=1e-6)


def test_board_rotation_puts_the_up_direction_up():
    for p in POSE_PLAN:
        R = board_rotation(p.vector)
        assert np.allclose(R @ p.vector, [0, 0, 1], atol=1e-12)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)


def test_board_pictures_are_drawn_from_the_rotation():
    svgs = {p.name: board_svg(p.vector, title=p.name) for p in POSE_PLAN}
    assert len(set(svgs.values())) == len(POSE_PLAN)
    for s in svgs.values():
        root = ET.fromstring(s)                       # well-formed SVG
        labels = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text")]
        assert {"X", "Y", "Z"} <= set(labels)
    # level: the Z arrow's label is drawn above the board; upside down, below it
    def label_y(svg, name):
        root = ET.fromstring(svg)
        return next(float(t.get("y")) for t in root.iter("{http://www.w3.org/2000/svg}text") if t.text == name)
    up, down = board_svg([0, 0, 1]), board_svg([0, 0, -1])
    assert label_y(up, "Z") < 60 < label_y(down, "Z")
    # on the terminal: X up puts the X above the connector '@', which is near the floor
    lines = board_text([1, 0, 0]).splitlines()
    row_x = next(i for i, line in enumerate(lines) if "X" in line)
    row_at = max(i for i, line in enumerate(lines) if "@" in line)
    assert row_x < row_at and "‾" in lines[-1]


def test_human_presenter_lists_missing_attitudes_and_names_the_one_held(capsys):
    from imubench.cli.terminal import HumanPresenter
    plan = [(p.name, p.vector) for p in POSE_PLAN]
    ui = HumanPresenter()
    ui.present_todo(plan[2:], plan[:2], 26)
    ui.live({"attitude": plan[2][0], "words": pose_words(plan[2][1]), "state": "still", "captured": False, "hint": ""})
    out = capsys.readouterr().out
    assert "[2/26 captured] present any missing attitude, in any order" in out
    ui.present_todo(plan[3:], plan[:3], 26)                           # later: the names only
    assert "missing: -X up (nose down), +Y up" in " ".join(capsys.readouterr().out.split())
    assert "X up, connector to the floor" in out and "-X+Y+Z corner" in out and "+Z up (level)" not in out
    assert f"the board is in {plan[2][0]}: X up, connector to the floor (capturing, hold still)" in out
    assert "@" in out and "‾" in out                                   # the drawing


def test_one_page_owns_a_device_the_others_watch(monkeypatch):
    import imubench.station.state as S
    st = StationState()
    owner, other = st.new_client(), st.new_client()           # identities the server issues
    assert owner != other and st.client(owner) == owner and st.client("made-up") is None
    assert st.claim("socket://a:1", owner) == owner and st.owns("socket://a:1", owner)
    assert st.claim("socket://a:1", other) is None                    # read-only
    assert st.claim("socket://a:1", owner) == owner                   # the owner again (a reload)
    assert st.claim("socket://b:2", other) == other                   # another device is free
    snap = st.snapshot(other)
    mine = {b["key"]: b["yours"] for b in snap["boards"]}
    assert mine == {"socket://a:1": False, "socket://b:2": True}
    assert all("owner" not in b for b in snap["boards"])              # tokens never leave the server
    monkeypatch.setattr(S, "OWNER_GRACE_S", 0.0)
    # an owner whose page is open (its event stream) keeps the device, however long ago it spoke
    st.stream_opened(owner)
    assert st.claim("socket://a:1", other) is None
    # an owner that went away (no page open for the grace time) gives the device up
    st.stream_closed(owner)
    assert {b["key"]: b["owned"] for b in st.snapshot(other)["boards"]}["socket://a:1"] is False   # the pages may claim it
    assert st.claim("socket://a:1", other) == other


def test_station_options_are_checked_with_one_line_each():
    s = Station(allow_sim=False)
    with pytest.raises(StationError, match="give the device's port"):
        s.options({"port": " "})
    with pytest.raises(StationError, match="method must be one of multi, six, not 'seven'"):
        s.options({"port": "socket://x:1", "method": "seven"})
    with pytest.raises(StationError, match="start the station with --sim"):
        s.options({"port": "sim"})
    assert s.options({"port": "/dev/ttyUSB0"})["method"] == "multi"     # multi is the default
    with pytest.raises(StationError, match="6 attitudes give 5 motion.*rotation method needs at least 6"):
        s.options({"port": "/dev/ttyUSB0", "method": "six", "gyro": "rotation"})     # refused before capture


def test_station_server_answers_bad_requests_in_one_line(tmp_path):
    import http.cookiejar
    from imubench.station.server import Server
    server = Server(Station(workdir=tmp_path, allow_sim=False)).start()
    origin = server.url.rstrip("/")
    opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(http.cookiejar.CookieJar()))
    session = {}
    try:
        def call(path, data=None, headers=None):
            # as the page does it: its Origin, JSON, the session it traded the launch secret for
            req = urllib.request.Request(server.url + path, data=None if data is None else json.dumps(data).encode(),
                                         headers={"Content-Type": "application/json", "Origin": origin, **session,
                                                  **(headers or {})})
            try:
                with opener.open(req, timeout=10) as r:
                    return r.status, r.read().decode()
            except urllib.error.HTTPError as e:
                return e.code, e.read().decode()
        code, page = call("")
        assert code == 200 and "/static/station.js" in page and "http" not in page.split("<body>")[1].split("://")[0]
        code, js = call("static/station.js")
        assert code == 200 and "/api/events" in js and "X-Imubench-Session" in js
        code, body = call("pose.svg?up=1,0,0")
        assert code == 403 and "no session of this station" in json.loads(body)["error"]
        code, body = call("api/session", {}, {"X-Imubench-Launch": server.launch_url.split("#token=")[1]})
        assert code == 200                                            # the page's first request: its session
        session["X-Imubench-Session"] = json.loads(body)["session"]
        assert call("pose.svg?up=0,0,0")[0] == 400
        code, svg = call("pose.svg?up=1,0,0")
        assert code == 200 and svg.startswith("<svg")
        code, body = call("api/claim", {"key": "socket://127.0.0.1:1"})
        assert code == 200 and json.loads(body) == {"key": "socket://127.0.0.1:1", "yours": True}
        code, body = call("api/start", {"port": "socket://127.0.0.1:1", "gyro": "spin"})
        assert code == 400 and json.loads(body)["error"].startswith("gyro must be one of")
        assert call("report/none/report.html")[0] == 404
        assert call("export/none/calibration-x.px4.params")[0] == 404
        code, svg = call("turn.svg?axis=0,0,1&angle=360")          # a known-angle turn by hand
        assert code == 200 and "+360°" in svg
        assert call("turn.svg?axis=0,0,1&angle=full")[0] == 400
    finally:
        server.stop()


def test_known_angle_turns_by_hand_on_the_station_page(tmp_path):
    """--gyro turns from the page: for X, Y and Z up the page asks for the attitude (a step),
    then for one full turn by hand (its own picture); the simulated person does both and the
    gyro is calibrated from the turns."""
    st = Station(workdir=tmp_path, db=tmp_path / "h.sqlite", sim_speed=0, sim_seed=3)      # no ceiling: no page watches
    try:
        # 100 Hz (the station API's rate_hz; the default is 500): the turns by hand are what this
        # test is about, and a 360° turn integrates as well from a fifth of the samples
        st.start({"port": "sim", "gyro": "turns", "write": False, "rate_hz": 100}, token=None)
        st.wait("sim", timeout=600)
        b = st.state.boards["sim"]
    finally:
        st.close()
    assert b.status == "done", (b.error, b.log[-5:])
    hand = [t for t in b.turns if t.get("by_hand")]
    assert len(hand) == 3 and [t["state"] for t in hand] == ["done"] * 3
    assert [np.argmax(np.abs(t["axis"])) for t in hand] == [0, 1, 2] and all(t["angle_deg"] == 360 for t in hand)
    steps = [x for x in b.steps if x["kind"] == "turn-pose"]
    assert len(steps) == 3 and all(x["state"] == "done" for x in steps) and "lie still" in steps[0]["text"]
    assert any(r[0] == "gyro Mxx − 1" for r in b.result["parameters"]), b.result["parameters"]
    # a download per board of every calibration format of the export registry (issue 34)
    from imubench.results import exports as X
    ex = {e["kind"]: e for e in b.result["exports"]}
    assert set(ex) == set(X.names("calibration")) | {"index"}
    for e in b.result["exports"]:
        assert e["url"] == f"/export/sim/{e['name']}" and st.export_path("sim", e["name"]).is_file()
    assert st.export_path("sim", "../session.json") is None and st.export_path("other", ex["px4"]["name"]) is None
    assert "# Holds: " in st.export_path("sim", ex["kalibr"]["name"]).read_text()
    assert "not usable" in ex["px4"]["label"] and "NOT USABLE AS IS" in st.export_path("sim", ex["px4"]["name"]).read_text()


def test_any_order_with_a_hint_no_timeout_and_adaptive_stop(tmp_path):
    """A person who first holds the board between two attitudes gets a hint (and no abort);
    then the attitudes come in the person's random order and the adaptive session stops when
    every parameter is at its target."""
    from imubench.device.sim import VirtualBench
    from imubench.procedures.virtual import SimPerson
    from imubench.procedures.session import Session, SessionConfig, plan_for

    class Watch(SimPerson):
        hints, events = [], []

        def say(self, text):
            self.hints.append(text)

        def live(self, st):
            pass

        def pose_event(self, name, state, detail):
            self.events.append((name, state))

    # 100 Hz, not the default 500: the order, the hint and the adaptive stop do not depend on
    # the rate (the adaptive hold is to a sigma target, whatever the rate)
    cfg = SessionConfig(method="multi", gyro=None, write=False, adaptive=True, pose_timeout_s=None, rate_hz=100)
    with VirtualBench(speed=0, seed=11, truth="random") as vb, vb.device() as dev:     # lockstep, no ceiling
        person = Watch(vb, seed=4, wrong_first=True)
        result = Session(dev, tmp_path / "s", cfg, person).run(plan_for("multi"))
    assert any("in no planned attitude" in h for h in person.hints), person.hints[:10]
    names = [p["name"] for p in result["poses"]]
    assert names == person.order[:len(names)]
    assert names != [n for n, _ in plan_for("multi")][:len(names)]        # not the plan's order
    t = Targets()
    assert t.min_attitudes <= len(names) < 26
    assert all(v <= {"b": t.accel_bias_mg, "s": t.accel_scale_ppm, "a": t.accel_nonorth_mrad}[k[0]]
               for k, v in result["accel_sigmas"].items())
    done = [n for n, s in person.events if s == "done"]
    assert done == names
    assert result["bench_time_s"] > 0 and result["passed"]


def test_station_commands_fail_in_one_line(tmp_path, capsys, monkeypatch):
    # in-process (the command's main, as `python -m imubench` calls it): the one-line usage
    # errors are the library's; the busy-port test below runs the command as a process
    from imubench.cli import main as imubench
    monkeypatch.delenv("IMUBENCH_PORT", raising=False)
    assert imubench(["station", "--http-port", "70000"]) == 2
    err = capsys.readouterr().err
    assert "70000 is not a TCP port" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert imubench(["calibrate", "--ui", "web", "--dir", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "no device: give --port URL" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_the_verdict_says_in_words_why_six_faces_failed():
    from imubench.results.report import calibration_verdict
    result = {"passed": False, "method": "six", "accel_rms_after_mg": 3.2, "tolerances": {"accel_rms_mg": 1.0},
              "accel": {"extra": {"chi2_red": 5.5e6}}, "faces_off_square_deg": 1.3}
    status, words = calibration_verdict(result)
    assert status == "fail"
    assert "the six faces are 1.3° off square (χ²/dof 5.5e+06): use --method multi" in words
    assert "nothing was written to the device" in words


def test_the_suggested_next_attitude_helps_the_fit_most():
    from imubench.calib.accel import dilution
    from imubench.procedures.poses import suggest_next
    plan = [(p.name, p.vector) for p in POSE_PLAN]
    assert suggest_next([[0, 0, 1]], plan[1:]) == "-Z up (upside down)"       # spread first
    done = [v for _, v in plan[:6] + plan[18:22]]           # the faces and four corners
    todo = plan[6:18] + plan[22:]
    best = suggest_next(done, todo)
    after = {n: dilution(np.array(done + [v])) for n, v in todo}
    worst_after = {n: float(np.max(s)) for n, s in after.items() if s is not None}
    assert worst_after[best] == min(worst_after.values()) < max(worst_after.values())
    assert suggest_next(done, []) is None


def test_a_busy_port_is_refused_before_anything_starts(tmp_path):
    """The page's port is bound before the session starts: a port in use is one line, and no
    board was opened, nothing captured."""
    import socket
    import subprocess
    import sys
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        for extra in (["--sim-boards", "2"], []):
            d = tmp_path / f"s{len(extra)}"
            r = subprocess.run([sys.executable, "-m", "imubench", "calibrate", "--sim", *extra, "--ui", "web",
                                "--http-port", str(port), "--dir", str(d), "--db", str(tmp_path / "h.sqlite")],
                               capture_output=True, text=True, timeout=120)
            assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
            assert r.stderr.strip().splitlines() == [
                f"imubench calibrate: error: the station cannot listen on 127.0.0.1:{port}: Address already in use; "
                "give another --http-port, or 0 for any free port"], r.stderr
            assert not d.exists()
    finally:
        busy.close()


def test_ctrl_c_stops_every_board_of_a_station_session_on_the_page(tmp_path):
    import signal
    import subprocess
    import sys
    p = subprocess.Popen([sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-boards", "2", "--sim-speed", "2",
                          "--ui", "web", "--http-port", "0", "--dir", str(tmp_path / "st"),
                          "--db", str(tmp_path / "h.sqlite")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         # SIGINT to its default in the child: a run started in the background by a
                         # non-interactive shell ignores it, and the child would too
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []
    try:
        for line in p.stdout:
            seen.append(line)
            if "presents" in line:           # the plate moves: the boards are capturing
                break
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    out = "".join(seen) + out
    # every stop recorded the same way (issue 38): stopped with the stage, exit 130 as in the terminal
    assert p.returncode == 130 and "Traceback" not in out + err, out + err
    assert err.strip() == ("imubench calibrate: error: interrupted; interrupted (Ctrl-C): 0 of 2 boards passed; 0 "
                           "finished boards recorded, 2 recorded as stopped (with their stage); continue them with "
                           f"imubench calibrate --resume {tmp_path / 'st'}"), err
    assert out.count("STOPPED") == 2 and out.count("at poses: stopped: interrupted (Ctrl-C)") == 2, out
    assert "link lost" not in out + err
    assert (tmp_path / "st" / "slot-1" / "capture-1.bin").stat().st_size > 0
