"""`python -m imubench.device.arm --target f103|f4 [options]`: the exact STM32 image under the
emulator, serving the virtual device's serial endpoint (socket://) and control channel.
Options and the start-up line are those of imubench-sim (firmware/boards/sim/sim_main.c), so
VirtualBench(target="f103") starts it the way it starts the host build:

    --tcp PORT --control PORT --flash FILE --speed X --seed N --truth default|random
    --uid HEX24 --baud B (the image sets its own baud rate: only 2000000 is accepted)
    --elf FILE (default: the image imubench.device.artifacts finds, the package's or build/arm's;
               repeatable: every ELF given is an image
               the board can run, see below)  --no-hse (the crystal does not start)
    --pty      the serial port on a pseudo-terminal (its path in the start-up line's "pty")
    --boot0    BOOT0 high: the board starts in the STM32 ROM bootloader on USART1 (AN3155,
               bootloader.py), for stm32flash on the pty; Go starts the image written, and
               every reset (power cut, reboot) enters the bootloader again

The flash: the parameter pages are FILE (--flash), the code pages FILE.code. A board whose
FILE.code does not exist yet holds the first --elf image (as if programmed at the factory);
once FILE.code exists (the bootloader wrote it) a reset with BOOT0 low boots whatever it
holds, run as the --elf image whose code it matches; a blank, half-written or unknown image
does not run (the core stays in reset, as a hard-faulting board would: reflash it).

It exits on SIGTERM/SIGINT/SIGHUP, on the control command "quit" and when its parent dies.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import signal
import sys
import tempfile
from pathlib import Path

from imubench.device import artifacts

from .simlib import SimLibError, load
from .targets import TARGETS


def _parse_args(argv: list[str] | None) -> tuple[argparse.Namespace, bytes | None]:
    """The options, checked (argparse's error and exit 2 on a bad one), and the UID given."""
    ap = argparse.ArgumentParser(prog="python -m imubench.device.arm",
                                 description="the exact STM32 image against the virtual device's sensor models")
    ap.add_argument("--target", choices=sorted(TARGETS), required=True)
    ap.add_argument("--elf", action="append")
    ap.add_argument("--boot0", action="store_true")
    ap.add_argument("--tcp", type=int, default=0)
    ap.add_argument("--control", type=int, default=0)
    ap.add_argument("--flash")
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--clock", choices=("realtime", "lockstep"), default="realtime")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--truth", choices=("default", "random"), default="default")
    ap.add_argument("--uid")
    ap.add_argument("--baud", type=int, default=2000000)
    ap.add_argument("--pty", action="store_true")
    ap.add_argument("--no-hse", action="store_true")
    ap.add_argument("--parts", default="", help="the board's parts, e.g. accel=adxl359,gyro_z=adxrs453")
    a = ap.parse_args(argv)
    if a.baud != 2000000:
        ap.error("the image configures its own baud rate (2000000): --baud cannot change it")
    if not (0 <= a.speed <= 1e6):
        ap.error("--speed must be in 0 .. 1e6")
    uid = None
    if a.uid is not None:
        try:
            uid = bytes.fromhex(a.uid)
        except ValueError:
            uid = b""
        if len(uid) != 12:
            ap.error("--uid must be 24 hex digits")
    return a, uid


def _startup_line(a, lib, target, elf, flash: str, code_file: str, uid: bytes) -> dict:
    """The start-up line imubench-sim prints (VirtualBench reads it): endpoints, pid, files."""
    port = lib.simlib_tcp_port()
    ctl = lib.simlib_control_port()
    pty_name = lib.simlib_pty_name().decode() or None
    line = {"pty": pty_name, "port_url": f"socket://127.0.0.1:{port}" if port >= 0 else pty_name,
            "tcp_port": port if port >= 0 else None,
            "control": f"127.0.0.1:{ctl}", "control_port": ctl, "pid": os.getpid(),
            "flash": os.path.realpath(flash), "seed": a.seed, "speed": a.speed, "clock": a.clock, "baud": a.baud,
            "truth": a.truth, "uid": uid.hex(), "build": f"arm-{a.target}",
            "target": a.target, "elf": str(elf), "cpi": target.cpi, "boot0": a.boot0,
            "code_flash": os.path.realpath(code_file) if os.path.exists(code_file) else None}
    if a.boot0:
        line["bootloader"] = {"framing": "8E1 (AN3155; a pty cannot show parity)",
                              "product_id": "0x%03X" % (0x410 if a.target == "f103" else 0x413)}
    return line


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _stop_on_signal_or_orphan():
    """should_stop(): true after SIGTERM, SIGINT or SIGHUP, or once the parent process died."""
    stop = {"sig": 0}

    def on_signal(sig, frame):
        stop["sig"] = sig
    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, on_signal)
    parent = os.getppid()

    def should_stop() -> bool:
        return bool(stop["sig"]) or (parent != 1 and os.getppid() != parent)
    return should_stop


def _remove_temporary_flash(tmpdir: str, files: list[str]) -> None:
    try:
        for f in files:
            if os.path.exists(f):
                os.unlink(f)
        os.rmdir(tmpdir)
    except OSError:
        pass


class _StartError(Exception):
    """What keeps the emulator from starting (printed, exit 2)."""


def _artifacts(a, target) -> tuple:
    """(the models library loaded, the default ELF or None, the ELFs the board can run). Nothing
    is built here: VirtualBench (arm_command) built it before starting this process."""
    try:
        lib_file = artifacts.models_library(build=False)
    except artifacts.ArtifactError as e:
        raise _StartError(e) from None
    try:
        default_elf = artifacts.arm_image(target.image, build=False)
    except artifacts.ArtifactError as e:
        if not a.elf:
            raise _StartError(e) from None
        default_elf = None          # --elf names the images the board can run
    elfs = [Path(e) for e in a.elf] if a.elf else [default_elf]
    if not elfs[0].is_file():
        raise _StartError(f"{elfs[0]} is missing: build the images with `make firmware`")
    try:
        return load(lib_file), default_elf, elfs
    except SimLibError as e:
        raise _StartError(e) from None


def main(argv: list[str] | None = None) -> int:
    a, uid = _parse_args(argv)
    target = TARGETS[a.target]
    try:
        lib, default_elf, elfs = _artifacts(a, target)
    except _StartError as e:
        print(f"imubench-arm: {e}", file=sys.stderr)
        return 2
    elf = elfs[0]
    tmpdir = None
    flash = a.flash
    if flash is None:
        tmpdir = tempfile.mkdtemp(prefix="imubench-arm-")
        flash = os.path.join(tmpdir, "flash.bin")

    lib.simlib_set_pty(1 if a.pty else 0)
    lib.simlib_set_identity_target(a.target.encode())   # the seed names a board of this target
    err = ctypes.create_string_buffer(160)
    if lib.simlib_set_parts(a.parts.encode(), err, len(err)) != 0:
        print(f"imubench-arm: --parts {err.value.decode()}", file=sys.stderr)
        return 2
    tcp = a.tcp if not a.pty or a.tcp else -1     # --pty alone: no TCP endpoint
    if lib.simlib_open(a.seed, 1 if a.truth == "random" else 0, uid, tcp, a.control, a.speed) != 0:
        print("imubench-arm: cannot open the serial endpoint / control channel", file=sys.stderr)
        return 1
    lib.simlib_set_lockstep(1 if a.clock == "lockstep" else 0)

    from .bootloader import BootloaderServer, FlashFile, RomBootloader, code_path, open_code
    from .image import flash_segments, match_elf
    from .machine import Machine
    from .serve import Server

    code_file = code_path(flash)
    candidates = [str(e) for e in elfs if e.is_file()]
    if default_elf is not None and default_elf.is_file() and str(default_elf) not in candidates:
        candidates.append(str(default_elf))
    if a.boot0 and not os.path.exists(code_file):
        # the board comes with the first image in its code pages (factory-programmed)
        try:
            code = open_code(flash, target)
            for addr, data in flash_segments(str(elf), target):
                code.write(addr - target.flash_base, data)
        except (OSError, ValueError) as e:
            print(f"imubench-arm: {e}", file=sys.stderr)
            return 2

    def new_machine(elf_path: str, t0: float) -> Machine:
        mp = Path(elf_path).with_suffix(".map")
        return Machine(target, elf_path, str(mp) if mp.is_file() else None, lib, flash, seed=a.seed,
                       hse=not a.no_hse, t0=t0, boot0=a.boot0)

    def boot_elf() -> str | None:
        """The image the code pages hold (None: nothing the emulator can run)."""
        if not os.path.exists(code_file):
            return str(elf)
        with open(code_file, "rb") as f:
            code = f.read()
        return match_elf(code, candidates, target)

    try:
        first = None if a.boot0 else boot_elf()
        if not a.boot0 and first is None:
            print(f"imubench-arm: the code pages ({code_file}) hold no image the emulator knows "
                  f"(blank, half written, or not one of --elf): start it with --boot0 and flash it",
                  file=sys.stderr)
            return 2
        machine = new_machine(first, 0.0) if first else None
    except (ValueError, KeyError, OSError) as e:
        print(f"imubench-arm: {e}", file=sys.stderr)
        return 2
    uidb = (ctypes.c_uint8 * 12)()
    lib.simlib_uid(uidb)
    print(json.dumps(_startup_line(a, lib, target, elf, flash, code_file, bytes(uidb))), flush=True)


    should_stop = _stop_on_signal_or_orphan()
    rom = None
    t_dev = 0.0
    try:
        while not should_stop():
            if machine is None:
                if rom is None:
                    rom = RomBootloader(target, open_code(flash, target),
                                        FlashFile(flash, target.param_size), bytes(uidb), lib, _log)
                else:
                    rom.code = open_code(flash, target)
                    rom.params = FlashFile(flash, target.param_size)
                    rom.reset()
                _log(f"[imubench-arm {a.target}] ROM bootloader (BOOT0 high): waiting for 0x7F")
                bl = BootloaderServer(rom, lib, a.speed, t_dev, _log)
                act = bl.serve(should_stop)
                t_dev = bl.now()
                if act[0] == "stop":
                    break
                if act[0] == "reset":
                    continue                   # BOOT0 still high: the bootloader again
                image = boot_elf()
                if image is None:
                    _log(f"[imubench-arm {a.target}] Go 0x{act[1]:08X}: the code pages hold no image the "
                        "emulator knows (blank, half written or not one of --elf): the core does not run; "
                        "reset (power cut) into the bootloader and flash it again")
                    continue
                _log(f"[imubench-arm {a.target}] Go 0x{act[1]:08X}: starting {image}")
                machine = new_machine(image, t_dev)
            server = Server(machine, lib, a.speed, lockstep=a.clock == "lockstep")
            server.serve(should_stop)
            t_dev = machine.now()
            machine.flash.close()
            if not machine.exit_to_rom:
                machine = None
                break
            machine = None
    finally:
        # why it ended, as the host build logs it (sim_main.c)
        why = "signal or parent gone" if should_stop() else "quit" if lib.simlib_quit() else "stopped"
        _log(f"[imubench-arm {a.target}] exiting ({why})")
        if machine is not None:
            machine.flash.close()
        lib.simlib_close()
        if tmpdir is not None:
            _remove_temporary_flash(tmpdir, [flash, code_path(flash)])
    return 0


if __name__ == "__main__":
    sys.exit(main())
