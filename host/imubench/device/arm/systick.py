"""SysTick, the Cortex-M system timer (ARMv7-M ARM B3.3; PM0056/PM0214 4.5).

CTRL (ENABLE, TICKINT, CLKSOURCE, COUNTFLAG), LOAD (24 bit), VAL (24 bit, any write clears
it and COUNTFLAG), CALIB. The counter runs from the core clock (CLKSOURCE = 1) or the core
clock / 8 (STM32: HCLK/8) in device time: VAL is computed from device time, never stepped.
Reaching 0 sets COUNTFLAG and, with TICKINT, pends the SysTick exception; several wraps
while the core could not take the exception (e.g. a flash erase stall) pend it once, as on
hardware.
"""
from __future__ import annotations

from .nvic import SYSTICK


class SysTick:
    def __init__(self, machine):
        self.m = machine
        self.reset()

    def reset(self) -> None:
        self.ctrl = 0
        self.load = 0
        self.countflag = 0
        self.t_ref = 0.0   # device time at which the counter held v_ref
        self.v_ref = 0
        self.f = 1.0
        self.next_zero = float("inf")

    def _freq(self) -> float:
        f = self.m.rcc.hclk_hz()
        return f if self.ctrl & 4 else f / 8.0

    def _counts(self, t: float) -> int:
        return int((t - self.t_ref) * self.f + 1e-6)

    def value(self, t: float) -> int:
        if not self.ctrl & 1:
            return self.v_ref
        c = self._counts(t)
        if c <= self.v_ref:
            return self.v_ref - c
        period = self.load + 1
        return self.load - ((c - self.v_ref - 1) % period)

    def _zero_after(self, t: float) -> float:
        """Device time of the first count to 0 strictly after t."""
        if not self.ctrl & 1 or self.load == 0:
            return float("inf")
        period = self.load + 1
        c = self._counts(t)
        if self.v_ref > 0 and c < self.v_ref:
            k = self.v_ref
        else:
            first = self.v_ref if self.v_ref > 0 else period
            k = first + ((c - first) // period + 1) * period if c >= first else first
        return self.t_ref + k / self.f

    def _rebase(self, t: float) -> None:
        self.v_ref = self.value(t)
        self.t_ref = t
        self.f = self._freq()
        self.next_zero = self._zero_after(t)

    def clock_changed(self, t: float) -> None:
        if self.ctrl & 1:
            self._rebase(t)

    def update(self, t: float) -> None:
        """Process the counts to 0 up to device time t."""
        if t >= self.next_zero:
            self.countflag = 1
            if self.ctrl & 2:
                self.m.nvic.set_pending(SYSTICK)
            self.next_zero = self._zero_after(t)

    def next_event(self) -> float:
        return self.next_zero

    def read(self, off: int, t: float) -> int:
        self.update(t)
        if off == 0x0:
            v = self.ctrl | (self.countflag << 16)
            self.countflag = 0
            return v
        if off == 0x4:
            return self.load
        if off == 0x8:
            return self.value(t)
        if off == 0xC:
            return 0x40000000 | (int(self.m.rcc.hclk_hz() / 8 / 100) & 0xFFFFFF)  # CALIB: SKEW, 10 ms
        return 0

    def write(self, off: int, value: int, t: float) -> None:
        self.update(t)
        if off == 0x0:
            was = self.ctrl & 1
            self.v_ref = self.value(t) if was else self.v_ref
            self.ctrl = value & 7
            self.t_ref = t
            self.f = self._freq()
            self.next_zero = self._zero_after(t)
            self.m.events_changed()
        elif off == 0x4:
            self._rebase(t)
            self.load = value & 0xFFFFFF
            self.next_zero = self._zero_after(t)
            self.m.events_changed()
        elif off == 0x8:
            self.v_ref = 0
            self.t_ref = t
            self.countflag = 0
            self.f = self._freq()
            self.next_zero = self._zero_after(t)
            self.m.events_changed()
