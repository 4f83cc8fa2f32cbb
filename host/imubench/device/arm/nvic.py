"""NVIC, system control block and the exception model of the Cortex-M3/M4 (the part
Unicorn does not have).

Registers (ARM DDI 0403 ARMv7-M Architecture Reference Manual B3.2/B3.4; ST PM0056 / PM0214
4.3-4.4): ISER/ICER/ISPR/ICPR/IABR (0xE000E100..), IPR bytes (0xE000E400..), ICSR, VTOR,
AIRCR, SCR, CCR, SHPR1-3, SHCSR, CPACR. SysTick (0xE000E010) is systick.py, dispatched from
here because it lives in the same 4 KiB System Control Space page.

Exception model (ARMv7-M ARM B1.5): an exception is taken when it is pending, enabled (IRQs
via ISER; SysTick/PendSV always) and its group priority is higher (numerically lower) than
the current execution priority, which is the priority of the highest active exception or,
in thread mode, 256; PRIMASK = 1 raises the execution priority to 0. With the reset value
of AIRCR.PRIGROUP and the 4 priority bits of an STM32 every bit is group priority. Entry and
return (stacking, vector fetch, EXC_RETURN) are done by core.py.
"""
from __future__ import annotations

SYSTICK = 15
PENDSV = 14
SVCALL = 11
HARDFAULT = 3

ICSR_PENDSTSET = 1 << 26
ICSR_PENDSTCLR = 1 << 25
ICSR_PENDSVSET = 1 << 28
ICSR_PENDSVCLR = 1 << 27
AIRCR_VECTKEY = 0x05FA
AIRCR_SYSRESETREQ = 1 << 2
PRIO_MASK = 0xF0  # STM32: 4 implemented priority bits


class Nvic:
    """Pending/enabled/active state and the SCB registers."""

    def __init__(self, machine, n_irq: int):
        self.m = machine
        self.n_irq = n_irq
        self.reset()

    def reset(self) -> None:
        self.enabled: set[int] = set()     # external IRQ numbers
        self.pending: set[int] = set()     # exception numbers
        self.active: list[int] = []        # exception numbers, innermost last
        self.ipr = bytearray(self.n_irq)   # external IRQ priority bytes
        self.shpr = bytearray(12)          # SHPR1..3: exceptions 4..15
        self.vtor = 0
        self.aircr = 0
        self.scr = 0
        self.ccr = 0x200                   # STKALIGN
        self.shcsr = 0
        self.cpacr = 0

    # ---------------------------------------------------------------- state
    def priority(self, exc: int) -> int:
        if exc == HARDFAULT:
            return -1
        if exc >= 16:
            return self.ipr[exc - 16] & PRIO_MASK
        if 4 <= exc < 16:
            return self.shpr[exc - 4] & PRIO_MASK
        return -2

    def set_pending(self, exc: int) -> None:
        if exc not in self.pending:
            self.pending.add(exc)
            self.m.exception_maybe_ready()

    def pend_irq(self, irq: int) -> None:
        self.set_pending(16 + irq)

    def exec_priority(self, primask: int) -> int:
        p = 256
        for e in self.active:
            p = min(p, self.priority(e))
        if primask & 1:
            p = min(p, 0)
        return p

    def next_exception(self, primask: int) -> int | None:
        """The pending exception that would preempt now, or None."""
        if not self.pending:
            return None
        cur = self.exec_priority(primask)
        best, best_p = None, 1000
        for e in sorted(self.pending):
            if e >= 16 and (e - 16) not in self.enabled:
                continue
            p = self.priority(e)
            if p < cur and p < best_p:
                best, best_p = e, p
        return best

    def wakeable(self) -> bool:
        """WFI wakes on any pending enabled exception of higher priority than the current
        execution priority, ignoring PRIMASK (ARMv7-M ARM B1.5.19)."""
        return self.next_exception(0) is not None

    def activate(self, exc: int) -> None:
        self.pending.discard(exc)
        self.active.append(exc)

    def deactivate(self) -> int | None:
        return self.active.pop() if self.active else None

    # ------------------------------------------------------------ registers
    def read(self, off: int, size: int) -> int:
        if 0x100 <= off < 0x180:
            return self._bits(self.enabled, (off - 0x100) // 4, 0)
        if 0x180 <= off < 0x200:
            return self._bits(self.enabled, (off - 0x180) // 4, 0)
        if 0x200 <= off < 0x300:
            return self._bits(self.pending, ((off - 0x200) % 0x80) // 4, 16)
        if 0x300 <= off < 0x380:
            return self._bits(set(self.active), (off - 0x300) // 4, 16)
        if 0x400 <= off < 0x400 + self.n_irq:
            return int.from_bytes(self.ipr[off - 0x400:off - 0x400 + size].ljust(size, b"\0"), "little")
        if off == 0xD00:
            return 0x412FC231 if self.m.target.cpu == "cortex-m3" else 0x410FC241  # CPUID
        if off == 0xD04:
            return self._icsr()
        if off == 0xD08:
            return self.vtor
        if off == 0xD0C:
            return (0xFA05 << 16) | (self.aircr & 0x700)
        if off == 0xD10:
            return self.scr
        if off == 0xD14:
            return self.ccr
        if 0xD18 <= off < 0xD24:
            i = off - 0xD18
            return int.from_bytes(self.shpr[i:i + size], "little")
        if off == 0xD24:
            return self.shcsr
        if off == 0xD88:
            return self.cpacr
        if 0xD28 <= off < 0xD40:
            return 0  # fault status registers: no faults are modelled as such
        self.m.unmodelled("SCS", off, size, None)
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if 0x100 <= off < 0x180:
            self._set_bits(self.enabled, (off - 0x100) // 4, value, 0, True)
            self.m.exception_maybe_ready()
        elif 0x180 <= off < 0x200:
            self._set_bits(self.enabled, (off - 0x180) // 4, value, 0, False)
        elif 0x200 <= off < 0x280:
            self._set_bits(self.pending, (off - 0x200) // 4, value, 16, True)
            self.m.exception_maybe_ready()
        elif 0x280 <= off < 0x300:
            self._set_bits(self.pending, (off - 0x280) // 4, value, 16, False)
        elif 0x400 <= off < 0x400 + self.n_irq:
            i = off - 0x400
            self.ipr[i:i + size] = value.to_bytes(size, "little")[: self.n_irq - i]
        elif off == 0xD04:
            if value & ICSR_PENDSTSET:
                self.set_pending(SYSTICK)
            if value & ICSR_PENDSTCLR:
                self.pending.discard(SYSTICK)
            if value & ICSR_PENDSVSET:
                self.set_pending(PENDSV)
            if value & ICSR_PENDSVCLR:
                self.pending.discard(PENDSV)
        elif off == 0xD08:
            self.vtor = value & 0xFFFFFF80
        elif off == 0xD0C:
            if (value >> 16) != AIRCR_VECTKEY:
                return  # writes without the key are ignored (B3.2.6)
            self.aircr = value & 0x700
            if value & AIRCR_SYSRESETREQ:
                self.m.request_reset("reboot", "SYSRESETREQ")
        elif off == 0xD10:
            self.scr = value & 0x16
        elif off == 0xD14:
            self.ccr = value & 0x31B
        elif 0xD18 <= off < 0xD24:
            i = off - 0xD18
            self.shpr[i:i + size] = value.to_bytes(size, "little")
            self.m.exception_maybe_ready()
        elif off == 0xD24:
            self.shcsr = value
        elif off == 0xD88:
            self.cpacr = value & 0x00F00000
        elif 0xD28 <= off < 0xD40:
            pass  # write-1-to-clear fault status: nothing recorded
        else:
            self.m.unmodelled("SCS", off, size, value)

    def _icsr(self) -> int:
        v = 0
        if self.active:
            v |= self.active[-1] & 0x1FF
            if len(self.active) == 1:
                v |= 1 << 11  # RETTOBASE
        pend = [e for e in self.pending if e < 16 or (e - 16) in self.enabled]
        if pend:
            best = min(pend, key=lambda e: (self.priority(e), e))
            v |= (best & 0x1FF) << 12
            if any(e >= 16 for e in pend):
                v |= 1 << 22
        if SYSTICK in self.pending:
            v |= ICSR_PENDSTSET
        if PENDSV in self.pending:
            v |= ICSR_PENDSVSET
        return v

    @staticmethod
    def _bits(s: set[int], word: int, base: int) -> int:
        v = 0
        for b in range(32):
            if base + 32 * word + b in s:
                v |= 1 << b
        return v

    @staticmethod
    def _set_bits(s: set[int], word: int, value: int, base: int, on: bool) -> None:
        for b in range(32):
            if value >> b & 1:
                (s.add if on else s.discard)(base + 32 * word + b)
