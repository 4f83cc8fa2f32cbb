"""The virtual device's two clocks (imubench.device.clock, docs/simulator.md "Clocks").

lockstep (the default): device time moves only inside the host's waits, nothing the device
sends is dropped however slow the host is, and the same seed and command give the same bytes
idle and beside CPU-bound processes. realtime (named here, where its behaviour is the point):
the device runs against the wall clock and drops what a host that does not read leaves.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from imubench.device.link import Device
from imubench.device.sim import SimError, VirtualBench
from imubench.files import tree_digest


def _stall_reader(link, wall_s: float) -> threading.Thread:
    """Keep the link's reader thread from decoding for wall_s (a host too busy to read): it
    blocks on the link's lock after its next read, and the socket's buffers fill."""
    held = threading.Event()

    def hold():
        with link._cond:
            held.set()
            time.sleep(wall_s)
    t = threading.Thread(target=hold, daemon=True)
    t.start()
    held.wait()
    return t


def test_realtime_clock_drops_what_a_stalled_host_does_not_read():
    import socket
    with VirtualBench(speed=20, seed=4, clock="realtime") as vb, Device.open(vb.port_url, timeout=3.0) as dev:
        # a small receive window, so that the OS does not hold megabytes for the stalled host
        dev.link.port._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        dev.start_stream(4000)
        dev.read(n_samples=400)
        _stall_reader(dev.link, 4.0).join()          # 80 s of device time at 4 kHz, unread
        # the device's own count (the link is megabytes behind: a reply would wait behind them)
        assert vb.status()["samples_dropped"] > 0     # the device could not send them


def test_lockstep_clock_loses_nothing_to_a_stalled_host():
    with VirtualBench(speed=0, seed=4) as vb, Device.open(vb.port_url, timeout=3.0) as dev:
        assert vb.clock.lockstep and dev.clock is vb.clock
        dev.start_stream(4000)
        t0 = vb.now()
        staller = _stall_reader(dev.link, 2.0)
        b = dev.read(n_samples=40000)                 # 10 s of device time while the reader stalls
        staller.join()
        st = dev.stats()
        dev.stop_stream()
        assert len(b) == 40000
        assert st.samples_dropped == 0 and st.frames_dropped == 0
        assert dev.link.decoder.stats.samples_missing == 0
        assert (b.sample_index[-1] - b.sample_index[0]) == 39999
        assert vb.now() - t0 == pytest.approx(10.0, abs=0.1)      # device time: what was asked


def test_lockstep_device_stands_still_while_the_host_does_not_wait():
    with VirtualBench(speed=0, seed=4) as vb:
        t0 = vb.status()["time_us"]
        time.sleep(0.3)
        assert vb.status()["time_us"] == t0
        vb.wait(2.5)
        assert vb.status()["time_us"] == t0 + 2_500_000


def test_run_is_refused_on_the_realtime_clock_and_checked():
    with VirtualBench(speed=1, seed=4, clock="realtime") as vb:
        with pytest.raises(SimError, match="lockstep"):
            vb.control("run", until_us=1)
    with VirtualBench(speed=0, seed=4) as vb:
        with pytest.raises(SimError, match="stop must be"):
            vb.control("run", until_us=1, stop="forever")
        with pytest.raises(SimError, match="needs die_tolerance_c"):
            vb.control("run", until_us=1, stop="dies")


def test_the_rom_bootloader_runs_on_the_realtime_clock_by_name():
    """BOOT0 high: stm32flash talks to the ROM bootloader and grants no device time."""
    with pytest.raises(SimError, match="real-time clock only"):
        VirtualBench(target="f103", boot0=True, clock="lockstep", start=False)
    vb = VirtualBench(target="f103", boot0=True, start=False)
    try:
        assert vb.clock_name == "realtime" and not vb.clock.lockstep
    finally:
        vb.close()
    vb = VirtualBench(target="f103", start=False)
    try:
        assert vb.clock_name == "lockstep" and vb.clock.lockstep       # the image itself: lockstep
    finally:
        vb.close()


# ------------------------------------------------------------------ same seed, same bytes
#: session.json fields that hold wall times, paths and ports (everything else must match)
VOLATILE = {"started", "finished", "session_started", "capture_dir", "port", "uri", "cal_time_unix_s",
            "cal_id", "run_started", "wall_s", "db"}


def _normalised(obj):
    if isinstance(obj, dict):
        return {k: _normalised(v) for k, v in obj.items() if k not in VOLATILE}
    if isinstance(obj, list):
        return [_normalised(v) for v in obj]
    return obj


@contextlib.contextmanager
def _beside(busy: int):
    """`busy` CPU-bound processes running for the length of the block."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(busy)]
    try:
        yield
    finally:
        for h in hogs:
            h.kill()
            h.wait()


def _calibrate_digest(d: Path) -> tuple[str, dict]:
    """What `imubench calibrate --sim` wrote into d: (SHA-256 of the capture, session.json
    without wall times and paths)."""
    caps = sorted(d.glob("capture-*.bin"))
    assert caps
    digest = hashlib.sha256(b"".join(c.read_bytes() for c in caps)).hexdigest()
    return digest, _normalised(json.loads((d / "session.json").read_text()))


def _command_captures(d: Path) -> str:
    """The SHA-256 of every .bin a command wrote into d, by path."""
    digest, _ = tree_digest(d)                  # the hash bench/determinism.py takes
    assert digest is not None, "the command wrote no .bin"
    return digest


def _arm_session(target: str, path: Path) -> str:
    """A short session on the ARM image in lockstep (info, a stream, a turn while streaming):
    the SHA-256 of the link's capture."""
    with VirtualBench(speed=0, seed=3, target=target) as vb, open(path, "wb") as cap, \
            Device.open(vb.port_url, capture=cap, timeout=5.0) as dev:
        assert vb.info["clock"] == "lockstep"
        dev.info()
        dev.start_stream(1000)
        dev.read(n_samples=300)
        vb.rotate("z", rate_dps=90, duration_s=0.3)
        dev.read(duration_s=0.2)
        dev.stop_stream()
    return hashlib.sha256(path.read_bytes()).hexdigest()


#: issue 33's five cases (docs/simulator.md, bench/determinism.py): the command a user types
#: for the host build (`imubench calibrate --sim --sim-seed 5`, every default), four boards on
#: one virtual fixture and a warm-up of a part with short time constants (both smaller), and a
#: stream with a turn on the F103 and F4 images
COMMANDS = {
    "host": ["calibrate", "--sim", "--sim-seed", "5", "--dir", "DIR", "--db", "DIR.db"],
    "station": ["calibrate", "--sim", "--sim-seed", "5", "--sim-boards", "4", "--method", "six",
                "--gyro", "bias", "--hold", "0.5", "--dir", "DIR", "--db", "DIR.db"],
    "warmup": ["thermal", "--sim", "--warmup", "--sim-seed", "7", "--tau", "30", "--out", "DIR"],
}
CASES = [*COMMANDS, "f103", "f4"]


def _run_case(case: str, root: Path):
    """One case under root: the digest of what it wrote."""
    if case in COMMANDS:
        d = root / case
        r = subprocess.run([sys.executable, "-m", "imubench",
                            *[str(d) + a[3:] if a.startswith("DIR") else a for a in COMMANDS[case]]],
                           capture_output=True, text=True, timeout=600, cwd=root)
        assert r.returncode == 0, (case, r.stdout[-2000:] + r.stderr[-2000:])
        return _calibrate_digest(d) if case == "host" else _command_captures(d)
    return _arm_session(case, root / f"{case}.bin")


@pytest.fixture(scope="module")
def busy(tmp_path_factory) -> dict:
    """Every case at once beside two CPU-bound processes (each in a thread of its own: the
    commands are processes of their own, the ARM sessions run an emulator process each): the
    busy runs share the two cores with the two hogs and with each other, a heavier load than
    one run beside two hogs, for a fraction of the hogs' CPU time. Each test then runs its
    case idle, alone, and compares."""
    from concurrent.futures import ThreadPoolExecutor
    root = tmp_path_factory.mktemp("busy")
    with _beside(2), ThreadPoolExecutor(len(CASES)) as pool:
        futures = {case: pool.submit(_run_case, case, root) for case in CASES}
        return {case: f.result() for case, f in futures.items()}


def test_same_seed_same_session_idle_and_beside_two_busy_processes(busy, tmp_path):
    """`imubench calibrate --sim --sim-seed 5` (lockstep, every default): stream, poses,
    write-back, verification."""
    idle = _run_case("host", tmp_path)
    assert idle[0] == busy["host"][0]                 # the captures, byte for byte
    assert idle[1] == busy["host"][1]                 # every number of the session


@pytest.mark.parametrize("case", ["station", "warmup"])
def test_a_station_and_a_warmup_give_the_same_bytes_idle_and_busy(case, busy, tmp_path):
    """The other two command cases of issue 33's table, smaller: four boards on one virtual
    fixture, and a warm-up of a part with short time constants."""
    assert _run_case(case, tmp_path) == busy[case]


@pytest.mark.parametrize("target", ["f103", "f4"])
def test_the_arm_images_give_the_same_bytes_idle_and_busy(target, busy, tmp_path):
    assert _run_case(target, tmp_path) == busy[target]
