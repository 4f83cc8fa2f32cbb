"""`imubench flash`: write the firmware image to a board (openocd, st-flash or stm32flash)."""
from __future__ import annotations

import tempfile
from pathlib import Path

from imubench.cli.common import existing_file, image_help


def register(sub) -> None:
    from imubench.device.flash import PROBE_ORDER, TARGET_CFG
    source, default, no_build = image_help()
    p = sub.add_parser("flash", help="write the firmware to a board (openocd, st-flash, stm32flash)",
                       description=f"{source} onto a board, then verify it (docs/firmware.md, Flashing).")
    p.add_argument("--board", choices=sorted(TARGET_CFG), required=True, help="which board")
    p.add_argument("--probe", choices=PROBE_ORDER,
                   help="programmer (default: the first of openocd, st-flash, stm32flash found)")
    p.add_argument("--port", metavar="DEV", help="serial device for --probe serial (e.g. /dev/ttyUSB0)")
    p.add_argument("--image", type=existing_file, metavar="FILE",
                   help=f"image to flash (default: {default})")
    p.add_argument("--no-build", action="store_true", help=no_build)
    p.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.device.flash import (
        PROBES,
        FlashError,
        _run,
        build_firmware,
        check_image_board,
        check_port,
        choose_probe,
        image_bytes,
        plan,
    )
    image = Path(a.image).resolve() if a.image else None
    probe = choose_probe(a.probe, need_tool=not a.dry_run)
    with tempfile.TemporaryDirectory(prefix="imubench-flash-") as tmp:
        if a.dry_run:
            p = plan(a.board, probe, image, a.port, Path(tmp))
            print(f"# {a.board} via {probe} ({PROBES[probe][2]}); image {p.image}"
                  + ("" if p.image.exists() else " (not built yet)"))
            for s in p.steps:
                print(s.shell())
                if s.verify_against is not None:
                    print(f"# then compare the read-back with {s.verify_against}")
            return 0
        if image is None and not a.no_build:
            build_firmware()
        p = plan(a.board, probe, image, a.port, Path(tmp))
        if not p.image.exists():
            from imubench.device import artifacts
            hint = "" if a.image or artifacts.installed() else "; run `make firmware`"
            raise FlashError(f"no image {p.image}{hint}", 2)
        tag = check_image_board(a.board, p.image)       # before anything is erased
        if probe == "serial":
            check_port(a.port)
        if tag is None:
            print(f"note: {p.image.name} carries no imubench board tag: its chip cannot be checked", flush=True)
        print(f"flashing {p.image} to the {a.board} via {probe} ({PROBES[probe][2]})", flush=True)
        for s in p.steps:
            _run(s, a.board)
        data = image_bytes(p.image)
        import hashlib
        print(f"image: build {tag['build'] if tag else 'unknown'}, {len(data)} bytes, "
              f"sha256 {hashlib.sha256(data).hexdigest()}", flush=True)
    if probe == "serial":
        _print_identity(a.port)
    print("done", flush=True)
    return 0


def _print_identity(port: str) -> None:
    """The booted board's identity, as `imubench info` prints it (the image runs on the same
    USART1 the bootloader used)."""
    import time

    from imubench.cli.stream import _print_info
    from imubench.device.flash import FlashError
    from imubench.device.link import Device, DeviceError, LinkError
    last = None
    for _ in range(3):
        time.sleep(0.5)
        try:
            with Device.open(port) as dev:
                _print_info(dev.info())
            return
        except (DeviceError, LinkError, OSError) as e:
            last = e
    raise FlashError(f"written, but the board did not answer on {port} after the start: {last}", 1)
