/*
 * cortex_m.h - the few Cortex-M3/M4 core registers the imubench boards use, written by hand
 * (no CMSIS, no vendor HAL). Only what is used is defined.
 *
 * Sources (ST programming manuals of the Cortex-M cores, same addresses on M3 and M4):
 *   PM0056 (STM32F10xxx Cortex-M3 programming manual) / PM0214 (STM32F4 Cortex-M4):
 *     4.3 Nested vectored interrupt controller (NVIC): ISER, ICER, IPR
 *     4.4 System control block (SCB): ICSR, VTOR, AIRCR, SHPR3
 *     4.5 SysTick timer (STK): CTRL, LOAD, VAL
 *   PM0214 4.6 Floating point unit (FPU): CPACR (coprocessor access control)
 */
#ifndef IB_CORTEX_M_H
#define IB_CORTEX_M_H

#include <stdint.h>

#define IB_REG32(addr) (*(volatile uint32_t *)(addr))
#define IB_REG16(addr) (*(volatile uint16_t *)(addr))
#define IB_REG8(addr) (*(volatile uint8_t *)(addr))

/* ---- SysTick (PM0056/PM0214 4.5) ---- */
#define STK_CTRL IB_REG32(0xE000E010u)
#define STK_LOAD IB_REG32(0xE000E014u)
#define STK_VAL IB_REG32(0xE000E018u)
#define STK_CTRL_ENABLE (1u << 0)
#define STK_CTRL_TICKINT (1u << 1)
#define STK_CTRL_CLKSOURCE (1u << 2) /* 1 = processor clock (AHB), 0 = AHB/8 */

/* ---- NVIC (4.3) ---- */
#define NVIC_ISER(n) IB_REG32(0xE000E100u + 4u * (n))
#define NVIC_ICER(n) IB_REG32(0xE000E180u + 4u * (n))
#define NVIC_ICPR(n) IB_REG32(0xE000E280u + 4u * (n))
#define NVIC_IPR_BYTE(irq) IB_REG8(0xE000E400u + (irq))

/* ---- SCB (4.4) ---- */
#define SCB_ICSR IB_REG32(0xE000ED04u)
#define SCB_VTOR IB_REG32(0xE000ED08u)
#define SCB_AIRCR IB_REG32(0xE000ED0Cu)
#define SCB_SHPR3 IB_REG32(0xE000ED20u) /* bits 31:24 SysTick priority, 23:16 PendSV */
#define SCB_ICSR_PENDSTSET (1u << 26)   /* SysTick exception pending */
#define SCB_AIRCR_VECTKEY (0x05FAu << 16)
#define SCB_AIRCR_SYSRESETREQ (1u << 2)

/* ---- FPU (PM0214 4.6.1): CP10/CP11 full access = bits 23:20 all set ---- */
#define SCB_CPACR IB_REG32(0xE000ED88u)

static inline void ib_irq_enable(unsigned irq, uint8_t prio)
{
    NVIC_IPR_BYTE(irq) = prio; /* STM32: only the upper 4 bits are implemented */
    NVIC_ICPR(irq >> 5) = 1u << (irq & 31u);
    NVIC_ISER(irq >> 5) = 1u << (irq & 31u);
}

static inline void ib_irq_disable(unsigned irq) { NVIC_ICER(irq >> 5) = 1u << (irq & 31u); }

/* PRIMASK save/restore: a short critical section that nests. */
static inline uint32_t ib_irq_save(void)
{
    uint32_t pm;
    __asm volatile("mrs %0, primask\n\tcpsid i" : "=r"(pm)::"memory");
    return pm;
}

static inline void ib_irq_restore(uint32_t pm) { __asm volatile("msr primask, %0" ::"r"(pm) : "memory"); }

static inline void ib_dsb(void) { __asm volatile("dsb 0xF" ::: "memory"); }
static inline void ib_isb(void) { __asm volatile("isb 0xF" ::: "memory"); }
static inline void ib_wfi(void) { __asm volatile("wfi" ::: "memory"); }
static inline void ib_compiler_barrier(void) { __asm volatile("" ::: "memory"); }

/* Bounded wait for (*reg & mask) == want: 1 when it came true within `loops` reads, else 0.
 * Every wait on a clock or flash flag goes through this (under QEMU they never come true). */
static inline int ib_wait_reg(const volatile uint32_t *reg, uint32_t mask, uint32_t want, uint32_t loops)
{
    for (uint32_t i = 0; i < loops; i++) {
        if ((*reg & mask) == want) {
            return 1;
        }
    }
    return 0;
}

#endif
