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

Here the protocol; the chip's memory as the commands read, program and erase it (the parts'
bootloader facts, the flash files) in bootloader_memory.py; the process that serves the engine
on the board's serial endpoint in bootloader_server.py.
"""
from __future__ import annotations

from .bootloader_memory import CHIP, KIB, ChipMemory, FlashFile, code_path, open_code  # noqa: F401 - named here too
from .bootloader_server import BootloaderServer  # noqa: F401 - the process side, named here too

ACK, NACK = 0x79, 0x1F

# stm32flash's reset stub (ldr r1,[pc,#4]; ldr r2,[pc,#8]; str r2,[r1]; b .; AIRCR; VECTKEY|SYSRESETREQ)
RESET_STUB = bytes([0x01, 0x49, 0x02, 0x4A, 0x0A, 0x60, 0xFE, 0xE7, 0x0C, 0xED, 0x00, 0xE0,
                    0x04, 0x00, 0xFA, 0x05])


class RomBootloader(ChipMemory):
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
