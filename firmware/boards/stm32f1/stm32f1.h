/*
 * stm32f1.h - hand-written register definitions for the STM32F103 (and the STM32F100 of
 * QEMU's stm32vldiscovery, which has the same addresses for everything used here).
 * No vendor HAL or CMSIS device header: only the registers and bits this firmware uses.
 *
 * Sources:
 *   RM0008 Rev 21 (STM32F101/102/103/105/107 reference manual)
 *     3.3  Memory map (peripheral base addresses)
 *     7.3  RCC registers: CR, CFGR, AHBENR, APB2ENR
 *     9.2  GPIO registers: CRL, CRH, IDR, ODR, BSRR, BRR
 *     13.4 DMA registers: ISR, IFCR, CCRx, CNDTRx, CPARx, CMARx (table 78: USART1_TX =
 *          DMA1 ch 4, SPI1_RX = ch 2, SPI1_TX = ch 3)
 *     10.1.2 Interrupt and exception vectors (vector table positions)
 *     30.2 Unique device ID register (96 bits at 0x1FFFF7E8)
 *   PM0075 (STM32F10xxx Flash memory programming manual)
 *     3    Flash memory registers: ACR, KEYR, SR, CR, AR; 2.3/2.4 program and page erase
 *   USART and SPI: common_arm/arm_board.h (RM0008 27.6 and 25.5).
 */
#ifndef IB_STM32F1_H
#define IB_STM32F1_H

#include "cortex_m.h"

/* ---- base addresses (RM0008 3.3) ---- */
#define F1_RCC_BASE 0x40021000u
#define F1_FLASH_R_BASE 0x40022000u
#define F1_DMA1_BASE 0x40020000u
#define F1_GPIOA_BASE 0x40010800u
#define F1_GPIOB_BASE 0x40010C00u
#define F1_AFIO_BASE 0x40010000u
#define F1_USART1_BASE 0x40013800u
#define F1_SPI1_BASE 0x40013000u
#define F1_UID_BASE 0x1FFFF7E8u

/* ---- IRQ numbers (RM0008 10.1.2, table 63) ---- */
#define F1_IRQ_DMA1_CH2 12u
#define F1_IRQ_DMA1_CH4 14u
#define F1_IRQ_SPI1 35u
#define F1_IRQ_USART1 37u
#define F1_IRQ_COUNT 68u /* vector table entries after the 16 core exceptions (CL devices) */

/* ---- RCC (RM0008 7.3) ---- */
#define RCC_CR IB_REG32(F1_RCC_BASE + 0x00u)
#define RCC_CFGR IB_REG32(F1_RCC_BASE + 0x04u)
#define RCC_AHBENR IB_REG32(F1_RCC_BASE + 0x14u)
#define RCC_APB2ENR IB_REG32(F1_RCC_BASE + 0x18u)
#define RCC_CR_HSION (1u << 0)
#define RCC_CR_HSIRDY (1u << 1)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_HSEBYP (1u << 18)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_CFGR_SW_MASK (3u << 0)
#define RCC_CFGR_SW_HSI (0u << 0)
#define RCC_CFGR_SW_PLL (2u << 0)
#define RCC_CFGR_SWS_MASK (3u << 2)
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_CFGR_PPRE1_DIV2 (4u << 8)  /* APB1 <= 36 MHz */
#define RCC_CFGR_PLLSRC_HSE (1u << 16) /* 0: HSI / 2 */
#define RCC_CFGR_PLLMUL(x) ((uint32_t)((x) - 2u) << 18) /* x = 2..16 */
#define RCC_AHBENR_DMA1EN (1u << 0)
#define RCC_APB2ENR_AFIOEN (1u << 0)
#define RCC_APB2ENR_IOPAEN (1u << 2)
#define RCC_APB2ENR_IOPBEN (1u << 3)
#define RCC_APB2ENR_SPI1EN (1u << 12)
#define RCC_APB2ENR_USART1EN (1u << 14)

/* ---- FLASH interface (PM0075 3) ---- */
#define FLASH_ACR IB_REG32(F1_FLASH_R_BASE + 0x00u)
#define FLASH_KEYR IB_REG32(F1_FLASH_R_BASE + 0x04u)
#define FLASH_SR IB_REG32(F1_FLASH_R_BASE + 0x0Cu)
#define FLASH_CR IB_REG32(F1_FLASH_R_BASE + 0x10u)
#define FLASH_AR IB_REG32(F1_FLASH_R_BASE + 0x14u)
#define FLASH_ACR_LATENCY(n) ((uint32_t)(n) << 0) /* 0: <=24 MHz, 1: <=48, 2: <=72 */
#define FLASH_ACR_PRFTBE (1u << 4)
#define FLASH_KEY1 0x45670123u
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR_BSY (1u << 0)
#define FLASH_SR_PGERR (1u << 2)
#define FLASH_SR_WRPRTERR (1u << 4)
#define FLASH_SR_EOP (1u << 5)
#define FLASH_CR_PG (1u << 0)
#define FLASH_CR_PER (1u << 1)
#define FLASH_CR_STRT (1u << 6)
#define FLASH_CR_LOCK (1u << 7)

/* ---- GPIO (RM0008 9.2): 4 bits per pin, CNF[1:0] MODE[1:0] ---- */
#define GPIO_CRL(b) IB_REG32((b) + 0x00u)
#define GPIO_CRH(b) IB_REG32((b) + 0x04u)
#define GPIO_ODR(b) IB_REG32((b) + 0x0Cu)
#define GPIO_BSRR(b) IB_REG32((b) + 0x10u)
#define GPIO_BRR(b) IB_REG32((b) + 0x14u)
#define F1_PIN_OUT_PP_50 0x3u  /* general purpose output push-pull, 50 MHz */
#define F1_PIN_AF_PP_50 0xBu   /* alternate function output push-pull, 50 MHz */
#define F1_PIN_IN_PULL 0x8u    /* input with pull-up / pull-down (ODR selects) */

/* ---- DMA1 (RM0008 13.4); channel n = 1..7 ---- */
#define DMA1_ISR IB_REG32(F1_DMA1_BASE + 0x00u)
#define DMA1_IFCR IB_REG32(F1_DMA1_BASE + 0x04u)
#define DMA1_CCR(n) IB_REG32(F1_DMA1_BASE + 0x08u + 20u * ((n) - 1u))
#define DMA1_CNDTR(n) IB_REG32(F1_DMA1_BASE + 0x0Cu + 20u * ((n) - 1u))
#define DMA1_CPAR(n) IB_REG32(F1_DMA1_BASE + 0x10u + 20u * ((n) - 1u))
#define DMA1_CMAR(n) IB_REG32(F1_DMA1_BASE + 0x14u + 20u * ((n) - 1u))
#define DMA_ISR_GIF(n) (1u << (4u * ((n) - 1u)))
#define DMA_ISR_TCIF(n) (2u << (4u * ((n) - 1u)))
#define DMA_ISR_TEIF(n) (8u << (4u * ((n) - 1u)))
#define DMA_IFCR_ALL(n) (0xFu << (4u * ((n) - 1u)))
#define DMA_CCR_EN (1u << 0)
#define DMA_CCR_TCIE (1u << 1)
#define DMA_CCR_TEIE (1u << 3)
#define DMA_CCR_DIR (1u << 4) /* 1: memory -> peripheral */
#define DMA_CCR_MINC (1u << 7)
#define DMA_CCR_PL_HIGH (2u << 12)
#define DMA_CCR_PL_VHIGH (3u << 12)

#endif
