/*
 * arm_board.h - the STM32 board layer shared by the F1 and F4 ports.
 *
 * firmware/boards/common_arm/arm_board.c implements the ib_board_t (board.h) once: SysTick
 * time base and sample tick, USART1 link (RX interrupt into a ring; TX ring drained by DMA
 * or by polling TXE), SPI1 with four GPIO chip selects, reboot, main(). What differs
 * between the chips (clock tree, pins, DMA controller, flash controller, unique ID, vector
 * table) lives in firmware/boards/stm32f1/chip_f1.c and firmware/boards/stm32f4/chip_f4.c
 * behind the chip_* functions below. USART and SPI have the same register layout on both
 * families, so their drivers are here.
 *
 * Build-time settings (-D flags from firmware/arm.mk; defaults below):
 *   IB_CFG_QEMU        1: image for qemu-system-arm (stm32vldiscovery / netduinoplus2):
 *                      no RCC/PLL start-up (QEMU's RCC reads 0), the CPU clock QEMU assumes
 *                      (IB_CFG_QEMU_SYSCLK_HZ), polled TX (no DMA model, no TXE interrupt),
 *                      clock source reported as IB_CLOCK_SOURCE_HSI, board QEMU_F1/QEMU_F4
 *   IB_CFG_TX_DMA      1: TX ring drained by DMA (default: hardware builds), 0: polled TXE
 *   IB_CFG_SPI_DMA     1: the bus's start() (asynchronous transfers: SPI1 RX/TX by DMA, the
 *                      completion interrupt calls the driver's done()), so the core reads a
 *                      sample as a chain of transfers while the main loop is free (default:
 *                      hardware builds). 0 (QEMU: no SPI DMA model): transfers polled only.
 *   IB_CFG_TX_RING     TX ring bytes (power of two). The core sends a sample batch only
 *                      when link_tx_free() >= frame + 2 reply frames (~800 bytes for a
 *                      16-sample raw batch), so keep it >= 1024.
 *   IB_CFG_RX_RING     RX ring bytes (power of two)
 *   IB_CFG_BAUD        link baud rate, default 2000000 (protocol/SPEC.md, link budget)
 *   IB_CFG_HSE_HZ      crystal frequency (F1: 8 MHz only; F4: 8, 12 or 25 MHz; default 8 MHz)
 *   IB_CFG_SPI_MAX_HZ  SPI clock ceiling (ADXRS450 <= 8.08 MHz, ADXL355 <= 10 MHz)
 *   IB_BUILD_ID        build id string (git describe --always --dirty)
 */
#ifndef IB_ARM_BOARD_H
#define IB_ARM_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "cortex_m.h"
#include "flash_if.h"
#include "spi_bus.h"

#ifndef IB_CFG_QEMU
#define IB_CFG_QEMU 0
#endif
#ifndef IB_CFG_TX_DMA
#define IB_CFG_TX_DMA (!IB_CFG_QEMU)
#endif
#ifndef IB_CFG_SPI_DMA
#define IB_CFG_SPI_DMA (!IB_CFG_QEMU)
#endif
#ifndef IB_CFG_TX_RING
#define IB_CFG_TX_RING 1024u
#endif
#ifndef IB_CFG_RX_RING
#define IB_CFG_RX_RING 256u
#endif
#ifndef IB_CFG_BAUD
#define IB_CFG_BAUD 2000000u
#endif
#ifndef IB_CFG_HSE_HZ
#define IB_CFG_HSE_HZ 8000000u
#endif
#ifndef IB_CFG_SPI_MAX_HZ
#define IB_CFG_SPI_MAX_HZ 6000000u
#endif
#ifndef IB_BUILD_ID
#define IB_BUILD_ID "unknown"
#endif

#if (IB_CFG_TX_RING & (IB_CFG_TX_RING - 1u)) != 0 || (IB_CFG_RX_RING & (IB_CFG_RX_RING - 1u)) != 0
#error "IB_CFG_TX_RING and IB_CFG_RX_RING must be powers of two"
#endif
#if IB_CFG_QEMU && IB_CFG_TX_DMA
#error "QEMU models no DMA: IB_CFG_TX_DMA must be 0 for a QEMU image"
#endif

/* ---- USART (same layout on F1 and F4) ----
 * RM0008 (STM32F10x reference manual) 27.6 USART registers;
 * RM0090 (STM32F405/407 reference manual) 30.6 USART registers. */
#define USART_SR(b) IB_REG32((b) + 0x00u)
#define USART_DR(b) IB_REG32((b) + 0x04u)
#define USART_BRR(b) IB_REG32((b) + 0x08u)
#define USART_CR1(b) IB_REG32((b) + 0x0Cu)
#define USART_CR2(b) IB_REG32((b) + 0x10u)
#define USART_CR3(b) IB_REG32((b) + 0x14u)
#define USART_SR_PE (1u << 0)
#define USART_SR_FE (1u << 1)
#define USART_SR_NE (1u << 2)
#define USART_SR_ORE (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TC (1u << 6)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_UE (1u << 13)
#define USART_CR3_DMAT (1u << 7)

/* ---- SPI (same layout on F1 and F4) ----
 * RM0008 25.5 SPI and I2S registers; RM0090 28.5 SPI and I2S registers. */
#define SPI_CR1(b) IB_REG32((b) + 0x00u)
#define SPI_CR2(b) IB_REG32((b) + 0x04u)
#define SPI_SR(b) IB_REG32((b) + 0x08u)
#define SPI_DR(b) IB_REG32((b) + 0x0Cu)
#define SPI_CR1_CPHA (1u << 0)
#define SPI_CR1_CPOL (1u << 1)
#define SPI_CR1_MSTR (1u << 2)
#define SPI_CR1_BR_SHIFT 3 /* bits 5:3, f_PCLK / 2^(BR+1) */
#define SPI_CR1_SPE (1u << 6)
#define SPI_CR1_SSI (1u << 8)
#define SPI_CR1_SSM (1u << 9)
#define SPI_CR2_RXDMAEN (1u << 0)
#define SPI_CR2_TXDMAEN (1u << 1)
#define SPI_SR_RXNE (1u << 0)
#define SPI_SR_TXE (1u << 1)
#define SPI_SR_MODF (1u << 5)
#define SPI_SR_OVR (1u << 6)
#define SPI_SR_BSY (1u << 7)

/* ---- what a chip port supplies (chip_f1.c / chip_f4.c) ---- */

typedef struct {
    uint32_t sysclk_hz;   /* core clock = SysTick clock */
    uint32_t pclk2_hz;    /* APB2: USART1 and SPI1 */
    uint8_t clock_source; /* enum ib_clock_source (protocol_gen.h) */
} arm_clocks_t;

/* Each chip directory also has a chip.h (included by arm_board.c) defining
 * CHIP_USART1_BASE, CHIP_USART1_IRQ, CHIP_SPI1_BASE and CHIP_BOARD_ID (IB_BOARD_*). */

/* Clock tree: HSE -> PLL with bounded waits, falling back to HSI (-> PLL), filling clk.
 * A QEMU image only reports the clock QEMU assumes. */
void chip_clock_init(arm_clocks_t *clk);

/* Peripheral clocks and pins: USART1 TX/RX, SPI1 SCK/MISO/MOSI, four chip selects (high). */
void chip_periph_init(void);

/* Drive chip select `cs` (IB_CS_*): level 0 = selected. */
void chip_cs_write(uint8_t cs, int level);

/* 96-bit unique device ID. */
void chip_read_uid(uint8_t uid[12]);

/* Fill the flash interface (slots from the linker script; flash_if.h). */
void chip_flash_init(ib_flash_if_t *fl);

/* Flash callbacks and CPU time source for the chip flash driver: bounded waits. */
uint32_t arm_time_us(void);

#if IB_CFG_TX_DMA
/* USART1 TX DMA: one memory-to-peripheral transfer at a time. The DMA interrupt
 * (transfer complete / error) must call arm_tx_dma_irq(). */
void chip_tx_dma_init(uint32_t usart_dr_addr);
void chip_tx_dma_start(const uint8_t *p, uint32_t n);
int chip_tx_dma_done(void);   /* 1 once the running transfer finished (or failed) */
void chip_tx_dma_stop(void);  /* clear flags, disable the channel/stream */
void arm_tx_dma_irq(void);
#endif

#if IB_CFG_SPI_DMA
/* SPI1 by DMA: one RX (peripheral-to-memory) and one TX (memory-to-peripheral) channel of n
 * bytes; *_inc 0 = the same byte every time; both channels off and their flags clear when
 * it is called. The RX channel's transfer-complete/error interrupt must call
 * arm_spi_dma_irq(); chip_spi_dma_finish() then leaves both channels off with their flags
 * clear and returns 0, or -1 on a transfer error. chip_spi_dma_abort() stops both channels
 * whatever they are doing (a completion that never came) and clears their flags. */
void chip_spi_dma_init(uint32_t spi_dr_addr);
/* static inline in chip.h (it runs for every transfer):
 * void chip_spi_dma_start(const uint8_t *tx, int tx_inc, uint8_t *rx, int rx_inc, uint32_t n); */
int chip_spi_dma_finish(void);
void chip_spi_dma_abort(void);
void arm_spi_dma_irq(void);
#endif

/* Interrupt handlers defined in arm_board.c, referenced by the chips' vector tables. */
void SysTick_Handler(void);
void USART1_IRQHandler(void);

/* Vector table (chip_f1.c / chip_f4.c) and start-up (startup.c) */
extern void (*const g_vectors[])(void);
__attribute__((noreturn)) void Reset_Handler(void);
__attribute__((noreturn)) void Default_Handler(void);
int main(void);

#endif
