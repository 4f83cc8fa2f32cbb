"""The firmware image as the emulated board holds it: which code region (core, drivers, board,
C library) each half-word of flash belongs to, from the linker map; the flash segments of an
ELF; and which of several ELFs a flash's code is."""
from __future__ import annotations

import re

from .core import ElfImage
from .targets import Target


def code_regions(map_path: str, target: Target) -> bytearray:
    """Per half-word of the code region: 1 core, 2 drivers, 3 board, 4 C library, 0 other,
    from the linker map's input sections (.text*)."""
    n = (target.param_base - target.flash_base) // 2
    regions = bytearray(n)
    sec = None
    pat = re.compile(r"^\s*(\.\S+)?\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S+)")
    with open(map_path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.startswith(" .") and len(line.split()) == 1:
                sec = line.split()[0]
                continue
            mo = pat.match(line)
            if not mo:
                sec = None if line.startswith(" .") is False and not line.startswith("   ") else sec
                continue
            name = mo.group(1) or sec
            sec = None
            if not name or not name.startswith(".text"):
                continue
            addr, size, obj = int(mo.group(2), 16), int(mo.group(3), 16), mo.group(4)
            if size == 0 or not target.flash_base <= addr < target.param_base:
                continue
            if "/firmware/core/" in obj:
                kind = 1
            elif "/firmware/drivers/" in obj:
                kind = 2
            elif "/firmware/boards/" in obj:
                kind = 3
            else:
                kind = 4
            lo = (addr - target.flash_base) // 2
            hi = min(n, (addr + size - target.flash_base + 1) // 2)
            regions[lo:hi] = bytes([kind]) * (hi - lo)
    return regions


def flash_segments(elf_path: str, target: Target) -> list[tuple[int, bytes]]:
    """The loadable bytes an image puts into the code pages."""
    img = ElfImage(elf_path)
    return [(a, d) for a, d in img.segments if target.flash_base <= a < target.param_base]


def match_elf(code: bytes, candidates: list[str], target: Target) -> str | None:
    """The ELF (of those the emulator was given) whose code is what the code pages hold: the
    emulator runs an image through its symbols (fast-forward hooks), so a flash written by a
    tool (stm32flash) is run as the ELF it matches. None: blank, half written or unknown."""
    for path in candidates:
        try:
            segs = flash_segments(path, target)
        except (OSError, ValueError):
            continue
        if segs and all(code[a - target.flash_base:a - target.flash_base + len(d)] == d for a, d in segs):
            return path
    return None
