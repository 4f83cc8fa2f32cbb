/*
 * stm32f4.h - hand-written register definitions for the STM32F405/407 (and the STM32F405 of
 * QEMU's netduinoplus2). No vendor HAL or CMSIS device header: only the registers and
 * bits this firmware uses.
 *
 * Sources:
 *   RM0090 Rev 19 (STM32F405/415, F407/417, F427/437, F429/439 reference manual)
 *     2.3  Memory map (peripheral base addresses)
 *     3.9  Flash interface registers: ACR, KEYR, SR, CR (3.6/3.7 erase and program
 *          sequences; 3.3 sector organisation)
 *     5.4  PWR registers: CR (VOS)
 *     7.3  RCC registers (F405/407 chapter): CR, PLLCFGR, CFGR, AHB1ENR, APB1ENR, APB2ENR
 *     8.4  GPIO registers: MODER, OTYPER, OSPEEDR, PUPDR, BSRR, AFRL, AFRH
 *     10.5 DMA registers: LISR/HISR, LIFCR/HIFCR, SxCR, SxNDTR, SxPAR, SxM0AR, SxFCR
 *          (10.3.3 request mapping, table 43: USART1_TX = DMA2 stream 7 channel 4,
 *          SPI1_RX = stream 0 channel 3, SPI1_TX = stream 3 channel 3)
 *     12.2 Interrupt and exception vectors (vector table positions)
 *     39.1 Unique device ID register (96 bits at 0x1FFF7A10)
 *   USART and SPI: common_arm/arm_board.h (RM0090 30.6 and 28.5).
 */
#ifndef IB_STM32F4_H
#define IB_STM32F4_H

#include "cortex_m.h"

/* ---- base addresses (RM0090 2.3) ---- */
#define F4_PWR_BASE 0x40007000u
#define F4_GPIOA_BASE 0x40020000u
#define F4_GPIOB_BASE 0x40020400u
#define F4_RCC_BASE 0x40023800u
#define F4_FLASH_R_BASE 0x40023C00u
#define F4_DMA2_BASE 0x40026400u
#define F4_USART1_BASE 0x40011000u
#define F4_SPI1_BASE 0x40013000u
#define F4_UID_BASE 0x1FFF7A10u

/* ---- IRQ numbers (RM0090 12.2, table 61) ---- */
#define F4_IRQ_SPI1 35u
#define F4_IRQ_USART1 37u
#define F4_IRQ_DMA2_STREAM0 56u
#define F4_IRQ_DMA2_STREAM7 70u
#define F4_IRQ_COUNT 82u

/* ---- RCC (RM0090 7.3) ---- */
#define RCC_CR IB_REG32(F4_RCC_BASE + 0x00u)
#define RCC_PLLCFGR IB_REG32(F4_RCC_BASE + 0x04u)
#define RCC_CFGR IB_REG32(F4_RCC_BASE + 0x08u)
#define RCC_AHB1ENR IB_REG32(F4_RCC_BASE + 0x30u)
#define RCC_APB1ENR IB_REG32(F4_RCC_BASE + 0x40u)
#define RCC_APB2ENR IB_REG32(F4_RCC_BASE + 0x44u)
#define RCC_CR_HSION (1u << 0)
#define RCC_CR_HSIRDY (1u << 1)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_PLLCFGR_M(x) ((uint32_t)(x) << 0)          /* 2..63: VCO input = src / M */
#define RCC_PLLCFGR_N(x) ((uint32_t)(x) << 6)          /* 50..432: VCO = input * N */
#define RCC_PLLCFGR_P(x) ((uint32_t)((x) / 2u - 1u) << 16) /* 2,4,6,8: SYSCLK = VCO / P */
#define RCC_PLLCFGR_SRC_HSE (1u << 22)
#define RCC_PLLCFGR_Q(x) ((uint32_t)(x) << 24) /* 2..15: 48 MHz domain = VCO / Q */
/* The reserved bits (RM0090 7.3.2: "must be kept at reset value"; bit 29 resets to 1):
 * a write of PLLCFGR keeps them as read. */
#define RCC_PLLCFGR_RESERVED 0xF0BC8000u
#define RCC_CFGR_SW_MASK (3u << 0)
#define RCC_CFGR_SW_HSI (0u << 0)
#define RCC_CFGR_SW_PLL (2u << 0)
#define RCC_CFGR_SWS_MASK (3u << 2)
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_CFGR_PPRE1_DIV4 (5u << 10) /* APB1 <= 42 MHz */
#define RCC_CFGR_PPRE2_DIV2 (4u << 13) /* APB2 <= 84 MHz */
#define RCC_AHB1ENR_GPIOAEN (1u << 0)
#define RCC_AHB1ENR_GPIOBEN (1u << 1)
#define RCC_AHB1ENR_DMA2EN (1u << 22)
#define RCC_APB1ENR_PWREN (1u << 28)
#define RCC_APB2ENR_USART1EN (1u << 4)
#define RCC_APB2ENR_SPI1EN (1u << 12)

/* ---- PWR (RM0090 5.4.1) ---- */
#define PWR_CR IB_REG32(F4_PWR_BASE + 0x00u)
#define PWR_CR_VOS (1u << 14) /* F405/407: 1 = scale 1 (168 MHz) */

/* ---- FLASH interface (RM0090 3.9) ---- */
#define FLASH_ACR IB_REG32(F4_FLASH_R_BASE + 0x00u)
#define FLASH_KEYR IB_REG32(F4_FLASH_R_BASE + 0x04u)
#define FLASH_SR IB_REG32(F4_FLASH_R_BASE + 0x0Cu)
#define FLASH_CR IB_REG32(F4_FLASH_R_BASE + 0x10u)
#define FLASH_ACR_LATENCY(n) ((uint32_t)(n) << 0) /* 5 wait states at 168 MHz, 2.7-3.6 V */
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)
#define FLASH_ACR_ICRST (1u << 11)
#define FLASH_ACR_DCRST (1u << 12)
#define FLASH_KEY1 0x45670123u
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR_EOP (1u << 0)
#define FLASH_SR_OPERR (1u << 1)
#define FLASH_SR_WRPERR (1u << 4)
#define FLASH_SR_PGAERR (1u << 5)
#define FLASH_SR_PGPERR (1u << 6)
#define FLASH_SR_PGSERR (1u << 7)
#define FLASH_SR_BSY (1u << 16)
#define FLASH_SR_ERRORS (FLASH_SR_OPERR | FLASH_SR_WRPERR | FLASH_SR_PGAERR | FLASH_SR_PGPERR | FLASH_SR_PGSERR)
#define FLASH_CR_PG (1u << 0)
#define FLASH_CR_SER (1u << 1)
#define FLASH_CR_SNB(n) ((uint32_t)(n) << 3)
#define FLASH_CR_PSIZE_X32 (2u << 8)
#define FLASH_CR_STRT (1u << 16)
#define FLASH_CR_LOCK (1u << 31)

/* ---- GPIO (RM0090 8.4) ---- */
#define GPIO_MODER(b) IB_REG32((b) + 0x00u)
#define GPIO_OTYPER(b) IB_REG32((b) + 0x04u)
#define GPIO_OSPEEDR(b) IB_REG32((b) + 0x08u)
#define GPIO_PUPDR(b) IB_REG32((b) + 0x0Cu)
#define GPIO_BSRR(b) IB_REG32((b) + 0x18u)
#define GPIO_AFR(b, n) IB_REG32((b) + 0x20u + 4u * (n)) /* n = 0: AFRL (pins 0-7), 1: AFRH */
#define F4_MODE_IN 0u
#define F4_MODE_OUT 1u
#define F4_MODE_AF 2u
#define F4_PULL_NONE 0u
#define F4_PULL_UP 1u
#define F4_PULL_DOWN 2u
#define F4_SPEED_FAST 2u

/* ---- DMA2 (RM0090 10.5); stream s = 0..7 ---- */
#define DMA2_LISR IB_REG32(F4_DMA2_BASE + 0x00u)
#define DMA2_HISR IB_REG32(F4_DMA2_BASE + 0x04u)
#define DMA2_LIFCR IB_REG32(F4_DMA2_BASE + 0x08u)
#define DMA2_HIFCR IB_REG32(F4_DMA2_BASE + 0x0Cu)
#define DMA2_SCR(s) IB_REG32(F4_DMA2_BASE + 0x10u + 0x18u * (s))
#define DMA2_SNDTR(s) IB_REG32(F4_DMA2_BASE + 0x14u + 0x18u * (s))
#define DMA2_SPAR(s) IB_REG32(F4_DMA2_BASE + 0x18u + 0x18u * (s))
#define DMA2_SM0AR(s) IB_REG32(F4_DMA2_BASE + 0x1Cu + 0x18u * (s))
#define DMA2_SFCR(s) IB_REG32(F4_DMA2_BASE + 0x24u + 0x18u * (s))
/* stream 7 flags in HISR / HIFCR */
#define DMA_HISR_FEIF7 (1u << 22)
#define DMA_HISR_DMEIF7 (1u << 24)
#define DMA_HISR_TEIF7 (1u << 25)
#define DMA_HISR_HTIF7 (1u << 26)
#define DMA_HISR_TCIF7 (1u << 27)
#define DMA_HIFCR_ALL7 (DMA_HISR_FEIF7 | DMA_HISR_DMEIF7 | DMA_HISR_TEIF7 | DMA_HISR_HTIF7 | DMA_HISR_TCIF7)
#define DMA_SCR_EN (1u << 0)
#define DMA_SCR_TEIE (1u << 2)
#define DMA_SCR_TCIE (1u << 4)
#define DMA_SCR_DIR_M2P (1u << 6)
#define DMA_SCR_MINC (1u << 10)
#define DMA_SCR_PL_HIGH (2u << 16)
#define DMA_SCR_PL_VHIGH (3u << 16)
/* LISR/LIFCR flags of streams 0 and 3 (FEIF, DMEIF, TEIF, HTIF, TCIF) */
#define DMA_LISR_TEIF0 (1u << 3)
#define DMA_LISR_DMEIF0 (1u << 2)
#define DMA_LIFCR_ALL0 0x3Du
#define DMA_LISR_TEIF3 (1u << 25)
#define DMA_LISR_DMEIF3 (1u << 24)
#define DMA_LIFCR_ALL3 (0x3Du << 22)
#define DMA_SCR_CHSEL(c) ((uint32_t)(c) << 25)

#endif
