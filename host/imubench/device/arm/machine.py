"""The emulated board: the exact STM32 image on the Unicorn CPU, its peripherals, the sensor
models, the serial endpoint and the control channel of the virtual device, and the event
loop that runs them in device time.

Device time and events (docs/firmware.md, "The ARM images under emulation"): device time is
the executed instruction count x CPI / SYSCLK (clock.py). The loop runs the CPU until the
instruction count at which the next event falls due (a SysTick count to 0, the end of a DMA
transfer, a received byte, a control-channel deadline), processes the event (pending
exceptions are then taken) and runs on. Reads of peripheral registers see their state at the
current device time.

Fast-forward (what makes a session run near real time in Python):
  * WFI: the core sleeps until the next event that wakes it; device time jumps there.
  * the main loop with nothing to do: when two consecutive passes of the image's main loop
    (marked by the entry of ib_core_poll) leave SRAM (.data/.bss, the stack excluded)
    unchanged, with no peripheral write and no exception in between, the next pass would be
    the same again until an event or the sample tick falls due: device time jumps to the
    earliest of the next event and the tick's due time (read from the image's own variables
    g_tick_next_us / g_tick_period_us, in its own microsecond clock g_ms + SysTick).
  * the board's delay (b_delay_us): after its start time is read, later reads of the time
    jump to its end or the next event, whichever is first.
  * polling SPI SR while a frame is in flight: time jumps to the frame's end.
  * a flash program/erase: time jumps over it at the write that starts it (the core stalls
    on flash fetches during the operation on hardware).
Skipped time is accounted as idle (WFI, main loop) or busy (delay, SPI, flash stall); the
CPU load figures of bench/arm_cycles.py count only idle time as free.
"""
from __future__ import annotations

import random
import sys
import time
from ctypes import c_uint8, c_uint64

from unicorn import UcError
from unicorn.arm_const import UC_ARM_REG_PC

from .clock import Clock
from .core import Cpu, ElfImage
from .dma import DmaF1, DmaF4
from .flash import FlashF1, FlashF4
from .gpio import AfioF1, GpioF1, GpioF4
from .nvic import Nvic
from .rcc import RccF1, RccF4
from .spi import Spi
from .systick import SysTick
from .targets import Target
from .uid import UniqueId
from .usart import Usart
from .wiring import BusWiring
from .fastforward import FastForward

REGION_NAMES = ("other", "core", "drivers", "board", "lib")
INF = float("inf")
MAX_LAG_WALL_S = 0.2
RESET_POWER_CUT = 2


class Machine(BusWiring, FastForward):
    """The board: its peripherals and the event loop (the bus wiring: arm/wiring.py; the
    fast-forward hooks: arm/fastforward.py)."""

    def __init__(self, target: Target, elf_path: str, map_path: str | None, lib, flash_path: str,
                 seed: int = 1, hse: bool = True, log=None, t0: float = 0.0, boot0: bool = False):
        self.target = target
        self.lib = lib
        self._log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.img = ElfImage(elf_path)
        self.cpu = Cpu(self, target, self.img, lib)
        f1 = target.name == "f103"
        self.rcc = RccF1(self, hse) if f1 else RccF4(self, hse)
        self.clock = Clock(lib, target.cpi, self.rcc.sysclk_hz())
        self.clock._t_base = t0       # device time goes on across a bootloader session
        self.boot0 = boot0            # a reset enters the ROM bootloader instead of the image
        self.exit_to_rom = False
        self.nvic = Nvic(self, target.n_irq)
        self.systick = SysTick(self)
        if f1:
            self.gpio = {"GPIOA": GpioF1(self, "GPIOA"), "GPIOB": GpioF1(self, "GPIOB")}
            self.afio = AfioF1(self)
        else:
            self.gpio = {"GPIOA": GpioF4(self, "GPIOA"), "GPIOB": GpioF4(self, "GPIOB")}
            self.afio = None
        self.spi = Spi(self, lib)
        self.usart = Usart(self, lib, target.irq_usart1)
        usart_dr = target.periph["USART1"] + 4
        self.dma = (DmaF1 if f1 else DmaF4)(self, self.usart, target.irq_dma_tx, usart_dr)
        self.flash = (FlashF1 if f1 else FlashF4)(self, lib, target, flash_path)
        uid = (c_uint8 * 12)()
        lib.simlib_uid(uid)
        self.uid = UniqueId(target.sysmem_page, target.uid_addr, target.fsize_addr, target.flash_kib, bytes(uid))
        self.rng = random.Random(seed)

        # statistics
        self.faults = 0
        self.unmodelled_count = 0
        self._unmodelled_seen: set = set()
        self.boots = 0
        self.reboots = 0
        self.power_cuts = 0
        self.exceptions = 0
        self.idle_jumps = 0
        self.idle_instructions = 0  # instructions of main-loop passes that did nothing
        self._prev_ic = 0
        self.effects = 0            # peripheral writes and side-effect reads (idle detection)

        # run state
        self.running = False
        self.dead = False           # a reset was requested: peripherals ignore the rest
        self.reset_req: tuple[str, str] | None = None
        self.next_ev = INF
        self.t_stop = INF
        self._prev_ram = None
        self._prev_sig = None
        self.delay: list | None = None
        self.cs_low: int | None = None

        self._map(map_path)
        self._sym = {n: self.img.sym(n) for n in ("g_ms", "g_tick_period_us", "g_tick_next_us",
                                                  "g_systick_load", "g_cycles_per_us", "_sdata", "_ebss")}
        tick_syms = [self._sym[n] for n in ("g_ms", "g_tick_period_us", "g_tick_next_us", "g_systick_load",
                                             "g_cycles_per_us")]
        self._tick_lo, self._tick_len = min(tick_syms), max(tick_syms) + 4 - min(tick_syms)
        self._ram_lo = self._sym["_sdata"]
        self._ram_len = self._sym["_ebss"] - self._sym["_sdata"]
        # The core's time bookkeeping (uptime, last time seen) changes on every pass of the
        # main loop, as a function of time only: left out of the idle comparison.
        members = self.img.struct_members("core/core.c", "ib_core")
        core = self.img.sym("g_core")
        self._ram_excl = [(core + members[k] - self._ram_lo, 4) for k in ("uptime_ms", "uptime_us_rem",
                                                                           "last_time_us")]
        self._stream_state_addr = core + members["stream_state"]
        self.power_on()

    # --------------------------------------------------------------- services
    def log(self, msg: str) -> None:
        self._log(f"[imubench-arm {self.target.name} {self.now():.6f}] {msg}")

    def unmodelled(self, what: str, off: int, size: int, value) -> None:
        self.unmodelled_count += 1
        key = (what, off)
        if key not in self._unmodelled_seen:
            self._unmodelled_seen.add(key)
            v = "read" if value is None else f"write 0x{value:X}"
            self.log(f"unmodelled {what} register +0x{off:03X} ({size} bytes, {v})")

    def now(self) -> float:
        return self.clock.now()

    def set_model_time(self, t: float) -> None:
        """Bring the sensor models and the control channel to device time t (whole µs, rounded:
        a device time a hair under an event's µs, from the float arithmetic, must still reach
        it). While an SPI transaction is open the models stay at its chip-select time: it is
        answered from that state byte by byte and committed from it at chip select rise, so
        the sensors must not move on in between (an ADXL355 FIFO that filled meanwhile made the
        commit differ from the bytes the image had received)."""
        spi = self.spi
        if spi.cs is not None and spi.tx and t > spi.t_cs:
            t = spi.t_cs
        self.lib.simlib_set_time(round(t * 1e6))

    def events_changed(self) -> None:
        self._recompute_next()
        if self.running:
            self.lib.simlib_set_limit(self.clock.limit_for(min(self.next_ev, self.t_stop)))
            if self.nvic.pending:
                self.exception_maybe_ready()

    def _recompute_next(self) -> None:
        self.next_ev = min(self.systick.next_event(), self.dma.next_event(), self.usart.next_event(),
                           self.ext_deadline)

    ext_deadline = INF   # control-channel / physics deadline (device s)

    def stop_soon(self) -> None:
        """Stop the CPU at the next block boundary. Not uc.emu_stop(): called from an MMIO
        callback that makes the access be executed again on resume (a register write would
        happen twice)."""
        self.lib.simlib_set_limit(0)

    MASKED_POLL = 16   # instructions between checks while an exception waits for PRIMASK

    def exception_maybe_ready(self) -> None:
        if not self.running:
            return
        if self.nvic.next_exception(self.cpu.primask()) is not None:
            self.stop_soon()
        elif self.nvic.next_exception(0) is not None:
            # masked by PRIMASK: clearing it is an instruction, not an access we see, so
            # look again every few instructions until the exception has been taken
            self.lib.simlib_set_limit(self.clock.instructions() + self.MASKED_POLL)

    def clock_changed(self) -> None:
        for name in self._gates:
            self._gates[name] = self.rcc.clock_on(name)
        f = self.rcc.sysclk_hz()
        if f != self.clock.f_hz:
            now = self.now()
            self.clock.set_freq(f)
            self.systick.clock_changed(now)
            self.events_changed()

    def _after_skip(self) -> None:
        now = self.now()
        if now >= self.next_ev:
            self._process(now)
        if self.running:
            self.lib.simlib_set_limit(self.clock.limit_for(min(self.next_ev, self.t_stop)))
            if self.nvic.pending:
                self.exception_maybe_ready()

    def busy_wait_until(self, t: float) -> None:
        self.clock.skip(t - self.now(), "busy")
        self._after_skip()

    def stall(self, seconds: float) -> None:
        self.clock.skip(seconds, "stall")
        self._after_skip()

    def request_reset(self, kind: str, why: str) -> None:
        if self.reset_req is None or kind == "power_cut":
            self.reset_req = (kind, why)
        self.dead = True
        if self.running:
            self.stop_soon()

    def model_error(self, e: Exception) -> None:
        import traceback
        self.faults += 1
        self.log("peripheral model error (a bug in the emulator, not the image):\n" + "".join(
            traceback.format_exception(type(e), e, e.__traceback__)))

    def cpu_fault(self, msg: str) -> None:
        self.faults += 1
        self.log(f"CPU fault: {msg}; the image's fault handler resets the MCU")
        self.request_reset("reboot", "CPU fault")

    def pins_changed(self, port: str, old: int, new: int) -> None:
        low = None
        for i, (p, pin) in enumerate(self.target.cs_pins):
            g = self.gpio[p]
            if g.is_output(pin) and not (g.odr >> pin) & 1:   # an input pin selects nothing
                if low is not None:
                    self.log(f"SPI: chip selects {low} and {i} low together (bus contention)")
                low = i if low is None else low
        if low != self.cs_low:
            self.cs_low = low
            self.spi.select(low, self.now())

    # ------------------------------------------------------------------ events
    def _process(self, t: float) -> None:
        self.systick.update(t)
        self.dma.update(t)
        self.usart.update(t)
        self.spi.update(t)
        self._recompute_next()

    # -------------------------------------------------------------- idle hooks
    def power_on(self) -> None:
        uc = self.cpu.uc
        garbage = bytes(self.rng.getrandbits(8) for _ in range(self.target.ram_size))
        uc.mem_write(self.target.ram_base, garbage)   # SRAM content at power-up is undefined
        for addr, data in self.img.segments:
            if self.target.ram_base <= addr:
                uc.mem_write(addr, data)
        self._reset_all()

    def _reset_all(self) -> None:
        now = self.now()
        self.usart.drain(now)
        for p in (self.rcc, self.nvic, self.systick, *self.gpio.values(), self.spi, self.usart, self.dma,
                  self.flash):
            p.reset()
        if self.afio is not None:
            self.afio.reset()
        self.cs_low = None
        self.clock.set_freq(self.rcc.sysclk_hz())
        self.cpu.reset()
        self.dead = False
        self.delay = None
        self._prev_ram = None
        self.boots += 1
        self.lib.simlib_flash_boot()
        self._recompute_next()

    def take_reset(self) -> None:
        kind, why = self.reset_req
        self.reset_req = None
        if kind == "power_cut":
            self.power_cuts += 1
            self.set_model_time(self.now())
            self.lib.simlib_power_cycle_models()
            self.usart.reset()
            self.lib.simlib_link_reset()
            self.log(f"{why}: power-cycling the sensors and the MCU")
            if self.boot0:
                self.exit_to_rom = True
                return
            self.power_on()
        else:
            self.reboots += 1
            if self.boot0:
                self.log(f"reset ({why}): BOOT0 is high, the ROM bootloader starts")
                self.exit_to_rom = True
                return
            self.log(f"reset ({why}): restarting the image")
            self._reset_all()

    # --------------------------------------------------------------------- run
    def run_until(self, t_stop: float, wall_budget_s: float = 0.01, idle_cap: float = INF) -> None:
        """Run the board until device time t_stop (or the wall budget is used up). A core
        sleeping in WFI does not sleep past idle_cap (speed 0: idle device time follows the
        wall clock, as imubench-sim's does)."""
        wall_end = time.monotonic() + wall_budget_s
        cpu = self.cpu
        while True:
            now = self.now()
            if now >= t_stop or time.monotonic() > wall_end:
                return
            if self.reset_req is not None:
                self.take_reset()
                if self.exit_to_rom:
                    return
                continue
            self._process(now)
            while True:
                exc = self.nvic.next_exception(cpu.primask())
                if exc is None:
                    break
                if cpu.wfi:
                    cpu.wfi = False
                    cpu.uc.reg_write(UC_ARM_REG_PC, cpu.wfi_pc + 2)
                self.nvic.activate(exc)
                cpu.enter_exception(exc, self.nvic.vtor or self.target.flash_base)
                self.exceptions += 1
            if cpu.wfi:
                if self.nvic.wakeable():
                    cpu.wfi = False
                    cpu.uc.reg_write(UC_ARM_REG_PC, cpu.wfi_pc + 2)
                else:
                    if now >= idle_cap:
                        return
                    target = min(self.next_ev, t_stop, idle_cap)
                    self.clock.skip(target - now, "idle")
                    continue
            self.t_stop = t_stop
            limit = self.clock.limit_for(min(self.next_ev, t_stop))
            if self.nvic.pending and self.nvic.next_exception(0) is not None:   # waiting for PRIMASK
                limit = min(limit, self.clock.instructions() + self.MASKED_POLL)
            self.lib.simlib_set_limit(limit)
            self.running = True
            try:
                cpu.run()
            except UcError as e:
                self.running = False
                if self.reset_req is None:
                    self.cpu_fault(f"{e} at pc 0x{cpu.pc():08X}")
                continue
            finally:
                self.running = False
            if cpu.exc_exit:
                cpu.exit_exception()
                self.nvic.deactivate()

    def instructions_by_region(self) -> dict[str, int]:
        out = (c_uint64 * 8)()
        self.lib.simlib_region_counts(out)
        return {REGION_NAMES[i]: out[i] for i in range(len(REGION_NAMES))}

    def streaming(self) -> bool:
        return int.from_bytes(self.cpu.uc.mem_read(self._sym["g_tick_period_us"], 4), "little") != 0

    def tick_hz(self) -> int:
        p = int.from_bytes(self.cpu.uc.mem_read(self._sym["g_tick_period_us"], 4), "little")
        return round(1e6 / p) if p else 0

    def publish(self) -> None:
        """What the control channel's status reports about the firmware side."""
        state = self.cpu.uc.mem_read(self._stream_state_addr, 1)[0]
        self.lib.simlib_set_state(state, self.tick_hz(), 0, 0, self.boots,
                                  self.power_cuts, self.reboots)
        self.lib.simlib_set_target(self.target.name.encode(), self.clock.instructions(), self.faults,
                                   self.unmodelled_count, self.spi.mismatches, self.clock.skipped["idle"],
                                   self.rcc.sysclk_hz())
        regions = (c_uint64 * 8)()
        self.lib.simlib_region_counts(regions)
        sk = self.clock.skipped
        self.lib.simlib_set_arm_detail(regions, self.idle_instructions, sk["busy"], sk["stall"], self.spi.bus_time,
                                       self.spi.bytes, self.spi.transactions, self.clock.cpi)
