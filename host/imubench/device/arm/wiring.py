"""The emulated board's bus: every peripheral, the system control space, the flash interface
and the unique-ID area mapped into the CPU's address space, each gated by its RCC clock, and the
hooks on the image's own functions (the main loop, the board's delay, its time read, the
interrupt unmasks) that the fast-forward (arm/fastforward.py) uses. A mixin of Machine
(arm/machine.py), which holds the peripherals it maps."""
from __future__ import annotations

from .image import code_regions


class BusWiring:
    # ------------------------------------------------------------------ wiring
    def _map(self, map_path: str | None) -> None:
        t = self.target
        regions = []
        self._gates: dict[str, bool] = {}

        def periph(name, obj, timed):
            base = t.periph[name]
            gate = self._gates
            gate[name] = self.rcc.clock_on(name)

            if timed:
                def rd(off, size, obj=obj, name=name):
                    if self.dead:
                        return 0
                    if not gate[name]:
                        return self._clock_off(name, off, size, None)
                    now = self.clock.now()
                    if now >= self.next_ev:
                        self._process(now)
                    return obj.read(off, size, now)

                def wr(off, size, value, obj=obj, name=name):
                    if self.dead:
                        return
                    self.effects += 1
                    if not gate[name]:
                        self._clock_off(name, off, size, value)
                        return
                    now = self.clock.now()
                    if now >= self.next_ev:
                        self._process(now)
                    obj.write(off, size, value, now)
            else:
                def rd(off, size, obj=obj, name=name):
                    if self.dead:
                        return 0
                    if not gate[name]:
                        return self._clock_off(name, off, size, None)
                    return obj.read(off, size)

                def wr(off, size, value, obj=obj, name=name):
                    if self.dead:
                        return
                    self.effects += 1
                    if not gate[name]:
                        self._clock_off(name, off, size, value)
                        return
                    obj.write(off, size, value)
            regions.append((base, 0x400, rd, wr))

        periph("RCC", self.rcc, False)
        periph("FLASH", self.flash, False)
        periph("GPIOA", self.gpio["GPIOA"], False)
        periph("GPIOB", self.gpio["GPIOB"], False)
        if self.afio is not None:
            periph("AFIO", self.afio, False)
        if "PWR" in t.periph:
            class _Pwr:
                read = self.rcc.pwr_read
                write = self.rcc.pwr_write
            periph("PWR", _Pwr, False)
        periph("SPI1", self.spi, True)
        periph("USART1", self.usart, True)
        periph("DMA", self.dma, True)

        def scs_rd(off, size):
            if self.dead:
                return 0
            now = self.now()
            if now >= self.next_ev:
                self._process(now)
            if 0x10 <= off < 0x20:
                return self.systick.read(off - 0x10, now)
            return self.nvic.read(off, size)

        def scs_wr(off, size, value):
            if self.dead:
                return
            self.effects += 1
            now = self.now()
            if 0x10 <= off < 0x20:
                self.systick.write(off - 0x10, value, now)
            else:
                self.nvic.write(off, size, value)
        regions.append((0xE000E000, 0x1000, scs_rd, scs_wr))

        def fl_rd(off, size):
            return self.flash.read_mem(off, size)

        def fl_wr(off, size, value):
            if self.dead:
                return
            self.effects += 1
            self.flash.program(off, size, value)
        regions.append((t.param_base, t.param_size, fl_rd, fl_wr))

        def uid_rd(off, size):
            return self.uid.read(off, size)

        def uid_wr(off, size, value):
            self.unmodelled("system memory", off, size, value)
        regions.append((t.sysmem_page, 0x400, uid_rd, uid_wr))

        self.cpu.map_memory(regions)
        if map_path is None:
            reg = bytearray((t.param_base - t.flash_base) // 2)
        else:
            reg = code_regions(map_path, t)
        self.cpu.install_counter(reg)
        for a in self.cpu.wfi_addresses():
            self.cpu.hook_at(a, lambda a=a: self._on_wfi(a))
        for a in self.cpu.unmask_addresses():
            self.cpu.hook_at(a, self._on_unmask)
        self.cpu.hook_at(self.img.sym("ib_core_poll"), self._on_main_loop)
        self.cpu.hook_at(self.img.sym("b_delay_us"), self._on_delay)
        self.cpu.hook_at(self.img.sym("arm_time_us"), self._on_time_read)

    def _clock_off(self, name, off, size, value):
        key = ("clock", name)
        if key not in self._unmodelled_seen:
            self._unmodelled_seen.add(key)
            self.log(f"{name}: register 0x{off:03X} accessed with its clock off (RCC): "
                     f"{'write ignored' if value is not None else 'reads 0'}")
        self.unmodelled_count += 1
        return 0
