"""Reset and clock control: what SYSCLK, HCLK and PCLK2 the image configured, and which
peripheral clocks are on.

F1: RM0008 Rev 21 7.3 (CR, CFGR, CIR, APB2RSTR, APB1RSTR, AHBENR, APB2ENR, APB1ENR, BDCR,
CSR). HSI 8 MHz; the board's crystal (HSE) is 8 MHz; PLL = (HSE / (1 + PLLXTPRE) or HSI / 2)
x PLLMUL.
F4: RM0090 Rev 19 7.3 (CR, PLLCFGR, CFGR, AHBxENR, APBxENR, ...), HSI 16 MHz, HSE 8 MHz;
PLL = src / M x N / P. F4's PWR CR/CSR (RM0090 5.4) live here too (VOS, VOSRDY).

Oscillator and PLL ready flags follow their enable bits at once (start-up and lock times,
a few hundred microseconds on hardware, are not modelled); SWS follows SW when the selected
source is ready. `hse=False` models a board whose crystal does not start (HSERDY never
sets), to exercise the image's fallback to HSI.
"""
from __future__ import annotations

MHZ = 1_000_000
AHB_DIV = {8: 2, 9: 4, 10: 8, 11: 16, 12: 64, 13: 128, 14: 256, 15: 512}
APB_DIV = {4: 2, 5: 4, 6: 8, 7: 16}


class RccF1:
    HSI = 8 * MHZ
    HSE = 8 * MHZ

    def __init__(self, machine, hse: bool = True):
        self.m = machine
        self.hse_ok = hse
        self.reset()

    def reset(self) -> None:
        self.cr = 0x00000083
        self.cfgr = 0
        self.regs = {0x08: 0, 0x0C: 0, 0x10: 0, 0x14: 0x14, 0x18: 0, 0x1C: 0, 0x20: 0, 0x24: 0x0C000000}
        self._sws_last = 0

    def _ready_cr(self) -> int:
        v = self.cr & ~((1 << 1) | (1 << 17) | (1 << 25))
        if self.cr & 1:
            v |= 1 << 1
        if self.cr & (1 << 16) and self.hse_ok:
            v |= 1 << 17
        if self.cr & (1 << 24) and self._pll_src_ready():
            v |= 1 << 25
        return v

    def _pll_src_ready(self) -> bool:
        return bool(self.cr & (1 << 16) and self.hse_ok) if self.cfgr & (1 << 16) else bool(self.cr & 1)

    def _sws(self) -> int:
        cr = self._ready_cr()
        sw = self.cfgr & 3
        ok = {0: cr & 2, 1: cr & (1 << 17), 2: cr & (1 << 25)}.get(sw, 0)
        return sw if ok else self._sws_last

    def sysclk_hz(self) -> float:
        sws = self._sws()
        if sws == 1:
            return self.HSE
        if sws == 2:
            mul = min(((self.cfgr >> 18) & 0xF) + 2, 16)
            src = (self.HSE / (2 if self.cfgr & (1 << 17) else 1)) if self.cfgr & (1 << 16) else self.HSI / 2
            return src * mul
        return self.HSI

    def hclk_hz(self) -> float:
        return self.sysclk_hz() / AHB_DIV.get((self.cfgr >> 4) & 0xF, 1)

    def pclk2_hz(self) -> float:
        return self.hclk_hz() / APB_DIV.get((self.cfgr >> 11) & 7, 1)

    def clock_on(self, name: str) -> bool:
        bits = {"AFIO": (0x18, 0), "GPIOA": (0x18, 2), "GPIOB": (0x18, 3), "SPI1": (0x18, 12),
                "USART1": (0x18, 14), "DMA": (0x14, 0)}
        if name not in bits:
            return True
        reg, bit = bits[name]
        return bool(self.regs[reg] >> bit & 1)

    def read(self, off: int, size: int) -> int:
        if off == 0x00:
            return self._ready_cr()
        if off == 0x04:
            return (self.cfgr & ~0xC) | (self._sws() << 2)
        if off in self.regs:
            return self.regs[off]
        self.m.unmodelled("RCC", off, size, None)
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x00:
            if (self._sws() == 2) and not value & (1 << 24):
                value |= 1 << 24  # PLLON cannot be cleared while the PLL clocks the system
            self.cr = value & 0x010D00F9 | (self.cr & 0xFF00)
        elif off == 0x04:
            self.cfgr = value & 0x077FFFF3
        elif off in self.regs:
            self.regs[off] = value & self.WRITABLE.get(off, 0xFFFFFFFF)
        else:
            self.m.unmodelled("RCC", off, size, value)
            return
        self._sws_last = self._sws()
        self.m.clock_changed()

    # the bits the F103 family defines (ST's SVD; tests/firmware/test_svd_registers.py), the rest reserved
    WRITABLE = {0x0C: 0x0038FFFD, 0x10: 0x3AFEC9FF, 0x14: 0x557, 0x18: 0x0038FFFD, 0x1C: 0x3AFEC9FF}


class RccF4:
    HSI = 16 * MHZ
    HSE = 8 * MHZ

    def __init__(self, machine, hse: bool = True):
        self.m = machine
        self.hse_ok = hse
        self.reset()

    def reset(self) -> None:
        self.cr = 0x00000083
        self.pllcfgr = 0x24003010
        self.cfgr = 0
        self.regs = {0x0C: 0, 0x10: 0, 0x14: 0, 0x18: 0, 0x20: 0, 0x24: 0, 0x30: 0x00100000, 0x34: 0,
                     0x38: 0, 0x40: 0, 0x44: 0, 0x50: 0x7E6791FF, 0x54: 0xF1, 0x58: 0x1, 0x60: 0x36FEC9FF,
                     0x64: 0x75F33, 0x70: 0, 0x74: 0x0E000000, 0x80: 0, 0x84: 0x20003000}
        self.pwr_cr = 0x4000
        self.pwr_csr = 0
        self._sws_last = 0

    def _ready_cr(self) -> int:
        v = self.cr & ~((1 << 1) | (1 << 17) | (1 << 25))
        if self.cr & 1:
            v |= 1 << 1
        if self.cr & (1 << 16) and self.hse_ok:
            v |= 1 << 17
        src_ready = (self.cr & (1 << 16) and self.hse_ok) if self.pllcfgr & (1 << 22) else self.cr & 1
        if self.cr & (1 << 24) and src_ready:
            v |= 1 << 25
        return v

    def _sws(self) -> int:
        cr = self._ready_cr()
        sw = self.cfgr & 3
        ok = {0: cr & 2, 1: cr & (1 << 17), 2: cr & (1 << 25)}.get(sw, 0)
        return sw if ok else self._sws_last

    def sysclk_hz(self) -> float:
        sws = self._sws()
        if sws == 1:
            return self.HSE
        if sws == 2:
            m = self.pllcfgr & 0x3F
            n = (self.pllcfgr >> 6) & 0x1FF
            p = 2 * (((self.pllcfgr >> 16) & 3) + 1)
            src = self.HSE if self.pllcfgr & (1 << 22) else self.HSI
            return src / max(m, 2) * n / p
        return self.HSI

    def hclk_hz(self) -> float:
        return self.sysclk_hz() / AHB_DIV.get((self.cfgr >> 4) & 0xF, 1)

    def pclk2_hz(self) -> float:
        return self.hclk_hz() / APB_DIV.get((self.cfgr >> 13) & 7, 1)

    def clock_on(self, name: str) -> bool:
        bits = {"GPIOA": (0x30, 0), "GPIOB": (0x30, 1), "DMA": (0x30, 22), "USART1": (0x44, 4),
                "SPI1": (0x44, 12), "PWR": (0x40, 28)}
        if name not in bits:
            return True
        reg, bit = bits[name]
        return bool(self.regs[reg] >> bit & 1)

    def read(self, off: int, size: int) -> int:
        if off == 0x00:
            return self._ready_cr()
        if off == 0x04:
            return self.pllcfgr
        if off == 0x08:
            return (self.cfgr & ~0xC) | (self._sws() << 2)
        if off in self.regs:
            return self.regs[off]
        self.m.unmodelled("RCC", off, size, None)
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x00:
            if self._sws() == 2 and not value & (1 << 24):
                value |= 1 << 24
            self.cr = value & 0x050D00F9 | (self.cr & 0xFF00)   # PLLI2SRDY (27) read-only
        elif off == 0x04:
            if not self.cr & (1 << 24):  # PLL configuration only while the PLL is off
                if not value & self.PLLCFGR_KEEP:
                    self.m.log("RCC_PLLCFGR written with reserved bit 29 cleared (RM0090 7.3.2: keep at reset value 1)")
                    self.m.unmodelled_count += 1
                self.pllcfgr = value & 0x0F437FFF | self.PLLCFGR_KEEP
        elif off == 0x08:
            self.cfgr = value & 0xFFFFFCF3
        elif off in self.regs:
            w = self.WRITABLE.get(off, 0xFFFFFFFF)
            self.regs[off] = value & w | self.RESET_KEEP.get(off, 0) & ~w
        else:
            self.m.unmodelled("RCC", off, size, value)
            return
        self._sws_last = self._sws()
        self.m.clock_changed()

    RESET_KEEP = {0x54: 0x30}   # AHB2LPENR 5:4 (CRYP/HASH of the F415/417): reserved here, reset value 1
    PLLCFGR_KEEP = 1 << 29    # reserved, reset value 1, "must be kept at reset value"
    # the bits the F405/407 define (ST's SVD; tests/firmware/test_svd_registers.py), the rest reserved
    WRITABLE = {0x10: 0x226011FF, 0x14: 0xC1, 0x18: 0x1, 0x20: 0x36FEC9FF, 0x24: 0x75933, 0x30: 0x7E7411FF,
                0x34: 0xC1, 0x38: 0x1, 0x40: 0x36FEC9FF, 0x44: 0x75F33, 0x50: 0x7E6791FF, 0x54: 0xC1, 0x58: 0x1,
                0x60: 0x36FEC9FF, 0x64: 0x75F33}

    # PWR (0x40007000)
    def pwr_read(self, off: int, size: int) -> int:
        if off == 0x0:
            return self.pwr_cr
        if off == 0x4:
            return self.pwr_csr | (1 << 14 if self.cr & (1 << 25) else 0)  # VOSRDY once the PLL runs
        self.m.unmodelled("PWR", off, size, None)
        return 0

    def pwr_write(self, off: int, size: int, value: int) -> None:
        if off == 0x0:
            self.pwr_cr = value & 0x43FF    # F405/407 (RM0090 5.4.1); bits 12+ of the F42x are reserved
        elif off == 0x4:
            self.pwr_csr = value & 0x300
        else:
            self.m.unmodelled("PWR", off, size, value)
