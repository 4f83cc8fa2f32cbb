/* chip.h - what firmware/boards/common_arm/arm_board.c needs to know about the STM32F1. */
#ifndef IB_CHIP_H
#define IB_CHIP_H

#include "protocol_gen.h"
#include "stm32f1.h"

#define CHIP_USART1_BASE F1_USART1_BASE
#define CHIP_USART1_IRQ F1_IRQ_USART1
#define CHIP_SPI1_BASE F1_SPI1_BASE
#if IB_CFG_QEMU
#define CHIP_BOARD_ID IB_BOARD_QEMU_F1
#else
#define CHIP_BOARD_ID IB_BOARD_STM32F103
#endif

#endif
