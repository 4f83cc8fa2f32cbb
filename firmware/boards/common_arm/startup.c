/*
 * startup.c - reset and fault handling shared by the STM32 images. The vector tables are in
 * the chip files (chip_f1.c, chip_f4.c); the linker scripts (sections.ld) define the
 * symbols used here.
 *
 * RAM layout (sections.ld): the stack comes FIRST, at the bottom of RAM, growing down
 * towards 0x1FFFFFFF, then .data and .bss. A stack overflow therefore faults (reserved
 * address space below SRAM) instead of silently corrupting the core's state.
 *
 * Every fault and every unexpected interrupt resets the MCU (SYSRESETREQ): a bench device
 * that hangs is worse than one that reboots, and the host sees the reboot (a new boot info).
 */
#include <stddef.h>
#include <stdint.h>

#include "arm_board.h"

extern uint32_t _sidata[], _sdata[], _edata[], _sbss[], _ebss[]; /* sections.ld */

__attribute__((noreturn, used)) void Reset_Handler(void)
{
#if defined(__ARM_FP)
    /* Cortex-M4F: CP10/CP11 full access before any floating-point instruction
     * (PM0214 4.6.1). */
    SCB_CPACR |= 0xFu << 20;
    ib_dsb();
    ib_isb();
#endif
    /* Our vector table, also when entered from the ROM bootloader's Go command (stm32flash
     * -g), where address 0 may still alias system memory. */
    SCB_VTOR = (uint32_t)(uintptr_t)g_vectors;
    /* word counts from the linker symbols' addresses (distinct objects to C) */
    const size_t n_data = ((uintptr_t)_edata - (uintptr_t)_sdata) / 4u;
    const size_t n_bss = ((uintptr_t)_ebss - (uintptr_t)_sbss) / 4u;
    for (size_t i = 0; i < n_data; i++) {
        _sdata[i] = _sidata[i];
    }
    for (size_t i = 0; i < n_bss; i++) {
        _sbss[i] = 0u;
    }
    (void)main();
    for (;;) {
        Default_Handler();
    }
}

__attribute__((noreturn)) void Default_Handler(void)
{
    ib_dsb();
    SCB_AIRCR = SCB_AIRCR_VECTKEY | SCB_AIRCR_SYSRESETREQ;
    ib_dsb();
    for (;;) {
    }
}
