/*
 * chip_f1.c - STM32F103 specifics behind common_arm/arm_board.h: vector table, clock tree,
 * pins, USART1 TX DMA, flash driver (ib_flash_if_t), unique ID. The QEMU image
 * (stm32vldiscovery, an STM32F100 with the same addresses) is this file built with
 * IB_CFG_QEMU=1.
 *
 * Clock (RM0008 7.2): HSE 8 MHz -> PLL x9 = 72 MHz (APB2 72 MHz, APB1 36 MHz, flash 2 wait
 * states + prefetch). Every wait is bounded; if the crystal does not start, HSI/2 x16 =
 * 64 MHz; if the PLL does not lock either, HSI 8 MHz. Both fallbacks report
 * IB_CLOCK_SOURCE_HSI_FALLBACK. The QEMU image skips all of it (QEMU's RCC reads 0) and
 * assumes the 24 MHz QEMU's stm32vldiscovery clocks SysTick with.
 *
 * Pins (blue pill / any F103 in LQFP48 or larger):
 *   USART1  PA9 TX (AF push-pull), PA10 RX (input, pull-up)
 *   SPI1    PA5 SCK, PA7 MOSI (AF push-pull), PA6 MISO (input, pull-down: a missing
 *           sensor reads 0x00, as under QEMU)
 *   CS      PA4 ADXL355, PB0 ADXRS450 X, PB1 ADXRS450 Y, PB10 ADXRS450 Z (push-pull, high)
 *   SPI1 and USART1 are on their default (not remapped) pins: no AFIO remap needed.
 *
 * Flash (PM0075): 1 KiB pages; the two parameter slots are the last two pages of the
 * flash the linker script describes (__ib_param_slot0/1): program_unit 2 (half-words).
 */
#include <string.h>

#include "arm_board.h"
#include "chip.h"

#ifndef IB_CFG_QEMU_SYSCLK_HZ
#define IB_CFG_QEMU_SYSCLK_HZ 24000000u
#endif

#define RCC_WAIT_LOOPS 200000u      /* HSE start-up takes a few ms at most */
#define FLASH_PROG_TIMEOUT_US 2000u  /* half-word: 52..70 us */
#define FLASH_ERASE_TIMEOUT_US 200000u /* page: 20..40 ms */

/* ---------------------------------------------------------------- vectors */

extern uint32_t _estack;
void DMA1_Channel4_IRQHandler(void);
void DMA1_Channel2_IRQHandler(void);

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Woverride-init"
__attribute__((section(".isr_vector"), used)) void (*const g_vectors[16u + F1_IRQ_COUNT])(void) = {
    [0] = (void (*)(void))(uintptr_t)&_estack,
    [1] = Reset_Handler,
    [2 ... 15 + F1_IRQ_COUNT] = Default_Handler,
    [7] = 0, [8] = 0, [9] = 0, [10] = 0, [13] = 0, /* reserved */
    [15] = SysTick_Handler,
#if IB_CFG_TX_DMA
    [16u + F1_IRQ_DMA1_CH4] = DMA1_Channel4_IRQHandler,
#endif
#if IB_CFG_SPI_DMA
    [16u + F1_IRQ_DMA1_CH2] = DMA1_Channel2_IRQHandler,
#endif
    [16u + F1_IRQ_USART1] = USART1_IRQHandler,
};
#pragma GCC diagnostic pop

/* ------------------------------------------------------------------ clock */

#if !IB_CFG_QEMU
static int wait_reg(volatile uint32_t *reg, uint32_t mask, uint32_t want)
{
    return ib_wait_reg(reg, mask, want, RCC_WAIT_LOOPS);
}

/* Switch SYSCLK to the PLL configured by cfgr_pll (source + multiplier). 1 on success;
 * on failure SYSCLK stays on HSI. */
static int pll_start(uint32_t cfgr_pll, uint32_t sysclk_hz)
{
    RCC_CFGR &= ~RCC_CFGR_SW_MASK; /* HSI while reconfiguring */
    (void)wait_reg(&RCC_CFGR, RCC_CFGR_SWS_MASK, 0u);
    RCC_CR &= ~RCC_CR_PLLON;
    if (!wait_reg(&RCC_CR, RCC_CR_PLLRDY, 0u)) {
        return 0;
    }
    FLASH_ACR = FLASH_ACR_PRFTBE | FLASH_ACR_LATENCY(sysclk_hz > 48000000u ? 2u : sysclk_hz > 24000000u ? 1u : 0u);
    RCC_CFGR = cfgr_pll | RCC_CFGR_PPRE1_DIV2 | RCC_CFGR_SW_HSI;
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_reg(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        RCC_CR &= ~RCC_CR_PLLON;
        return 0;
    }
    RCC_CFGR = (RCC_CFGR & ~RCC_CFGR_SW_MASK) | RCC_CFGR_SW_PLL;
    if (!wait_reg(&RCC_CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SWS_PLL)) {
        RCC_CFGR &= ~RCC_CFGR_SW_MASK;
        RCC_CR &= ~RCC_CR_PLLON;
        return 0;
    }
    return 1;
}
#endif

void chip_clock_init(arm_clocks_t *clk)
{
#if IB_CFG_QEMU
    clk->sysclk_hz = IB_CFG_QEMU_SYSCLK_HZ;
    clk->pclk2_hz = IB_CFG_QEMU_SYSCLK_HZ;
    clk->clock_source = IB_CLOCK_SOURCE_HSI;
#else
#if IB_CFG_HSE_HZ != 8000000u
#error "the STM32F1 clock set-up assumes an 8 MHz crystal (x9 = 72 MHz)"
#endif
    RCC_CR |= RCC_CR_HSION;
    (void)wait_reg(&RCC_CR, RCC_CR_HSIRDY, RCC_CR_HSIRDY);
    RCC_CR |= RCC_CR_HSEON;
    if (wait_reg(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY) &&
        pll_start(RCC_CFGR_PLLSRC_HSE | RCC_CFGR_PLLMUL(9u), 72000000u)) {
        clk->sysclk_hz = 72000000u;
        clk->pclk2_hz = 72000000u;
        clk->clock_source = IB_CLOCK_SOURCE_HSE_PLL;
        return;
    }
    RCC_CR &= ~RCC_CR_HSEON;
    clk->clock_source = IB_CLOCK_SOURCE_HSI_FALLBACK;
    if (pll_start(RCC_CFGR_PLLMUL(16u), 64000000u)) { /* PLLSRC = HSI / 2 */
        clk->sysclk_hz = 64000000u;
        clk->pclk2_hz = 64000000u;
        return;
    }
    RCC_CFGR = RCC_CFGR_SW_HSI;
    FLASH_ACR = FLASH_ACR_PRFTBE | FLASH_ACR_LATENCY(0u);
    clk->sysclk_hz = 8000000u;
    clk->pclk2_hz = 8000000u;
#endif
}

/* ------------------------------------------------------------------- pins */

static void pin_mode(uint32_t port, unsigned pin, uint32_t mode)
{
    volatile uint32_t *cr = pin < 8u ? &GPIO_CRL(port) : &GPIO_CRH(port);
    unsigned sh = (pin & 7u) * 4u;
    *cr = (*cr & ~(0xFu << sh)) | (mode << sh);
}

void chip_periph_init(void)
{
    RCC_APB2ENR |= RCC_APB2ENR_AFIOEN | RCC_APB2ENR_IOPAEN | RCC_APB2ENR_IOPBEN | RCC_APB2ENR_SPI1EN |
                   RCC_APB2ENR_USART1EN;
    RCC_AHBENR |= RCC_AHBENR_DMA1EN;
    (void)RCC_APB2ENR; /* read back: clocks running before the first access */

    /* levels first (chip selects high, PA10 pull-up, PA6 pull-down), then modes */
    GPIO_BSRR(F1_GPIOA_BASE) = (1u << 4) | (1u << 10) | (1u << (6 + 16));
    GPIO_BSRR(F1_GPIOB_BASE) = (1u << 0) | (1u << 1) | (1u << 10);
    pin_mode(F1_GPIOA_BASE, 4, F1_PIN_OUT_PP_50);
    pin_mode(F1_GPIOA_BASE, 5, F1_PIN_AF_PP_50);
    pin_mode(F1_GPIOA_BASE, 6, F1_PIN_IN_PULL);
    pin_mode(F1_GPIOA_BASE, 7, F1_PIN_AF_PP_50);
    pin_mode(F1_GPIOA_BASE, 9, F1_PIN_AF_PP_50);
    pin_mode(F1_GPIOA_BASE, 10, F1_PIN_IN_PULL);
    pin_mode(F1_GPIOB_BASE, 0, F1_PIN_OUT_PP_50);
    pin_mode(F1_GPIOB_BASE, 1, F1_PIN_OUT_PP_50);
    pin_mode(F1_GPIOB_BASE, 10, F1_PIN_OUT_PP_50);
}

void chip_cs_write(uint8_t cs, int level)
{
    if (cs < IB_CS_COUNT) {
        *chip_cs_bsrr(cs) = level ? chip_cs_bit(cs) : chip_cs_bit(cs) << 16;
    }
}

void chip_read_uid(uint8_t uid[12])
{
#if IB_CFG_QEMU && !defined(IB_CFG_QEMU_READ_UID)
    /* QEMU 7.2's stm32vldiscovery maps nothing at 0x1FFFF7E8: a read would BusFault.
     * Report a fixed, recognisable ID instead. */
    static const uint8_t q[12] = {'Q', 'E', 'M', 'U', '-', 'S', 'T', 'M', '3', '2', 'F', '1'};
    memcpy(uid, q, 12);
#else
    for (unsigned i = 0; i < 3u; i++) {
        uint32_t w = IB_REG32(F1_UID_BASE + 4u * i);
        memcpy(uid + 4u * i, &w, 4);
    }
#endif
}

/* ------------------------------------------------------------------ TX DMA */

#if IB_CFG_TX_DMA
#define TX_CH 4u /* USART1_TX: DMA1 channel 4 (RM0008 13.3.7, table 78) */

void chip_tx_dma_init(uint32_t usart_dr_addr)
{
    DMA1_CCR(TX_CH) = 0;
    DMA1_IFCR = DMA_IFCR_ALL(TX_CH);
    DMA1_CPAR(TX_CH) = usart_dr_addr;
    ib_irq_enable(F1_IRQ_DMA1_CH4, 0x80u);
}

void chip_tx_dma_start(const uint8_t *p, uint32_t n)
{
    ib_dsb(); /* the queued bytes are in SRAM before the DMA may read them */
    DMA1_CCR(TX_CH) = 0;
    DMA1_IFCR = DMA_IFCR_ALL(TX_CH);
    DMA1_CMAR(TX_CH) = (uint32_t)(uintptr_t)p;
    DMA1_CNDTR(TX_CH) = n;
    DMA1_CCR(TX_CH) = DMA_CCR_DIR | DMA_CCR_MINC | DMA_CCR_TCIE | DMA_CCR_TEIE | DMA_CCR_PL_HIGH | DMA_CCR_EN;
}

int chip_tx_dma_done(void) { return (DMA1_ISR & (DMA_ISR_TCIF(TX_CH) | DMA_ISR_TEIF(TX_CH))) != 0u; }

void chip_tx_dma_stop(void)
{
    DMA1_CCR(TX_CH) = 0;
    DMA1_IFCR = DMA_IFCR_ALL(TX_CH);
}

void DMA1_Channel4_IRQHandler(void) { arm_tx_dma_irq(); }
#endif

/* ----------------------------------------------------------------- SPI DMA */

#if IB_CFG_SPI_DMA
/* SPI_RX_CH, SPI_TX_CH: chip.h */

void chip_spi_dma_init(uint32_t spi_dr_addr)
{
    DMA1_CCR(SPI_RX_CH) = 0;
    DMA1_CCR(SPI_TX_CH) = 0;
    DMA1_IFCR = DMA_IFCR_ALL(SPI_RX_CH) | DMA_IFCR_ALL(SPI_TX_CH);
    DMA1_CPAR(SPI_RX_CH) = spi_dr_addr;
    DMA1_CPAR(SPI_TX_CH) = spi_dr_addr;
    ib_irq_enable(F1_IRQ_DMA1_CH2, 0x80u);
}

/* chip_spi_dma_start(): chip.h */

int chip_spi_dma_finish(void)
{
    uint32_t isr = DMA1_ISR;
    DMA1_CCR(SPI_RX_CH) = 0;
    DMA1_CCR(SPI_TX_CH) = 0;
    DMA1_IFCR = DMA_IFCR_ALL(SPI_RX_CH) | DMA_IFCR_ALL(SPI_TX_CH);
    return (isr & (DMA_ISR_TEIF(SPI_RX_CH) | DMA_ISR_TEIF(SPI_TX_CH))) ? -1 : 0;
}

/* F1 channels stay enabled at the end of a transfer (RM0008 13.3.3): finish disables them. */
void chip_spi_dma_abort(void) { (void)chip_spi_dma_finish(); }

void DMA1_Channel2_IRQHandler(void) { arm_spi_dma_irq(); }
#endif

/* ------------------------------------------------------------------ flash */

extern const uint8_t __ib_param_slot0[], __ib_param_slot1[], __ib_param_slot_size[];

static ib_flash_if_t *g_fl;

static int in_slot(uint32_t addr, size_t len)
{
    for (int i = 0; i < 2; i++) {
        uint32_t a = g_fl->slot_addr[i];
        if (addr >= a && len <= g_fl->slot_size && addr - a <= g_fl->slot_size - len) {
            return 1;
        }
    }
    return 0;
}

/* Wait for BSY to clear, bounded in time (and in passes, should SysTick stall). */
static int flash_wait(uint32_t timeout_us)
{
    uint32_t t0 = arm_time_us();
    for (uint32_t i = 0; i < 10000000u; i++) {
        if (!(FLASH_SR & FLASH_SR_BSY)) {
            return 0;
        }
        if (arm_time_us() - t0 > timeout_us) {
            break;
        }
    }
    return (FLASH_SR & FLASH_SR_BSY) ? -1 : 0;
}

static void flash_unlock(void)
{
    if (FLASH_CR & FLASH_CR_LOCK) { /* a second key sequence while unlocked would fault */
        FLASH_KEYR = FLASH_KEY1;
        FLASH_KEYR = FLASH_KEY2;
    }
}

static void flash_lock(void) { FLASH_CR |= FLASH_CR_LOCK; }

static int sr_error(uint32_t sr)
{
    if (sr & FLASH_SR_WRPRTERR) {
        return IB_FLASH_ERR_PROTECTED;
    }
    if (sr & FLASH_SR_PGERR) {
        return IB_FLASH_ERR_NOT_ERASED;
    }
    return IB_FLASH_OK;
}

static int f1_erase(void *ctx, uint32_t addr)
{
    (void)ctx;
    if (addr != g_fl->slot_addr[0] && addr != g_fl->slot_addr[1]) {
        return IB_FLASH_ERR_RANGE;
    }
    flash_unlock();
    if (flash_wait(FLASH_ERASE_TIMEOUT_US) != 0) {
        flash_lock();
        return IB_FLASH_ERR_TIMEOUT;
    }
    FLASH_SR = FLASH_SR_PGERR | FLASH_SR_WRPRTERR | FLASH_SR_EOP; /* write 1 to clear */
    FLASH_CR |= FLASH_CR_PER;
    FLASH_AR = addr;
    FLASH_CR |= FLASH_CR_STRT;
    (void)FLASH_SR; /* BSY is set one cycle after STRT */
    int rc = flash_wait(FLASH_ERASE_TIMEOUT_US);
    uint32_t sr = FLASH_SR;
    FLASH_CR &= ~FLASH_CR_PER;
    FLASH_SR = FLASH_SR_PGERR | FLASH_SR_WRPRTERR | FLASH_SR_EOP;
    flash_lock();
    if (rc != 0) {
        return IB_FLASH_ERR_TIMEOUT;
    }
    if (sr & FLASH_SR_WRPRTERR) {
        return IB_FLASH_ERR_PROTECTED;
    }
    return (sr & FLASH_SR_PGERR) ? IB_FLASH_ERR : IB_FLASH_OK;
}

static int f1_program(void *ctx, uint32_t addr, const void *data, size_t len)
{
    (void)ctx;
    if ((addr & 1u) || (len & 1u) || !in_slot(addr, len)) {
        return IB_FLASH_ERR_RANGE;
    }
    const uint8_t *d = (const uint8_t *)data;
    int rc = IB_FLASH_OK;
    flash_unlock();
    if (flash_wait(FLASH_PROG_TIMEOUT_US) != 0) {
        flash_lock();
        return IB_FLASH_ERR_TIMEOUT;
    }
    for (size_t i = 0; i < len && rc == IB_FLASH_OK; i += 2u) {
        uint16_t hw;
        memcpy(&hw, d + i, 2);
        FLASH_SR = FLASH_SR_PGERR | FLASH_SR_WRPRTERR | FLASH_SR_EOP;
        FLASH_CR |= FLASH_CR_PG;
        IB_REG16(addr + i) = hw;
        if (flash_wait(FLASH_PROG_TIMEOUT_US) != 0) {
            rc = IB_FLASH_ERR_TIMEOUT;
        } else {
            rc = sr_error(FLASH_SR);
        }
        FLASH_CR &= ~FLASH_CR_PG;
    }
    FLASH_SR = FLASH_SR_PGERR | FLASH_SR_WRPRTERR | FLASH_SR_EOP;
    flash_lock();
    return rc;
}

static int f1_read(void *ctx, uint32_t addr, void *data, size_t len)
{
    (void)ctx;
    if (!in_slot(addr, len)) {
        return IB_FLASH_ERR_RANGE;
    }
    memcpy(data, (const void *)(uintptr_t)addr, len);
    return IB_FLASH_OK;
}

void chip_flash_init(ib_flash_if_t *fl)
{
    g_fl = fl;
    fl->slot_addr[0] = (uint32_t)(uintptr_t)__ib_param_slot0;
    fl->slot_addr[1] = (uint32_t)(uintptr_t)__ib_param_slot1;
    fl->slot_size = (uint32_t)(uintptr_t)__ib_param_slot_size;
    fl->program_unit = 2u;
    fl->erase = f1_erase;
    fl->program = f1_program;
    fl->read = f1_read;
    fl->ctx = NULL;
}
