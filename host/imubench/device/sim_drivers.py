"""The virtual bench's drivers: what talks to a running simulator, one concern each.

    ControlChannel  the JSON-lines control connection: control(cmd, **fields) -> reply
    TimeDriver      device time: status, now, wait, wait_idle, set_speed
    MotionDriver    the turntable: set_orientation, rotate, set_rate, path
    ClimateDriver   the chamber and the dies: set_temperature, set_thermal, die_temperatures
    TruthDriver     the sensors' true errors: set_truth, randomize_truth, get_truth
    FaultDriver     what goes wrong: inject, clear_faults, power_cut, flash_ops

Each driver is given the channel (and the time driver, for waits) and nothing else: none starts
or stops a process (imubench.device.sim_resource, sim_strategy). The commands and their
arguments are firmware/boards/sim/sim_control.c's.
"""
from __future__ import annotations

import json
import socket
import threading
from typing import Any, Sequence

from imubench.device.sim_resource import SimError, SimProcess

__all__ = ["ControlChannel", "TimeDriver", "MotionDriver", "ClimateDriver", "TruthDriver", "FaultDriver"]


class ControlChannel:
    """The control connection to one simulator process (resource): one request, one reply per
    line, one request at a time."""

    def __init__(self, resource: SimProcess):
        self.resource = resource
        self._sock: socket.socket | None = None
        self._rfile = None
        self._lock = threading.Lock()

    def connect(self) -> None:
        self.disconnect()
        s = socket.create_connection(self.resource.control_address, timeout=5.0)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s
        self._rfile = s.makefile("rb")

    def disconnect(self) -> None:
        for obj in (self._rfile, self._sock):
            if obj is not None:
                try:
                    obj.close()
                except OSError:
                    pass
        self._rfile = self._sock = None

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def quit(self) -> None:
        """Ask the simulator to exit (best effort: a gone process is not an error). A
        connection dropped earlier (a command that failed or was interrupted, a grant past
        its guard) is opened anew: without the quit the process is only ended by SIGTERM
        after the stop timeout."""
        if self.resource.running:
            try:
                if self._sock is None:
                    self.connect()
                self._sock.settimeout(1.0)
                self._sock.sendall(b'{"cmd": "quit"}\n')
                self._rfile.readline()
            except (OSError, ValueError):
                pass
        self.disconnect()

    def control(self, _cmd: str | None = None, *, timeout: float | None = 10.0, **fields) -> dict:
        """Send one control command (`control("status")` or `control(cmd="status")`) and
        return the reply; SimError when the simulator answers ok=false or is gone."""
        if _cmd is not None:
            fields["cmd"] = _cmd
        if "cmd" not in fields:
            raise ValueError("no cmd given")
        line = (json.dumps(fields) + "\n").encode()
        tail = self.resource.log_tail
        with self._lock:
            if not self.resource.running:
                raise SimError(f"the virtual device is not running{tail(10)}")
            if self._sock is None:
                self.connect()
            try:
                self._sock.settimeout(timeout)
                self._sock.sendall(line)
                reply = self._rfile.readline()
            except (socket.timeout, TimeoutError) as e:
                self.disconnect()     # a late reply must not answer the next request
                raise SimError(f"no reply to {fields['cmd']} within {timeout} s") from e
            except OSError as e:
                self.disconnect()
                raise SimError(f"control channel failed: {e}{tail(10)}") from e
            except BaseException:
                # Ctrl-C between the request and its reply: the reply would answer the next
                # request (a `run` reply read as `status`'s), so the connection goes with it
                self.disconnect()
                raise
        if not reply:
            self.disconnect()
            raise SimError(f"the virtual device closed the control channel{tail(10)}")
        r = json.loads(reply)
        if not r.get("ok"):
            raise SimError(f"{fields['cmd']}: {r.get('error', 'refused')}")
        return r


class TimeDriver:
    """Device time: where it is, waiting on it, and how fast it may run. clock is the bench's
    (imubench.device.clock: a LockstepClock grants device time; WALL lets it run)."""

    def __init__(self, channel: ControlChannel, resource: SimProcess, clock):
        self.channel, self.resource, self.clock = channel, resource, clock

    def timeout_for(self, device_s: float) -> float:
        """A timeout for waiting device_s of device time: device seconds in lockstep (plus a
        margin), wall seconds on the real-time clock."""
        if self.clock.lockstep:
            return device_s + 30.0
        sp = float(self.resource.speed)
        return 30.0 + (device_s / sp if sp > 0 else device_s / 50.0)

    def status(self) -> dict:
        return self.channel.control("status")

    def now(self) -> float:
        """Device time, s (lockstep: where the device is frozen; real-time: asks it)."""
        if self.clock.lockstep:
            self.clock.sync()       # a process started from this one may have run the device
            return self.clock.now()
        return float(self.status()["time_us"]) * 1e-6

    def set_speed(self, speed: float) -> dict:
        r = self.channel.control("set_speed", speed=float(speed))
        self.resource.speed = speed
        return r

    def wait(self, device_s: float) -> dict:
        """Return after device_s seconds of device time (lockstep: granted, with every link
        byte of that time received by the host)."""
        if self.clock.lockstep:
            self.clock.sync()
            return self.clock.run(float(device_s))
        return self.channel.control("wait", device_s=float(device_s), timeout=self.timeout_for(device_s))

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
        return self.channel.control("wait_idle", timeout=timeout, **kw)


class MotionDriver:
    """The turntable: the board's attitude and its turns."""

    def __init__(self, channel: ControlChannel, time: TimeDriver):
        self.channel, self.time = channel, time

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
        return self.channel.control("set_orientation", **kw)

    def rotate(self, axis: str | Sequence[float], rate_dps: float, duration_s: float,
               wait: bool = True) -> dict:
        """Turn about a board-frame axis ("x", "-y", or a vector) at rate_dps for duration_s
        of device time; with wait, return when the move is over."""
        ax = axis if isinstance(axis, str) else [float(x) for x in axis]
        r = self.channel.control("rotate", axis=ax, rate_dps=float(rate_dps), duration_s=float(duration_s))
        if wait:
            self.time.wait_idle(timeout=self.time.timeout_for(duration_s))
        return r

    def set_rate(self, rate_dps: Sequence[float]) -> dict:
        return self.channel.control("set_rate", rate_dps=[float(x) for x in rate_dps])

    def path(self, legs: Sequence[dict], wait: bool = True) -> dict:
        """Drive a path: legs [{"duration_s": T, "move_m": [dx, dy, dz] (level frame),
        "axis": "z", "turn_deg": A}, ...] back to back, each rest to rest on a minimum-jerk
        profile (firmware/boards/sim/sim_physics.c). With wait, return when it is driven.
        The reply carries t_start_us, t_end_us (device time) and duration_s."""
        r = self.channel.control("path", legs=[dict(leg) for leg in legs])
        if wait:
            self.time.wait_idle(timeout=self.time.timeout_for(float(r["duration_s"])))
        return r


class ClimateDriver:
    """The climate chamber and the dies' thermal model."""

    def __init__(self, channel: ControlChannel, time: TimeDriver):
        self.channel, self.time = channel, time

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
        r = self.channel.control("set_temperature", **kw)
        if wait and ramp_c_per_s:
            span = abs(float(c) - float(self.time.status()["temperature_c"]))
            self.time.wait_idle(temperature=True, timeout=self.time.timeout_for(span / float(ramp_c_per_s)))
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
        return self.channel.control("set_thermal", **kw)

    def die_temperatures(self) -> list[float]:
        """The four dies' temperatures now, degC (ADXL355, gyro X, Y, Z)."""
        return [float(x) for x in self.time.status()["die_temperature_c"]]


class TruthDriver:
    """The sensors' true errors (what a calibration should find)."""

    def __init__(self, channel: ControlChannel):
        self.channel = channel

    def set_truth(self, accel: dict | None = None, gyro: Sequence[dict | None] | dict | None = None) -> dict:
        kw: dict[str, Any] = {}
        if accel is not None:
            kw["accel"] = accel
        if gyro is not None:
            kw["gyro"] = gyro
        return self.channel.control("set_truth", **kw)

    def randomize_truth(self, seed: int | None = None) -> dict:
        return self.channel.control("randomize_truth", **({} if seed is None else {"seed": int(seed)}))

    def get_truth(self) -> dict:
        return self.channel.control("get_truth")


class FaultDriver:
    """Faults: sensors, the link, the power and the flash."""

    def __init__(self, channel: ControlChannel):
        self.channel = channel

    def inject(self, fault: str, **kw) -> dict:
        """inject("gyro_fault_bits", sensor="gyro_x", bits=0x10, persistent=False),
        inject("gyro_parity", sensor="gyro_y", count=3), inject("missing", sensor="accel"),
        inject("spi_error", sensor="gyro_z", count=5), inject("link_drop", count=100),
        inject("link_flip", count=10), inject("clear")."""
        return self.channel.control("inject", fault=fault, **kw)

    def clear_faults(self) -> dict:
        return self.inject("clear")

    def power_cut(self, after_flash_ops: int | None = None) -> dict:
        """Cut the power now, or during the after_flash_ops-th next flash operation."""
        if after_flash_ops is None:
            return self.channel.control("power_cut")
        return self.channel.control("power_cut", after_flash_ops=int(after_flash_ops))

    def flash_ops(self) -> int:
        """Flash operations (program or erase calls) since the device last booted."""
        return int(self.channel.control("flash_ops")["flash_ops"])
