"""The embedded flash: its interface registers and the parameter pages/sectors behind it.

F1: PM0075 (STM32F10xxx Flash memory programming manual) 3: ACR, KEYR, OPTKEYR, SR (BSY,
PGERR, WRPRTERR, EOP), CR (PG, PER, MER, STRT, LOCK, ...), AR, OBR, WRPR. Programming is by
half-word; a half-word that is not erased (0xFFFF) can only be programmed with 0x0000,
anything else sets PGERR and programs nothing (PM0075 2.3.3). Page erase (PER, AR, STRT)
fills the 1 KiB page with 0xFF. Times: half-word 52.5 us, page erase 20 ms (PM0075 / the
STM32F103x8 datasheet, table "Flash memory characteristics", typical tPROG and tERASE).
F4: RM0090 3.5-3.9: ACR, KEYR, OPTKEYR, SR (EOP, OPERR, WRPERR, PGAERR, PGPERR, PGSERR, BSY),
CR (PG, SER, MER, SNB, PSIZE, STRT, LOCK, ...). Programming by PSIZE units; bits only go
1 -> 0 (a programmed unit can be programmed again with zeros). Sector erase fills the whole
sector with 0xFF. Times: word (x32) 16 us, 128 KiB sector 1 s (STM32F405 datasheet, table
"Flash memory programming", typical tprog and tERASE128KB at x32).

The key sequence KEY1, KEY2 unlocks CR; a wrong key locks it until reset. While an
operation runs the core cannot fetch from flash: device time jumps over the operation at
the write that starts it ("stall"; interrupts that fall due meanwhile are taken after it,
several SysTick wraps collapse into one, as on hardware). The data cache of the F4 is not
modelled (reads always see the array).

Only the parameter pages/sectors are modelled as writable flash (targets.py), persisted in a
file (write-through). Power cuts: every unlock..lock span of the interface is one flash
operation, counted by the control channel's power_cut {after_flash_ops} exactly as the host
build counts its flash driver's calls (one erase or one program() call). The operation the
cut falls into is left half done: an erase has erased the first half of its page/sector; a
program has programmed the first half of its units (the rest stay as they were), and the
power goes off.
"""
from __future__ import annotations

import os

KEY1, KEY2 = 0x45670123, 0xCDEF89AB


class Flash:
    """The parameter region's backing store + the interface registers of one family."""

    def __init__(self, machine, lib, target, path: str):
        self.m = machine
        self.lib = lib
        self.t = target
        self.base = target.param_base
        self.size = target.param_size
        self.path = path
        self.mem = bytearray(b"\xff" * self.size)
        self._open()
        self.reset()
        self.ops_total = 0

    # ------------------------------------------------------------- backing
    def _open(self) -> None:
        if os.path.exists(self.path) and os.path.getsize(self.path) > 0:
            size = os.path.getsize(self.path)
            if size != self.size:
                raise ValueError(f"{self.path} has {size} bytes but the {self.t.name} parameter flash "
                                 f"is {self.size} bytes: a flash file of another target?")
            with open(self.path, "rb") as f:
                self.mem[:] = f.read()
        else:
            with open(self.path, "wb") as f:
                f.write(self.mem)
        self.fd = os.open(self.path, os.O_RDWR)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def _persist(self, off: int, n: int) -> None:
        os.pwrite(self.fd, bytes(self.mem[off:off + n]), off)

    def read_mem(self, off: int, size: int) -> int:
        return int.from_bytes(self.mem[off:off + size], "little")

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        self.locked = True
        self.key_state = 0          # 1: KEY1 seen
        self.key_error = False
        self.acr = self.t.flash_acr_reset
        self.cr = 0
        self.sr = 0
        self.ar = 0
        self.op_open = False
        self.op_cut = False
        self.op_writes: list[tuple[int, bytes]] = []  # (offset, previous bytes) programmed in this op

    def _op_begin(self) -> None:
        self.op_open = True
        self.op_writes = []
        self.ops_total += 1
        self.m.set_model_time(self.m.now())
        self.op_cut = bool(self.lib.simlib_flash_op())

    def _op_end(self) -> None:
        if not self.op_open:
            return
        self.op_open = False
        if self.op_cut:
            half = (len(self.op_writes) + 1) // 2
            for off, old in reversed(self.op_writes[half:]):
                self.mem[off:off + len(old)] = old
                self._persist(off, len(old))
            self.m.log(f"flash: power cut during a program operation ({half} of {len(self.op_writes)} units written)")
            self.m.request_reset("power_cut", "power cut during a flash operation")

    def _unlocked(self) -> None:
        self.locked = False
        self._op_begin()

    def _lock(self) -> None:
        if not self.locked:
            self.locked = True
            self._op_end()

    def _key(self, value: int) -> None:
        if self.key_error or not self.locked:
            self.key_error = True     # a key while unlocked or a wrong key: locked until reset
            self.m.log("flash: wrong key sequence: FLASH_CR locked until reset")
            self.locked = True
            return
        if self.key_state == 0 and value == KEY1:
            self.key_state = 1
        elif self.key_state == 1 and value == KEY2:
            self.key_state = 0
            self._unlocked()
        else:
            self.key_state = 0
            self.key_error = True
            self.m.log("flash: wrong key sequence: FLASH_CR locked until reset")

    def _stall(self, seconds: float) -> None:
        self.m.stall(seconds)

    def _erase_range(self, off: int, n: int) -> None:
        if self.op_cut:
            n2 = n // 2
            self.mem[off:off + n2] = b"\xff" * n2
            self._persist(off, n2)
            self._stall(self.t.erase_s / 2)
            self.m.log(f"flash: power cut during the erase at 0x{self.base + off:08X} (half erased)")
            self.m.request_reset("power_cut", "power cut during a flash erase")
            return
        self.mem[off:off + n] = b"\xff" * n
        self._persist(off, n)
        self._stall(self.t.erase_s)


class FlashF1(Flash):
    SR_BSY, SR_PGERR, SR_WRPRTERR, SR_EOP = 1 << 0, 1 << 2, 1 << 4, 1 << 5
    CR_PG, CR_PER, CR_MER, CR_STRT, CR_LOCK = 1 << 0, 1 << 1, 1 << 2, 1 << 6, 1 << 7

    def read(self, off: int, size: int) -> int:
        if off == 0x00:
            return self.acr
        if off == 0x0C:
            return self.sr
        if off == 0x10:
            return self.cr | (self.CR_LOCK if self.locked else 0)
        if off == 0x14:
            return self.ar
        if off == 0x1C:
            return 0x03FFFFFC   # OBR: RDPRT off, user option bytes erased
        if off == 0x20:
            return 0xFFFFFFFF   # WRPR: nothing write protected
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x00:
            self.acr = (value & 0x1F) | (0x20 if value & 0x10 else 0)   # PRFTBS (RO) follows PRFTBE
        elif off == 0x04:
            self._key(value)
        elif off == 0x0C:
            self.sr &= ~(value & (self.SR_PGERR | self.SR_WRPRTERR | self.SR_EOP))
        elif off == 0x10:
            if value & self.CR_LOCK:
                self.cr = value & ~self.CR_LOCK & 0x1677
                self._lock()
                return
            if self.locked:
                return
            self.cr = value & 0x1677     # PG PER MER OPTPG OPTER STRT OPTWRE ERRIE EOPIE
            if value & self.CR_STRT:
                self.cr &= ~self.CR_STRT
                if self.cr & self.CR_PER:
                    page = (self.ar - self.base) // self.t.erase_unit
                    if 0 <= page < self.size // self.t.erase_unit:
                        self._erase_range(page * self.t.erase_unit, self.t.erase_unit)
                        self.sr |= self.SR_EOP
                    else:
                        self.m.log(f"flash: erase of page 0x{self.ar:08X} outside the parameter pages refused")
                        self.sr |= self.SR_WRPRTERR
                elif self.cr & self.CR_MER:
                    self.m.log("flash: mass erase refused (it would erase the image)")
                    self.sr |= self.SR_WRPRTERR
        elif off == 0x14:
            self.ar = value
        else:
            self.m.unmodelled("FLASH", off, size, value)

    def program(self, off: int, size: int, value: int) -> None:
        """A CPU write into the parameter pages."""
        if self.locked or not self.cr & self.CR_PG:
            self.m.log(f"flash: write to 0x{self.base + off:08X} without PG: ignored")
            return
        if size != 2:
            self.m.log(f"flash: {size}-byte write to 0x{self.base + off:08X}: the F1 programs half-words")
            self.sr |= self.SR_PGERR
            return
        old = self.mem[off:off + 2]
        cur = int.from_bytes(old, "little")
        value &= 0xFFFF
        if cur != 0xFFFF and value != 0:
            self.sr |= self.SR_PGERR
            self._stall(self.t.program_s)
            return
        self.op_writes.append((off, bytes(old)))
        self.mem[off:off + 2] = value.to_bytes(2, "little")
        self._persist(off, 2)
        self._stall(self.t.program_s)
        self.sr |= self.SR_EOP


class FlashF4(Flash):
    SR_EOP, SR_OPERR, SR_WRPERR, SR_PGAERR, SR_PGPERR, SR_PGSERR, SR_BSY = (1 << 0, 1 << 1, 1 << 4, 1 << 5,
                                                                          1 << 6, 1 << 7, 1 << 16)
    CR_PG, CR_SER, CR_MER, CR_STRT, CR_LOCK = 1 << 0, 1 << 1, 1 << 2, 1 << 16, 1 << 31

    def read(self, off: int, size: int) -> int:
        if off == 0x00:
            return self.acr
        if off == 0x0C:
            return self.sr
        if off == 0x10:
            return self.cr | (self.CR_LOCK if self.locked else 0)
        if off == 0x14:
            return 0x0FFFAAED   # OPTCR reset value
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x00:
            dcrst = value & 0x1000 if not self.acr & 0x400 else self.acr & 0x1000
            self.acr = (value & 0x0707) | dcrst   # ICRST is write-only (reads 0); DCRST only while DCEN = 0
        elif off == 0x04:
            self._key(value)
        elif off == 0x0C:
            self.sr &= ~(value & 0xF3)
        elif off == 0x10:
            if value & self.CR_LOCK:
                self.cr = value & 0x0301037F
                self._lock()
                return
            if self.locked:
                return
            self.cr = value & 0x0301037F
            if value & self.CR_STRT:
                self.cr &= ~self.CR_STRT
                if self.cr & self.CR_SER:
                    snb = (self.cr >> 3) & 0xF
                    off_s = self.t.sector_offset(snb)
                    if off_s is None:
                        self.m.log(f"flash: erase of sector {snb} outside the parameter sectors refused")
                        self.sr |= self.SR_WRPERR
                    else:
                        self._erase_range(off_s, self.t.erase_unit)
                        self.sr |= self.SR_EOP
                elif self.cr & self.CR_MER:
                    self.m.log("flash: mass erase refused (it would erase the image)")
                    self.sr |= self.SR_WRPERR
        elif off == 0x14:
            pass
        else:
            self.m.unmodelled("FLASH", off, size, value)

    def program(self, off: int, size: int, value: int) -> None:
        if self.locked or not self.cr & self.CR_PG:
            self.sr |= self.SR_PGSERR
            return
        psize = 1 << ((self.cr >> 8) & 3)
        if size != psize:
            self.sr |= self.SR_PGPERR
            return
        if off % size:
            self.sr |= self.SR_PGAERR
            return
        old = bytes(self.mem[off:off + size])
        new = (int.from_bytes(old, "little") & value).to_bytes(size, "little")
        self.op_writes.append((off, old))
        self.mem[off:off + size] = new
        self._persist(off, size)
        self._stall(self.t.program_s)
        self.sr |= self.SR_EOP
