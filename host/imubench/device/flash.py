"""Flash the STM32 firmware onto a board.

    imubench flash --board f103|f4 [--probe openocd|stlink|serial] [--port DEV] [--image PATH]
                   [--no-build] [--dry-run]

The image is build/arm/<board>/imubench.{elf,bin,hex}, built first with `make -s firmware`
(unless --image or --no-build is given). Probes and the exact commands run:

  openocd   ST-LINK through OpenOCD (Debian package openocd); programs, verifies, resets:
              openocd -f interface/stlink.cfg -f target/stm32f1x.cfg (stm32f4x.cfg)
                      -c "program <elf> verify reset exit"
  stlink    stlink-tools' st-flash (Debian package stlink-tools):
              st-flash --reset write <bin> 0x08000000
              st-flash read <tmp> 0x08000000 <size>      then compared with <bin> here
              st-flash reset                              (run the new firmware)
  serial    the STM32 ROM bootloader on USART1 (PA9/PA10; BOOT0 high, reset), with
            stm32flash (Debian package stm32flash); needs --port:
              stm32flash -w <hex> -v -g 0x0 <port>

Without --probe, the first probe whose tool is on PATH is used (openocd, st-flash,
stm32flash). --dry-run prints the commands without running anything (with --probe it does
not need the tool installed). Exit status: 0 done,
1 a tool failed or the verify found a difference (the tool's output is shown), 2 usage
error, missing tool or missing image.
"""
from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from imubench.errors import ImubenchError
from imubench.files import MAX_IMAGE_BYTES, read_bytes

ROOT = Path(__file__).resolve().parents[3]
FLASH_BASE = 0x08000000

TARGET_CFG = {"f103": "target/stm32f1x.cfg", "f4": "target/stm32f4x.cfg"}

# probe -> (tool executable, Debian package, what it is)
PROBES = {
    "openocd": ("openocd", "openocd", "ST-LINK (or another SWD adapter) through OpenOCD"),
    "stlink": ("st-flash", "stlink-tools", "ST-LINK with stlink-tools' st-flash"),
    "serial": ("stm32flash", "stm32flash", "the STM32 ROM bootloader on USART1"),
}
PROBE_ORDER = ("openocd", "stlink", "serial")


class FlashError(ImubenchError):
    def __init__(self, msg: str, code: int = 1):
        super().__init__(msg)
        self.code = code


@dataclass
class Step:
    argv: list[str]
    verify_against: Path | None = None   # st-flash read: compare this file with the read-back
    readback: Path | None = None

    def shell(self) -> str:
        return " ".join(shlex.quote(a) for a in self.argv)


@dataclass
class Plan:
    probe: str
    image: Path
    steps: list[Step] = field(default_factory=list)


def image_paths(board: str, root: Path = ROOT) -> dict[str, Path]:
    d = root / "build" / "arm" / board
    return {ext: d / f"imubench.{ext}" for ext in ("elf", "bin", "hex")}


def choose_probe(requested: str | None, need_tool: bool = True) -> str:
    if requested:
        tool, pkg, what = PROBES[requested]
        if need_tool and shutil.which(tool) is None:
            raise FlashError(f"--probe {requested} needs {tool} ({what}), which is not on PATH; "
                             f"install it: sudo apt-get install {pkg}", 1)
        return requested
    for p in PROBE_ORDER:
        if shutil.which(PROBES[p][0]):
            return p
    raise FlashError("no flashing tool found on PATH (looked for openocd, st-flash, stm32flash); install one: "
                     + ", ".join(f"sudo apt-get install {PROBES[p][1]} ({PROBES[p][2]})" for p in PROBE_ORDER), 1)


def _tcl_path(p: Path) -> str:
    s = str(p)
    return "{" + s + "}" if any(c in s for c in " \t\"{}[]$;\\") else s


def plan(board: str, probe: str, image: Path | None, port: str | None, tmpdir: Path) -> Plan:
    paths = image_paths(board)
    if probe == "openocd":
        img = image or paths["elf"]
        prog = f"program {_tcl_path(img)}"
        if img.suffix == ".bin":
            prog += f" 0x{FLASH_BASE:08X}"
        return Plan(probe, img, [Step(["openocd", "-f", "interface/stlink.cfg", "-f", TARGET_CFG[board],
                                       "-c", f"{prog} verify reset exit"])])
    if probe == "stlink":
        img = image or paths["bin"]
        if img.suffix in (".elf", ".hex"):
            raise FlashError(f"st-flash writes raw binaries: give a .bin image, not {img.name}", 2)
        size = img.stat().st_size if img.exists() else 0
        back = tmpdir / "readback.bin"
        return Plan(probe, img, [
            Step(["st-flash", "--reset", "write", str(img), f"0x{FLASH_BASE:08x}"]),
            Step(["st-flash", "read", str(back), f"0x{FLASH_BASE:08x}", f"0x{size:x}"],
                 verify_against=img, readback=back),
            Step(["st-flash", "reset"]),
        ])
    if probe == "serial":
        if not port:
            raise FlashError("--probe serial needs --port DEV (the USB-serial adapter on USART1 PA9/PA10, "
                             "e.g. /dev/ttyUSB0); put the board in its bootloader first (BOOT0 = 1, reset)", 2)
        img = image or paths["hex"]
        return Plan(probe, img, [Step(["stm32flash", "-w", str(img), "-v", "-g", "0x0", port])])
    raise FlashError(f"unknown probe {probe}", 2)


def _run(step: Step) -> None:
    print(f"$ {step.shell()}", flush=True)
    try:
        p = subprocess.Popen(step.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             errors="replace")
    except OSError as e:
        raise FlashError(f"cannot run {step.argv[0]}: {e}", 2) from e
    out = []
    for line in p.stdout:
        out.append(line)
        sys.stdout.write(line)
        sys.stdout.flush()
    rc = p.wait()
    if rc != 0:
        raise FlashError(f"{step.argv[0]} failed (exit {rc})" + ("; its output is above" if out else
                                                                  " and printed nothing")
                         + "; check the probe's cable, the board's power and BOOT0", 1)
    if step.verify_against is not None:
        want = read_bytes(step.verify_against, MAX_IMAGE_BYTES, "the image")
        try:
            got = read_bytes(step.readback, MAX_IMAGE_BYTES, "the read-back")
        except OSError as e:
            raise FlashError(f"verify failed: {step.argv[0]} read produced no file ({e})", 1) from e
        if got[:len(want)] != want or len(got) < len(want):
            n = min(len(got), len(want))
            first = next((i for i in range(n) if got[i] != want[i]), n)
            raise FlashError(f"verify failed: flash differs from {step.verify_against} at offset 0x{first:X} "
                             f"(address 0x{FLASH_BASE + first:08X}); read {len(got)} of {len(want)} bytes", 1)
        print(f"verified: {len(want)} bytes at 0x{FLASH_BASE:08X} match {step.verify_against.name}", flush=True)


def build_firmware() -> None:
    r = subprocess.run(["make", "-s", "-C", str(ROOT), "firmware"], capture_output=True, text=True)
    if r.returncode != 0:
        last = (r.stderr.strip() or r.stdout.strip() or "no output").splitlines()[-1]
        raise FlashError(f"`make firmware` failed ({last}); run `make firmware` in {ROOT} to see the whole output", 1)
    sys.stdout.write(r.stdout)
