"""The virtual device: the firmware core built for Linux with register-level sensor models
(firmware/boards/sim), driven from Python.

    from imubench.device.sim import VirtualBench
    from imubench.device.link import Device

    with VirtualBench(speed=20, seed=1) as bench:         # starts imubench-sim
        with Device.open(bench.port_url) as dev:         # socket://127.0.0.1:PORT
            dev.start_stream(rate_hz=1000)
            bench.rotate("z", rate_dps=90, duration_s=1)  # turntable: 90 deg about board Z
            ...
        print(bench.get_truth())                         # what calibration should find

The process runs in its own process group; `stop()` (also at exit of the with-block and at
interpreter exit) asks it to quit, then SIGTERMs and SIGKILLs the group, and always reaps
it. The simulator also exits by itself when its parent process dies.

Clocks. clock="lockstep" (the default): device time moves only while the host waits on the
device (imubench.device.clock.LockstepClock: a Device opened on this bench's port grants
the time its waits need; wait() and wait_idle() grant theirs), nothing the device sends is
dropped, and every bench action applies at the device time the device is frozen at: the
same seed and the same host code give the same bytes on any machine, idle or busy. `speed`
is then a ceiling (0: none). clock="realtime": device time runs at `speed` times the wall
clock whatever the host does, and bytes the host does not read in time are dropped, as with
a real board (the link-fault and slow-host tests name it).

The control channel is JSON lines over TCP (one request, one reply per line); see
firmware/boards/sim/sim_control.c for every command and its arguments. `control()` sends
one and returns the reply as a dict, raising SimError when the simulator refuses it.
"""
from __future__ import annotations

import atexit
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import threading
import time
import weakref
from pathlib import Path
from typing import Any, Sequence

from imubench.device import artifacts
from imubench.device import clock as clocks
from imubench.device.tmpdirs import owned_tmpdir
from imubench.errors import ImubenchError
from imubench.parts_gen import PARTS

__all__ = ["CLOCKS", "SimError", "TARGETS", "VirtualBench", "arm_command", "build_sim", "repo_root"]

# What runs the firmware: "host" = the core and drivers built for Linux (imubench-sim);
# "f103" / "f4" = the exact STM32 image under the ARM emulator (imubench.device.arm), against
# the same sensor models, serial endpoint and control channel.
TARGETS = ("host", "f103", "f4")
# How device time moves (module docstring): "lockstep" (deterministic, the default) or
# "realtime" (against the wall clock, bytes dropped when the host lags).
CLOCKS = ("lockstep", "realtime")


def arm_command(target: str) -> list[str]:
    """The command that starts the ARM emulator for `target` (the options are imubench-sim's),
    after making sure its image and the models library are there (imubench.device.artifacts:
    the installed package's, or the checkout's built with `make` first)."""
    import sys
    try:
        artifacts.models_library()
        elf = artifacts.arm_image(target)
    except artifacts.ArtifactError as e:
        raise SimError(str(e)) from e
    if not elf.is_file():
        raise SimError(f"the {target} image {elf} is missing: build the images with `make firmware`")
    host = str(Path(__file__).resolve().parents[2])   # this imubench package, not another one
    code = (f"import sys; sys.path.insert(0, {host!r}); "
            "from imubench.device.arm.__main__ import main; sys.exit(main())")
    return [sys.executable, "-c", code, "--target", target]


class SimError(ImubenchError, RuntimeError):
    """The virtual device could not be built or started, or refused a control command."""


def repo_root() -> Path:
    """The source checkout this package lives in (host/imubench/device/sim.py -> repo root)."""
    root = artifacts.checkout_root()
    if root is None:
        raise SimError(f"{artifacts.PACKAGE} does not run from an imubench source checkout")
    return root


def build_sim() -> Path:
    """The simulator's executable: the installed package's, or the checkout's (`make -s sim`)."""
    try:
        return artifacts.sim_binary()
    except artifacts.ArtifactError as e:
        raise SimError(str(e)) from e


_LIVE: "weakref.WeakSet[VirtualBench]" = weakref.WeakSet()

TMP_PREFIX = "imubench-vbench-"


@atexit.register
def _stop_all() -> None:
    for b in list(_LIVE):
        try:
            b.close()
        except Exception:  # noqa: BLE001 - best effort at interpreter exit
            pass


SIM_PART_SLOTS = {"accel": ("accel",), "gyro": ("gyro_x", "gyro_y", "gyro_z"),
                  "gyro_x": ("gyro_x",), "gyro_y": ("gyro_y",), "gyro_z": ("gyro_z",)}


def sim_parts_spec(parts: str | dict | None) -> str:
    """The virtual board's parts (protocol/parts.toml) as the simulator's --parts text, e.g.
    "accel=adxl359,gyro_z=adxrs453" (or a dict {"accel": "adxl359"}); slots accel, gyro (all
    three), gyro_x, gyro_y, gyro_z; slots not named keep the ADXL355 and ADXRS450s. "" for the
    default board. ValueError, one line naming the slots and parts known, for anything else."""
    if not parts:
        return ""
    items = parts.items() if isinstance(parts, dict) else (
        tuple(x.split("=", 1)) if "=" in x else (x, "") for x in str(parts).replace(" ", "").split(",") if x)
    out = []
    for slot, name in items:
        slot, name = str(slot).lower(), str(name).lower()
        if slot not in SIM_PART_SLOTS:
            raise ValueError(f"--sim-parts: {slot!r} is no slot (slots: {', '.join(SIM_PART_SLOTS)}; "
                             "e.g. accel=adxl359,gyro_z=adxrs453)")
        kind = "accel_triad" if slot == "accel" else "gyro_axis"
        known = sorted(p.name.lower() for p in PARTS.values() if p.kind == kind)
        if name not in known:
            raise ValueError(f"--sim-parts: {slot}={name or '?'}: the {'accelerometer' if slot == 'accel' else 'gyro'} "
                             f"parts are {', '.join(known)}")
        out.append(f"{slot}={name}")
    return ",".join(out)


class VirtualBench:
    """One simulator process (the virtual device, its turntable and climate chamber).

    speed     device time per wall time (20 for CI; 1 = real time; 0 = as fast as possible);
              with clock="lockstep" a ceiling
    clock     "lockstep" (the default: device time granted by the host's waits, deterministic)
              or "realtime" (device time against the wall clock; module docstring; the
              default with boot0, whose ROM bootloader serves stm32flash, which grants nothing)
    seed      seed of the sensor models (noise, random truth, serial numbers, uid)
    truth     "default" (ideal parts with datasheet noise) or "random" (errors drawn from seed)
    flash     parameter flash file; None = a temporary file kept for this object's lifetime
              (restart() keeps it, so saved parameters survive)
    pty       also expose the link on a pseudo-terminal (`.pty`)
    boot0     (f103, f4) BOOT0 high: the board starts in its ROM bootloader (AN3155) on the link,
              for stm32flash on the pty; with it low the board boots what its flash holds
    elf       (f103, f4) the images the board can run (the first one is in a new board's flash)
    tcp       expose the link on TCP 127.0.0.1 (True = a free port, or a port number)
    thermal   switch the dies' thermal model on at start (and after every restart): each
              sensor's die lags the chamber with its own time constant and warms by its own
              self-heating (set_thermal; docs/simulator.md). Off (the default) every die is
              at the chamber's temperature
    """

    def __init__(self, speed: float = 20, seed: int = 1, truth: str = "default",
                 flash: str | os.PathLike | None = None, pty: bool = False,
                 baud: int = 2000000, *, tcp: bool | int = True, control_port: int = 0,
                 uid: str | None = None, binary: str | os.PathLike | None = None,
                 startup_timeout: float = 15.0, start: bool = True, target: str = "host",
                 boot0: bool = False, elf: Sequence[str | os.PathLike] | None = None,
                 thermal: bool = False, clock: str | None = None, parts: str | dict | None = None):
        if target not in TARGETS:
            raise ValueError(f"target must be one of {', '.join(TARGETS)}")
        # BOOT0 high: the ROM bootloader serves stm32flash on the pty, which grants no time
        clock = ("realtime" if boot0 else "lockstep") if clock is None else clock
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}")
        if clock == "lockstep" and boot0:
            raise SimError("the ROM bootloader (boot0) runs on the real-time clock only: stm32flash grants "
                           "no device time")
        self.clock_name = clock
        self.clock = clocks.LockstepClock(self) if clock == "lockstep" else clocks.WALL
        self.target = target
        if (boot0 or elf) and target == "host":
            raise ValueError("boot0 and elf are settings of the ARM targets (f103, f4)")
        self.boot0 = bool(boot0)            # BOOT0 high: the ROM bootloader (stm32flash on the pty)
        self.elf = [str(e) for e in elf] if elf else []   # images the board may run (the first: factory)
        if truth not in ("default", "random"):
            raise ValueError("truth must be 'default' or 'random'")
        if not pty and tcp is False:
            raise ValueError("give pty=True or tcp")
        self.parts = sim_parts_spec(parts)   # checked here: a bad name is one line, not a dead process
        self.speed = speed
        self.seed = int(seed)
        self.truth = truth
        self.thermal = bool(thermal)
        self.pty_enabled = bool(pty)
        self.baud = int(baud)
        self.uid = uid
        self.startup_timeout = startup_timeout
        self._tcp_req: int | None = None if tcp is False else (0 if tcp is True else int(tcp))
        self._control_req = int(control_port)
        self._tmpdir = owned_tmpdir(TMP_PREFIX)
        self.flash = str(Path(flash).resolve()) if flash is not None else os.path.join(self._tmpdir, "flash.bin")
        self.log_path = os.path.join(self._tmpdir, "sim.log")
        self._binary = Path(binary) if binary is not None else None
        self.proc: subprocess.Popen | None = None
        self.info: dict[str, Any] = {}
        self._sock: socket.socket | None = None
        self._rfile = None
        self._lock = threading.Lock()
        self._closed = False
        if start:
            try:
                self.start()
            except BaseException:
                self.close()            # no process, no temporary directory left behind
                raise

    # ------------------------------------------------------------ lifecycle
    @property
    def binary(self) -> Path:
        if self._binary is None:
            self._binary = build_sim()
        return self._binary

    def start(self) -> "VirtualBench":
        if self.proc is not None and self.proc.poll() is None:
            raise SimError("the virtual device is already running")
        self._start(self._tcp_req, self._control_req)
        return self

    def _start(self, tcp_port: int | None, control_port: int) -> None:
        prefix = [str(self.binary)] if self.target == "host" else arm_command(self.target)
        args = [*prefix, "--speed", repr(float(self.speed)), "--seed", str(self.seed),
                "--truth", self.truth, "--flash", self.flash, "--baud", str(self.baud),
                "--control", str(control_port)]
        if self.clock.lockstep:
            args += ["--clock", "lockstep"]
        if self.pty_enabled:
            args.append("--pty")
        if self.boot0:
            args.append("--boot0")
        for e in self.elf:
            args += ["--elf", e]
        if tcp_port is not None:
            args += ["--tcp", str(tcp_port)]
        if self.uid:
            args += ["--uid", self.uid]
        if self.parts:
            args += ["--parts", self.parts]
        if self.target == "host":
            args += ["--orphan-cleanup", self._tmpdir]      # a SIGKILLed host's folder goes with the sim
        log = open(self.log_path, "ab")
        try:
            log.write(f"--- {' '.join(args)}\n".encode())
            log.flush()
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                         stderr=log, start_new_session=True)
        finally:
            log.close()
        _LIVE.add(self)
        try:
            line = self._read_startup_line()
            self.info = json.loads(line)
            self._connect_control()
            if self.clock.lockstep:
                self.clock.sync()
                clocks.unregister(self.clock)
                clocks.register(self.port_url, self.clock, control=self.info["control"])
                if self.pty:
                    clocks.register(self.pty, self.clock, control=self.info["control"])
            if self.thermal:
                self.set_thermal(True)
        except BaseException:
            self._kill()
            raise

    def _read_startup_line(self) -> str:
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        buf = b""
        deadline = time.monotonic() + self.startup_timeout
        while b"\n" not in buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise SimError(f"the virtual device printed no start-up line within "
                               f"{self.startup_timeout:g} s{self._log_tail()}")
            r, _, _ = select.select([fd], [], [], min(left, 0.2))
            if r:
                chunk = os.read(fd, 4096)
                if not chunk:
                    code = self.proc.wait(timeout=5)
                    raise SimError(f"the virtual device exited at start-up (code {code})"
                                   f"{self._log_tail()}")
                buf += chunk
        line = buf.split(b"\n", 1)[0].decode()
        try:
            json.loads(line)
        except ValueError as e:
            raise SimError(f"bad start-up line from the virtual device: {line!r}") from e
        return line

    def _connect_control(self) -> None:
        self._disconnect_control()
        s = socket.create_connection(("127.0.0.1", int(self.info["control_port"])), timeout=5.0)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s
        self._rfile = s.makefile("rb")

    def _disconnect_control(self) -> None:
        for obj in (self._rfile, self._sock):
            if obj is not None:
                try:
                    obj.close()
                except OSError:
                    pass
        self._rfile = self._sock = None

    def _log_tail(self, n: int = 30) -> str:
        try:
            lines = Path(self.log_path).read_text(errors="replace").splitlines()[-n:]
        except OSError:
            return ""
        return ("\n--- simulator log (" + self.log_path + "):\n" + "\n".join(lines)) if lines else ""

    @property
    def log(self) -> str:
        """Everything the simulator wrote to stderr (all runs of this object)."""
        try:
            return Path(self.log_path).read_text(errors="replace")
        except OSError:
            return ""

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def port_url(self) -> str:
        """pyserial URL of the device's serial link (socket:// when TCP is on, else the pty)."""
        return self.info["port_url"]

    @property
    def pty(self) -> str | None:
        return self.info.get("pty")

    @property
    def tcp_port(self) -> int | None:
        return self.info.get("tcp_port")

    @property
    def control_address(self) -> tuple[str, int]:
        return ("127.0.0.1", int(self.info["control_port"]))

    def stop(self, timeout: float = 3.0) -> None:
        """Stop the process: quit command, then SIGTERM, then SIGKILL of its process group;
        always reaps it. The flash file is kept."""
        proc = self.proc
        if proc is None:
            return
        if proc.poll() is None and self._sock is not None:
            try:
                self._sock.settimeout(1.0)
                self._sock.sendall(b'{"cmd": "quit"}\n')
                self._rfile.readline()
            except (OSError, ValueError):
                pass
        self._disconnect_control()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self._kill()
        self._reap()

    def _kill(self) -> None:
        proc = self.proc
        if proc is None:
            return
        for sig, wait in ((signal.SIGTERM, 2.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            try:
                os.killpg(proc.pid, sig)    # own session: the group id is its pid
            except ProcessLookupError:
                break
            try:
                proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        self._disconnect_control()
        self._reap()

    def _reap(self) -> None:
        proc = self.proc
        if proc is None:
            return
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        if proc.stdout is not None:
            proc.stdout.close()
        self.proc = None
        _LIVE.discard(self)

    def restart(self) -> "VirtualBench":
        """Stop and start again with the same flash file (saved parameters survive) and, if
        they are still free, the same ports."""
        old_tcp, old_ctl = self.info.get("tcp_port"), self.info.get("control_port")
        self.stop()
        tcp = None if self._tcp_req is None else (old_tcp if old_tcp is not None else self._tcp_req)
        try:
            self._start(tcp, old_ctl if old_ctl is not None else self._control_req)
        except SimError:
            self._start(self._tcp_req, self._control_req)
        return self

    def close(self) -> None:
        """stop() and remove the temporary directory (and the flash file if it lives there)."""
        self.stop()
        if self.clock.lockstep:
            clocks.unregister(self.clock)
        if not self._closed:
            self._closed = True
            shutil.rmtree(self._tmpdir, ignore_errors=True)

    def __enter__(self) -> "VirtualBench":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            if self.proc is not None:
                self._kill()
        except Exception:  # noqa: BLE001
            pass

    # ------------------------------------------------------------ control
    def control(self, _cmd: str | None = None, *, timeout: float | None = 10.0, **fields) -> dict:
        """Send one control command (`control("status")` or `control(cmd="status")`) and
        return the reply; SimError when the simulator answers ok=false or is gone."""
        if _cmd is not None:
            fields["cmd"] = _cmd
        if "cmd" not in fields:
            raise ValueError("no cmd given")
        line = (json.dumps(fields) + "\n").encode()
        with self._lock:
            if not self.running:
                raise SimError(f"the virtual device is not running{self._log_tail(10)}")
            if self._sock is None:
                self._connect_control()
            try:
                self._sock.settimeout(timeout)
                self._sock.sendall(line)
                reply = self._rfile.readline()
            except (socket.timeout, TimeoutError) as e:
                self._disconnect_control()     # a late reply must not answer the next request
                raise SimError(f"no reply to {fields['cmd']} within {timeout} s") from e
            except OSError as e:
                self._disconnect_control()
                raise SimError(f"control channel failed: {e}{self._log_tail(10)}") from e
        if not reply:
            self._disconnect_control()
            raise SimError(f"the virtual device closed the control channel{self._log_tail(10)}")
        r = json.loads(reply)
        if not r.get("ok"):
            raise SimError(f"{fields['cmd']}: {r.get('error', 'refused')}")
        return r

    def _wait_timeout(self, device_s: float) -> float:
        """A timeout for waiting device_s of device time: device seconds in lockstep (plus a
        margin), wall seconds on the real-time clock."""
        if self.clock.lockstep:
            return device_s + 30.0
        sp = float(self.speed)
        return 30.0 + (device_s / sp if sp > 0 else device_s / 50.0)

    def now(self) -> float:
        """Device time, s (lockstep: where the device is frozen; real-time: asks it)."""
        if self.clock.lockstep:
            self.clock.sync()       # a process started from this one may have run the device
            return self.clock.now()
        return float(self.status()["time_us"]) * 1e-6

    # convenience wrappers
    def status(self) -> dict:
        return self.control("status")

    def set_orientation(self, gravity: Sequence[float] | None = None, roll_deg: float | None = None,
                        pitch_deg: float | None = None, yaw_deg: float | None = None) -> dict:
        """Gravity = direction of the measured specific force in the board frame (level:
        [0, 0, 1]), or roll/pitch/yaw in degrees (ZYX, right-handed about board X/Y/Z)."""
        kw: dict[str, Any] = {}
        if gravity is not None:
            kw["gravity"] = [float(x) for x in gravity]
        for k, v in (("roll_deg", roll_deg), ("pitch_deg", pitch_deg), ("yaw_deg", yaw_deg)):
            if v is not None:
                kw[k] = float(v)
        return self.control("set_orientation", **kw)

    def rotate(self, axis: str | Sequence[float], rate_dps: float, duration_s: float,
               wait: bool = True) -> dict:
        """Turn about a board-frame axis ("x", "-y", or a vector) at rate_dps for duration_s
        of device time; with wait, return when the move is over."""
        ax = axis if isinstance(axis, str) else [float(x) for x in axis]
        r = self.control("rotate", axis=ax, rate_dps=float(rate_dps), duration_s=float(duration_s))
        if wait:
            self.wait_idle(timeout=self._wait_timeout(duration_s))
        return r

    def set_rate(self, rate_dps: Sequence[float]) -> dict:
        return self.control("set_rate", rate_dps=[float(x) for x in rate_dps])

    def path(self, legs: Sequence[dict], wait: bool = True) -> dict:
        """Drive a path: legs [{"duration_s": T, "move_m": [dx, dy, dz] (level frame),
        "axis": "z", "turn_deg": A}, ...] back to back, each rest to rest on a minimum-jerk
        profile (firmware/boards/sim/sim_physics.c). With wait, return when it is driven.
        The reply carries t_start_us, t_end_us (device time) and duration_s."""
        r = self.control("path", legs=[dict(leg) for leg in legs])
        if wait:
            self.wait_idle(timeout=self._wait_timeout(float(r["duration_s"])))
        return r

    def set_temperature(self, c: float, ramp_c_per_s: float | None = None, wait: bool = False,
                        soak: bool = False) -> dict:
        """Set the chamber (ambient) to c degC, at once or ramping at ramp_c_per_s; with wait,
        return when the ramp is over. soak=True: the chamber and every die at c at once, as
        after hours in a fridge (self-heating then builds up again with the dies' lag); it
        cannot ramp. The reply carries temperature_c and die_temperature_c [4]."""
        kw: dict[str, Any] = {"c": float(c)}
        if soak:
            if ramp_c_per_s:
                raise ValueError("a soak puts the board at c at once: give soak or ramp_c_per_s, not both")
            kw["soak"] = True
        if ramp_c_per_s:
            kw["ramp_c_per_s"] = float(ramp_c_per_s)
        r = self.control("set_temperature", **kw)
        if wait and ramp_c_per_s:
            span = abs(float(c) - float(self.status()["temperature_c"]))
            self.wait_idle(temperature=True, timeout=self._wait_timeout(span / float(ramp_c_per_s)))
        return r

    def set_thermal(self, enabled: bool = True, tau_s: Sequence[float] | float | None = None,
                    self_heat_c: Sequence[float] | float | None = None) -> dict:
        """Switch the dies' thermal model on or off and/or change its figures (per die: ADXL355,
        gyro X, Y, Z; one number for all four). tau_s: first-order time constant of each die
        to the chamber, s; self_heat_c: each die's steady rise over the chamber when powered,
        degC. Omitted figures keep theirs (the nominal ones, or those drawn with the random
        truth). Switching on starts every die at the chamber's temperature (as a power-up).
        Returns {"thermal": {enabled, tau_s, self_heat_c}, "die_temperature_c": [4], ...}."""
        kw: dict[str, Any] = {"enabled": bool(enabled)}
        for k, v in (("tau_s", tau_s), ("self_heat_c", self_heat_c)):
            if v is not None:
                kw[k] = float(v) if isinstance(v, (int, float)) else [float(x) for x in v]
        return self.control("set_thermal", **kw)

    def die_temperatures(self) -> list[float]:
        """The four dies' temperatures now, degC (ADXL355, gyro X, Y, Z)."""
        return [float(x) for x in self.status()["die_temperature_c"]]

    def set_speed(self, speed: float) -> dict:
        r = self.control("set_speed", speed=float(speed))
        self.speed = speed
        return r

    def set_truth(self, accel: dict | None = None, gyro: Sequence[dict | None] | dict | None = None) -> dict:
        kw: dict[str, Any] = {}
        if accel is not None:
            kw["accel"] = accel
        if gyro is not None:
            kw["gyro"] = gyro
        return self.control("set_truth", **kw)

    def randomize_truth(self, seed: int | None = None) -> dict:
        return self.control("randomize_truth", **({} if seed is None else {"seed": int(seed)}))

    def get_truth(self) -> dict:
        return self.control("get_truth")

    def inject(self, fault: str, **kw) -> dict:
        """inject("gyro_fault_bits", sensor="gyro_x", bits=0x10, persistent=False),
        inject("gyro_parity", sensor="gyro_y", count=3), inject("missing", sensor="accel"),
        inject("spi_error", sensor="gyro_z", count=5), inject("link_drop", count=100),
        inject("link_flip", count=10), inject("clear")."""
        return self.control("inject", fault=fault, **kw)

    def clear_faults(self) -> dict:
        return self.inject("clear")

    def power_cut(self, after_flash_ops: int | None = None) -> dict:
        """Cut the power now, or during the after_flash_ops-th next flash operation."""
        if after_flash_ops is None:
            return self.control("power_cut")
        return self.control("power_cut", after_flash_ops=int(after_flash_ops))

    def flash_ops(self) -> int:
        """Flash operations (program or erase calls) since the device last booted."""
        return int(self.control("flash_ops")["flash_ops"])

    def wait(self, device_s: float) -> dict:
        """Return after device_s seconds of device time (lockstep: granted, with every link
        byte of that time received by the host)."""
        if self.clock.lockstep:
            self.clock.sync()
            return self.clock.run(float(device_s))
        return self.control("wait", device_s=float(device_s), timeout=self._wait_timeout(device_s))

    def wait_idle(self, temperature: bool = False, timeout: float | None = 600.0,
                  die_tolerance_c: float | None = None, device_limit_s: float = 86400.0) -> dict:
        """Return when no move (and with temperature=True, no temperature ramp) is running;
        with die_tolerance_c also when every die is within that of its steady temperature
        (chamber + self-heating; at once with the thermal model off). timeout: wall seconds
        on the real-time clock. Lockstep: the device runs to the first device time the
        condition holds, at most device_limit_s (SimError when it did not)."""
        if self.clock.lockstep:
            stop = "dies" if die_tolerance_c is not None else "temperature" if temperature else "idle"
            self.clock.sync()
            r = self.clock.run(float(device_limit_s), stop=stop, die_tolerance_c=die_tolerance_c)
            if not r.get("done"):
                raise SimError(f"wait_idle: the bench was not idle ({stop}) within {device_limit_s:g} s of "
                               "device time")
            return r
        kw: dict[str, Any] = {"temperature": bool(temperature) or die_tolerance_c is not None}
        if die_tolerance_c is not None:
            kw["die_tolerance_c"] = float(die_tolerance_c)
        return self.control("wait_idle", timeout=timeout, **kw)

    def device(self, **kw):
        """An imubench.device.link.Device connected to this bench's link."""
        from imubench.device.link import Device
        return Device.open(self.port_url, **kw)

    def __repr__(self) -> str:
        state = f"pid {self.pid}" if self.running else "stopped"
        return (f"<VirtualBench {self.info.get('port_url', '?')} speed={self.speed} seed={self.seed} "
                f"clock={self.clock_name} {state}>")


# ---------------------------------------------------------------- command line
