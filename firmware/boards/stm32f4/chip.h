/* chip.h - what firmware/boards/common_arm/arm_board.c needs to know about the STM32F4. */
#ifndef IB_CHIP_H
#define IB_CHIP_H

#include "protocol_gen.h"
#include "stm32f4.h"

#define CHIP_USART1_BASE F4_USART1_BASE
#define CHIP_USART1_IRQ F4_IRQ_USART1
#define CHIP_SPI1_BASE F4_SPI1_BASE
#if IB_CFG_QEMU
#define CHIP_BOARD_ID IB_BOARD_QEMU_F4
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F4
#endif

#endif
