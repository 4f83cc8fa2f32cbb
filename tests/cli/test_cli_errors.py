"""Every subcommand, given the classic mistakes, fails the one way (imubench.cli.common):

    one line on stderr `imubench CMD: error: what happened; what to do`,
    exit 2 (usage), 1 (failure) or 130 (interrupted), no traceback, nothing captured lost.

Each kind of mistake runs the real command line in a subprocess, as a user runs it, at least
once (SUBPROCESS_CASES: the interpreter's exit, its stderr and exit code seen from outside); the
other cases of the same kind run the same entry point, imubench.cli.main, in this process, where
an exception that escaped it would fail the test as a traceback would.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from inproc import run_main
from procio import finish
from imubench.wire import frame as P
from imubench.wire.decoder import decode_bytes
from imubench.wire.protocol_gen import BatchHeader, RawBatch

REFUSED = "socket://127.0.0.1:1"          # nothing listens there: the port does not open
NO_DEVICE = "/dev/ttyIMUBENCH-NOPE0"      # a serial device that does not exist
PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8


def env_without_port(tmp: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("IMUBENCH_PORT", "IMUBENCH_DEBUG")}
    env["TMPDIR"] = str(tmp)               # where a virtual device would leave a folder
    return env


def run(argv, tmp: Path, timeout=120):
    return subprocess.run([sys.executable, "-m", "imubench", *argv], capture_output=True, text=True,
                          timeout=timeout, env=env_without_port(tmp), cwd=tmp, stdin=subprocess.DEVNULL)


def run_in_process(argv, tmp: Path, monkeypatch, capsys) -> subprocess.CompletedProcess:
    """imubench.cli.main(argv) as `run` starts it (no port in the environment, TMPDIR and the
    working directory `tmp`, stdin empty), its exit code and output as a subprocess's."""
    return run_main(argv, monkeypatch, capsys, cwd=tmp, env={"TMPDIR": tmp},
                    unset=("IMUBENCH_PORT", "IMUBENCH_DEBUG"))


def assert_one_error_line(r, cmd: str, code: int, *needles: str):
    out = r.stdout + r.stderr
    assert "Traceback" not in out, out
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, f"stderr must be one line, got {len(lines)}:\n{r.stderr}"
    assert lines[0].startswith(f"imubench {cmd}: error: "), lines[0]
    assert r.returncode == code, f"exit {r.returncode}, expected {code}: {lines[0]}"
    for n in needles:
        assert n in lines[0], f"{n!r} not in: {lines[0]}"
    return lines[0]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    """The things users give by mistake: a directory, a PNG, text, a missing file, a full disk."""
    d = tmp_path_factory.mktemp("mistakes")
    (d / "a_dir").mkdir()
    (d / "picture.png").write_bytes(PNG)
    (d / "notes.txt").write_text("these are my notes, not a capture\n" * 20)
    session = d / "session"                       # a calibration session dir with a damaged state
    session.mkdir()
    (session / "session.json").write_text("{ this is not json")
    closure = d / "closure"                       # a closure dir with a damaged result
    closure.mkdir()
    (closure / "closure.json").write_text("[1, 2")
    (closure / "capture.bin").write_bytes(PNG)
    n = 8
    frames = []
    for i in range(5):
        recs = dict(accel_x_counts=np.full(n, 0), accel_y_counts=np.full(n, 0),
                    accel_z_counts=np.full(n, 256000), status=np.zeros(n, int), gyro_counts=np.zeros((n, 3), int))
        hdr = BatchHeader(sample_index=i * n, period_us=1000, count=n, accel_range_g=2, accel_temp_counts=1885)
        frames.append(P.encode(RawBatch(header=hdr), i, i * n * 1000, records=recs))
    (d / "capture.bin").write_bytes(b"".join(frames))
    return {"dir": d / "a_dir", "png": d / "picture.png", "txt": d / "notes.txt", "missing": d / "nope.bin",
            "session": session, "closure": closure, "capture": d / "capture.bin", "full": "/dev/full", "tmp": d}


# (command, arguments, exit code, words the one line must contain)
DEVICE_COMMANDS = [
    ("calibrate", []), ("closure", []), ("allan", ["--duration", "1s"]), ("attitude", []),
    ("thermal", []), ("monitor", []), ("info", []),
]
CASES = (
    # no port: neither --port nor IMUBENCH_PORT
    [(c, a, 2, ["no port given", "--port", "IMUBENCH_PORT"]) for c, a in DEVICE_COMMANDS]
    # a port that does not open
    + [(c, a + ["--port", REFUSED], 1, ["cannot open", REFUSED, "check"]) for c, a in DEVICE_COMMANDS]
    + [("info", ["--port", NO_DEVICE], 1, ["cannot open", NO_DEVICE])]
    # a rate the protocol does not support, checked before anything is sent (no port needed)
    + [(c, a + ["--rate", "333"], 2, ["333 Hz is not a stream rate", "allowed: 20, 25, 40"])
       for c, a in DEVICE_COMMANDS if c not in ("thermal", "info")]
    + [("monitor", ["--rate", "fast"], 2, ["'fast' is not a rate in Hz"])]
    # unknown methods and choices
    + [("calibrate", ["--method", "seven"], 2, ["invalid choice: 'seven'", "six", "multi"]),
       ("calibrate", ["--gyro", "spin"], 2, ["invalid choice: 'spin'", "turntable"]),
       ("attitude", ["--filter", "best"], 2, ["invalid choice: 'best'"]),
       ("closure", ["--path", "circle"], 2, ["invalid choice: 'circle'"]),
       ("flash", ["--board", "f7"], 2, ["invalid choice: 'f7'"]),
       ("qemu", ["--board", "f7"], 2, ["invalid choice: 'f7'"]),
       ("sim", ["--truth", "perfect"], 2, ["invalid choice: 'perfect'"]),
       ("sim", ["--target", "f7"], 2, ["invalid choice: 'f7'", "f103"]),
       ("sim", ["--boot0"], 2, ["--boot0 is a setting of the STM32 boards", "--target f103"]),
       ("sim", ["--target", "f103", "--baud", "115200"], 2, ["cannot change the f103 image's baud rate"]),
       ("calibrate", ["--sim", "--target", "stm32"], 2, ["invalid choice: 'stm32'"]),
       ("calibrate", ["--redo", "+X"], 2, ["--redo goes with --resume"]),
       ("calibrate", ["--sim", "--sim-clock", "realtime", "--sim-speed", "0"], 2,
        ["--sim-speed 0 (no ceiling) needs the lockstep clock", "--sim-speed 20"]),
       ("closure", ["--sim", "--sim-speed", "-1"], 2, ["-1 must be zero or a positive number"]),
       ("thermal", ["--temps", "25"], 2, ["at least two temperatures"]),
       ("thermal", ["--ramp", "1"], 2, ["--ramp goes with --sim"]),
       ("allan", [], 2, ["--duration is required"]),
       ("allan", ["--duration", "soon"], 2, ["bad duration"])]
    # a directory where a file belongs
    + [("decode", ["{dir}"], 2, ["is a directory"]),
       ("decode", ["{capture}", "--csv", "{dir}"], 2, ["is a directory"]),
       ("allan", ["--analyse", "{dir}"], 2, ["is a directory"]),
       ("monitor", ["--record", "{dir}"], 2, ["is a directory"]),
       ("attitude", ["--csv", "{dir}"], 2, ["is a directory"]),
       ("history", ["--db", "{dir}"], 2, ["is a directory"]),
       ("calibrate", ["--db", "{dir}"], 2, ["is a directory"]),
       ("flash", ["--board", "f103", "--image", "{dir}"], 2, ["is a directory"]),
       ("qemu", ["--params", "{dir}"], 2, ["is a directory"]),
       ("param-page", ["--layout", "f103", "-o", "{dir}"], 2, ["is a directory"]),
       ("report", ["{session}", "--thermal", "{dir}"], 2, ["is a directory"])]
    # a file where a directory belongs, and files that do not exist
    + [("report", ["{png}"], 2, ["is a file, not a directory"]),
       ("closure", ["--analyse", "{png}"], 2, ["is a file, not a directory"]),
       ("calibrate", ["--resume", "{png}"], 2, ["is a file, not a directory"]),
       ("calibrate", ["--dir", "{png}"], 2, ["is a file"]),
       ("decode", ["{missing}"], 2, ["no such file"]),
       ("allan", ["--analyse", "{missing}"], 2, ["no such file"]),
       ("report", ["{missing}"], 2, ["no such directory"]),
       ("report", ["{dir}"], 2, ["has no session.json"])]
    # garbage: a file that is not what the command reads
    + [("decode", ["{png}"], 1, ["is not an imubench capture"]),
       ("decode", ["{txt}"], 1, ["is not an imubench capture"]),
       ("allan", ["--analyse", "{png}"], 1, ["no raw samples"]),
       ("history", ["--db", "{png}"], 1, ["imubench history database"]),
       ("history", ["--db", "{capture}", "B559FCF4"], 1, ["imubench history database"]),
       # the history is opened before anything is captured, not after the session it would lose
       ("calibrate", ["--db", "{png}", "--port", REFUSED], 1, ["history database", "nothing was captured"]),
       ("calibrate", ["--sim", "--db", "postgresql://nobody@127.0.0.1:1/x"], 1,
        ["history database: cannot open postgresql://nobody@127.0.0.1:1/x", "connection", "nothing was captured"]),
       ("report", ["{session}"], 1, ["session.json", "damaged"]),
       ("calibrate", ["--resume", "{session}", "--port", REFUSED], 1, ["session.json", "damaged"]),
       ("closure", ["--analyse", "{closure}"], 1, ["closure.json", "damaged"]),
       ("param-page", ["--layout", "f103", "--params", "{png}", "-o", "{tmp}/page.bin"], 1, ["not JSON"]),
       ("param-page", ["--layout", "f103", "--params", "{capture}", "-o", "{tmp}/page.bin"], 1, ["not JSON"])]
    # a device as an output (it was the way to a full disk): outputs are regular files only
    + [("decode", ["{capture}", "--csv", "{full}"], 1, ["/dev/full is a character device, not a regular file"])]
    # not a command at all
    + [("calibrat", [], 2, ["invalid choice: 'calibrat'"])]
)


def _case_id(c):
    return f"{c[0]} {' '.join(c[1])}".replace(REFUSED, "REFUSED").replace("{", "").replace("}", "")


# one case of each kind of mistake runs as a user runs it, in a subprocess of `python -m imubench`
SUBPROCESS_CASES = {
    "calibrate ",                                   # no port
    "info --port REFUSED",                          # a port that does not open (socket)
    "info --port " + NO_DEVICE,                     # a serial device that does not exist
    "allan --duration 1s --rate 333",               # a rate the protocol does not support
    "calibrate --method seven",                     # an unknown choice (argparse)
    "sim --boot0",                                  # a usage error the command checks itself
    "decode dir",                                   # a directory where a file belongs
    "report png",                                   # a file where a directory belongs
    "decode missing",                               # no such file
    "decode png",                                   # garbage
    "calibrate --db png --port REFUSED",            # a history that is not one, before any capture
    "report session",                               # a damaged session.json
    "decode capture --csv full",                    # a device as an output
    "calibrat ",                                    # not a command
}
assert SUBPROCESS_CASES <= {_case_id(c) for c in CASES}, SUBPROCESS_CASES - {_case_id(c) for c in CASES}


@pytest.mark.parametrize("cmd,args,code,needles", CASES, ids=[_case_id(c) for c in CASES])
def test_mistake_gives_one_line(files, cmd, args, code, needles, monkeypatch, capsys):
    argv = [cmd] + [a.format(**{k: str(v) for k, v in files.items()}) for a in args]
    if _case_id((cmd, args)) in SUBPROCESS_CASES:
        r = run(argv, files["tmp"])
    else:
        r = run_in_process(argv, files["tmp"], monkeypatch, capsys)
    prefix_cmd = cmd if cmd != "calibrat" else ""
    if cmd == "calibrat":            # an unknown command is the top-level parser's error
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert r.stderr.strip().startswith("imubench: error: argument COMMAND: invalid choice: 'calibrat'")
        assert len(r.stderr.strip().splitlines()) == 1
        return
    assert_one_error_line(r, prefix_cmd, code, *needles)


def test_a_full_disk_while_recording_keeps_what_was_written(files, tmp_path):
    """monitor --record onto a full disk: the error names it, the command stops cleanly."""
    from imubench.device.fake import FakeDevice
    with FakeDevice(seed=3) as fake:
        r = run(["monitor", "--port", fake.port_url, "--record", "/dev/full", "--duration", "3"], tmp_path)
    assert_one_error_line(r, "monitor", 1, "no space left")


def test_debug_shows_the_traceback(files):
    """--debug (or IMUBENCH_DEBUG=1) lets the traceback through, for a bug report."""
    r = run(["decode", "--debug", str(files["png"])], files["tmp"])
    assert r.returncode != 0
    r = run(["--debug", "info", "--port", REFUSED], files["tmp"])
    assert "Traceback" in r.stderr and "LinkError" in r.stderr


# ----------------------------------------------------------------------- Ctrl-C in the middle
def _terminal_sigint():
    """In the child: Ctrl-C's default disposition, as a command started from a terminal has it.
    A pytest started in the background of a non-interactive shell (nohup, `cmd &`) ignores
    SIGINT, and its children inherit that: the Ctrl-C tests then saw commands run to the end."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt(argv, tmp: Path, marker: str, timeout: float = 120.0):
    """Start the command, wait until its output shows `marker`, send SIGINT as a terminal's
    Ctrl-C does, and return (exit code, stdout, stderr)."""
    p = subprocess.Popen([sys.executable, "-m", "imubench", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env_without_port(tmp), cwd=tmp, stdin=subprocess.DEVNULL,
                         preexec_fn=_terminal_sigint)
    out = []
    t0 = time.monotonic()
    try:
        while True:
            line = p.stdout.readline()
            if not line:
                break
            out.append(line)
            if marker in line:
                time.sleep(0.3)
                p.send_signal(signal.SIGINT)
                break
            assert time.monotonic() - t0 < timeout, "".join(out)
        rest, err = finish(p, timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, "".join(out) + rest, err


def _vbench_dirs(tmp: Path) -> list:
    return sorted(tmp.glob("imubench-vbench-*"))


def test_ctrl_c_in_calibrate_keeps_the_session_and_says_how_to_resume(tmp_path):
    d = tmp_path / "s"
    code, out, err = _interrupt(["calibrate", "--sim", "--sim-seed", "5", "--method", "six", "--gyro", "bias",
                                 "--no-write", "--dir", str(d), "--db", str(tmp_path / "h.sqlite")],
                                tmp_path, marker="to go")
    r = subprocess.CompletedProcess([], code, out, err)
    line = assert_one_error_line(r, "calibrate", 130, "interrupted", f"imubench calibrate --resume {d}")
    assert "everything captured is kept" in line
    state = json.loads((d / "session.json").read_text())
    assert len(state["poses"]) >= 1                  # the pose(s) captured before Ctrl-C are kept
    caps = list(d.glob("capture-*.bin"))
    _, raw, _, stats = decode_bytes(caps[0].read_bytes())
    assert raw is not None and stats.frames_ok > 0
    last = max(p["stop_index"] for p in state["poses"])
    assert raw.sample_index[-1] + 1 >= last          # every sample the poses came from is on disk
    assert _vbench_dirs(tmp_path) == []              # the virtual device cleaned up after itself
    # the hint works: resuming captures only what is missing and finishes
    r2 = run(["calibrate", "--resume", str(d), "--sim", "--sim-seed", "5", "--no-write",
              "--db", str(tmp_path / "h.sqlite")], tmp_path, timeout=300)
    assert r2.returncode == 0, r2.stdout[-2000:] + r2.stderr
    assert "calibration PASSED" in r2.stdout and "Traceback" not in r2.stderr
    kept = {p["name"] for p in state["poses"]}
    captured_again = {n for n in kept if f"captured {n}:" in r2.stdout}
    assert not captured_again, f"resume captured {captured_again} again"
    assert _vbench_dirs(tmp_path) == []


def test_ctrl_c_in_closure_says_what_to_do(tmp_path):
    out_dir = tmp_path / "c"
    # the calibration closure --sim runs first shows its progress (on main: ~10 silent seconds)
    code, out, err = _interrupt(["closure", "--sim", "--out", str(out_dir)], tmp_path,
                                marker="virtual bench presents", timeout=60)
    r = subprocess.CompletedProcess([], code, out, err)
    assert_one_error_line(r, "closure", 130, "interrupted", "imubench closure")
    assert _vbench_dirs(tmp_path) == []


def test_ctrl_c_in_thermal_keeps_what_was_measured(tmp_path):
    out_dir = tmp_path / "t"
    code, out, err = _interrupt(["thermal", "--sim", "--temps", "10,40", "--samples", "200", "--out", str(out_dir)],
                                tmp_path, marker="recording in")
    r = subprocess.CompletedProcess([], code, out, err)
    assert_one_error_line(r, "thermal", 130, "interrupted", str(out_dir / "thermal.json"))
    rec = json.loads((out_dir / "thermal.json").read_text())
    assert rec["status"] == "failed" and "KeyboardInterrupt" in rec["error"]
    assert _vbench_dirs(tmp_path) == []


def test_ctrl_c_stops_imubench_sim_even_while_it_says_where_it_listens(tmp_path):
    """`imubench sim` serves until Ctrl-C: a Ctrl-C right after its first line (before it has
    printed the rest and waits) is a stop like any other, exit 0, its folder removed."""
    p = subprocess.Popen([sys.executable, "-m", "imubench", "sim", "--speed", "0", "--thermal-lag"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env_without_port(tmp_path),
                         cwd=tmp_path, stdin=subprocess.DEVNULL, preexec_fn=_terminal_sigint)
    try:
        first = p.stdout.readline()
        p.send_signal(signal.SIGINT)
        rest, err = finish(p, timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert first.startswith("virtual device ("), first + err
    assert p.returncode == 0 and "interrupted" not in err and "Traceback" not in err, (first + rest, err)
    assert _vbench_dirs(tmp_path) == []


def test_ctrl_c_ends_a_live_view_normally(tmp_path):
    """monitor and attitude are live views: Ctrl-C is how they end (exit 0, a summary, and the
    recording closed with every byte in it)."""
    from imubench.device.fake import FakeDevice
    rec = tmp_path / "rec.bin"
    with FakeDevice(seed=4) as fake:
        code, out, err = _interrupt(["monitor", "--port", fake.port_url, "--rate", "200", "--interval", "0.2",
                                     "--record", str(rec)], tmp_path, marker="accel mean")
    assert code == 0 and "Traceback" not in err and "done:" in out
    _, raw, _, stats = decode_bytes(rec.read_bytes())
    assert raw is not None and len(raw) > 0 and stats.frames_rejected == 0


def test_monitor_in_process_gives_back_the_callers_ctrl_c_handler(tmp_path, monkeypatch, capsys):
    """monitor takes Ctrl-C to end its view; called in-process (main(), as tests and embedding
    programs call it) it set its own handler for good, and every later Ctrl-C was swallowed."""
    def mine(signum, frame):
        raise KeyboardInterrupt
    old = signal.signal(signal.SIGINT, mine)
    try:
        r = run_in_process(["monitor", "--port", REFUSED], tmp_path, monkeypatch, capsys)
        assert_one_error_line(r, "monitor", 1, "cannot open")
        assert signal.getsignal(signal.SIGINT) is mine
    finally:
        signal.signal(signal.SIGINT, old)


def test_a_refused_command_leaves_no_empty_history_database(tmp_path, capsys):
    """A usage error refused after the history was checked created an empty database (issue 38):
    a new SQLite file is now made by the first record; only whether it can be made is checked."""
    from imubench.cli import main as imubench
    db = tmp_path / "new" / "h.sqlite"
    assert imubench(["calibrate", "--redo", "+X up", "--db", str(db)]) == 2
    assert "--redo goes with --resume" in capsys.readouterr().err
    assert not db.exists() and not db.parent.exists()
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert imubench(["calibrate", "--sim", "--db", str(blocked / "h.sqlite")]) == 1
    assert "cannot create it" in capsys.readouterr().err


def test_ctrl_c_inside_an_import_is_an_interrupt_not_an_internal_error(monkeypatch, capsys):
    """A Ctrl-C that lands while a compiled module initialises surfaces as ImportError
    ("initialization failed"); it is reported as the interrupt it is, exit 130, one line."""
    import importlib
    cli_main = importlib.import_module("imubench.cli.main")
    history = importlib.import_module("imubench.cli.history")

    def boom(a):
        raise ImportError("initialization failed")
    monkeypatch.setattr(history, "run", boom)
    real = cli_main.build_parser

    def parser():
        ap = real()
        for action in ap._subparsers._group_actions:
            action.choices["history"].set_defaults(run=boom)
        return ap
    monkeypatch.setattr(cli_main, "build_parser", parser)
    rc = cli_main.main(["history"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 130 and len(err) == 1 and err[0].startswith("imubench history: error: interrupted"), err
