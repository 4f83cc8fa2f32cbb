"""The virtual device's board layer (firmware/boards/sim) and its Python wrapper
(imubench.device.sim): process start-up and shutdown, the control channel, the turntable physics,
the flash file, fault injection plumbing. End-to-end stream tests through the firmware
core live with the core's tests; the few here that talk to the device only check what
the board supplies (identity, link, flash, resets)."""
from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from imubench.device.sim import SimError, VirtualBench, build_sim, repo_root

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def sim_bin() -> Path:
    try:
        return build_sim()
    except SimError:
        if not (ROOT / "firmware" / "core" / "core.c").exists():
            pytest.skip("firmware/core/core.c is not written yet: the simulator cannot link")
        raise


@pytest.fixture
def bench(sim_bin):
    with VirtualBench(speed=20, seed=1, binary=sim_bin) as b:
        yield b


def _alive(pid: int) -> bool:
    """True while pid exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _rot(axis, angle_rad) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K


# ------------------------------------------------------------------ process
def test_build_and_repo_root(sim_bin):
    assert sim_bin == repo_root() / "build" / "host" / "imubench-sim"
    assert os.access(sim_bin, os.X_OK)


def test_startup_line(sim_bin, tmp_path):
    flash = tmp_path / "flash.bin"
    p = subprocess.Popen([str(sim_bin), "--tcp", "0", "--control", "0", "--flash", str(flash),
                          "--seed", "7", "--speed", "5"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        info = json.loads(p.stdout.readline())
        for key in ("pty", "port_url", "tcp_port", "control", "control_port", "pid", "flash", "seed"):
            assert key in info
        assert info["pty"] is None
        assert info["pid"] == p.pid
        assert info["seed"] == 7
        assert info["port_url"] == f"socket://127.0.0.1:{info['tcp_port']}"
        assert info["control"] == f"127.0.0.1:{info['control_port']}"
        assert Path(info["flash"]) == flash.resolve()
        assert flash.read_bytes() == b"\xff" * 4096          # created erased
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=5) == 0                         # clean exit on SIGTERM
        assert p.stdout.read() == ""                          # only the one line on stdout
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_default_flash_in_temp_dir_is_removed(sim_bin):
    p = subprocess.Popen([str(sim_bin)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    info = json.loads(p.stdout.readline())
    flash = Path(info["flash"])
    assert flash.is_file() and info["port_url"].startswith("socket://")
    p.send_signal(signal.SIGINT)
    assert p.wait(timeout=5) == 0
    assert not flash.exists() and not flash.parent.exists()


def test_bad_options(sim_bin):
    for args in (["--speed", "-1"], ["--truth", "odd"], ["--uid", "12"], ["--nope"], ["--tcp"]):
        r = subprocess.run([str(sim_bin), *args], capture_output=True, text=True, timeout=10)
        assert r.returncode == 2, args
        assert r.stdout == ""


def test_stop_leaves_no_process(sim_bin):
    b = VirtualBench(speed=20, binary=sim_bin)
    pid = b.pid
    assert _alive(pid)
    b.stop()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)                                   # gone and reaped
    assert not b.running
    b.close()


def test_stop_kills_a_process_that_ignores_quit(sim_bin):
    b = VirtualBench(speed=20, binary=sim_bin)
    pid = b.pid
    os.kill(pid, signal.SIGSTOP)                          # cannot answer quit or SIGTERM
    t0 = time.monotonic()
    b.stop(timeout=0.5)
    assert time.monotonic() - t0 < 10
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    b.close()


def test_quit_command(sim_bin):
    b = VirtualBench(speed=20, binary=sim_bin)
    proc = b.proc
    assert b.control("quit")["ok"] is True
    assert proc.wait(timeout=5) == 0
    b.close()


def test_the_arm_image_quits_between_grants():
    """The emulator of an ARM image on the lockstep clock takes "quit" when no run is granted
    (the host closing the bench): it used to look at quit only at the end of a grant, so every
    close waited out stop()'s 3 s and ended in SIGTERM (-15 is what SIGTERM would give)."""
    with VirtualBench(speed=0, seed=5, target="f103") as b:
        assert b.info["clock"] == "lockstep"
        b.wait(0.01)                                    # one grant run and answered
        proc = b.proc
        assert b.control("quit")["ok"] is True
        assert proc.wait(timeout=5) == 0


def test_exits_when_parent_dies(sim_bin):
    code = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(ROOT / 'host')!r})
        from imubench.device.sim import VirtualBench
        b = VirtualBench(speed=20, binary={str(sim_bin)!r})
        print(b.pid, flush=True)
        os._exit(0)          # no atexit, no stop(): only the simulator's own watch helps
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    pid = int(r.stdout.split()[0])
    deadline = time.monotonic() + 5
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(pid)


def test_restart_keeps_flash_byte_identical(sim_bin, tmp_path):
    flash = tmp_path / "flash.bin"
    pattern = bytes((i * 37 + 11) & 0xFF for i in range(4096))   # not a valid record
    flash.write_bytes(pattern)
    with VirtualBench(speed=20, flash=flash, binary=sim_bin) as b:
        assert b.flash == str(flash.resolve())
        pid1 = b.pid
        b.wait(1.5)                                       # booted: the core read the store
        b.restart()
        assert b.pid != pid1 and b.running
        b.wait(1.5)
        assert flash.read_bytes() == pattern              # reads never write
    assert flash.read_bytes() == pattern
    assert flash.exists()                                 # a caller's flash file is kept


def test_wrong_size_flash_file_is_refused(sim_bin, tmp_path):
    flash = tmp_path / "flash.bin"
    flash.write_bytes(b"\0" * 100)
    with pytest.raises(SimError, match="exited at start-up"):
        VirtualBench(speed=20, flash=flash, binary=sim_bin)


def test_pty_link(sim_bin):
    from imubench.device.link import Device
    with VirtualBench(speed=20, pty=True, tcp=False, binary=sim_bin) as b:
        assert b.pty is not None and b.pty.startswith("/dev/")
        assert b.port_url == b.pty and b.tcp_port is None
        with Device.open(b.port_url, timeout=1.0) as dev:
            dev.ping()


# ------------------------------------------------------------------ control channel
def test_control_commands_answer(bench):
    b = bench
    st = b.status()
    for key in ("time_us", "streaming", "gravity_board", "rate_dps", "temperature_c", "speed",
                "moving", "boots", "flash_ops", "link"):
        assert key in st
    assert st["speed"] == 20 and st["gravity_board"] == [0, 0, 1] and st["temperature_c"] == 25
    assert b.set_orientation(gravity=[0, 0, -1])["ok"]
    assert b.set_orientation(roll_deg=10)["ok"]
    assert b.rotate("x", 10, 0.1, wait=False)["ok"]
    assert b.wait_idle()["ok"]
    assert b.set_rate([0, 0, 5])["ok"]
    assert b.set_rate([0, 0, 0])["ok"]
    assert b.set_temperature(30)["ok"]
    assert b.set_temperature(35, ramp_c_per_s=50, wait=True)["ok"]
    assert b.status()["temperature_c"] == 35
    assert b.set_speed(40)["ok"] and b.status()["speed"] == 40
    assert b.wait(0.01)["ok"]
    assert b.set_truth(gyro=[{"bias_rad_s": 0.001}, None, None])["ok"]
    assert b.randomize_truth(5)["ok"]
    assert "accel" in b.get_truth()
    for kw in (dict(fault="gyro_fault_bits", sensor="gyro_x", bits=0x10, persistent=False),
               dict(fault="gyro_parity", sensor="gyro_y", count=2),
               dict(fault="missing", sensor="accel", on=False),
               dict(fault="spi_error", sensor="gyro_z", count=0),
               dict(fault="link_drop", count=0),
               dict(fault="link_flip", count=0),
               dict(fault="accel_stuck", on=False),
               dict(fault="accel_shadow", on=False),
               dict(fault="clear")):
        assert b.inject(**kw)["ok"], kw
    r = b.control("flash_ops")
    assert r["flash_ops"] >= 0 and r["power_cut_armed"] == 0
    assert b.power_cut(after_flash_ops=3)["ok"]
    assert b.control("flash_ops")["power_cut_armed"] == 3
    b.clear_faults()
    assert b.control("flash_ops")["power_cut_armed"] == 0


@pytest.mark.parametrize("cmd", [
    {"cmd": "no_such_command"},
    {"cmd": "status", "extra": 1},
    {"cmd": "set_orientation"},
    {"cmd": "set_orientation", "gravity": [0, 0, 0]},
    {"cmd": "set_orientation", "gravity": [0, 0]},
    {"cmd": "set_orientation", "gravity": [0, 0, 1], "roll_deg": 3},
    {"cmd": "rotate", "axis": "w", "rate_dps": 1, "duration_s": 1},
    {"cmd": "rotate", "axis": [0, 0, 0], "rate_dps": 1, "duration_s": 1},
    {"cmd": "rotate", "axis": "x", "rate_dps": 1},
    {"cmd": "rotate", "axis": "x", "rate_dps": 1, "duration_s": -1},
    {"cmd": "rotate", "axis": "x", "rate_dps": "fast", "duration_s": 1},
    {"cmd": "set_rate", "rate_dps": [1, 2]},
    {"cmd": "set_temperature"},
    {"cmd": "set_temperature", "c": 20, "ramp_c_per_s": -1},
    {"cmd": "set_speed", "speed": -2},
    {"cmd": "wait"},
    {"cmd": "set_truth", "accel": {"bias": [0, 0, 0]}},
    {"cmd": "set_truth", "accel": {"m": [[1, 0], [0, 1]]}},
    {"cmd": "set_truth", "gyro": [{}, {}, {}, {}]},
    {"cmd": "set_truth", "gyro": [{"noise_n": -1}]},
    {"cmd": "randomize_truth", "seed": -1},
    {"cmd": "inject"},
    {"cmd": "inject", "fault": "meteor"},
    {"cmd": "inject", "fault": "missing", "sensor": "gyro_w"},
    {"cmd": "inject", "fault": "gyro_fault_bits", "sensor": "accel", "bits": 2},
    {"cmd": "inject", "fault": "gyro_fault_bits", "sensor": "gyro_x", "bits": 0x1001},
    {"cmd": "inject", "fault": "spi_error", "sensor": "accel"},
    {"cmd": "inject", "fault": "spi_error", "sensor": "accel", "probability": 2},
    {"cmd": "power_cut", "after_flash_ops": 1.5},
])
def test_control_rejects_bad_requests(bench, cmd):
    with pytest.raises(SimError):
        bench.control(**cmd)
    assert bench.status()["ok"]                           # the channel still works


def test_control_raw_lines(bench):
    s = socket.create_connection(bench.control_address, timeout=5)
    f = s.makefile("rwb")

    def ask(line: bytes) -> dict:
        f.write(line + b"\n")
        f.flush()
        return json.loads(f.readline())

    r = ask(b"this is not json")
    assert r["ok"] is False and "JSON" in r["error"]
    assert ask(b"[1, 2]")["ok"] is False
    assert ask(b'{"no_cmd": 1}')["ok"] is False
    r = ask(b'{"cmd": "status", "id": 42}')
    assert r["ok"] is True and r["id"] == 42
    r = ask(b'{"cmd": "wait", "device_s": 0.05, "id": "w1"}')
    assert r["ok"] is True and r["id"] == "w1"
    # two requests in one write: answered in order, the second after the wait
    f.write(b'{"cmd": "wait", "device_s": 0.2, "id": 1}\n{"cmd": "status", "id": 2}\n')
    f.flush()
    r1, r2 = json.loads(f.readline()), json.loads(f.readline())
    assert (r1["id"], r2["id"]) == (1, 2) and r2["time_us"] >= r1["time_us"]
    s.close()


def test_wait_follows_device_time(bench):
    t0 = bench.status()["time_us"]
    w0 = time.monotonic()
    r = bench.wait(2.0)
    wall = time.monotonic() - w0
    assert r["time_us"] - t0 >= 2_000_000
    assert 0.05 < wall < 1.5                                   # speed 20: about 0.1 s
    bench.set_speed(0)
    w0 = time.monotonic()
    bench.wait(500.0)                                          # as fast as possible: a jump
    assert time.monotonic() - w0 < 1.0
    assert bench.status()["time_us"] - t0 >= 502_000_000


# ------------------------------------------------------------------ physics
def test_set_orientation(bench):
    b = bench
    r = b.set_orientation(gravity=[1, 0, 0])
    assert np.allclose(r["gravity_board"], [1, 0, 0])
    assert np.allclose(b.status()["gravity_board"], [1, 0, 0])
    assert np.allclose(b.get_truth()["world"]["specific_force_mps2"], [9.80665, 0, 0])
    b.set_orientation(gravity=[0, 3, -4])
    assert np.allclose(b.status()["gravity_board"], [0, 0.6, -0.8])
    b.set_orientation(gravity=[0, 0, -1])
    assert np.allclose(b.status()["gravity_board"], [0, 0, -1])
    # ZYX: f = g0 (-sin p, sin r cos p, cos r cos p); yaw does not move gravity
    b.set_orientation(roll_deg=30, pitch_deg=20, yaw_deg=75)
    st = b.status()
    r_, p_ = math.radians(30), math.radians(20)
    assert np.allclose(st["gravity_board"], [-math.sin(p_), math.sin(r_) * math.cos(p_),
                                             math.cos(r_) * math.cos(p_)])
    assert st["roll_deg"] == pytest.approx(30) and st["pitch_deg"] == pytest.approx(20)
    assert st["yaw_deg"] == pytest.approx(75)


@pytest.mark.parametrize("axis,rate_dps,duration_s", [
    ("x", 90, 1.0),        # Y (left) ends up pointing up
    ("y", 45, 2.0),        # nose down: X points down
    ("-z", 30, 0.5),
    ([1, 1, 0], 60, 1.5),
    ([0.3, -0.5, 0.8], -120, 0.75),
])
def test_rotate_turns_by_rate_times_duration(bench, axis, rate_dps, duration_s):
    b = bench
    b.set_orientation(roll_deg=10, pitch_deg=-20)
    g0 = np.array(b.status()["gravity_board"])
    t0 = b.status()["time_us"]
    r = b.rotate(axis, rate_dps, duration_s, wait=False)
    assert r["angle_deg"] == pytest.approx(rate_dps * duration_s)
    st = b.status()
    if st["moving"]:
        assert np.allclose(np.linalg.norm(st["rate_dps"]), abs(rate_dps))
    b.wait_idle()
    st = b.status()
    assert not st["moving"] and st["move"] is None
    assert st["time_us"] - t0 >= duration_s * 1e6
    assert st["rate_dps"] == [0, 0, 0]
    k = {"x": [1, 0, 0], "y": [0, 1, 0], "-z": [0, 0, -1]}.get(axis, axis) if isinstance(axis, str) else axis
    # body-fixed rotation by angle th: the up direction seen in the board frame turns by -th
    expect = _rot(k, -math.radians(rate_dps * duration_s)) @ g0
    assert np.allclose(st["gravity_board"], expect, atol=1e-9)
    assert np.allclose(b.get_truth()["world"]["gravity_board"], expect, atol=1e-9)


def test_rotate_simple_cases(bench):
    b = bench
    b.rotate("x", 90, 1.0)
    assert np.allclose(b.status()["gravity_board"], [0, 1, 0], atol=1e-12)
    b.set_orientation(gravity=[0, 0, 1])
    b.rotate("y", 90, 1.0)
    assert np.allclose(b.status()["gravity_board"], [-1, 0, 0], atol=1e-12)
    b.set_orientation(gravity=[0, 0, 1])
    b.rotate("z", 45, 8.0)                                     # a full turn about up
    assert np.allclose(b.status()["gravity_board"], [0, 0, 1], atol=1e-12)


def test_move_in_progress_and_set_rate(bench):
    b = bench
    b.set_speed(1)
    b.rotate("z", 10, 100.0, wait=False)
    st = b.status()
    assert st["moving"] and st["move"]["kind"] == "rotate"
    assert np.allclose(st["rate_dps"], [0, 0, 10])
    assert 0 < st["move"]["remaining_s"] <= 100
    b.set_rate([0, 5, 0])                                      # replaces the move
    st = b.status()
    assert not st["moving"] and st["move"]["kind"] == "rate"
    assert np.allclose(st["rate_dps"], [0, 5, 0])
    b.set_rate([0, 0, 0])
    assert b.status()["move"] is None


def test_temperature_ramp(bench):
    b = bench
    b.set_temperature(45, ramp_c_per_s=2.0)                   # 10 s of device time
    b.wait(5.0)
    t = b.status()["temperature_c"]
    assert 33 < t < 37
    b.wait_idle(temperature=True)
    assert b.status()["temperature_c"] == 45
    assert b.get_truth()["world"]["temperature_c"] == 45


# ------------------------------------------------------------------ truth
def test_set_and_get_truth(bench):
    b = bench
    before = b.get_truth()
    m = [[1.01, 0.002, 0], [0, 0.99, 0], [0.001, 0, 1.0]]
    b.set_truth(accel={"m": m, "bias_mps2": [0.01, -0.02, 0.03]},
                gyro=[None, {"bias_rad_s": 0.002, "sens": [0.01, 1.02, 0]}, {}])
    t = b.get_truth()
    assert t["accel"]["m"] == m
    assert t["accel"]["bias_mps2"] == [0.01, -0.02, 0.03]
    assert t["accel"]["noise_n"] == before["accel"]["noise_n"]          # untouched
    assert t["gyro"][0] == before["gyro"][0] or t["gyro"][0]["bias_rad_s"] == 0
    assert t["gyro"][1]["bias_rad_s"] == 0.002 and t["gyro"][1]["sens"] == [0.01, 1.02, 0]
    def drift(g):       # the parts of the true bias that wander (bias instability, random walk)
        return g["bi_bias_rad_s"] + g["rw_bias_rad_s"]
    assert t["gyro"][1]["true_bias_rad_s"] - drift(t["gyro"][1]) == pytest.approx(0.002, abs=1e-9)
    b.set_truth(accel={"bias_tc": 0.001}, gyro={"z": {"bias_tempco_rad_s_per_c": 1e-4}})
    b.set_temperature(35)
    t = b.get_truth()
    assert t["accel"]["bias_tc"] == [0.001] * 3
    assert t["accel"]["true_bias_mps2"][0] == pytest.approx(0.01 + 0.01, abs=1e-3)
    assert t["gyro"][2]["true_bias_rad_s"] - drift(t["gyro"][2]) == pytest.approx(1e-3, abs=5e-4)


def test_truth_is_deterministic_from_seed(sim_bin):
    with VirtualBench(speed=20, seed=3, truth="random", binary=sim_bin) as a, \
         VirtualBench(speed=20, seed=3, truth="random", binary=sim_bin) as b, \
         VirtualBench(speed=20, seed=4, truth="random", binary=sim_bin) as c:
        ta, tb, tc = a.get_truth(), b.get_truth(), c.get_truth()
        for k in ("m", "bias_mps2", "noise_n", "bias_tc", "scale_tc"):
            assert ta["accel"][k] == tb["accel"][k]
        assert ta["accel"]["m"] != [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
        assert ta["accel"]["bias_mps2"] != tc["accel"]["bias_mps2"]
        assert [g["serial"] for g in ta["gyro"]] == [g["serial"] for g in tb["gyro"]]
        assert a.info["uid"] == b.info["uid"] != c.info["uid"]
        a.randomize_truth(4)
        assert a.get_truth()["accel"]["bias_mps2"] == tc["accel"]["bias_mps2"]


# ------------------------------------------------------------------ with the core
def test_device_identity_and_link(bench):
    from imubench.device.link import Device
    from imubench.wire.protocol_gen import Board, ClockSource
    with Device.open(bench.port_url, timeout=1.0) as dev:
        dev.ping()
        info = dev.info()
        assert info.board == Board.SIM and info.clock_source == ClockSource.NONE
        assert info.baud == 2000000
        assert info.fw_build.startswith("sim-")
        assert bytes(info.mcu_uid).hex() == bench.info["uid"]
        assert info.sensors_present == 0b1111
        st = bench.status()
        assert st["link"]["tcp_client"] and st["link"]["bytes_received"] > 0
    sent = bench.status()["link"]["bytes_sent"]
    bench.inject("link_drop", count=5)
    with Device.open(bench.port_url, timeout=1.0) as dev:      # the first reply loses 5 bytes
        dev.ping()                                             # ... and is retried
    st = bench.status()["link"]
    assert st["bytes_dropped"] == 5 and st["bytes_sent"] > sent


def test_flash_ops_power_cut_and_restart(sim_bin, tmp_path):
    from imubench.device.link import Device, LinkTimeout
    from imubench.wire import params as PR
    from imubench.wire.protocol_gen import ParamSource
    flash = tmp_path / "flash.bin"
    with VirtualBench(speed=20, flash=flash, binary=sim_bin) as b:
        with Device.open(b.port_url, timeout=1.0, retries=0) as dev:
            assert b.flash_ops() == 0
            gen = dev.save_params()
            n_ops = b.flash_ops()
            assert n_ops >= 2                                   # at least erase + program
            saved = flash.read_bytes()
            assert saved != b"\xff" * 4096
            boots = b.status()["boots"]
            changed = PR.identity()
            changed.cal_id = 7
            dev.set_params(changed)                             # a different block: a real save
            b.power_cut(after_flash_ops=1)                      # the erase of the next save
            with pytest.raises(LinkTimeout):
                dev.save_params()
            st = b.status()
            assert st["boots"] == boots + 1 and st["power_cuts"] == 1
        time.sleep(0.2)
        with Device.open(b.port_url, timeout=1.0) as dev:
            info = dev.info()                                    # previous record survived
            assert info.param_source == ParamSource.FLASH and info.param_generation == gen
        b.power_cut()
        b.wait(1.5)
        assert b.status()["power_cuts"] == 2
        before = flash.read_bytes()
        b.restart()
        assert flash.read_bytes() == before
        with Device.open(b.port_url, timeout=1.0) as dev:
            info = dev.info()
            assert info.param_source == ParamSource.FLASH and info.param_generation == gen


def test_missing_sensor_at_power_cycle(bench):
    from imubench.device.link import Device
    bench.inject("missing", sensor="gyro_y")
    bench.power_cut()
    bench.wait(1.5)
    with Device.open(bench.port_url, timeout=1.0) as dev:
        assert dev.info().sensors_present == 0b1011
    bench.inject("clear")
    bench.power_cut()
    bench.wait(1.5)
    with Device.open(bench.port_url, timeout=1.0) as dev:
        assert dev.info().sensors_present == 0b1111


def test_spi_error_injection_reaches_the_core(bench):
    from imubench.device.link import Device
    with Device.open(bench.port_url, timeout=1.0) as dev:
        dev.start_stream(rate_hz=100)
        bench.inject("spi_error", sensor="gyro_z", count=3)
        bench.wait(0.5)
        assert bench.status()["spi_errors_injected"] == [0, 0, 0, 3]
        assert dev.stats().spi_errors >= 1
        dev.stop_stream()


def test_new_tcp_client_replaces_the_old_one(bench):
    from imubench.device.link import Device
    a = Device.open(bench.port_url, timeout=1.0)
    try:
        a.ping()
        with Device.open(bench.port_url, timeout=1.0) as b:
            b.ping()
            assert bench.status()["link"]["tcp_client"]
            deadline = time.monotonic() + 5
            while a.link.error is None and time.monotonic() < deadline:
                time.sleep(0.02)
            assert a.link.error is not None                    # the old client was closed
    finally:
        a.close()


def test_slow_link_drops_whole_batches(sim_bin):
    """At 115200 baud a 4 kHz raw stream does not fit: the TX ring fills, the core drops
    whole batches and counts them; no frame is ever cut."""
    from imubench.device.link import Device
    with VirtualBench(speed=2, baud=115200, binary=sim_bin) as b:
        with Device.open(b.port_url, timeout=2.0) as dev:
            assert dev.info().baud == 115200
            dev.start_stream(rate_hz=4000)
            s0 = b.status()
            blk = dev.read(n_samples=2000, timeout=30)
            s1 = b.status()
            st = dev.stats()
            dev.stop_stream()
            ds = dev.link.decoder.stats.as_dict()
        assert st.frames_dropped > 0 and st.samples_dropped > 0
        assert ds["crc"] == 0 and ds["cobs"] == 0 and ds["frames_missing"] == 0
        assert ds["samples_missing"] > 0
        # the UART drains at baud/10 bytes per second of device time
        sent = s1["link"]["bytes_sent"] - s0["link"]["bytes_sent"]
        dt_s = (s1["time_us"] - s0["time_us"]) / 1e6
        assert sent / dt_s == pytest.approx(11520, rel=0.1)
        assert len(blk) == 2000


def test_the_bench_is_a_resource_its_drivers_and_a_strategy(sim_bin):
    """Issue 35: the resource (the process and where it is), the drivers (the control channel and
    one per concern) and the strategy (the states) each work through their own small interface;
    VirtualBench answers the names it always had from them."""
    import inspect

    from imubench.device.sim import _LAYER_OF
    from imubench.device.sim_drivers import (ClimateDriver, ControlChannel, FaultDriver, MotionDriver, TimeDriver,
                                             TruthDriver)
    from imubench.device.sim_resource import SimProcess
    from imubench.device.sim_strategy import BenchStrategy
    for cls in (SimProcess, ControlChannel, TimeDriver, MotionDriver, ClimateDriver, TruthDriver, FaultDriver,
                BenchStrategy):
        public = [n for n, _ in inspect.getmembers(cls) if not n.startswith("_")]
        assert len(public) <= 16, (cls.__name__, public)
    vb = VirtualBench(speed=0, seed=3, binary=sim_bin, start=False)
    try:
        assert vb.strategy.state == "off" and not vb.running
        vb.strategy.transition("running")
        assert vb.strategy.state == "running" and vb.resource.running and vb.pid == vb.resource.pid
        for name, layer in _LAYER_OF.items():             # every old name comes from its layer
            assert hasattr(getattr(vb, layer), name), (name, layer)
        # a driver needs the channel only: a second channel on the same resource drives the same bench
        truth = TruthDriver(ControlChannel(vb.resource))
        assert truth.get_truth() == vb.get_truth() == vb.truth_driver.get_truth()
        vb.motion.set_orientation(gravity=[1, 0, 0])
        assert np.allclose(vb.status()["gravity_board"], [1, 0, 0])
        t0 = vb.time.now()
        vb.motion.rotate("z", 90.0, 0.5)                  # waits on the time driver
        assert vb.now() - t0 >= 0.5
        vb.strategy.transition("off")
        assert vb.strategy.state == "off" and vb.pid is None
        with pytest.raises(SimError, match="not running"):
            vb.motion.set_rate([0, 0, 0])
        vb.strategy.transition("running")                 # the same flash file, a new process
        assert vb.status()["ok"]
        with pytest.raises(AttributeError, match="no attribute 'spin'"):
            vb.spin()
        tmp = vb.resource._tmpdir
        vb.strategy.transition("gone")
        assert vb.strategy.state == "gone" and not os.path.exists(tmp)
        with pytest.raises(SimError, match="was closed"):
            vb.strategy.transition("running")
    finally:
        vb.close()


def test_ctrl_c_between_a_request_and_its_reply_leaves_no_stale_reply(sim_bin):
    """Ctrl-C while a control command waits for its reply: the reply still comes, later. Read by
    the next command it would answer the wrong question (a thermal run interrupted that way saved
    "KeyError: 'time_us'" instead of the interrupt), so the channel drops the connection and
    the next command opens a new one and gets its own reply."""
    vb = VirtualBench(speed=0, seed=3, binary=sim_bin)
    try:
        ch = vb.channel
        assert "time_us" in ch.control("status")

        class Interrupted:
            def __init__(self, rfile):
                self.rfile, self.hit = rfile, False

            def readline(self):                         # the first wait is interrupted
                if not self.hit:
                    self.hit = True
                    raise KeyboardInterrupt
                return self.rfile.readline()

            def close(self):
                self.rfile.close()
        ch._rfile = Interrupted(ch._rfile)
        with pytest.raises(KeyboardInterrupt):
            ch.control("get_truth")                     # sent; its reply is left in the socket
        st = ch.control("status")                       # a new connection: status's own reply
        assert "time_us" in st and "accel" not in st and not isinstance(ch._rfile, Interrupted)
    finally:
        vb.close()


def test_a_socket_port_closes_without_pyserials_pause_and_reopens_at_once(sim_bin, monkeypatch):
    """pyserial sleeps 0.3 s in every close of a socket:// port; a command pays it each time it
    lets a device go. Our close does not, and the virtual device takes the next client at once."""
    import serial.urlhandler.protocol_socket as ps

    from imubench.device.link import Device

    def no_pause(s):
        raise AssertionError(f"pyserial's close paused {s} s")
    vb = VirtualBench(speed=0, seed=3, binary=sim_bin)
    try:
        monkeypatch.setattr(ps.time, "sleep", no_pause)
        for _ in range(3):
            dev = Device.open(vb.port_url, timeout=0.5)
            assert dev.info().sensors_present == 0b1111
            sock = dev.link.port._socket
            dev.close()
            assert not dev.link.port.is_open and sock.fileno() == -1
    finally:
        vb.close()
