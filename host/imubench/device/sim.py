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

Three layers, as labgrid keeps them apart (docs/architecture.md, "The virtual bench's three
layers"): the resource (device/sim_resource.py, `SimProcess`: the process, its settings, ports
and log), the drivers (device/sim_drivers.py: the control channel, and one driver per concern:
`time`, `motion`, `climate`, `truth`, `faults`) and the strategy (device/sim_strategy.py,
`BenchStrategy`: off, running, gone, and the steps between them). `VirtualBench` puts one of
each together and answers every name the bench has always had (`bench.rotate(...)` is
`bench.motion.rotate(...)`, `bench.port_url` is `bench.resource.port_url`): new code may name
the layer it uses.
"""
from __future__ import annotations

import atexit
from typing import Any

from imubench.device import clock as clocks
from imubench.device.sim_drivers import (ClimateDriver, ControlChannel, FaultDriver, MotionDriver, TimeDriver,
                                         TruthDriver)
from imubench.device.sim_resource import (CLOCKS, LIVE, TARGETS, TMP_PREFIX, SimError, SimProcess,  # noqa: F401
                                          arm_command, build_sim)
from imubench.device.sim_strategy import BenchStrategy

__all__ = ["CLOCKS", "SimError", "TARGETS", "VirtualBench", "arm_command", "build_sim", "repo_root"]


def repo_root():
    """The source checkout this package lives in (host/imubench/device/sim.py -> repo root)."""
    from imubench.device import artifacts
    root = artifacts.checkout_root()
    if root is None:
        raise SimError(f"{artifacts.PACKAGE} does not run from an imubench source checkout")
    return root


@atexit.register
def _stop_all() -> None:
    for b in list(LIVE):
        try:
            b.close()
        except Exception:  # noqa: BLE001 - best effort at interpreter exit
            pass


# the names a VirtualBench answers for its layers: name -> the attribute of the layer that has it
_LAYER_OF = {
    **{n: "resource" for n in ("binary", "running", "pid", "port_url", "pty", "tcp_port", "control_address", "log",
                               "info", "proc", "flash", "log_path", "_tmpdir", "target", "boot0", "elf", "speed",
                               "seed", "truth", "thermal", "pty_enabled", "baud", "uid", "startup_timeout",
                               "clock_name")},
    "control": "channel",
    **{n: "time" for n in ("status", "now", "wait", "wait_idle", "set_speed")},
    **{n: "motion" for n in ("set_orientation", "rotate", "set_rate", "path")},
    **{n: "climate" for n in ("set_temperature", "set_thermal", "die_temperatures")},
    **{n: "truth_driver" for n in ("set_truth", "randomize_truth", "get_truth")},
    **{n: "faults" for n in ("inject", "clear_faults", "power_cut", "flash_ops")},
    **{n: "strategy" for n in ("restart", "transition", "state")},
}


class VirtualBench:
    """One simulator process (the virtual device, its turntable and climate chamber): its
    resource, drivers and strategy put together.

    speed     device time per wall time (1 = real time; 0 = as fast as possible); with
              clock="lockstep" a ceiling (default None: none), with "realtime" the pace
              (default None: 20)
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

    The layers: .resource (SimProcess), .channel (ControlChannel), .time, .motion, .climate,
    .truth_driver, .faults (the drivers) and .strategy (BenchStrategy); every name of theirs in
    _LAYER_OF is answered by the bench itself too.
    """

    def __init__(self, speed: float | None = None, seed: int = 1, truth: str = "default", flash=None, pty: bool = False,
                 baud: int = 2000000, *, tcp: bool | int = True, control_port: int = 0, uid: str | None = None,
                 binary=None, startup_timeout: float = 15.0, start: bool = True, target: str = "host",
                 boot0: bool = False, elf=None, thermal: bool = False, clock: str | None = None):
        self.resource = SimProcess(speed, seed, truth, flash, pty, baud, tcp=tcp, control_port=control_port,
                                   uid=uid, binary=binary, startup_timeout=startup_timeout, target=target,
                                   boot0=boot0, elf=elf, thermal=thermal, clock=clock)
        self.clock = clocks.LockstepClock(self) if self.resource.clock_name == "lockstep" else clocks.WALL
        self.channel = ControlChannel(self.resource)
        self.time = TimeDriver(self.channel, self.resource, self.clock)
        self.motion = MotionDriver(self.channel, self.time)
        self.climate = ClimateDriver(self.channel, self.time)
        self.truth_driver = TruthDriver(self.channel)
        self.faults = FaultDriver(self.channel)
        self.strategy = BenchStrategy(self.resource, self.channel, self.clock, self.climate, owner=self)
        if start:
            try:
                self.start()
            except BaseException:
                self.close()            # no process, no temporary directory left behind
                raise

    def __getattr__(self, name: str) -> Any:
        layer = _LAYER_OF.get(name)
        if layer is None or layer not in self.__dict__:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(self.__dict__[layer], name)

    def __dir__(self):
        return sorted(set(super().__dir__()) | set(_LAYER_OF))

    # ------------------------------------------------------------ lifecycle (the strategy's)
    def start(self) -> "VirtualBench":
        if self.resource.running:
            raise SimError("the virtual device is already running")
        self.strategy.start()
        return self

    def stop(self, timeout: float = 3.0) -> None:
        """Stop the process: quit command, then SIGTERM, then SIGKILL of its process group;
        always reaps it. The flash file is kept."""
        self.strategy.stop(timeout)

    def restart(self) -> "VirtualBench":
        """Stop and start again with the same flash file (saved parameters survive) and, if
        they are still free, the same ports."""
        self.strategy.restart()
        return self

    def close(self) -> None:
        """stop() and remove the temporary directory (and the flash file if it lives there)."""
        if "strategy" in self.__dict__:
            self.strategy.close()
        elif "resource" in self.__dict__:
            self.resource.remove()

    def __enter__(self) -> "VirtualBench":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            if self.__dict__.get("resource") is not None and self.resource.proc is not None:
                self.strategy.kill()
        except Exception:  # noqa: BLE001
            pass

    def device(self, **kw):
        """An imubench.device.link.Device connected to this bench's link."""
        from imubench.device.link import Device
        return Device.open(self.resource.port_url, **kw)

    def __repr__(self) -> str:
        r = self.__dict__.get("resource")
        if r is None:
            return "<VirtualBench (not made)>"
        state = f"pid {r.pid}" if r.running else "stopped"
        return (f"<VirtualBench {r.info.get('port_url', '?')} speed={r.speed} seed={r.seed} "
                f"clock={r.clock_name} {state}>")
