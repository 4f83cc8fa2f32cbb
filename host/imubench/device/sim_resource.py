"""The virtual bench's resource: one simulator process and where it is reached.

In labgrid's terms (a resource says what exists and where; a driver talks to it; a strategy
brings it into a state) this is the resource: the settings a simulator is started with, the
process once it runs, its start-up line (link URL, pty, TCP and control ports) and its log.
It spawns and ends the process; it sends no command (imubench.device.sim_drivers does) and
decides no state (imubench.device.sim_strategy does).
"""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import time
import weakref
from pathlib import Path
from typing import Any, Sequence

from imubench.device import artifacts
from imubench.device.tmpdirs import owned_tmpdir
from imubench.errors import ImubenchError

__all__ = ["CLOCKS", "SimError", "SimProcess", "TARGETS", "arm_command", "build_sim", "LIVE"]

# What runs the firmware: "host" = the core and drivers built for Linux (imubench-sim);
# "f103" / "f4" = the exact STM32 image under the ARM emulator (imubench.device.arm), against
# the same sensor models, serial endpoint and control channel.
TARGETS = ("host", "f103", "f4")
# How device time moves (imubench.device.sim): "lockstep" (deterministic, the default) or
# "realtime" (against the wall clock, bytes dropped when the host lags).
CLOCKS = ("lockstep", "realtime")
TMP_PREFIX = "imubench-vbench-"
# every bench whose process runs (imubench.device.sim stops them at interpreter exit)
LIVE: "weakref.WeakSet[Any]" = weakref.WeakSet()


class SimError(ImubenchError, RuntimeError):
    """The virtual device could not be built or started, or refused a control command."""


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


def build_sim() -> Path:
    """The simulator's executable: the installed package's, or the checkout's (`make -s sim`)."""
    try:
        return artifacts.sim_binary()
    except artifacts.ArtifactError as e:
        raise SimError(str(e)) from e


class SimProcess:
    """One simulator process: its settings (imubench.device.sim.VirtualBench lists them), the
    process, its start-up facts and its log. spawn() starts it and reads its start-up line;
    end() waits for it to exit (after a quit), else SIGTERMs and SIGKILLs its process group,
    and always reaps it; remove() deletes its temporary directory."""

    def __init__(self, speed: float | None = None, seed: int = 1, truth: str = "default",
                 flash: str | os.PathLike | None = None, pty: bool = False, baud: int = 2000000, *,
                 tcp: bool | int = True, control_port: int = 0, uid: str | None = None,
                 binary: str | os.PathLike | None = None, startup_timeout: float = 15.0, target: str = "host",
                 boot0: bool = False, elf: Sequence[str | os.PathLike] | None = None, thermal: bool = False,
                 clock: str | None = None):
        if target not in TARGETS:
            raise ValueError(f"target must be one of {', '.join(TARGETS)}")
        # BOOT0 high: the ROM bootloader serves stm32flash on the pty, which grants no time
        clock = ("realtime" if boot0 else "lockstep") if clock is None else clock
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}")
        if clock == "lockstep" and boot0:
            raise SimError("the ROM bootloader (boot0) runs on the real-time clock only: stm32flash grants "
                           "no device time")
        if (boot0 or elf) and target == "host":
            raise ValueError("boot0 and elf are settings of the ARM targets (f103, f4)")
        if truth not in ("default", "random"):
            raise ValueError("truth must be 'default' or 'random'")
        if not pty and tcp is False:
            raise ValueError("give pty=True or tcp")
        self.clock_name = clock
        self.target = target
        self.boot0 = bool(boot0)            # BOOT0 high: the ROM bootloader (stm32flash on the pty)
        self.elf = [str(e) for e in elf] if elf else []   # images the board may run (the first: factory)
        # no ceiling on the lockstep clock (the host's waits pace it); 20x real time on the wall clock
        self.speed = (0.0 if clock == "lockstep" else 20.0) if speed is None else speed
        self.seed = int(seed)
        self.truth = truth
        self.thermal = bool(thermal)
        self.pty_enabled = bool(pty)
        self.baud = int(baud)
        self.uid = uid
        self.startup_timeout = startup_timeout
        self.tcp_request: int | None = None if tcp is False else (0 if tcp is True else int(tcp))
        self.control_request = int(control_port)
        self._tmpdir = owned_tmpdir(TMP_PREFIX)
        self.flash = str(Path(flash).resolve()) if flash is not None else os.path.join(self._tmpdir, "flash.bin")
        self.log_path = os.path.join(self._tmpdir, "sim.log")
        self._binary = Path(binary) if binary is not None else None
        self.proc: subprocess.Popen | None = None
        self.info: dict[str, Any] = {}
        self.removed = False

    # ------------------------------------------------------------ where it is
    @property
    def binary(self) -> Path:
        if self._binary is None:
            self._binary = build_sim()
        return self._binary

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

    @property
    def log(self) -> str:
        """Everything the simulator wrote to stderr (all runs of this object)."""
        try:
            return Path(self.log_path).read_text(errors="replace")
        except OSError:
            return ""

    def log_tail(self, n: int = 30) -> str:
        try:
            lines = Path(self.log_path).read_text(errors="replace").splitlines()[-n:]
        except OSError:
            return ""
        return ("\n--- simulator log (" + self.log_path + "):\n" + "\n".join(lines)) if lines else ""

    # ------------------------------------------------------------ the process
    def command(self, tcp_port: int | None, control_port: int) -> list[str]:
        """The command line that starts this simulator."""
        prefix = [str(self.binary)] if self.target == "host" else arm_command(self.target)
        args = [*prefix, "--speed", repr(float(self.speed)), "--seed", str(self.seed),
                "--truth", self.truth, "--flash", self.flash, "--baud", str(self.baud),
                "--control", str(control_port)]
        if self.clock_name == "lockstep":
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
        if self.target == "host":
            args += ["--orphan-cleanup", self._tmpdir]      # a SIGKILLed host's folder goes with the sim
        return args

    def spawn(self, tcp_port: int | None, control_port: int, owner: Any) -> dict:
        """Start the process (in its own session) and read its start-up line into self.info;
        owner is kept in LIVE while it runs. On failure the process is killed."""
        if self.running:
            raise SimError("the virtual device is already running")
        args = self.command(tcp_port, control_port)
        log = open(self.log_path, "ab")
        try:
            log.write(f"--- {' '.join(args)}\n".encode())
            log.flush()
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                         stderr=log, start_new_session=True)
        finally:
            log.close()
        LIVE.add(owner)
        try:
            self.info = json.loads(self._read_startup_line())
        except BaseException:
            self.kill()
            raise
        return self.info

    def _read_startup_line(self) -> str:
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        buf = b""
        deadline = time.monotonic() + self.startup_timeout
        while b"\n" not in buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise SimError(f"the virtual device printed no start-up line within "
                               f"{self.startup_timeout:g} s{self.log_tail()}")
            r, _, _ = select.select([fd], [], [], min(left, 0.2))
            if r:
                chunk = os.read(fd, 4096)
                if not chunk:
                    code = self.proc.wait(timeout=5)
                    raise SimError(f"the virtual device exited at start-up (code {code})"
                                   f"{self.log_tail()}")
                buf += chunk
        line = buf.split(b"\n", 1)[0].decode()
        try:
            json.loads(line)
        except ValueError as e:
            raise SimError(f"bad start-up line from the virtual device: {line!r}") from e
        return line

    def end(self, timeout: float = 3.0) -> None:
        """Wait up to timeout for the process to exit (it was asked to quit), else kill it;
        always reaped."""
        if self.proc is None:
            return
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
        self.reap()

    def kill(self) -> None:
        """SIGTERM, then SIGKILL, its process group (its own session: the group id is its pid)."""
        proc = self.proc
        if proc is None:
            return
        for sig, wait in ((signal.SIGTERM, 2.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        self.reap()

    def reap(self) -> None:
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
        for owner in list(LIVE):
            if getattr(owner, "resource", None) is self:
                LIVE.discard(owner)

    def remove(self) -> None:
        """Delete the temporary directory (and the flash file if it lives there); once."""
        import shutil
        if not self.removed:
            self.removed = True
            shutil.rmtree(self._tmpdir, ignore_errors=True)
