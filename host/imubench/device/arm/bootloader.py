"""The STM32 ROM bootloader on USART1, as ST's application note AN3155 ("USART protocol used
in the STM32 bootloader", rev. 14) and AN2606 ("STM32 microcontroller system memory boot
mode") describe it, answering as the emulated chip's bootloader does:

  chip   product ID  bootloader  erase command             flash geometry
  F103   0x410       v2.2        Erase 0x43 (1-byte)       1 KiB pages (medium density)
  F4     0x413       v3.1        Extended Erase 0x44       sectors 4x16, 64, 7x128 KiB

Protocol (AN3155 2-3): after reset the bootloader waits for 0x7F (it measures the baud rate
on it) and answers ACK (0x79); bytes before it are ignored. A command is its code and its
complement; a wrong pair is answered NACK (0x1F). Addresses are 4 bytes MSB first plus their
XOR; data blocks carry N-1 and the XOR of N-1 and the data. Commands:
  Get 0x00, Get Version & Read Protection Status 0x01, Get ID 0x02, Read Memory 0x11,
  Go 0x21, Write Memory 0x31, Erase 0x43 (F1) / Extended Erase 0x44 (F4),
  Write Protect 0x63, Write Unprotect 0x73, Readout Protect 0x82, Readout Unprotect 0x92.
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
                 units=[1 * KIB] * 64, wrp_pages=4, option_base=0x1FFFF800,
                 sysmem=(0x1FFFF000, 0x1FFFF800)),
    "f4": dict(pid=0x413, version=0x31, erase=0x44, ram_reserved=0x3000,
               units=[16 * KIB] * 4 + [64 * KIB] + [128 * KIB] * 7, wrp_pages=1, option_base=0x1FFFC000,
               sysmem=(0x1FFF0000, 0x1FFF7800)),
}


class FlashFile:
    """Bytes of flash persisted in a file (write-through), created erased (0xFF)."""

    def __init__(self, path: str, size: int):
        self.path = path
        self.size = size
        self.mem = bytearray(b"\xff" * size)
        if os.path.exists(path) and os.path.getsize(path) > 0:
            n = os.path.getsize(path)
            if n != size:
                raise ValueError(f"{path} has {n} bytes, expected {size}: a flash file of another target?")
            with open(path, "rb") as f:
                self.mem[:] = f.read()
        else:
            with open(path, "wb") as f:
                f.write(self.mem)

    def write(self, off: int, data: bytes) -> None:
        self.mem[off:off + len(data)] = data
        with open(self.path, "r+b") as f:
            f.seek(off)
            f.write(data)


def code_path(flash_path: str) -> str:
    """The code pages of a virtual board (0x08000000 up to the parameter pages) live next to its
    parameter flash file: FILE.code."""
    return flash_path + ".code"


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

    def _region(self, addr: int, n: int):
        """(store, offset) for a flash/RAM/system range, None when not readable/writable as one."""
        t = self.t
        if t.flash_base <= addr and addr + n <= t.param_base:
            return self.code, addr - t.flash_base
        if t.param_base <= addr and addr + n <= t.param_base + t.param_size:
            return self.params, addr - t.param_base
        if t.ram_base <= addr and addr + n <= t.ram_base + t.ram_size:
            return "ram", addr - t.ram_base
        return None

    def _read(self, addr: int, n: int) -> bytes | None:
        r = self._region(addr, n)
        if r is not None:
            store, off = r
            return bytes(self.ram[off:off + n]) if store == "ram" else bytes(store.mem[off:off + n])
        t = self.t
        if t.uid_addr <= addr and addr + n <= t.uid_addr + 12:
            return self.uid[addr - t.uid_addr:addr - t.uid_addr + n]
        if t.fsize_addr <= addr and addr + n <= t.fsize_addr + 2:
            return t.flash_kib.to_bytes(2, "little")[addr - t.fsize_addr:addr - t.fsize_addr + n]
        ob = self.chip["option_base"]
        if ob <= addr and addr + n <= ob + 16:
            return bytes(self._option_bytes()[addr - ob:addr - ob + n])
        lo, hi = self.chip["sysmem"]
        if lo <= addr and addr + n <= hi:
            return b"\x00" * n              # the ROM's own code is not modelled: reads as zeros
        return None

    def _option_bytes(self) -> bytearray:
        if self.t.name == "f103":           # RDP, USER, Data0, Data1, WRP0..3 with complements
            rdp = 0x00 if self.rdp else 0xA5
            wrp = 0xFFFFFFFF
            for s in self.wrp:
                wrp &= ~(1 << (s // 4))
            vals = [rdp, 0xFF, 0xFF, 0xFF] + [(wrp >> (8 * i)) & 0xFF for i in range(4)]
            out = bytearray()
            for v in vals:
                out += bytes([v, v ^ 0xFF])
            return out
        nwrp = 0x0FFF
        for s in self.wrp:
            nwrp &= ~(1 << s)
        return bytearray([0xED, 0x00 if self.rdp else 0xAA, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
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
        t = self.t
        while data:
            if addr < t.param_base:
                n = min(len(data), t.param_base - addr)
                self.code.write(addr - t.flash_base, data[:n])
            else:
                n = min(len(data), t.param_base + t.param_size - addr)
                self.params.write(addr - t.param_base, data[:n])
            addr += n
            data = data[n:]

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
        r = self._region(addr, len(data))
        store, off = r
        old = bytes(store.mem[off:off + len(data)])
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
        store.write(off, bytes(new))
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

    def _open_address(self):
        """The start of Read and Write Memory: NACK under readout protection, else ACK, the
        address with its checksum and ACK; the address, or None when refused."""
        if self.rdp:
            self.out.append(NACK)
            return None
        self.out.append(ACK)
        addr = yield from self._address()
        if addr is None:
            return None
        self.out.append(ACK)
        return addr

    def _read_mem(self):
        addr = yield from self._open_address()
        if addr is None:
            return
        nb = yield 2
        if nb[1] != nb[0] ^ 0xFF:
            self.out.append(NACK)
            return
        n = nb[0] + 1
        data = self._read(addr, n)
        if data is None:
            self.out.append(NACK)
            return
        self.out.append(ACK)
        self.out += data

    def _write_mem(self):
        addr = yield from self._open_address()
        if addr is None:
            return
        nb = yield 1
        n = nb[0] + 1
        rest = yield n + 1
        data, cs = rest[:n], rest[n]
        x = nb[0]
        for v in data:
            x ^= v
        r = self._region(addr, n)
        if x != cs or r is None or (r[0] != "ram" and addr % 4):
            self.out.append(NACK)
            return
        if r[0] == "ram":
            if addr - self.t.ram_base < self.chip["ram_reserved"]:
                self.out.append(NACK)       # the bootloader's own RAM
                return
            self.ram[r[1]:r[1] + n] = data
            self.out.append(ACK)
            return
        for a in (addr, addr + n - 1):
            if self._wrp_unit(self._unit_of(a)) in self.wrp:
                self.out.append(NACK)
                return
        ok = self._program(addr, data)
        if self.action is None:
            self.out.append(ACK if ok else NACK)

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
        if x != rest[-1]:
            self.out.append(NACK)
            return
        step = self.chip["wrp_pages"]
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
