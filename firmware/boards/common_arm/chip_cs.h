/* chip_cs.h - the sensors' chip selects, wired alike on both boards: PA4 ADXL355,
 * PB0/PB1/PB10 ADXRS450 X/Y/Z. Included by each chip.h once it has defined CHIP_GPIOA_BASE,
 * CHIP_GPIOB_BASE and GPIO_BSRR (its register map).
 *
 * Chip select cs (IB_CS_*, < IB_CS_COUNT): the GPIO BSRR register that drives it and its
 * pin's bit there (write the bit: high, released; the bit << 16: low, selected). Inline:
 * the sample chain selects and releases a chip about ten times a sample. */
#ifndef IB_CHIP_CS_H
#define IB_CHIP_CS_H

#include <stdint.h>

#include "protocol_gen.h"

static inline volatile uint32_t *chip_cs_bsrr(uint8_t cs)
{
    return &GPIO_BSRR(cs == IB_CS_ACCEL ? CHIP_GPIOA_BASE : CHIP_GPIOB_BASE);
}

static inline uint32_t chip_cs_bit(uint8_t cs)
{
    static const uint16_t pin_bit[IB_CS_COUNT] = {1u << 4, 1u << 0, 1u << 1, 1u << 10};
    return pin_bit[cs];
}

#endif
