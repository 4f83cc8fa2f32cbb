"""Flash the STM32 firmware onto a board.

    imubench flash --board f103|f4 [--probe openocd|stlink|serial] [--port DEV] [--image PATH]
                   [--no-build] [--dry-run]

The image is the board's imubench.{elf,bin,hex} that imubench.device.artifacts finds: the
installed package's (built with the wheel, nothing to build), or the checkout's
build/arm/<board>/, built first with `make -s firmware` (unless --image or --no-build is
given). Probes and the exact commands run:

  openocd   ST-LINK through OpenOCD (Debian package openocd); programs, verifies, resets:
              openocd -f interface/stlink.cfg -f target/stm32f1x.cfg (stm32f4x.cfg)
                      -c "program <elf> verify reset exit"
  stlink    stlink-tools' st-flash (Debian package stlink-tools):
              st-flash --reset write <bin> 0x08000000
              st-flash read <tmp> 0x08000000 <size>      then compared with <bin> here
              st-flash reset                              (run the new firmware)
  serial    the STM32 ROM bootloader on USART1 (PA9/PA10; BOOT0 high, reset), with
            stm32flash (Debian package stm32flash); needs --port:
              stm32flash <port>                        reads the bootloader's product ID
              stm32flash -S 0x08000000:<n> -w <hex|bin> -v -g 0x08000000 <port>
            -S with the image's length makes stm32flash erase only the pages/sectors the image
            covers (page by page), whatever the file's kind; without it stm32flash 0.7 erases
            the pages a .bin covers too, but sends a global erase (the parameter pages too)
            for an image on stdin or one as large as the flash (docs/firmware.md). On a pseudo-terminal (the emulated board, /dev/pts/N) "-m 8n1" is
            added: Linux ptys clear PARENB, and stm32flash refuses a port that does not keep
            the 8E1 it set; a real USB-serial adapter gets stm32flash's 8E1.

Before anything is erased the image's own board tag (ib_image_tag, "imubench-image
board=stm32f103 build=...") must name --board, and for the serial probe the bootloader's
product ID (0x410 F103, 0x413 F4) too. After the write: the image's build id and SHA-256;
for the serial probe, the booted board's identity (as `imubench info`).

Without --probe, the first probe whose tool is on PATH is used (openocd, st-flash,
stm32flash). --dry-run prints the commands without running anything (with --probe it does
not need the tool installed). Exit status: 0 done,
1 a tool failed or the verify found a difference (the tool's output is shown), 2 usage
error, missing tool or missing image.
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from imubench.device import artifacts
from imubench.errors import ImubenchError
from imubench.files import MAX_IMAGE_BYTES, read_bytes

ROOT = artifacts.checkout_root()      # None when installed from a wheel
FLASH_BASE = 0x08000000
PRODUCT_ID = {"f103": 0x410, "f4": 0x413}      # AN2606 / stm32flash dev_table.c
TAG_BOARD = {"f103": "stm32f103", "f4": "stm32f4"}
TAG_MARK = b"imubench-image board="

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
    probe_id: bool = False               # stm32flash without an action: the bootloader's product ID

    def shell(self) -> str:
        return " ".join(shlex.quote(a) for a in self.argv)


@dataclass
class Plan:
    probe: str
    image: Path
    steps: list[Step] = field(default_factory=list)


def image_paths(board: str, root: Path | None = None) -> dict[str, Path]:
    d = root / "build" / "arm" / board if root is not None else artifacts.image_dir(board)
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


def image_bytes(path: Path) -> bytes:
    """The image as the bytes from FLASH_BASE on (.bin as is, .hex parsed, .elf's flash
    segments)."""
    data = path.read_bytes()
    if path.suffix == ".hex":
        mem: dict[int, int] = {}
        upper = 0
        for ln, line in enumerate(data.decode("ascii", "replace").splitlines(), 1):
            line = line.strip()
            if not line:
                continue
            try:
                rec = bytes.fromhex(line[1:])
            except ValueError:
                raise FlashError(f"{path}:{ln}: not an Intel HEX record", 2) from None
            if not line.startswith(":") or len(rec) < 5 or len(rec) != rec[0] + 5 or sum(rec) & 0xFF:
                raise FlashError(f"{path}:{ln}: bad Intel HEX record (length or checksum)", 2)
            n, addr, kind, payload = rec[0], rec[1] << 8 | rec[2], rec[3], rec[4:4 + rec[0]]
            if kind == 0:
                for i in range(n):
                    mem[upper + addr + i] = payload[i]
            elif kind == 4:
                upper = int.from_bytes(payload, "big") << 16
            elif kind == 2:
                upper = int.from_bytes(payload, "big") << 4
            elif kind == 1:
                break
        if not mem:
            return b""
        lo, hi = max(min(mem), FLASH_BASE), max(mem) + 1
        out = bytearray(b"\xff" * (hi - FLASH_BASE))
        for a, v in mem.items():
            if a >= lo:
                out[a - FLASH_BASE] = v
        return bytes(out)
    if data[:4] == b"\x7fELF":
        try:
            from elftools.elf.elffile import ELFFile
            import io
            elf = ELFFile(io.BytesIO(data))
            segs = [(seg["p_paddr"], seg.data()[:seg["p_filesz"]]) for seg in elf.iter_segments()
                    if seg["p_type"] == "PT_LOAD" and seg["p_filesz"] and seg["p_paddr"] >= FLASH_BASE
                    and seg["p_paddr"] < FLASH_BASE + 0x1000000]
        except Exception:  # noqa: BLE001 - a broken file is the user's input, said in one line
            return data
        if not segs:
            return b""
        end = max(a + len(d) for a, d in segs)
        out = bytearray(b"\xff" * (end - FLASH_BASE))
        for a, d in segs:
            out[a - FLASH_BASE:a - FLASH_BASE + len(d)] = d
        return bytes(out)
    return data


def image_tag(data: bytes) -> dict | None:
    """The image's own tag {"board", "build"} (None: an image without one)."""
    i = data.find(TAG_MARK)
    if i < 0:
        return None
    end = data.find(b"\0", i)
    text = data[i:end if end > 0 else i + 120].decode("ascii", "replace")
    fields = dict(f.split("=", 1) for f in text.split()[1:] if "=" in f)
    return {"board": fields.get("board", "?"), "build": fields.get("build", "?")}


def check_image_board(board: str, image: Path) -> dict | None:
    """Refuse an image built for another chip, before anything is erased."""
    tag = image_tag(image_bytes(image))
    if tag is not None and tag["board"] != TAG_BOARD[board]:
        raise FlashError(f"{image} is an image for the {tag['board']}, not the {TAG_BOARD[board]} "
                         f"(--board {board}): nothing written", 2)
    return tag


def check_port(port: str) -> None:
    if not os.path.exists(port):
        raise FlashError(f"{port}: no such serial port (the USB-serial adapter on USART1 PA9/PA10, "
                         "e.g. /dev/ttyUSB0; `ls /dev/ttyUSB* /dev/ttyACM*` lists them)", 2)


def is_pty(port: str) -> bool:
    return os.path.realpath(port).startswith("/dev/pts/")


def serial_mode(port: str) -> list[str]:
    return ["-m", "8n1"] if is_pty(port) else []


def parse_product_id(output: str) -> int | None:
    m = re.search(r"Device ID\s*:\s*0x([0-9a-fA-F]+)", output)
    return int(m.group(1), 16) if m else None


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
        if img.suffix == ".elf":
            raise FlashError(f"stm32flash writes .hex or .bin images: give one, not {img.name}", 2)
        n = len(image_bytes(img)) if img.exists() else 0
        n = (n + 3) & ~3
        mode = serial_mode(port)
        return Plan(probe, img, [
            Step(["stm32flash", *mode, port], probe_id=True),
            Step(["stm32flash", *mode, "-S", f"0x{FLASH_BASE:08x}:{n}", "-w", str(img), "-v",
                  "-g", f"0x{FLASH_BASE:08x}", port]),
        ])
    raise FlashError(f"unknown probe {probe}", 2)


def _run(step: Step, board: str | None = None) -> str:
    print(f"$ {step.shell()}", flush=True)
    try:
        p = subprocess.Popen(step.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    except OSError as e:
        raise FlashError(f"cannot run {step.argv[0]}: {e}", 2) from e
    # chunks, not lines: the tools draw their progress with carriage returns on one line
    import codecs
    dec = codecs.getincrementaldecoder("utf-8")(errors="replace")
    out = []
    while True:
        chunk = p.stdout.read1(4096)
        if not chunk:
            break
        text = dec.decode(chunk)
        out.append(text)
        sys.stdout.write(text)
        sys.stdout.flush()
    rc = p.wait()
    text = "".join(out)
    if step.probe_id:
        pid = parse_product_id(text)
        if rc != 0 or pid is None:
            raise FlashError(f"{step.argv[-1]} does not answer as an STM32 bootloader (stm32flash exit {rc}): "
                             "check the adapter's TX/RX on PA10/PA9, set BOOT0 high and press reset (also after a "
                             "flash cut off half way: the bootloader waits for the rest of it); nothing written", 1)
        if board is not None and pid != PRODUCT_ID[board]:
            other = {v: k for k, v in PRODUCT_ID.items()}.get(pid, f"chip 0x{pid:03X}")
            raise FlashError(f"the bootloader on {step.argv[-1]} reports product ID 0x{pid:03X} ({other}), "
                             f"not the {board}'s 0x{PRODUCT_ID[board]:03X}: nothing erased", 2)
        return text
    if rc != 0 and "Failed to verify" in text:
        line = next(ln for ln in text.splitlines() if "Failed to verify" in ln)
        raise FlashError(f"verify failed: {line.strip()}", 1)
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
    return text


def build_firmware() -> None:
    if artifacts.installed():
        return                          # the package's images were built with the wheel
    if ROOT is None:
        raise FlashError(str(artifacts.not_found()), 2)
    r = subprocess.run(["make", "-s", "-C", str(ROOT), "firmware"], capture_output=True, text=True)
    if r.returncode != 0:
        last = (r.stderr.strip() or r.stdout.strip() or "no output").splitlines()[-1]
        raise FlashError(f"`make firmware` failed ({last}); run `make firmware` in {ROOT} to see the whole output", 1)
    sys.stdout.write(r.stdout)
