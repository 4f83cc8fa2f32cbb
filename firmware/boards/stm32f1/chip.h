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
#define CHIP_BOARD_NAME "qemu_f1"
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F103
#define CHIP_BOARD_NAME "stm32f103"
#endif

#define CHIP_GPIOA_BASE F1_GPIOA_BASE
#define CHIP_GPIOB_BASE F1_GPIOB_BASE
#include "chip_cs.h"

#if IB_CFG_SPI_DMA
#define SPI_RX_CH 2u /* SPI1_RX: DMA1 channel 2, SPI1_TX: channel 3 (RM0008 13.3.7, table 78) */
#define SPI_TX_CH 3u

/* arm_board.h's chip_spi_dma_start, inline: it runs for every transfer of the sample chain. */
static inline void chip_spi_dma_start(const uint8_t *tx, int tx_inc, uint8_t *rx, int rx_inc, uint32_t n)
{
    DMA1_IFCR = DMA_IFCR_ALL(SPI_RX_CH) | DMA_IFCR_ALL(SPI_TX_CH);
    DMA1_CMAR(SPI_RX_CH) = (uint32_t)(uintptr_t)rx;
    DMA1_CNDTR(SPI_RX_CH) = n;
    /* RX above TX in priority: a received byte is taken before the next one is sent */
    DMA1_CCR(SPI_RX_CH) = (rx_inc ? DMA_CCR_MINC : 0u) | DMA_CCR_TCIE | DMA_CCR_TEIE | DMA_CCR_PL_VHIGH | DMA_CCR_EN;
    DMA1_CMAR(SPI_TX_CH) = (uint32_t)(uintptr_t)tx;
    DMA1_CNDTR(SPI_TX_CH) = n;
    DMA1_CCR(SPI_TX_CH) = DMA_CCR_DIR | (tx_inc ? DMA_CCR_MINC : 0u) | DMA_CCR_PL_HIGH | DMA_CCR_EN;
}
#endif

#endif
