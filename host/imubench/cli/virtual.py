"""`imubench sim`, `qemu` and `fake`: stand up a device without hardware, until Ctrl-C.

    sim    the firmware core built for Linux with the register-level sensor models
    qemu   the real STM32 image under qemu-system-arm (no sensor answers there)
    fake   the small Python stand-in the host-link tests use
"""
from __future__ import annotations

import contextlib
import shlex
import signal
import threading
import time

from imubench.cli.common import (
    CommandError,
    UsageError,
    add_sim_parts,
    add_target,
    baud,
    existing_file,
    image_help,
    new_file,
    non_negative_float,
)


def register(sub) -> None:
    p = sub.add_parser("sim", help="run the virtual device (firmware core + sensor models)",
                       description="Run the virtual device (the firmware core and drivers built for Linux, with "
                                   "register-level ADXL355/ADXRS450 models) on a TCP port and/or a pty, until "
                                   "Ctrl-C. Its JSON-lines control channel drives the virtual bench.")
    p.add_argument("--speed", type=non_negative_float, default=1.0,
                   help="device time per wall-clock time (1 = real time, 0 = as fast as it goes)")
    p.add_argument("--seed", type=int, default=1, help="seed of the sensor models")
    p.add_argument("--clock", choices=("realtime", "lockstep"), default="realtime",
                   help="realtime (the default here: another program connects, and nobody grants time): device "
                        "time runs against the wall clock and bytes not read in time are dropped; lockstep: "
                        "frozen until a client grants device time with the control command run "
                        "(docs/simulator.md)")
    p.add_argument("--truth", choices=("default", "random"), default="default",
                   help="ideal parts, or random errors drawn from the seed")
    p.add_argument("--flash", type=new_file, metavar="FILE",
                   help="parameter flash file, kept between runs (default: a temporary file, removed at exit)")
    p.add_argument("--pty", action="store_true", help="expose the link on a pseudo-terminal")
    add_sim_parts(p, "--parts", "--sim-parts")
    p.add_argument("--tcp", type=int, default=None, metavar="PORT",
                   help="expose the link on TCP 127.0.0.1:PORT (0 = a free port; the default without --pty)")
    p.add_argument("--control", type=int, default=0, metavar="PORT", help="control channel port (0 = a free port)")
    p.add_argument("--baud", type=baud, default=2000000, help="link speed the device reports")
    p.add_argument("--thermal-lag", action="store_true",
                   help="switch the dies' thermal model on: each sensor's die lags the chamber with its own "
                        "time constant (minutes) and warms by its own self-heating after power-up "
                        "(control channel set_thermal; docs/simulator.md). Off: every die is at the chamber")
    p.add_argument("--boot0", action="store_true",
                   help="(--target f103|f4) BOOT0 high: start in the STM32 ROM bootloader (AN3155) for "
                        "stm32flash / imubench flash --probe serial on the --pty; without it the board boots "
                        "what its flash holds (FILE.code next to --flash)")
    add_target(p)
    p.set_defaults(run=run_sim)

    from imubench.device.qemu import BOARDS
    p = sub.add_parser("qemu", help="run the real STM32 firmware image under qemu-system-arm",
                       description="Run a firmware image under qemu-system-arm on a TCP port until Ctrl-C "
                                   "(no sensor answers on its SPI bus there: docs/firmware.md).")
    p.add_argument("--board", choices=sorted(BOARDS), default="f103", help="which image")
    p.add_argument("--params", type=existing_file, metavar="PAGE",
                   help="parameter page to preload into slot 0 (imubench param-page writes one)")
    p.add_argument("--no-build", action="store_true", help=image_help()[2])
    p.set_defaults(run=run_qemu)

    p = sub.add_parser("fake", help="run the Python fake device on a pseudo-terminal",
                       description="A Python emulation of the protocol with a synthetic still board, on a pty.")
    p.add_argument("--seed", type=int, default=1, help="random seed of the synthetic samples")
    p.add_argument("--speed", type=non_negative_float, default=1.0, help="device time per wall-clock time")
    p.set_defaults(run=run_fake)

    p = sub.add_parser("param-page", help="build a parameter flash page (for QEMU or a factory image)",
                       description="Write the parameter-store record (docs/firmware.md) the firmware would write, "
                                   "byte for byte, into a flash page image.")
    from imubench.wire.paramstore import LAYOUTS
    p.add_argument("--layout", choices=sorted(LAYOUTS), required=True, help="board flash layout")
    p.add_argument("--params", type=existing_file, metavar="FILE",
                   help="parameters as JSON (Params fields); default: identity (factory) parameters")
    p.add_argument("--generation", type=int, default=1, help="record generation (newer wins)")
    p.add_argument("--cleared", action="store_true", help="a factory-reset record instead of parameters")
    p.add_argument("--fill", type=lambda s: int(s, 0), default=0xFF, help="byte value after the record")
    p.add_argument("-o", "--output", type=new_file, required=True, metavar="PAGE", help="the page image to write")
    p.set_defaults(run=run_param_page)


@contextlib.contextmanager
def _ctrl_c_stops():
    """Ctrl-C is how a serving command stops (exit 0), also while it is still printing where it
    listens, before _until_stopped has its own handler."""
    try:
        yield
    except KeyboardInterrupt:
        pass


def _until_stopped(alive, what: str) -> int:
    """Sleep until Ctrl-C or SIGTERM (0), or until alive() turns false (an error)."""
    stop = {"now": False}

    def on_signal(*_):
        stop["now"] = True

    old = []
    if threading.current_thread() is threading.main_thread():
        old = [(s, signal.signal(s, on_signal)) for s in (signal.SIGINT, signal.SIGTERM)]
    try:
        while not stop["now"]:
            if not alive():
                raise CommandError(f"{what} exited", "rerun with --debug, or see its log")
            time.sleep(0.2)
    finally:
        for s, h in old:
            signal.signal(s, h)
    return 0


def run_sim(a) -> int:
    from imubench.device.sim import VirtualBench
    tcp: bool | int = a.tcp if a.tcp is not None else (False if a.pty else True)
    if a.target != "host":
        if a.baud != 2000000:
            raise UsageError(f"--baud cannot change the {a.target} image's baud rate (2000000)",
                             "leave --baud out")
    elif a.boot0:
        raise UsageError("--boot0 is a setting of the STM32 boards", "give --target f103 or --target f4")
    with VirtualBench(speed=a.speed, seed=a.seed, truth=a.truth, flash=a.flash, pty=a.pty,
                      baud=a.baud, tcp=tcp, control_port=a.control, target=a.target, boot0=a.boot0,
                      thermal=a.thermal_lag, clock=a.clock, parts=a.sim_parts) as bench, _ctrl_c_stops():
        return _serve_sim(a, bench)
    return 0


def _serve_sim(a, bench) -> int:
    """Say where the started virtual device listens, then serve until Ctrl-C."""
    what = ("firmware core + sensor models" if a.target == "host" else
            f"the exact {a.target} image under the ARM emulator + sensor models")
    print(f"virtual device ({what}, speed {a.speed:g}) on {bench.port_url}", flush=True)
    if a.boot0:
        pid = bench.info.get("bootloader", {}).get("product_id", "?")
        print(f"BOOT0 high: the ROM bootloader (product ID {pid}) waits on {bench.port_url}; "
              f"flash it: imubench flash --board {a.target} --probe serial --port {bench.port_url}", flush=True)
        print("  (AN3155 frames are 8E1; a pty carries no parity, so imubench flash gives stm32flash -m 8n1 "
              "there)", flush=True)
    if a.thermal_lag:
        th = bench.status()["thermal"]
        from imubench.wire.board_parts import BoardParts
        from imubench.wire.ids import SLOT_NAMES
        chosen = dict(x.split("=", 1) for x in (bench.parts or "").split(",") if "=" in x)   # --sim-parts
        parts = BoardParts.of([chosen.get(s) for s in SLOT_NAMES])
        print(f"thermal model on (dies: {parts.accel.name}, gyro X, Y, Z {parts.gyro_words}): time constants "
              + ", ".join(f"{t / 60:.1f}" for t in th["tau_s"]) + " min, self-heating "
              + ", ".join(f"{c:.1f}" for c in th["self_heat_c"]) + " °C", flush=True)
    if bench.pty and bench.pty != bench.port_url:
        print(f"  also on the pseudo-terminal {bench.pty}", flush=True)
    host, port = bench.control_address
    print(f"control channel (JSON lines): {host}:{port}", flush=True)
    print(f"flash file: {bench.flash}", flush=True)
    print(f"try: IMUBENCH_PORT={bench.port_url} imubench monitor"
          + (" (once flashed: Go starts the image)" if a.boot0 else ""), flush=True)
    try:
        return _until_stopped(lambda: bench.running, "the virtual device")
    except CommandError as e:
        last = (bench.log.strip().splitlines() or ["no log"])[-1]
        raise CommandError(f"the virtual device exited ({last})", f"see its log {bench.log_path}") from e


def run_qemu(a) -> int:
    from imubench.device.qemu import ROOT, QemuBoard
    from imubench.files import MAX_IMAGE_BYTES, read_bytes
    page = read_bytes(a.params, MAX_IMAGE_BYTES, "the parameter page") if a.params else None
    with QemuBoard(a.board, page, build=not a.no_build) as q, _ctrl_c_stops():
        print(f"QEMU {q.machine} running {q.elf.relative_to(ROOT) if ROOT and q.elf.is_relative_to(ROOT) else q.elf}",
              flush=True)
        print(f"device on {q.port_url}  (the guest starts when the first client connects)", flush=True)
        print(f"try: imubench info --port {shlex.quote(q.port_url)}; Ctrl-C to stop", flush=True)
        try:
            return _until_stopped(q.alive, "QEMU")
        except CommandError as e:
            last = (q.log().strip().splitlines() or ["no output"])[-1]
            raise CommandError(f"QEMU exited ({last})", "rerun with --debug") from e
    return 0


def run_fake(a) -> int:
    from imubench.device.fake import FakeDevice
    with FakeDevice(seed=a.seed, speed=a.speed) as f, _ctrl_c_stops():
        print(f"fake device (Python emulation, synthetic still board) on {f.port_url}", flush=True)
        print(f"try: IMUBENCH_PORT={f.port_url} imubench monitor", flush=True)
        return _until_stopped(lambda: True, "the fake device")
    return 0


def run_param_page(a) -> int:
    import json

    from imubench.files import read_text, write_bytes
    from imubench.wire import params as PR
    from imubench.wire.paramstore import (
        LAYOUTS,
        cleared_record,
        params_record,
        slot_image,
    )
    lay = LAYOUTS[a.layout]
    if a.cleared:
        rec = cleared_record(generation=a.generation, program_unit=lay.program_unit)
    else:
        try:
            fields = json.loads(read_text(a.params, what="the parameter file", errors="replace")) if a.params else {}
        except ValueError as e:
            raise CommandError(f"{a.params} is not JSON ({e})", "give a JSON object of Params fields") from None
        params = PR.from_json(fields, partial=True)
        PR.validate(params)                      # what the device would refuse never reaches a page
        rec = params_record(params, generation=a.generation, program_unit=lay.program_unit)
    write_bytes(a.output, slot_image(rec, lay.slot_size, a.fill))
    print(f"{a.output}: {len(rec)}-byte record in a {lay.slot_size}-byte slot; load it at "
          f"0x{lay.slots[0]:08X} (slot 0) or 0x{lay.slots[1]:08X} (slot 1)")
    return 0
