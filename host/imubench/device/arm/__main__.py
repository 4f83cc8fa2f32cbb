"""`python -m imubench.device.arm --target f103|f4 [options]`: the exact STM32 image under the
emulator, serving the virtual device's serial endpoint (socket://) and control channel.
Options and the start-up line are those of imubench-sim (firmware/boards/sim/sim_main.c), so
VirtualBench(target="f103") starts it the way it starts the host build:

    --tcp PORT --control PORT --flash FILE --speed X --seed N --truth default|random
    --uid HEX24 --baud B (the image sets its own baud rate: only 2000000 is accepted)
    --elf FILE (default: the image imubench.device.artifacts finds: the package's or build/arm's)  --no-hse (the crystal does not start)

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m imubench.device.arm",
                                 description="the exact STM32 image against the virtual device's sensor models")
    ap.add_argument("--target", choices=sorted(TARGETS), required=True)
    ap.add_argument("--elf")
    ap.add_argument("--tcp", type=int, default=0)
    ap.add_argument("--control", type=int, default=0)
    ap.add_argument("--flash")
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--truth", choices=("default", "random"), default="default")
    ap.add_argument("--uid")
    ap.add_argument("--baud", type=int, default=2000000)
    ap.add_argument("--pty", action="store_true")
    ap.add_argument("--no-hse", action="store_true")
    a = ap.parse_args(argv)
    if a.pty:
        ap.error("--pty is not supported for the ARM targets: use the TCP endpoint (socket://)")
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
    target = TARGETS[a.target]
    try:   # nothing is built here: VirtualBench (arm_command) built it before starting this process
        elf = Path(a.elf) if a.elf else artifacts.arm_image(target.image, build=False)
        lib_file = artifacts.models_library(build=False)
    except artifacts.ArtifactError as e:
        print(f"imubench-arm: {e}", file=sys.stderr)
        return 2
    map_path = elf.with_suffix(".map")
    if not elf.is_file():
        print(f"imubench-arm: {elf} is missing: build the images with `make firmware`", file=sys.stderr)
        return 2
    try:
        lib = load(lib_file)
    except SimLibError as e:
        print(f"imubench-arm: {e}", file=sys.stderr)
        return 2
    tmpdir = None
    flash = a.flash
    if flash is None:
        tmpdir = tempfile.mkdtemp(prefix="imubench-arm-")
        flash = os.path.join(tmpdir, "flash.bin")

    if lib.simlib_open(a.seed, 1 if a.truth == "random" else 0, uid, a.tcp, a.control, a.speed) != 0:
        print("imubench-arm: cannot open the serial endpoint / control channel", file=sys.stderr)
        return 1

    from .machine import Machine, Server
    try:
        machine = Machine(target, str(elf), str(map_path) if map_path.is_file() else None, lib, flash,
                          seed=a.seed, hse=not a.no_hse)
    except (ValueError, KeyError, OSError) as e:
        print(f"imubench-arm: {e}", file=sys.stderr)
        return 2
    server = Server(machine, lib, a.speed)
    uidb = (ctypes.c_uint8 * 12)()
    lib.simlib_uid(uidb)
    port = lib.simlib_tcp_port()
    ctl = lib.simlib_control_port()
    line = {"pty": None, "port_url": f"socket://127.0.0.1:{port}", "tcp_port": port,
            "control": f"127.0.0.1:{ctl}", "control_port": ctl, "pid": os.getpid(),
            "flash": os.path.realpath(flash), "seed": a.seed, "speed": a.speed, "baud": a.baud,
            "truth": a.truth, "uid": bytes(uidb).hex(), "build": f"arm-{a.target}",
            "target": a.target, "elf": str(elf), "cpi": target.cpi}
    print(json.dumps(line), flush=True)

    stop = {"sig": 0}

    def on_signal(sig, frame):
        stop["sig"] = sig
    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, on_signal)
    parent = os.getppid()

    def should_stop() -> bool:
        return bool(stop["sig"]) or (parent != 1 and os.getppid() != parent)
    try:
        server.serve(should_stop)
    finally:
        machine.flash.close()
        lib.simlib_close()
        if tmpdir is not None:
            try:
                os.unlink(flash)
                os.rmdir(tmpdir)
            except OSError:
                pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
