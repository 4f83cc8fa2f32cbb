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
#define CHIP_BOARD_NAME "qemu_f4"
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F4
#define CHIP_BOARD_NAME "stm32f4"
#endif

#define CHIP_GPIOA_BASE F4_GPIOA_BASE
#define CHIP_GPIOB_BASE F4_GPIOB_BASE
#include "chip_cs.h"

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
