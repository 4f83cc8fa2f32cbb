"""GPIO ports A and B (and the F1's AFIO), as far as the images use them: pin modes and
output levels. An output level change is passed to the board wiring (targets.py), which
drives the sensors' chip selects.

F1: RM0008 9.2 (CRL, CRH, IDR, ODR, BSRR, BRR, LCKR; reset CRL/CRH = 0x44444444) and 9.4
(AFIO EVCR, MAPR, EXTICR1-4, MAPR2).
F4: RM0090 8.4 (MODER, OTYPER, OSPEEDR, PUPDR, IDR, ODR, BSRR, LCKR, AFRL, AFRH; port A and
B reset values 0xA8000000 / 0x00000280 MODER etc.).
IDR reads the output level for outputs and the pull (or the level the wiring drives, 0 for
none) for inputs; no analog behaviour, no drive strength.
"""
from __future__ import annotations


class GpioF1:
    def __init__(self, machine, name: str):
        self.m = machine
        self.name = name
        self.reset()

    def reset(self) -> None:
        self.crl = 0x44444444
        self.crh = 0x44444444
        self.odr = 0
        self.lckr = 0

    def _mode(self, pin: int) -> int:
        cr = self.crl if pin < 8 else self.crh
        return (cr >> ((pin & 7) * 4)) & 0xF

    def is_output(self, pin: int) -> bool:
        return bool(self._mode(pin) & 3)

    def idr(self) -> int:
        v = 0
        for pin in range(16):
            mode = self._mode(pin)
            if mode & 3 or mode == 0x8:   # an output, or an input with pull-up/-down (ODR selects)
                v |= (self.odr >> pin & 1) << pin
        return v

    def _set_odr(self, new: int) -> None:
        old, self.odr = self.odr, new & 0xFFFF
        if old != self.odr:
            self.m.pins_changed(self.name, old, self.odr)

    def read(self, off: int, size: int) -> int:
        return {0x0: self.crl, 0x4: self.crh, 0x8: self.idr(), 0xC: self.odr, 0x10: 0, 0x14: 0,
                0x18: self.lckr}.get(off, 0)

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x0:
            self.crl = value
            self.m.pins_changed(self.name, self.odr, self.odr)
        elif off == 0x4:
            self.crh = value
            self.m.pins_changed(self.name, self.odr, self.odr)
        elif off == 0xC:
            self._set_odr(value)
        elif off == 0x10:  # BSRR: set bits 15:0, reset bits 31:16 (set wins)
            self._set_odr((self.odr & ~(value >> 16)) | (value & 0xFFFF))
        elif off == 0x14:  # BRR
            self._set_odr(self.odr & ~value)
        elif off == 0x18:
            self.lckr = value & 0x1FFFF
        else:
            self.m.unmodelled(self.name, off, size, value)


class AfioF1:
    # EVCR, MAPR (SWJ_CFG 26:24 is write-only: reads 0), EXTICR1-4, MAPR2 (RM0008 9.4)
    WRITABLE = {0x0: 0xFF, 0x4: 0x001FFFFF, 0x8: 0xFFFF, 0xC: 0xFFFF, 0x10: 0xFFFF, 0x14: 0xFFFF, 0x1C: 0x7E0}

    def __init__(self, machine):
        self.m = machine
        self.regs: dict[int, int] = {}

    def reset(self) -> None:
        self.regs = {}

    def read(self, off: int, size: int) -> int:
        return self.regs.get(off, 0)

    def write(self, off: int, size: int, value: int) -> None:
        if off in self.WRITABLE:
            self.regs[off] = value & self.WRITABLE[off]
            if off == 0x4 and value & 1:
                self.m.log("AFIO: SPI1 remapped (MAPR.SPI1_REMAP): the board wires the default pins")
        else:
            self.m.unmodelled("AFIO", off, size, value)


class GpioF4:
    RESET = {"GPIOA": (0xA8000000, 0x0C000000, 0x64000000), "GPIOB": (0x00000280, 0x000000C0, 0x00000100)}

    def __init__(self, machine, name: str):
        self.m = machine
        self.name = name
        self.reset()

    def reset(self) -> None:
        moder, ospeedr, pupdr = self.RESET.get(self.name, (0, 0, 0))
        self.regs = {0x00: moder, 0x04: 0, 0x08: ospeedr, 0x0C: pupdr, 0x1C: 0, 0x20: 0, 0x24: 0}
        self.odr = 0

    def is_output(self, pin: int) -> bool:
        return (self.regs[0x00] >> (2 * pin) & 3) == 1

    def idr(self) -> int:
        v = 0
        moder, pupdr = self.regs[0x00], self.regs[0x0C]
        for pin in range(16):
            mode = moder >> (2 * pin) & 3
            if mode == 1:
                v |= (self.odr >> pin & 1) << pin
            elif mode in (0, 2) and (pupdr >> (2 * pin) & 3) == 1:
                v |= 1 << pin
        return v

    def _set_odr(self, new: int) -> None:
        old, self.odr = self.odr, new & 0xFFFF
        if old != self.odr:
            self.m.pins_changed(self.name, old, self.odr)

    def read(self, off: int, size: int) -> int:
        if off == 0x10:
            return self.idr()
        if off == 0x14:
            return self.odr
        if off == 0x18:
            return 0
        if off in self.regs:
            return self.regs[off]
        self.m.unmodelled(self.name, off, size, None)
        return 0

    def write(self, off: int, size: int, value: int) -> None:
        if off == 0x14:
            self._set_odr(value)
        elif off == 0x18:
            if size == 2:  # half-word access to BSRR's reset half (BSRRH) or set half
                value = value & 0xFFFF
            self._set_odr((self.odr & ~(value >> 16)) | (value & 0xFFFF))
        elif off in self.regs:
            self.regs[off] = value & {0x04: 0xFFFF, 0x1C: 0x1FFFF}.get(off, 0xFFFFFFFF)   # OTYPER, LCKR
            if off == 0x00:
                self.m.pins_changed(self.name, self.odr, self.odr)
        else:
            self.m.unmodelled(self.name, off, size, value)
