"""The exact STM32 images (build/arm/f103, build/arm/f4) run under the Unicorn engine against
the virtual device's sensor models: see docs/firmware.md ("The ARM images under emulation").

    core.py      the Cortex-M CPU (Unicorn), exception entry/return, instruction counter
    clock.py     device time from executed instructions (CPI x core clock), events
    nvic.py      NVIC and system control block registers, exception priorities
    systick.py   SysTick timer
    rcc.py       reset and clock control (F1 and F4) and the F4 power controller
    gpio.py      GPIO ports (F1 and F4 layouts) and the F1 AFIO
    spi.py       SPI1 master (polled or by DMA), chip selects to the C sensor models (libimumodels.so)
    usart.py     USART1 (TX shifted out at the baud rate, RX from the serial endpoint)
    dma.py       the DMA: USART1 TX (F1 DMA1 ch 4, F4 DMA2 stream 7), SPI1 RX/TX (F1 ch 2/3, F4 streams 0/3)
    flash.py     the flash interface (unlock, program, erase, busy times, power cuts)
    uid.py       the 96-bit unique device ID
    targets.py   the two boards: memory maps, interrupt numbers, wiring, CPI
    machine.py   the board: bus, event loop, idle fast-forward, serial endpoint, control
    __main__.py  `python -m imubench.device.arm --target f103 ...` (what VirtualBench starts)
"""
