/* chip.h - what firmware/boards/common_arm/arm_board.c needs to know about the STM32F4. */
#ifndef IB_CHIP_H
#define IB_CHIP_H

#include "protocol_gen.h"
#include "spi_bus.h"
#include "stm32f4.h"

#define CHIP_USART1_BASE F4_USART1_BASE
#define CHIP_USART1_IRQ F4_IRQ_USART1
#define CHIP_SPI1_BASE F4_SPI1_BASE
#if IB_CFG_QEMU
#define CHIP_BOARD_ID IB_BOARD_QEMU_F4
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F4
#endif

/* Chip select cs (IB_CS_*, < IB_CS_COUNT): the GPIO BSRR register that drives it and its
 * pin's bit there (write the bit: high, released; the bit << 16: low, selected). Inline:
 * the sample chain selects and releases a chip about ten times a sample. Pins: PA4
 * ADXL355, PB0/PB1/PB10 ADXRS450 X/Y/Z. */
static inline volatile uint32_t *chip_cs_bsrr(uint8_t cs)
{
    return &GPIO_BSRR(cs == IB_CS_ACCEL ? F4_GPIOA_BASE : F4_GPIOB_BASE);
}

static inline uint32_t chip_cs_bit(uint8_t cs)
{
    static const uint16_t pin_bit[IB_CS_COUNT] = {1u << 4, 1u << 0, 1u << 1, 1u << 10};
    return pin_bit[cs];
}

#if IB_CFG_SPI_DMA
#define SPI_RX_STREAM 0u /* SPI1_RX: DMA2 stream 0, SPI1_TX: stream 3, both channel 3 (RM0090 table 43) */
#define SPI_TX_STREAM 3u
#define SPI_DMA_CHANNEL 3u

/* arm_board.h's chip_spi_dma_start, inline: it runs for every transfer of the sample chain. */
static inline void chip_spi_dma_start(const uint8_t *tx, int tx_inc, uint8_t *rx, int rx_inc, uint32_t n)
{
    /* both streams are off and their flags clear here (EN cleared by hardware at the end of
     * the previous transfer, flags by finish; or by init / abort) */
    DMA2_SM0AR(SPI_RX_STREAM) = (uint32_t)(uintptr_t)rx;
    DMA2_SNDTR(SPI_RX_STREAM) = n;
    DMA2_SCR(SPI_RX_STREAM) = DMA_SCR_CHSEL(SPI_DMA_CHANNEL) | DMA_SCR_PL_VHIGH | (rx_inc ? DMA_SCR_MINC : 0u) |
                              DMA_SCR_TCIE | DMA_SCR_TEIE | DMA_SCR_EN;
    DMA2_SM0AR(SPI_TX_STREAM) = (uint32_t)(uintptr_t)tx;
    DMA2_SNDTR(SPI_TX_STREAM) = n;
    DMA2_SCR(SPI_TX_STREAM) = DMA_SCR_CHSEL(SPI_DMA_CHANNEL) | DMA_SCR_PL_HIGH | (tx_inc ? DMA_SCR_MINC : 0u) |
                              DMA_SCR_DIR_M2P | DMA_SCR_EN;
}
#endif

#endif
