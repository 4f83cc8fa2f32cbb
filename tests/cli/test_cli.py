"""The imubench command line, run as users run it (a subprocess), against the fake
device over a pty and on recorded files."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
from imubench.device.fake import FakeDevice
from imubench.wire import frame as P
from imubench.wire.protocol_gen import BatchHeader, RawBatch, Stats


def run(*args, env=None, timeout=60):
    return subprocess.run([sys.executable, "-m", "imubench", *args], capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, **(env or {})})


def _recording(tmp_path, corrupt=False):
    n = 8
    frames = []
    for i in range(10):
        recs = dict(accel_x_counts=np.full(n, 1000), accel_y_counts=np.full(n, -2000),
                    accel_z_counts=np.full(n, 256000), status=np.zeros(n, int), gyro_counts=np.zeros((n, 3), int))
        hdr = BatchHeader(sample_index=i * n, period_us=1000, count=n, accel_range_g=2, accel_temp_counts=1885)
        frames.append(P.encode(RawBatch(header=hdr), i, i * n * 1000, records=recs))
    frames.append(P.encode(Stats(frames_sent=10), 10, 80000))
    data = bytearray(b"".join(frames))
    if corrupt:
        data[300] ^= 0xFF       # one frame damaged
        data[0:0] = b"\x13\x37garbage\x00"     # line noise before the device's leading delimiter
    path = tmp_path / "rec.bin"
    path.write_bytes(bytes(data))
    return path


def test_decode_summary_and_exports(tmp_path):
    path = _recording(tmp_path)
    r = run("decode", str(path), "--json", "--npz", str(tmp_path / "s.npz"), "--csv", str(tmp_path / "s.csv"))
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.splitlines()[0])
    assert summary["raw"]["samples"] == 80
    assert summary["messages"] == {"stats": 1}
    assert abs(summary["raw"]["accel_mean_mps2"][2] - 9.80665) < 1e-6
    z = np.load(tmp_path / "s.npz")
    assert z["accel_counts"].shape == (80, 3) and np.all(z["sample_index"] == np.arange(80))
    rows = (tmp_path / "s.csv").read_text().splitlines()
    assert len(rows) == 81 and rows[0].startswith("t_us,sample_index")


def test_decode_counts_corruption_and_keeps_the_rest(tmp_path):
    path = _recording(tmp_path, corrupt=True)
    r = run("decode", str(path), "--json")
    summary = json.loads(r.stdout)
    d = summary["decoder"]
    assert d["frames_rejected"] >= 2          # the garbage prefix and the damaged frame
    assert d["frames_ok"] == 10               # 9 batches + stats
    assert summary["raw"]["samples"] == 72
    assert d["samples_missing"] == 8 and d["sample_gaps"] == 1


def test_decode_missing_file_is_a_clear_error(tmp_path):
    r = run("decode", str(tmp_path / "nope.bin"))
    assert r.returncode == 2 and "error" in r.stderr


def test_monitor_streams_and_records(tmp_path):
    rec = tmp_path / "mon.bin"
    with FakeDevice(seed=5) as fake:
        r = run("monitor", "--rate", "500", "--duration", "2.2", "--interval", "0.5", "--record", str(rec),
                env={"IMUBENCH_PORT": fake.port_url})
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if "|" in ln and "rej 0" in ln]
    assert len(lines) >= 3
    assert "done:" in r.stdout and "0 rejected" in r.stdout
    r2 = run("decode", str(rec), "--json")
    assert json.loads(r2.stdout)["raw"]["samples"] > 800


def test_info_and_missing_port(monkeypatch):
    with FakeDevice() as fake:
        r = run("info", "--port", fake.port_url)
    assert r.returncode == 0 and "ADXL355 IDs AD 1D ED 01" in r.stdout
    env = {k: v for k, v in os.environ.items() if k != "IMUBENCH_PORT"}
    r = subprocess.run([sys.executable, "-m", "imubench", "info"], capture_output=True, text=True, env=env)
    assert r.returncode == 2 and "IMUBENCH_PORT" in r.stderr


# ----------------------------------------------------------------------- one command line
def _subparsers():
    import argparse

    from imubench.cli.main import build_parser
    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    return ap, sub.choices


def test_every_option_has_help_and_shows_its_default():
    import argparse
    ap, commands = _subparsers()
    assert {"calibrate", "history", "report", "closure", "allan", "attitude", "thermal", "decode", "monitor",
            "info", "sim", "qemu", "fake", "param-page", "flash"} <= set(commands)
    for name, p in commands.items():
        assert p.description, f"{name} has no description"
        for act in p._actions:
            if isinstance(act, argparse._HelpAction):
                continue
            assert act.help and act.help.strip(), f"imubench {name} {act.dest}: no help text"
            d = act.default
            if d is None or d is False or d is argparse.SUPPRESS or (isinstance(d, (list, str)) and not d):
                continue
            shown = p._get_formatter()._expand_help(act)      # the help text as --help prints it
            assert "default" in shown, f"imubench {name} {act.dest}: the help does not show the default: {shown}"


def test_the_same_options_have_the_same_names():
    """--port/--baud wherever a device is opened; --sim/--sim-seed/--sim-speed wherever a
    command can start its own virtual device; --rate is always a protocol stream rate (calibrate's
    also takes a file's rate with --from: checked against the stream rates for a device)."""
    from imubench.cli.calibrate import rate_hz
    from imubench.cli.common import stream_rate
    _, commands = _subparsers()
    for name, p in commands.items():
        opts = {o: a for a in p._actions for o in a.option_strings}
        if "--port" in opts and name != "flash":
            assert "--baud" in opts, name
        if "--sim" in opts:
            assert {"--sim-seed", "--sim-speed"} <= set(opts), name
        if "--rate" in opts:
            if name == "allan":           # like calibrate's: a file's rate with --from (issue 26)
                assert opts["--rate"].type("102.4") == 102.4, name
                continue
            assert opts["--rate"].type is (rate_hz if name == "calibrate" else stream_rate), name
    r = run("calibrate", "--rate", "700", "--sim")
    assert r.returncode == 2 and "700 Hz is not a stream rate of the protocol" in r.stderr, r.stderr
    for name in ("calibrate", "closure", "thermal"):
        assert "--sim" in {o for a in commands[name]._actions for o in a.option_strings}, name


def test_version():
    r = run("--version")
    assert r.returncode == 0 and r.stdout.startswith("imubench ")
    from imubench import __version__
    assert __version__ in r.stdout and __version__ != "0+unknown"


def test_ids_one_format_in_info_and_history(tmp_path):
    """info prints the MCU UID and gyro serial numbers as upper-case hex; history lists and
    accepts them in exactly that form (a serial number finds its board)."""
    import re

    from imubench.results.history import History
    with FakeDevice(seed=2) as fake:
        r = run("info", "--port", fake.port_url)
    assert r.returncode == 0, r.stderr
    uid = re.search(r"MCU UID ([0-9A-F]{24})\b", r.stdout).group(1)
    sns = re.search(r"SN ([0-9A-F]{8}) ([0-9A-F]{8}) ([0-9A-F]{8})", r.stdout).groups()
    from test_history import make_result
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        h.record(make_result(uid, gyro_sn=tuple(int(s, 16) for s in sns)))
    listed = run("history", "--db", str(db))
    assert uid in listed.stdout
    for query in (sns[1], sns[1].lower(), "0x" + sns[2], uid[:6], uid):
        r = run("history", "--db", str(db), query)
        assert r.returncode == 0, (query, r.stderr)
        assert f"device {uid}" in r.stdout and " ".join(sns) in r.stdout


def test_monitor_duration_is_device_time_on_a_lockstep_virtual_device(tmp_path):
    """--duration counts the device's seconds (the link's clock): a frozen-between-waits
    virtual device gives exactly that much data however slow the machine is (issue 33)."""
    from imubench.device.sim import VirtualBench
    rec = tmp_path / "mon.bin"
    with VirtualBench(speed=0, seed=4) as vb:
        r = run("monitor", "--port", vb.port_url, "--rate", "500", "--duration", "3", "--interval", "1",
                "--record", str(rec))
    assert r.returncode == 0, r.stderr
    times = [float(ln.split()[0]) for ln in r.stdout.splitlines() if "|" in ln and "rej" in ln]
    assert times == [1.0, 2.0, 3.0], r.stdout
    n = json.loads(run("decode", str(rec), "--json").stdout)["raw"]["samples"]
    assert 1500 <= n <= 1500 + 64, n          # 3 s at 500 Hz, plus at most the batch in flight
