"""Device time of the emulated board: ONE clock, derived from executed instructions.

Device time advances by CPI / f_sysclk per executed instruction (the instruction counter is
libimumodels.so's Unicorn block hook), where f_sysclk is the core clock the image configured
through RCC (HSI at reset, then the PLL) and CPI is the target's documented cycles-per-
instruction figure (targets.py). SysTick, the USART's baud-rate drain, SPI transfer times
and flash program/erase times are all computed from this clock, so they agree.

Fast-forward: when the core waits (WFI, or a known busy-wait: the main loop with nothing to
do, a delay, SPI/flash flag polling) the machine moves device time to the next event
instead of executing the wait instruction by instruction (`skip`); the skipped time is
accounted by kind (idle vs busy-wait) so CPU load figures stay honest.
"""
from __future__ import annotations


class Clock:
    def __init__(self, lib, cpi: float, f_hz: float):
        self._icount = lib.simlib_icount
        self.cpi = cpi
        self.f_hz = f_hz
        self._spi = cpi / f_hz          # seconds per instruction
        self._t_base = 0.0
        self._ic_base = self._icount()
        self.skipped = {"idle": 0.0, "busy": 0.0, "stall": 0.0}

    def now(self) -> float:
        """Device time in seconds."""
        return self._t_base + (self._icount() - self._ic_base) * self._spi

    def _rebase(self) -> None:
        ic = self._icount()
        self._t_base += (ic - self._ic_base) * self._spi
        self._ic_base = ic

    def set_freq(self, f_hz: float) -> None:
        """The core clock changed (RCC switched SYSCLK)."""
        if f_hz != self.f_hz:
            self._rebase()
            self.f_hz = f_hz
            self._spi = self.cpi / f_hz

    def skip(self, dt: float, kind: str) -> None:
        """The core waited dt seconds without executing (fast-forward)."""
        if dt > 0.0:
            self._rebase()
            self._t_base += dt
            self.skipped[kind] += dt

    def limit_for(self, t: float) -> int:
        """Instruction count at which device time reaches t."""
        self._rebase()
        if t <= self._t_base:
            return self._ic_base
        n = (t - self._t_base) / self._spi
        return self._ic_base + (int(n) + 1 if n < 1e15 else 10**15)

    def instructions(self) -> int:
        return self._icount()
