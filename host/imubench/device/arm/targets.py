"""The two boards the images are built for, as the emulator wires them.

Addresses from the reference manuals (RM0008 3.3, RM0090 2.3), interrupt numbers from their
vector tables (RM0008 10.1.2, RM0090 12.2), the parameter flash from the images' linker
scripts (firmware/boards/stm32f1/f103.ld, firmware/boards/stm32f4/f4.ld), the chip selects
from the boards' wiring (firmware/boards/stm32f1/chip_f1.c, stm32f4/chip_f4.c pin lists).

CPI, the cycles per executed instruction that turns the instruction count into device time:
1.5 on both chips. It is an estimate, not a measurement: the Cortex-M3/M4 execute most data
processing instructions in 1 cycle, loads/stores in 2 (1 when pipelined), taken branches in
2-4 (ARM DDI 0337 Cortex-M3 Technical Reference Manual, 18.2 "Processor instruction timings";
ARM DDI 0439 Cortex-M4 TRM 3.3), plus flash wait states the prefetch buffer (F1, 2 wait
states at 72 MHz) or the ART accelerator (F4, 5 wait states at 168 MHz) mostly hide; 1.5 is
the middle of the 1.2-1.8 range such mixes give on branchy control code. Every CPU load
figure of bench/arm_cycles.py scales with it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

KIB = 1024


@dataclass(frozen=True)
class Target:
    name: str
    cpu: str                      # "cortex-m3" / "cortex-m4"
    image: str                    # build/arm/<image>/imubench.elf
    flash_base: int
    flash_size: int               # mapped flash (code + parameter region)
    ram_base: int
    ram_size: int
    param_base: int               # writable parameter region (modelled flash)
    param_size: int
    erase_unit: int               # page (F1) / sector (F4) bytes
    program_s: float              # one program unit
    erase_s: float                # one page / sector
    flash_acr_reset: int
    n_irq: int
    irq_usart1: int
    irq_dma_tx: int
    periph: dict = field(default_factory=dict)   # name -> base address
    sysmem_page: int = 0
    uid_addr: int = 0
    fsize_addr: int = 0
    flash_kib: int = 0
    cs_pins: tuple = ()           # chip select i -> (GPIO port name, pin)
    cpi: float = 1.5
    sysclk_nominal_hz: float = 0.0

    @property
    def code_file_size(self) -> int:
        """Bytes of the code file (bootloader.code_path): every flash byte outside the parameter
        region, [flash_base, param_base) then [param_base + param_size, flash_base + flash_size)."""
        return self.flash_size - self.param_size

    def sector_offset(self, snb: int) -> int | None:
        """F4: offset of sector snb in the parameter region (None: not a parameter sector)."""
        if self.name != "f4":
            return None
        return {10: 0, 11: 128 * KIB}.get(snb)


# The F103 board is an STM32F103CB (medium density, 128 KiB flash in 1 KiB pages, 20 KiB RAM;
# RM0008 3.3.3, DS5319 table 2): its F_SIZE register reads 128, its ROM bootloader accepts
# 0x08000000-0x0801FFFF (AN2606, "STM32F10xxx medium-density"; stm32flash's table for ID 0x410
# ends there too). The image and its parameter pages use only the lower 64 KiB
# (firmware/boards/stm32f1/f103.ld), so the same image also runs on a 64 KiB F103C8.
F103 = Target(
    name="f103", cpu="cortex-m3", image="f103",
    flash_base=0x08000000, flash_size=128 * KIB, ram_base=0x20000000, ram_size=20 * KIB,
    param_base=0x0800F800, param_size=2 * KIB, erase_unit=1 * KIB,
    program_s=52.5e-6, erase_s=20e-3, flash_acr_reset=0x30,
    n_irq=68, irq_usart1=37, irq_dma_tx=14,
    periph={"AFIO": 0x40010000, "GPIOA": 0x40010800, "GPIOB": 0x40010C00, "SPI1": 0x40013000,
            "USART1": 0x40013800, "DMA": 0x40020000, "RCC": 0x40021000, "FLASH": 0x40022000},
    sysmem_page=0x1FFFF400, uid_addr=0x1FFFF7E8, fsize_addr=0x1FFFF7E0, flash_kib=128,
    cs_pins=(("GPIOA", 4), ("GPIOB", 0), ("GPIOB", 1), ("GPIOB", 10)),
    sysclk_nominal_hz=72e6,
)

F4 = Target(
    name="f4", cpu="cortex-m4", image="f4",
    flash_base=0x08000000, flash_size=1024 * KIB, ram_base=0x20000000, ram_size=128 * KIB,
    param_base=0x080C0000, param_size=256 * KIB, erase_unit=128 * KIB,
    program_s=16e-6, erase_s=1.0, flash_acr_reset=0,
    n_irq=82, irq_usart1=37, irq_dma_tx=70,
    periph={"PWR": 0x40007000, "USART1": 0x40011000, "SPI1": 0x40013000, "GPIOA": 0x40020000,
            "GPIOB": 0x40020400, "RCC": 0x40023800, "FLASH": 0x40023C00, "DMA": 0x40026400},
    sysmem_page=0x1FFF7800, uid_addr=0x1FFF7A10, fsize_addr=0x1FFF7A22, flash_kib=1024,
    cs_pins=(("GPIOA", 4), ("GPIOB", 0), ("GPIOB", 1), ("GPIOB", 10)),
    sysclk_nominal_hz=168e6,
)

TARGETS = {"f103": F103, "f4": F4}
