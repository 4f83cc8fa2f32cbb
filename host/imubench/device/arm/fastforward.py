"""The emulated board's fast-forward (docs/firmware.md, "The ARM images under emulation"): the
hooks on WFI, the interrupt unmasks, the main loop with nothing to do, the board's delay and its
time reads, each of which lets device time jump to the next event instead of running the
instructions in between. A mixin of Machine (arm/machine.py), which holds the state it reads.
"""
from __future__ import annotations

from unicorn.arm_const import UC_ARM_REG_R1

INF = float("inf")


class FastForward:
    def _on_wfi(self, addr: int) -> None:
        self.cpu.wfi_pc = addr
        self.cpu.on_wfi()

    def _on_unmask(self) -> None:
        """An instruction that may clear PRIMASK is about to run: if an exception waits for
        it, stop right after (the next block boundary) so it is taken there. The periodic
        MASKED_POLL check alone misses short unmasked windows, e.g. the board's sleep loop
        (mask, check, WFI, unmask, mask again: 3 instructions unmasked)."""
        if self.nvic.pending and self.nvic.next_exception(0) is not None:
            self.stop_soon()

    def _tick_due(self) -> float:
        """Device time at which the image's main loop sees its sample tick due (inf: no
        tick; <= now: due)."""
        lo, raw = self._tick_lo, self.cpu.uc.mem_read(self._tick_lo, self._tick_len)
        s = self._sym

        def word(name):
            o = s[name] - lo
            return int.from_bytes(raw[o:o + 4], "little")
        period = word("g_tick_period_us")
        if period == 0:
            return INF
        nxt = word("g_tick_next_us")
        ms = word("g_ms")
        load = word("g_systick_load")
        cpu_us = word("g_cycles_per_us") or 1
        now = self.now()
        val = self.systick.value(now)
        if 15 in self.nvic.pending:
            ms += 1
        fw_us = (ms * 1000 + (load - val if val <= load else 0) // cpu_us) & 0xFFFFFFFF
        due = (nxt - fw_us) & 0xFFFFFFFF
        if due >= 0x80000000 or due == 0:
            return now
        return now + due * 1e-6 + 0.2e-6

    def _on_main_loop(self) -> None:
        uc = self.cpu.uc
        ram = uc.mem_read(self._ram_lo, self._ram_len)
        for o, n in self._ram_excl:
            ram[o:o + n] = b"\0\0\0\0"
        sig = (self.effects, self.exceptions)
        idle = ram == self._prev_ram and sig == self._prev_sig
        ic = self.clock.instructions()
        if idle:
            self.idle_instructions += ic - self._prev_ic   # that pass did nothing
        self._prev_ic = ic
        self._prev_ram, self._prev_sig = ram, sig
        if not idle:
            return
        now = self.now()
        target = min(self.next_ev, self._tick_due(), self.t_stop)
        if target > now and target < INF:
            self.clock.skip(target - now, "idle")
            self.idle_jumps += 1
            self._after_skip()
            self.stop_soon()

    def _on_delay(self) -> None:
        us = self.cpu.uc.reg_read(UC_ARM_REG_R1)
        self.delay = [us, None]

    def _on_time_read(self) -> None:
        d = self.delay
        if d is None:
            return
        now = self.now()
        if d[1] is None:
            d[1] = now + (d[0] + 1) * 1e-6
            return
        if now >= d[1]:
            self.delay = None
            return
        target = min(d[1], self.next_ev, self.t_stop)
        if target > now:
            self.clock.skip(target - now, "busy")
            self._after_skip()
            self.stop_soon()

    # ------------------------------------------------------------------- reset
