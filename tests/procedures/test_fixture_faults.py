"""One board's fault stays its own (issue 38): on the host build's virtual devices, with the
lockstep clock, a board killed, frozen (SIGSTOP: its link open, nothing answers), slowed, or
sending garbage at any stage fails alone, with its own stage and reason, within its own
deadline; every healthy board passes and the plate goes on for them.

A property test draws the fixture (2 to 16 boards), the faulty boards, their faults and the
stage each fault starts at (hypothesis, a few derandomized examples: each example is a whole
station session on real simulator processes, kept short: six attitudes, no gyro stage, a
short rest and hold, as fast as the machine goes)."""
from __future__ import annotations

import os
import signal
import threading
import time

# what the boards' threads import on first use, imported here first: pytest rewrites the
# imubench modules it imports (ast.parse), and two threads parsing at once trip CPython
# 3.11's AST recursion check (SystemError in one board, a failure of the test's making)
import imubench.calib.accel  # noqa: F401
import imubench.calib.frames  # noqa: F401
import imubench.calib.gsens  # noqa: F401
import imubench.calib.gyro  # noqa: F401
import imubench.calib.static  # noqa: F401
import imubench.procedures.poses  # noqa: F401
import imubench.results.export  # noqa: F401
import imubench.results.history  # noqa: F401
import imubench.wire.decoder  # noqa: F401
import imubench.wire.ids  # noqa: F401
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st
from imubench.device.sim import VirtualBench
from imubench.procedures.fixture import FixtureRun, Station
from imubench.procedures.session import SessionConfig
from imubench.procedures.virtual import PlatePresenter

#: link timeout of these sessions (device s; and the wall-clock guard of a frozen board's grants)
LINK_TIMEOUT_S = 2.0
#: how much wall time past its guard a faulty board may take to be failed (a loaded machine)
SLACK_WALL_S = 20.0
#: the virtual plate's turn rate, °/s (PlatePresenter's default is 90): these tests are about
#: faults, not the plate's pace; a quicker move is less device time to run for every board
#: (on the F103 image, a third less emulator time)
PLATE_RATE_DPS = 360.0
#: the stages a fault may start at (the board's published stage)
STAGES = ("connect", "rest", "poses", "plate", "write", "verify")     # plate: waiting at the plate
FAULTS = ("kill", "freeze", "slow", "garbage")


def _sigint_default() -> None:
    """In the child: SIGINT to its default (a test run started in the background by a
    non-interactive shell ignores SIGINT, and the child would inherit that: Python then
    installs no Ctrl-C handler, and the SIGINT these tests send would be ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _cfg() -> SessionConfig:
    return SessionConfig(method="six", gyro=None, rate_hz=100, rest_s=1.0, settle_s=0.2, hold_s=0.5,
                         verify_poses=2, pose_timeout_s=30.0)


class Faults:
    """Starts each board's fault when that board reaches its stage (from the board's event)."""

    def __init__(self, benches, plan: dict[int, tuple[str, str]]):
        self.benches, self.plan = benches, plan
        self.started: dict[int, tuple[str, float]] = {}     # slot -> (stage it started at, wall time)
        self.ended: dict[int, float] = {}                   # slot -> wall time it passed or failed
        self._slow_stop = threading.Event()
        self._lock = threading.Lock()

    def __call__(self, ev: dict) -> None:
        slot = ev["slot"]
        if ev["state"] != "running":
            self.ended.setdefault(slot, time.monotonic())
        want = self.plan.get(slot)
        if want is None or ev["state"] != "running":
            return
        at_plate = (ev["stage"] == "poses" and ev["message"].endswith("waiting for the plate")
                    and not ev["message"].startswith("0 of"))      # the first attitude needs no move
        if ev["stage"] != want[1] and not (want[1] == "plate" and at_plate):
            return
        with self._lock:
            if slot in self.started:
                return
            self.started[slot] = (ev["stage"], time.monotonic())
        vb = self.benches[slot - 1]
        kind = want[0]
        if kind == "kill":
            os.kill(vb.pid, signal.SIGKILL)
        elif kind == "freeze":
            os.kill(vb.pid, signal.SIGSTOP)
        elif kind == "garbage":
            vb.inject("link_flip", count=10**9)     # every byte it sends from now on has a bit flipped
        elif kind == "slow":
            threading.Thread(target=self._slow, args=(vb,), daemon=True).start()

    def _slow(self, vb) -> None:
        """Stopped for a while and again and again, each time well inside its guard: slow, not dead."""
        pid = vb.pid
        try:
            while not self._slow_stop.is_set():
                os.kill(pid, signal.SIGSTOP)
                self._slow_stop.wait(0.15)
                os.kill(pid, signal.SIGCONT)
                self._slow_stop.wait(0.1)
        except (OSError, TypeError):        # its process is gone (the session is over)
            pass

    def close(self) -> None:
        self._slow_stop.set()
        for vb in self.benches:
            try:
                if vb.running:
                    os.kill(vb.pid, signal.SIGCONT)
            except OSError:
                pass


def _station(tmp_path, n: int, plan: dict[int, tuple[str, str]], seed0: int = 500, target: str = "host",
             cfg: SessionConfig | None = None):
    benches = []
    faults = None
    try:
        for k in range(n):
            benches.append(VirtualBench(speed=0, seed=seed0 + k, truth="random", target=target))
        faults = Faults(benches, plan)
        run = FixtureRun([vb.port_url for vb in benches], tmp_path / "station", cfg or _cfg(),
                         PlatePresenter(benches, quiet=True, guard_wall_s=LINK_TIMEOUT_S, rate_dps=PLATE_RATE_DPS),
                         station=Station("S-faults"), on_event=faults, link_timeout_s=LINK_TIMEOUT_S,
                         say=lambda s: None, plots=False, plate_timeout_s=120.0)
        t0 = time.monotonic()
        res = run.run()
        return run, res, faults, time.monotonic() - t0
    finally:
        if faults is not None:
            faults.close()
        for vb in benches:
            vb.close()


def _check(run, res, faults, plan) -> None:
    for b in res.boards:
        kind, stage = plan.get(b.slot, ("healthy", None))
        if kind in ("healthy", "slow"):
            assert b.state == "passed", (b.slot, kind, b.stage, b.reason)
            continue
        assert b.slot in faults.started, (b.slot, kind, stage, b.state, b.stage)    # the fault did start
        assert b.state == "failed" and b.reason, (b.slot, kind, stage, b.state)
        # its own stage: where it was when the fault came, or the link that carried it
        assert b.stage in ({"plate": "poses"}.get(stage, stage), "link", "health"), (b.slot, kind, stage, b.stage, b.reason)
        # its own reason, not another board's: no "the other boards went on" wait for someone else
        assert "slot" not in b.reason or f"slot {b.slot}" in b.reason, b.reason
        # within its own deadline: the guard (wall) or the link timeout (device time), plus slack
        took = faults.ended[b.slot] - faults.started[b.slot][1]
        assert took <= LINK_TIMEOUT_S * 2 + 10.0 + SLACK_WALL_S, (b.slot, kind, stage, took)
    assert all(w["waited_s"] <= w["deadline_s"] for w in run.plate.waits)
    assert not [w for w in run.plate.waits if w["outcome"] == "deadline"]    # nobody waited out the plate


@st.composite
def fixtures(draw):
    n = draw(st.integers(2, 16))
    bad = draw(st.lists(st.integers(1, n), min_size=1, max_size=min(3, n - 1), unique=True))
    plan = {s: (draw(st.sampled_from(FAULTS)), draw(st.sampled_from(STAGES))) for s in bad}
    return n, plan


@settings(max_examples=5, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=list(HealthCheck))
@given(fixtures())
@example((16, {3: ("freeze", "poses"), 9: ("kill", "rest"), 14: ("garbage", "poses"), 16: ("slow", "connect")}))
def test_a_faulty_board_fails_alone_the_others_pass(tmp_path_factory, case):
    n, plan = case
    tmp = tmp_path_factory.mktemp("faults")
    run, res, faults, wall = _station(tmp, n, plan)
    if os.environ.get("IMUBENCH_SHOW_CASES"):
        print(f"\n{n} boards {plan}: {wall:.1f} s; " + "; ".join(
            f"{b.slot} {b.state} {b.stage} {b.reason or ''}"[:160] for b in res.boards if b.state != "passed"))
    _check(run, res, faults, plan)


def test_a_bench_whose_control_connection_was_dropped_still_quits():
    """A frozen board's grant past its guard (or an interrupted command) drops the bench's
    control connection; closing the bench afterwards must still ask the simulator to quit (a
    new connection), not leave it to SIGTERM after the stop timeout (3 s of every frozen-board
    session here). On a process continued after a freeze, as Faults.close does."""
    vb = VirtualBench(speed=0, seed=590, truth="random")
    try:
        with vb.device() as dev:
            dev.info()                              # a lockstep exchange on the channel
        os.kill(vb.pid, signal.SIGSTOP)
        vb.channel.disconnect()                     # what a failed or interrupted command does
        os.kill(vb.pid, signal.SIGCONT)
        assert not vb.channel.connected
        vb.stop()                                   # the log is kept until close()
        log = vb.resource.log
        assert "exiting (quit)" in log and "exiting (Terminated)" not in log, log[-400:]
    finally:
        vb.close()


def test_an_idle_f103_image_quits_when_asked():
    """The emulated F103 on the lockstep clock ends on the control command "quit" between
    grants too (it checked only after a grant: every close of an idle ARM-image bench waited
    the stop timeout, 3 s, for SIGTERM)."""
    vb = VirtualBench(speed=0, seed=591, truth="random", target="f103")
    try:
        with vb.device() as dev:
            dev.info()                              # grants run; then the device is idle
        vb.stop()                                   # quit over the control channel; the log is kept
        log = vb.resource.log
        assert "exiting (quit)" in log and "signal" not in log.split("exiting")[-1], log[-400:]
    finally:
        vb.close()


@pytest.mark.parametrize("stage", ["plate", "poses", "write"])
def test_a_frozen_board_is_dropped_from_the_plate_at_its_first_missed_deadline(tmp_path, stage):
    """The issue's case: a board frozen while the plate works (SIGSTOP: the link stays open,
    nothing answers). It fails at once at its own guard; the plate moves on for the others,
    who all pass, and no other board waits for it past its deadline."""
    plan = {2: ("freeze", stage)}
    run, res, faults, wall = _station(tmp_path, 4, plan, seed0=540)
    _check(run, res, faults, plan)
    b = res.boards[1]
    want = {"plate": "poses", "poses": "link"}.get(stage, stage)
    assert b.stage == want and "frozen" in b.reason, (b.stage, b.reason)
    if stage == "plate":            # found by the plate, which dropped it from its plan at once
        assert "stopped answering the plate" in b.reason and [w for w in run.plate.waits if w["outcome"] == "lost"]
    assert 2 not in run.plate.live


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_ctrl_c_sigterm_or_sighup_records_every_board_and_exits_130(tmp_path, sig):
    """A station session stopped in the terminal (Ctrl-C; SIGTERM from a service manager; SIGHUP, the
    terminal or the SSH link to the host lost):
    every board is recorded (record.json, a history row), the unfinished ones as stopped with
    their stage, station.json is completed, the table is printed, the exit code is 130, and
    nothing says "link lost" (issue 38, point 3)."""
    import json
    import subprocess
    import sys

    from imubench.results.history import History
    d, db = tmp_path / "st", tmp_path / "h.sqlite"
    cmd = [sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-boards", "3", "--sim-speed", "50",
           "--method", "six", "--gyro", "none", "--rate", "100", "--dir", str(d), "--db", str(db), "--link-timeout", "2"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_sigint_default)
    out = []
    try:
        for line in p.stdout:               # stopped once a board is at its attitudes
            out.append(line)
            if ": poses" in line:
                p.send_signal(sig)
                break
        rest, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    text = "".join(out) + rest
    assert p.returncode == 130, (text, err)
    assert "Traceback" not in err and "link lost" not in text + err, (text, err)
    assert "interrupted" in err and "recorded as stopped" in err and "--resume" in err, err
    assert "STOPPED" in text                                        # the table, with the stopped boards
    st = json.loads((d / "station.json").read_text())
    assert st["finished"] and st["stopped"]
    assert {signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP"}.get(sig, "Ctrl-C") in st["stopped"]
    states = [b["state"] for b in st["boards"]]
    assert "stopped" in states and set(states) <= {"passed", "failed", "stopped"}
    for b in st["boards"]:
        rec = json.loads((d / f"slot-{b['slot']}" / "record.json").read_text())
        if b["state"] == "stopped":
            assert rec["failure"]["stopped"] and rec["failure"]["stage"] == b["stage"] != "link"
    with History(db, readonly=True) as h:
        assert len(h.session_runs(st["session_id"])) == 3


def test_a_stopped_station_session_resumes_each_board_where_it_stopped(tmp_path):
    """Stopped at once (Ctrl-C), then `--resume DIR --sim`: the same virtual boards (seeds from
    station.json), each continues its own capture on its own device, finished boards stay
    finished, the session id is kept; the history holds the stopped runs and the passed ones."""
    import json
    import subprocess
    import sys

    from imubench.results.history import History
    d, db = tmp_path / "st", tmp_path / "h.sqlite"
    base = [sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-speed", "50", "--method", "six",
            "--gyro", "none", "--rate", "100", "--db", str(db), "--link-timeout", "2"]
    p = subprocess.Popen(base + ["--sim-boards", "2", "--sim-seed", "77", "--dir", str(d)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_sigint_default)
    try:
        seen = 0
        for line in p.stdout:
            if "captured" in line or ": poses" in line:
                seen += 1
            if seen >= 2:
                p.send_signal(signal.SIGINT)
                break
        p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130
    first = json.loads((d / "station.json").read_text())
    poses_before = {b["slot"]: len(json.loads((d / f"slot-{b['slot']}" / "session.json").read_text())["poses"])
                    for b in first["boards"] if (d / f"slot-{b['slot']}" / "session.json").is_file()}
    # the resumed run stops nowhere: no ceiling (the lockstep clock gives the same session)
    r = subprocess.run(base + ["--resume", str(d), "--sim-speed", "0"], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, (r.stdout[-2000:], r.stderr)
    st = json.loads((d / "station.json").read_text())
    assert st["session_id"] == first["session_id"] and st["resumed"] and st["finished"] and not st["stopped"]
    assert [b["state"] for b in st["boards"]] == ["passed", "passed"]
    for b in st["boards"]:
        assert b["device"]["mcu_uid"] == json.loads((d / f"slot-{b['slot']}" / "session.json").read_text())["device"]["mcu_uid"]
    assert "2 of 2 boards passed" in r.stdout
    # the captures went on (the streams before the stop are kept)
    for slot, n in poses_before.items():
        assert (d / f"slot-{slot}" / "capture-1.bin").is_file()
        assert len(json.loads((d / f"slot-{slot}" / "session.json").read_text())["poses"]) >= max(n, 6)
    with History(db, readonly=True) as h:
        runs = h.session_runs(st["session_id"])
    assert sum(1 for x in runs if x["passed"]) == 2


def test_a_frozen_board_on_the_f103_image(tmp_path):
    """The same on the exact F103 image under the emulator: two boards, slot 2 frozen while it
    waits at the plate after its first attitude; slot 1 passes, slot 2 fails at its own stage
    within its guard (the emulated board's grants are as guarded as the host build's)."""
    cfg = SessionConfig(method="six", gyro=None, rate_hz=100, rest_s=1.0, settle_s=0.2, hold_s=0.5,
                        write=False, pose_timeout_s=30.0)
    plan = {2: ("freeze", "plate")}
    run, res, faults, wall = _station(tmp_path, 2, plan, seed0=560, target="f103", cfg=cfg)
    _check(run, res, faults, plan)
    b = res.boards[1]
    assert b.state == "failed" and "frozen" in b.reason, (b.stage, b.reason)
    assert res.boards[0].state == "passed"
