"""The emulated chip's memory as its ROM bootloader sees it (bootloader.py has the protocol):
each part's bootloader facts (AN2606: product ID, version, erase command, the RAM it keeps,
the flash pages/sectors, the option bytes and system memory), the flash kept in two files (the
code pages and the parameter pages, written through), and the reads, programs and erases the
commands perform, with their device time and the power cuts the control channel arms.
"""
from __future__ import annotations

import os

KIB = 1024

CHIP = {
    # product ID, bootloader version, commands (Get's list), RAM the bootloader keeps, units
    "f103": dict(pid=0x410, version=0x22, erase=0x43, ram_reserved=0x200,
                 units=[1 * KIB] * 128, wrp_pages=4, option_base=0x1FFFF800,
                 sysmem=(0x1FFFF000, 0x1FFFF800), otp=None),
    "f4": dict(pid=0x413, version=0x31, erase=0x44, ram_reserved=0x3000,
               units=[16 * KIB] * 4 + [64 * KIB] + [128 * KIB] * 7, wrp_pages=1, option_base=0x1FFFC000,
               sysmem=(0x1FFF0000, 0x1FFF8000), otp=(0x1FFF7800, 0x1FFF7A10)),
}


class FlashFile:
    """Bytes of flash persisted in a file (write-through), created erased (0xFF)."""

    def __init__(self, path: str, size: int, grow_from: int = 0):
        """grow_from: a file of that many bytes is taken and extended with erased bytes (the
        F103's code file from before the board had 128 KiB: the code pages below the parameter
        pages only)."""
        self.path = path
        self.size = size
        self.mem = bytearray(b"\xff" * size)
        if os.path.exists(path) and os.path.getsize(path) > 0:
            n = os.path.getsize(path)
            if n != size and not (grow_from and n == grow_from):
                raise ValueError(f"{path} has {n} bytes, expected {size}: a flash file of another target?")
            with open(path, "rb") as f:
                self.mem[:n] = f.read()
            if n != size:
                with open(path, "ab") as f:
                    f.write(self.mem[n:])
        else:
            with open(path, "wb") as f:
                f.write(self.mem)

    def write(self, off: int, data: bytes) -> None:
        self.mem[off:off + len(data)] = data
        with open(self.path, "r+b") as f:
            f.seek(off)
            f.write(data)


def code_path(flash_path: str) -> str:
    """The code pages of a virtual board (every flash page that is not a parameter page: from
    0x08000000 up to the parameter pages, then any above them) live next to its parameter flash
    file: FILE.code."""
    return flash_path + ".code"


def open_code(flash_path: str, target) -> FlashFile:
    """The code file of a board (a shorter one from an earlier memory map grows, erased)."""
    return FlashFile(code_path(flash_path), target.code_file_size,
                     grow_from=target.param_base - target.flash_base)


class ChipMemory:
    """The memory half of RomBootloader: needs self.t (targets.Target), self.chip (CHIP's entry),
    self.code / self.params (FlashFile), self.uid, self.ram, self.rdp, self.wrp, self.ob_user,
    self.lib, self.log, and keeps self.busy_s, self.erased_units, self.flash_ops, self.action."""

    # ------------------------------------------------------------- geometry
    def units(self) -> list[tuple[int, int]]:
        """(address, size) of every page/sector of the emulated chip's flash."""
        out, a = [], self.t.flash_base
        for size in self.chip["units"]:
            out.append((a, size))
            a += size
        return out

    def _flash_pieces(self, addr: int, n: int) -> list[tuple[FlashFile, int, int]]:
        """[addr, addr+n) in flash as (store, offset, length) pieces: the code file below the
        parameter pages, the parameter file, the code file again above them."""
        t = self.t
        p_end = t.param_base + t.param_size
        spans = [(t.flash_base, t.param_base, self.code, 0), (t.param_base, p_end, self.params, 0),
                 (p_end, t.flash_base + t.flash_size, self.code, t.param_base - t.flash_base)]
        out = []
        for lo, hi, store, base in spans:
            a, b = max(lo, addr), min(hi, addr + n)
            if a < b:
                out.append((store, base + a - lo, b - a))
        return out

    def _areas(self):
        """(start, end, kind) of every range the bootloader reads: flash, RAM, system memory,
        option bytes (AN2606's memory map of the part)."""
        t, c = self.t, self.chip
        return [(t.flash_base, t.flash_base + t.flash_size, "flash"),
                (t.ram_base, t.ram_base + t.ram_size, "ram"),
                (c["sysmem"][0], c["sysmem"][1], "system"),
                (c["option_base"], c["option_base"] + 16, "option")]

    def _area(self, addr: int) -> tuple[int, int, str] | None:
        for a in self._areas():
            if a[0] <= addr < a[1]:
                return a
        return None

    def _system_memory(self) -> bytes:
        """System memory as read: the ROM's code (not modelled) as zeros, the F4's OTP area
        erased (0xFF), the flash-size register and the unique ID in their places."""
        t, c = self.t, self.chip
        lo, hi = c["sysmem"]
        mem = bytearray(hi - lo)
        if c["otp"]:
            mem[c["otp"][0] - lo:c["otp"][1] - lo] = b"\xff" * (c["otp"][1] - c["otp"][0])
        mem[t.uid_addr - lo:t.uid_addr - lo + 12] = self.uid
        mem[t.fsize_addr - lo:t.fsize_addr - lo + 2] = t.flash_kib.to_bytes(2, "little")
        return bytes(mem)

    def _read(self, addr: int, n: int) -> bytes | None:
        """n bytes from addr, None when [addr, addr+n) is not inside one readable area."""
        a = self._area(addr)
        if a is None or addr + n > a[1]:
            return None
        lo, _, kind = a
        if kind == "flash":
            return b"".join(bytes(st.mem[off:off + k]) for st, off, k in self._flash_pieces(addr, n))
        if kind == "ram":
            return bytes(self.ram[addr - lo:addr - lo + n])
        if kind == "system":
            return self._system_memory()[addr - lo:addr - lo + n]
        return bytes(self._option_bytes()[addr - lo:addr - lo + n])

    def _option_bytes(self) -> bytearray:
        if self.t.name == "f103":           # RDP, USER, Data0, Data1, WRP0..3 with complements
            rdp = 0x00 if self.rdp else 0xA5
            wrp = 0xFFFFFFFF
            for s in self.wrp:
                wrp &= ~(1 << (s // 4))
            vals = [rdp, *self.ob_user] + [(wrp >> (8 * i)) & 0xFF for i in range(4)]
            out = bytearray()
            for v in vals:
                out += bytes([v, v ^ 0xFF])
            return out
        nwrp = 0x0FFF
        for s in self.wrp:
            nwrp &= ~(1 << s)
        return bytearray([self.ob_user[0], 0x00 if self.rdp else 0xAA, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
                          nwrp & 0xFF, nwrp >> 8, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00])

    def _unit_of(self, addr: int) -> int:
        for i, (a, size) in enumerate(self.units()):
            if a <= addr < a + size:
                return i
        return -1

    def _wrp_unit(self, unit: int) -> int:
        return unit // self.chip["wrp_pages"] * self.chip["wrp_pages"]

    # ------------------------------------------------------------ flash ops
    def _op_cut(self) -> bool:
        """One flash operation (as the control channel's power_cut {after_flash_ops} counts)."""
        self.flash_ops += 1
        return bool(self.lib.simlib_flash_op()) if self.lib is not None else False

    def _fill(self, addr: int, data: bytes) -> None:
        """Write bytes over [addr, addr+len) in whichever store(s) hold them."""
        i = 0
        for store, off, k in self._flash_pieces(addr, len(data)):
            store.write(off, data[i:i + k])
            i += k

    def _erase_unit(self, unit: int) -> bool:
        """Erase one page/sector; False: a power cut fell into it (half erased, power off)."""
        a, size = self.units()[unit]
        cut = self._op_cut()
        n = size // 2 if cut else size
        self._fill(a, b"\xff" * n)
        self.busy_s += self.t.erase_s * (size / self.t.erase_unit if self.t.name == "f4" else 1.0)
        self.erased_units.append(unit)
        if cut:
            self.log(f"bootloader: power cut during the erase of {self._unit_name(unit)} (half erased)")
            self.action = ("power_cut",)
            return False
        return True

    def _unit_name(self, unit: int) -> str:
        a, size = self.units()[unit]
        kind = "page" if self.t.name == "f103" else "sector"
        return f"{kind} {unit} (0x{a:08X}, {size // KIB} KiB)"

    def _program(self, addr: int, data: bytes) -> bool:
        """Write Memory into flash: F1 by half-words (a half-word not erased takes only 0x0000),
        F4 by bytes (bits go 1 -> 0 only). False: refused (NACK) or cut."""
        cut = self._op_cut()
        if cut:
            data = data[:len(data) // 2]
        old = self._read(addr, len(data))
        if self.t.name == "f103":
            new = bytearray(old)
            for i in range(0, len(data) - 1, 2):
                cur = old[i] | old[i + 1] << 8
                val = data[i] | data[i + 1] << 8
                if cur != 0xFFFF and val != 0:        # PM0075 2.3.3: PGERR, nothing programmed
                    self.log(f"bootloader: write to 0x{addr + i:08X}: half-word not erased (PGERR)")
                    return False
                new[i:i + 2] = data[i:i + 2]
            self.busy_s += self.t.program_s * (len(data) // 2)
        else:
            new = bytes(o & d for o, d in zip(old, data))
            self.busy_s += self.t.program_s * (len(data) // 4)
        self._fill(addr, bytes(new))
        if cut:
            self.log(f"bootloader: power cut during the write at 0x{addr:08X} (half written)")
            self.action = ("power_cut",)
            return False
        return True
