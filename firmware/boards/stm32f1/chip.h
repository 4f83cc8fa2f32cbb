/* chip.h - what firmware/boards/common_arm/arm_board.c needs to know about the STM32F1. */
#ifndef IB_CHIP_H
#define IB_CHIP_H

#include "protocol_gen.h"
#include "spi_bus.h"
#include "stm32f1.h"

#define CHIP_USART1_BASE F1_USART1_BASE
#define CHIP_USART1_IRQ F1_IRQ_USART1
#define CHIP_SPI1_BASE F1_SPI1_BASE
#if IB_CFG_QEMU
#define CHIP_BOARD_ID IB_BOARD_QEMU_F1
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F103
#endif

/* Chip select cs (IB_CS_*, < IB_CS_COUNT): the GPIO BSRR register that drives it and its
 * pin's bit there (write the bit: high, released; the bit << 16: low, selected). Inline:
 * the sample chain selects and releases a chip about ten times a sample. Pins: PA4
 * ADXL355, PB0/PB1/PB10 ADXRS450 X/Y/Z. */
static inline volatile uint32_t *chip_cs_bsrr(uint8_t cs)
{
    return &GPIO_BSRR(cs == IB_CS_ACCEL ? F1_GPIOA_BASE : F1_GPIOB_BASE);
}

static inline uint32_t chip_cs_bit(uint8_t cs)
{
    static const uint16_t pin_bit[IB_CS_COUNT] = {1u << 4, 1u << 0, 1u << 1, 1u << 10};
    return pin_bit[cs];
}

#endif
