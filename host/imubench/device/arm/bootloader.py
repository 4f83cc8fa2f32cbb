"""The STM32 ROM bootloader on USART1, as ST's application note AN3155 ("USART protocol used
in the STM32 bootloader", rev. 14) and AN2606 ("STM32 microcontroller system memory boot
mode") describe it, answering as the emulated chip's bootloader does:

  chip          product ID  bootloader  erase command         flash geometry
  F103 (CB)     0x410       v2.2        Erase 0x43 (1-byte)   128 KiB, 1 KiB pages 0-127
  F4 (F405/7)   0x413       v3.1        Extended Erase 0x44   1 MiB, sectors 4x16, 64, 7x128 KiB

Memory the bootloader reads and writes (AN2606 "Bootloader memory management" for these
parts; RM0008 30.1-30.2, RM0090 3.1, 39.1-39.2): the whole flash as one contiguous range (the
parameter pages are ordinary flash: a read, write or erase may cross their border), RAM above
the bootloader's own, system memory with the flash-size register and the unique ID in it
(F1 0x1FFFF000-0x1FFFF7FF, F4 0x1FFF0000-0x1FFF7FFF with the OTP area 0x1FFF7800-0x1FFF7A0F),
read at any length and alignment that stays inside it, and the option bytes (F1 0x1FFFF800,
16 bytes; F4 0x1FFFC000, 16 bytes). The ROM's own code is not modelled: its bytes read as 0x00.

Protocol (AN3155 2-3): after reset the bootloader waits for 0x7F (it measures the baud rate
on it) and answers ACK (0x79); bytes before it are ignored. A command is its code and its
complement; a wrong pair is answered NACK (0x1F). Addresses are 4 bytes MSB first plus their
XOR; data blocks carry N-1 and the XOR of N-1 and the data. Commands:
  Get 0x00, Get Version & Read Protection Status 0x01, Get ID 0x02, Read Memory 0x11,
  Go 0x21, Write Memory 0x31, Erase 0x43 (F1) / Extended Erase 0x44 (F4),
  Write Protect 0x63, Write Unprotect 0x73, Readout Protect 0x82, Readout Unprotect 0x92.
Address checks at the step AN3155 names: Read Memory and Write Memory NACK an address that is
not in readable (writable) memory right after the address and its checksum, Go one that is not
a jump target; the length (Read) or the data (Write) are then NACKed only for their checksum,
for running past the end of the memory the address is in, or (Write) for an address that is
not 4-byte aligned or a page that is write protected. Write Memory to the option bytes is
allowed: the bootloader programs them and the chip resets (AN3155 3.6), read and write
protection take their new values from them.
Protection as the chip: with readout protection active Read Memory, Write Memory, Go and
Erase are NACKed; Readout Unprotect mass-erases the flash (the parameter pages too), clears
the protection and resets; Write Protect / Unprotect change the write-protection option
bytes and reset; a write or erase of a protected page/sector is NACKed. Option bytes are
kept in this process only (not in the flash file).

Limits of the model: the serial framing of AN3155 is 8 data bits, EVEN parity, 1 stop bit
(8E1); a pseudo-terminal carries bytes, not frames, so parity (and the baud rate measured on
0x7F) cannot be shown or checked here. Replies come at once in wall time; device time
advances by the typical program/erase times (targets.py). Go into RAM runs nothing but
stm32flash's reset stub (a write of SYSRESETREQ to AIRCR), recognised and performed as a
system reset; other RAM code is refused (NACK). Go into flash starts the image whose ELF the
emulator knows (see image.match_elf).
"""
from __future__ import annotations

import os

ACK, NACK = 0x79, 0x1F
KIB = 1024

# stm32flash's reset stub (ldr r1,[pc,#4]; ldr r2,[pc,#8]; str r2,[r1]; b .; AIRCR; VECTKEY|SYSRESETREQ)
RESET_STUB = bytes([0x01, 0x49, 0x02, 0x4A, 0x0A, 0x60, 0xFE, 0xE7, 0x0C, 0xED, 0x00, 0xE0,
                    0x04, 0x00, 0xFA, 0x05])

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


class RomBootloader:
    """The protocol engine: bytes in (feed), bytes out (take_output), actions for the board
    (go / reset / power cut), flash in two files (code pages, parameter pages)."""

    def __init__(self, target, code: FlashFile, params: FlashFile, uid_bytes: bytes, lib=None,
                 log=lambda msg: None):
        self.t = target
        self.chip = CHIP[target.name]
        self.code = code
        self.params = params
        self.uid = uid_bytes
        self.lib = lib
        self.log = log
        self.ram = bytearray(target.ram_size)
        self.rdp = False
        self.wrp: set[int] = set()       # write-protected pages/sectors
        self.ob_user = b"\xff\xff\xff" if target.name == "f103" else b"\xed"   # USER (F1: + Data0/1)
        self.busy_s = 0.0                # device time spent programming/erasing
        self.erased_units: list[int] = []  # every page/sector erased (in order), for the tests
        self.flash_ops = 0
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self.synced = False
        self.out = bytearray()
        self.action: tuple | None = None
        self._gen = self._protocol()
        self._need = next(self._gen)
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        for b in data:
            if self.action is not None:
                return                      # the board is leaving the bootloader: the rest is lost
            self._buf.append(b)
            if len(self._buf) >= self._need:
                chunk, self._buf = bytes(self._buf), bytearray()
                self._need = self._gen.send(chunk)

    def take_output(self) -> bytes:
        out, self.out = bytes(self.out), bytearray()
        return out

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

    # -------------------------------------------------------------- protocol
    def _protocol(self):
        """The bootloader's loop as a generator: yields how many bytes it needs, gets them."""
        while not self.synced:
            b = yield 1
            if b[0] == 0x7F:
                self.synced = True
                self.out.append(ACK)
        while True:
            pair = yield 2
            cmd = pair[0]
            if pair[1] != cmd ^ 0xFF or cmd not in self._commands():
                self.out.append(NACK)
                continue
            yield from self._commands()[cmd]()

    def _commands(self):
        c = {0x00: self._get, 0x01: self._gvr, 0x02: self._gid, 0x11: self._read_mem, 0x21: self._go,
             0x31: self._write_mem, 0x63: self._write_protect, 0x73: self._write_unprotect,
             0x82: self._readout_protect, 0x92: self._readout_unprotect}
        c[self.chip["erase"]] = self._erase if self.chip["erase"] == 0x43 else self._ext_erase
        return c

    def _get(self):
        cmds = [0x00, 0x01, 0x02, 0x11, 0x21, 0x31, self.chip["erase"], 0x63, 0x73, 0x82, 0x92]
        self.out += bytes([ACK, len(cmds), self.chip["version"], *cmds, ACK])
        return
        yield

    def _gvr(self):
        self.out += bytes([ACK, self.chip["version"], 0x00, 0x00, ACK])
        return
        yield

    def _gid(self):
        pid = self.chip["pid"]
        self.out += bytes([ACK, 1, pid >> 8, pid & 0xFF, ACK])
        return
        yield

    def _address(self):
        """Receive an address + XOR checksum; None (after a NACK) when bad."""
        b = yield 5
        if b[0] ^ b[1] ^ b[2] ^ b[3] != b[4]:
            self.out.append(NACK)
            return None
        return int.from_bytes(b[:4], "big")

    def _open_address(self, valid):
        """The start of Read and Write Memory: NACK under readout protection, else ACK, the
        address with its checksum, and ACK when valid(address) holds (NACK right there when not,
        AN3155 3.4/3.6); the address, or None when refused."""
        if self.rdp:
            self.out.append(NACK)
            return None
        self.out.append(ACK)
        addr = yield from self._address()
        if addr is None:
            return None
        if not valid(addr):
            self.out.append(NACK)
            return None
        self.out.append(ACK)
        return addr

    def _writable(self, addr: int) -> bool:
        a = self._area(addr)
        if a is None or a[2] == "system":
            return False
        return not (a[2] == "ram" and addr - self.t.ram_base < self.chip["ram_reserved"])

    def _read_mem(self):
        addr = yield from self._open_address(lambda a: self._area(a) is not None)
        if addr is None:
            return
        nb = yield 2
        if nb[1] != nb[0] ^ 0xFF:
            self.out.append(NACK)
            return
        n = nb[0] + 1
        data = self._read(addr, n)
        if data is None:
            self.log(f"bootloader: Read Memory 0x{addr:08X}+{n}: runs past the end of its memory")
            self.out.append(NACK)
            return
        self.out.append(ACK)
        self.out += data

    def _write_mem(self):
        addr = yield from self._open_address(self._writable)
        if addr is None:
            return
        nb = yield 1
        n = nb[0] + 1
        rest = yield n + 1
        data, cs = rest[:n], rest[n]
        x = nb[0]
        for v in data:
            x ^= v
        lo, hi, kind = self._area(addr)
        if x != cs or addr + n > hi or (kind == "flash" and addr % 4):
            self.out.append(NACK)
            return
        if kind == "ram":
            self.ram[addr - lo:addr - lo + n] = data
            self.out.append(ACK)
            return
        if kind == "option":
            self._write_option_bytes(addr - lo, data)
            self.out.append(ACK)
            self.action = ("reset",)        # AN3155 3.6: the option bytes are written, then a system reset
            return
        units = range(self._unit_of(addr), self._unit_of(addr + n - 1) + 1)
        if any(self._wrp_unit(u) in self.wrp for u in units):
            self.out.append(NACK)
            return
        ok = self._program(addr, data)
        if self.action is None:
            self.out.append(ACK if ok else NACK)

    def _write_option_bytes(self, off: int, data: bytes) -> None:
        """Write Memory into the option bytes: the bootloader erases them all and programs the
        bytes given (AN3155 3.6); what is not given stays erased (0xFF). Read protection and
        write protection follow the new values (F1: RDP 0xA5 = unprotected, WRPn bit 0 = 4
        pages protected, RM0008 4.7.1/4.7.2 / PM0075 2.5; F4: RDP 0xAA = level 0, nWRP bit 0 =
        sector protected, RM0090 3.6/3.7.1). Complement bytes (F1) are the chip's own."""
        ob = bytearray(b"\xff" * 16)
        ob[off:off + len(data)] = data
        step = self.chip["wrp_pages"]
        self.wrp = set()
        if self.t.name == "f103":
            self.rdp = ob[0] != 0xA5
            self.ob_user = bytes([ob[2], ob[4], ob[6]])
            wrp = ob[8] | ob[10] << 8 | ob[12] << 16 | ob[14] << 24
            for bit in range(len(self.chip["units"]) // step):
                if not wrp >> bit & 1:
                    self.wrp.add(bit * step)
        else:
            self.rdp = ob[1] != 0xAA
            self.ob_user = bytes([ob[0]])
            nwrp = ob[8] | ob[9] << 8
            for sector in range(len(self.chip["units"])):
                if not nwrp >> sector & 1:
                    self.wrp.add(sector)
        self.log("bootloader: option bytes written (read protection "
                 f"{'on' if self.rdp else 'off'}, write protected {sorted(self.wrp) or 'none'}): system reset")

    def _erase(self):
        """F1 Erase (0x43): N then N+1 page numbers and the XOR; 0xFF 0x00 = global erase."""
        if self.rdp:
            self.out.append(NACK)
            return
        self.out.append(ACK)
        nb = yield 1
        if nb[0] == 0xFF:
            c = yield 1
            if c[0] != 0x00:
                self.out.append(NACK)
                return
            yield from self._mass_erase()
            return
        rest = yield nb[0] + 2
        pages, cs = rest[:-1], rest[-1]
        x = nb[0]
        for p in pages:
            x ^= p
        yield from self._erase_list(list(pages), x == cs)

    def _ext_erase(self):
        """F4 Extended Erase (0x44): N (2 bytes) then N+1 2-byte sector numbers and the XOR;
        0xFFFF = mass erase, 0xFFFE / 0xFFFD = bank 1 / bank 2 (one bank here: NACK)."""
        if self.rdp:
            self.out.append(NACK)
            return
        self.out.append(ACK)
        nb = yield 2
        n = nb[0] << 8 | nb[1]
        if n >= 0xFFF0:
            c = yield 1
            if c[0] != nb[0] ^ nb[1] or n != 0xFFFF:
                self.out.append(NACK)
                return
            yield from self._mass_erase()
            return
        rest = yield 2 * (n + 1) + 1
        x = nb[0] ^ nb[1]
        for v in rest[:-1]:
            x ^= v
        sectors = [rest[2 * i] << 8 | rest[2 * i + 1] for i in range(n + 1)]
        yield from self._erase_list(sectors, x == rest[-1])

    def _erase_list(self, units: list[int], cs_ok: bool):
        n_units = len(self.chip["units"])
        if not cs_ok or any(u >= n_units or self._wrp_unit(u) in self.wrp for u in units):
            self.out.append(NACK)
            return
        for u in units:
            if not self._erase_unit(u):
                return
        self.log("bootloader: erased " + ", ".join(self._unit_name(u) for u in units))
        self.out.append(ACK)
        return
        yield

    def _mass_erase(self):
        if self.wrp:
            self.out.append(NACK)
            return
        for u in range(len(self.chip["units"])):
            if not self._erase_unit(u):
                return
        self.log("bootloader: mass erase (every page, the parameter pages too)")
        self.out.append(ACK)
        return
        yield

    def _go(self):
        if self.rdp:
            self.out.append(NACK)
            return
        self.out.append(ACK)
        addr = yield from self._address()
        if addr is None:
            return
        t = self.t
        if t.flash_base <= addr < t.param_base:
            self.out.append(ACK)
            self.action = ("go", addr)
        elif t.ram_base <= addr < t.ram_base + t.ram_size:
            code = self._read(addr + 8, len(RESET_STUB))
            if code == RESET_STUB:
                self.out.append(ACK)
                self.action = ("reset",)
            else:
                self.log(f"bootloader: Go 0x{addr:08X}: code in RAM is not run by the emulator")
                self.out.append(NACK)
        else:
            self.out.append(NACK)

    def _write_protect(self):
        if self.rdp:
            self.out.append(NACK)
            return
        self.out.append(ACK)
        nb = yield 1
        rest = yield nb[0] + 2
        x = nb[0]
        for v in rest[:-1]:
            x ^= v
        step = self.chip["wrp_pages"]
        if x != rest[-1] or any(s * step >= len(self.chip["units"]) for s in rest[:-1]):
            self.out.append(NACK)           # a bad checksum, or a sector the part does not have
            return
        for s in rest[:-1]:
            self.wrp.add(s * step)
        self.out.append(ACK)
        self.action = ("reset",)            # the option bytes are reloaded: a system reset

    def _write_unprotect(self):
        if self.rdp:
            self.out.append(NACK)
            return
        self.wrp.clear()
        self.out += bytes([ACK, ACK])
        self.action = ("reset",)
        return
        yield

    def _readout_protect(self):
        if self.rdp:
            self.out.append(NACK)
            return
        self.rdp = True
        self.out += bytes([ACK, ACK])
        self.action = ("reset",)
        return
        yield

    def _readout_unprotect(self):
        self.out.append(ACK)
        self.wrp.clear()
        for u in range(len(self.chip["units"])):
            if not self._erase_unit(u):
                return
        self.rdp = False
        self.log("bootloader: readout unprotect: the whole flash erased")
        self.out.append(ACK)
        self.action = ("reset",)
        return
        yield


class BootloaderServer:
    """The process while the board is in its ROM bootloader: bytes from the serial endpoint
    (pty or TCP) to the protocol engine and back, the control channel served (power_cut,
    quit, status). Device time follows the wall clock (x speed) plus the flash busy time."""

    def __init__(self, rom: RomBootloader, lib, speed: float, t0: float, log):
        self.rom = rom
        self.lib = lib
        self.speed = speed if speed > 0 else 1.0
        self.t0 = t0
        self.log = log
        import time
        self._time = time
        self.wall0 = time.monotonic()
        self.busy0 = rom.busy_s
        self.power_cuts = 0

    def now(self) -> float:
        return self.t0 + (self._time.monotonic() - self.wall0) * self.speed + (self.rom.busy_s - self.busy0)

    def serve(self, should_stop) -> tuple:
        """Until the bootloader leaves (("go", addr) / ("reset",)) or the process stops (("stop",))."""
        import ctypes

        from . import simlib
        lib, rom = self.lib, self.rom
        pfd = (simlib.PollFd * 16)()
        buf = (ctypes.c_uint8 * 512)()
        lib.simlib_set_state(0, 0, 0, 0, 0, self.power_cuts, 0)
        while not should_stop():
            lib.simlib_set_time(round(self.now() * 1e6))
            lib.sim_control_check_waits()
            if lib.simlib_quit():
                return ("stop",)
            if lib.simlib_take_reset() == 2:
                rom.action = ("power_cut",)
            n = lib.simlib_link_rx_pending()
            while n:
                got = lib.simlib_link_pull(buf, min(n, len(buf)))
                if not got:
                    break
                rom.feed(bytes(buf[:got]))
                n = lib.simlib_link_rx_pending()
            out = rom.take_output()
            if out and rom.action != ("power_cut",):
                lib.simlib_set_time(round(self.now() * 1e6))
                lib.simlib_link_push(out, len(out))
                lib.simlib_link_flush()
            if rom.action is not None:
                act, rom.action = rom.action, None
                if act[0] == "power_cut":
                    self.power_cuts += 1
                    lib.simlib_set_state(0, 0, 0, 0, 0, self.power_cuts, 0)
                    self.log("power cut: the board restarts in its bootloader (BOOT0 high)")
                    lib.simlib_power_cycle_models()
                    lib.simlib_link_reset()
                    rom.reset()
                    continue
                return act
            # wait for bytes or a control request
            poller, lfd, cfd, slot, n_ctl = simlib.sim_poller(lib, pfd)
            try:
                ready = poller.poll(20)
            except InterruptedError:
                continue
            ctl = False
            for fd, ev in ready:
                if fd == lfd:
                    lib.simlib_link_accept()
                elif fd == cfd:
                    lib.simlib_link_receive()
                elif fd in slot:
                    pfd[slot[fd]].revents = ev
                    ctl = True
            if ctl:
                lib.sim_control_handle(pfd, n_ctl)
        return ("stop",)
