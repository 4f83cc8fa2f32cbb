"""The STM32 firmware under qemu-system-arm, as a device on a TCP port.

    with QemuBoard("f103") as q:                 # or "f4"; param_page=bytes to preload slot 0
        with Device.open(q.port_url) as dev:     # socket://127.0.0.1:PORT
            print(dev.info())

QemuBoard takes the QEMU images of the installed package (built with the wheel), or in the
source checkout builds them first (`make -s firmware`, which installs the ARM toolchain and
qemu-system-arm through `make system-deps` when run as root), then starts

    qemu-system-arm -M stm32vldiscovery|netduinoplus2 -nographic -display none -monitor none
        -serial tcp:127.0.0.1:PORT,server=on,wait=on,nodelay=on
        -kernel build/arm/qemu-f1|qemu-f4/imubench.elf
        [-device loader,file=PAGE,addr=SLOT0,force-raw=on]

USART1 is the TCP port. With wait=on QEMU does not start the guest before the first client
connects, so that client sees everything from the boot 0x00 and boot info on; nodelay=on
turns Nagle's algorithm off (QEMU writes the guest's bytes one by one; with Nagle and the
host's delayed ACK every reply would wait ~40 ms). After a client disconnects QEMU accepts
the next one; the guest keeps running. The process runs in its own process group and is
always killed and reaped on exit.

What QEMU 7.2 models and what the images do about it: docs/firmware.md.

    imubench qemu --board f103|f4 [--params PAGE.bin]     (main_qemu)
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from imubench.device import artifacts
from imubench.errors import ImubenchError

ROOT = artifacts.checkout_root()      # None when installed from a wheel
QEMU = "qemu-system-arm"

# board -> (QEMU machine, image directory under build/arm, parameter slot 0 address)
BOARDS = {
    "f103": ("stm32vldiscovery", "qemu-f1", 0x0801F800),
    "f4": ("netduinoplus2", "qemu-f4", 0x080C0000),
}
BOARD_ALIASES = {"f1": "f103", "qemu-f1": "f103", "f103": "f103", "f4": "f4", "qemu-f4": "f4"}


class QemuError(ImubenchError, RuntimeError):
    pass


_built = False


def build_firmware(force: bool = False) -> None:
    """`make -s firmware` once per process (installs the toolchain when missing and root)."""
    global _built
    if _built and not force:
        return
    if artifacts.installed():
        return                          # the package's images were built with the wheel
    if ROOT is None:
        raise QemuError(str(artifacts.not_found()))
    r = subprocess.run(["make", "-s", "-C", str(ROOT), "firmware"], capture_output=True, text=True)
    if r.returncode != 0:
        raise QemuError(f"`make firmware` failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}")
    _built = True


def image_path(board: str) -> Path:
    return artifacts.image_dir(BOARDS[board][1]) / "imubench.elf"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class QemuBoard:
    """One qemu-system-arm process running the board's QEMU image."""

    def __init__(self, board: str = "f103", param_page: bytes | None = None, *, build: bool = True,
                 elf: str | Path | None = None, param_addr: int | None = None,
                 extra_args: tuple[str, ...] = (), start_timeout: float = 10.0):
        if board not in BOARD_ALIASES:
            raise ValueError(f"unknown board {board!r}: f103 or f4")
        self.board = BOARD_ALIASES[board]
        self.machine, self.image_name, slot0 = BOARDS[self.board]
        self.param_page = param_page
        self.param_addr = slot0 if param_addr is None else param_addr
        self.build = build
        self.elf = Path(elf) if elf else image_path(self.board)
        self.extra_args = tuple(extra_args)
        self.start_timeout = start_timeout
        self.port: int | None = None
        self.proc: subprocess.Popen | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._log_path: Path | None = None

    @property
    def port_url(self) -> str:
        if self.port is None:
            raise QemuError("QEMU is not running")
        return f"socket://127.0.0.1:{self.port}"

    def command(self, port: int) -> list[str]:
        cmd = [QEMU, "-M", self.machine, "-nographic", "-display", "none", "-monitor", "none",
               "-serial", f"tcp:127.0.0.1:{port},server=on,wait=on,nodelay=on",
               "-kernel", str(self.elf)]
        if self.param_page is not None:
            page = Path(self._tmp.name) / "param_page.bin"
            page.write_bytes(self.param_page)
            cmd += ["-device", f"loader,file={page},addr=0x{self.param_addr:08X},force-raw=on"]
        return cmd + list(self.extra_args)

    def log(self) -> str:
        """QEMU's own stdout/stderr so far (not the guest's serial port)."""
        try:
            return self._log_path.read_text(errors="replace") if self._log_path else ""
        except OSError:
            return ""

    def start(self) -> "QemuBoard":
        if self.build:
            build_firmware()
        if shutil.which(QEMU) is None:
            raise QemuError(f"{QEMU} not found on PATH: run `make system-deps` as root "
                            "(or apt-get install qemu-system-arm)")
        if not self.elf.exists():
            raise QemuError(f"no firmware image {self.elf}: run `make firmware`")
        self._tmp = tempfile.TemporaryDirectory(prefix="imubench-qemu-")
        self._log_path = Path(self._tmp.name) / "qemu.log"
        last = ""
        for _attempt in range(3):  # the free port may be taken between probe and bind
            port = _free_port()
            with open(self._log_path, "wb") as log:
                self.proc = subprocess.Popen(self.command(port), stdin=subprocess.DEVNULL, stdout=log,
                                             stderr=subprocess.STDOUT, start_new_session=True)
            if self._wait_listening(port):
                self.port = port
                return self
            last = self.log()
            self._kill()
        self.close()
        raise QemuError(f"{QEMU} did not start listening:\n{last}")

    def _wait_listening(self, port: int) -> bool:
        """QEMU prints 'waiting for connection' once it listens (wait=on). Connecting to probe
        would consume the first connection, so watch the log and the process instead."""
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                return False
            if "waiting for connection" in self.log():
                return True
            time.sleep(0.01)
        return False

    def _kill(self) -> None:
        p, self.proc = self.proc, None
        if p is None:
            return
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                p.wait(timeout=3)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(timeout=5)
        else:
            p.wait()

    def close(self) -> None:
        self._kill()
        self.port = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def __enter__(self) -> "QemuBoard":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # last resort: never leave a QEMU behind
        try:
            self._kill()
        except Exception:  # noqa: BLE001
            pass
