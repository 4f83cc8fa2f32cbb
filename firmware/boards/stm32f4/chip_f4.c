/*
 * chip_f4.c - STM32F405/407 specifics behind common_arm/arm_board.h: vector table, clock
 * tree, pins, USART1 TX DMA, flash driver (ib_flash_if_t), unique ID. The QEMU image
 * (netduinoplus2, an STM32F405) is this file built with IB_CFG_QEMU=1.
 *
 * Clock (RM0090 7.2): HSE (IB_CFG_HSE_HZ, default 8 MHz; 12 and 25 MHz work too) / M to
 * 1 MHz, x336 = 336 MHz VCO, /2 = 168 MHz SYSCLK, /7 = 48 MHz; AHB 168 MHz, APB2 84 MHz
 * (USART1, SPI1), APB1 42 MHz; flash 5 wait states + prefetch + caches; VOS scale 1. Every
 * wait is bounded; if the crystal does not start, HSI 16 MHz / 16 feeds the same PLL
 * (still 168 MHz); if the PLL does not lock, HSI 16 MHz (USART1 then at most 1 Mbaud).
 * Both fallbacks report IB_CLOCK_SOURCE_HSI_FALLBACK. The QEMU image skips all of it
 * (QEMU's RCC reads 0) and assumes QEMU's 168 MHz SysTick clock.
 *
 * Pins:
 *   USART1  PA9 TX, PA10 RX (AF7; RX pulled up)
 *   SPI1    PA5 SCK, PA6 MISO, PA7 MOSI (AF5; MISO pulled down: a missing sensor reads 0x00)
 *   CS      PA4 ADXL355, PB0 ADXRS450 X, PB1 ADXRS450 Y, PB10 ADXRS450 Z (push-pull, high)
 *
 * Flash (RM0090 3.6/3.7): slots in sectors 10 and 11 (linker script), program_unit 4
 * (PSIZE x32, needs VDD 2.7-3.6 V). After every erase/program the data cache is reset so
 * the read-back verify sees the flash, not stale cache lines.
 */
#include <string.h>

#include "arm_board.h"
#include "chip.h"

#ifndef IB_CFG_QEMU_SYSCLK_HZ
#define IB_CFG_QEMU_SYSCLK_HZ 168000000u
#endif

#define RCC_WAIT_LOOPS 400000u
#define DMA_WAIT_LOOPS 10000u
#define FLASH_PROG_TIMEOUT_US 2000u      /* word: 16 us typ., 100 us max */
#define FLASH_ERASE_TIMEOUT_US 5000000u  /* 128 KiB sector at x32: 1 s typ., 2 s max */

/* ---------------------------------------------------------------- vectors */

extern uint32_t _estack;
void DMA2_Stream7_IRQHandler(void);
void DMA2_Stream0_IRQHandler(void);

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Woverride-init"
__attribute__((section(".isr_vector"), used)) void (*const g_vectors[16u + F4_IRQ_COUNT])(void) = {
    [0] = (void (*)(void))(uintptr_t)&_estack,
    [1] = Reset_Handler,
    [2 ... 15 + F4_IRQ_COUNT] = Default_Handler,
    [7] = 0, [8] = 0, [9] = 0, [10] = 0, [13] = 0, /* reserved */
    [15] = SysTick_Handler,
#if IB_CFG_TX_DMA
    [16u + F4_IRQ_DMA2_STREAM7] = DMA2_Stream7_IRQHandler,
#endif
#if IB_CFG_SPI_DMA
    [16u + F4_IRQ_DMA2_STREAM0] = DMA2_Stream0_IRQHandler,
#endif
    [16u + F4_IRQ_USART1] = USART1_IRQHandler,
};
#pragma GCC diagnostic pop

/* ------------------------------------------------------------------ clock */

#if !IB_CFG_QEMU
static int wait_reg(volatile uint32_t *reg, uint32_t mask, uint32_t want)
{
    return ib_wait_reg(reg, mask, want, RCC_WAIT_LOOPS);
}

/* SYSCLK = 168 MHz from the PLL fed by src (HSE or HSI) divided by m to 1 MHz. 1 on success;
 * on failure SYSCLK stays on HSI. */
static int pll_start(uint32_t src, uint32_t m)
{
    RCC_CFGR &= ~RCC_CFGR_SW_MASK;
    (void)wait_reg(&RCC_CFGR, RCC_CFGR_SWS_MASK, 0u);
    RCC_CR &= ~RCC_CR_PLLON;
    if (!wait_reg(&RCC_CR, RCC_CR_PLLRDY, 0u)) {
        return 0;
    }
    RCC_PLLCFGR = (RCC_PLLCFGR & RCC_PLLCFGR_RESERVED) | RCC_PLLCFGR_M(m) | RCC_PLLCFGR_N(336u) |
                  RCC_PLLCFGR_P(2u) | src | RCC_PLLCFGR_Q(7u);
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_reg(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        RCC_CR &= ~RCC_CR_PLLON;
        return 0;
    }
    FLASH_ACR = FLASH_ACR_LATENCY(5u) | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    RCC_CFGR = RCC_CFGR_PPRE1_DIV4 | RCC_CFGR_PPRE2_DIV2 | RCC_CFGR_SW_HSI;
    RCC_CFGR |= RCC_CFGR_SW_PLL;
    if (!wait_reg(&RCC_CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SWS_PLL)) {
        RCC_CFGR = RCC_CFGR_SW_HSI;
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
    clk->pclk2_hz = IB_CFG_QEMU_SYSCLK_HZ / 2u;
    clk->clock_source = IB_CLOCK_SOURCE_HSI;
#else
#if IB_CFG_HSE_HZ % 1000000u != 0u || IB_CFG_HSE_HZ < 4000000u || IB_CFG_HSE_HZ > 26000000u
#error "IB_CFG_HSE_HZ must be a whole number of MHz between 4 and 26"
#endif
    RCC_APB1ENR |= RCC_APB1ENR_PWREN;
    (void)RCC_APB1ENR;
    PWR_CR |= PWR_CR_VOS;
    RCC_CR |= RCC_CR_HSION;
    (void)wait_reg(&RCC_CR, RCC_CR_HSIRDY, RCC_CR_HSIRDY);
    RCC_CR |= RCC_CR_HSEON;
    clk->sysclk_hz = 168000000u;
    clk->pclk2_hz = 84000000u;
    if (wait_reg(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY) &&
        pll_start(RCC_PLLCFGR_SRC_HSE, IB_CFG_HSE_HZ / 1000000u)) {
        clk->clock_source = IB_CLOCK_SOURCE_HSE_PLL;
        return;
    }
    RCC_CR &= ~RCC_CR_HSEON;
    clk->clock_source = IB_CLOCK_SOURCE_HSI_FALLBACK;
    if (pll_start(0u, 16u)) { /* HSI 16 MHz / 16 */
        return;
    }
    RCC_CFGR = RCC_CFGR_SW_HSI;
    clk->sysclk_hz = 16000000u;
    clk->pclk2_hz = 16000000u;
#endif
}

/* ------------------------------------------------------------------- pins */

static void pin_cfg(uint32_t port, unsigned pin, uint32_t mode, uint32_t af, uint32_t pull)
{
    unsigned s2 = pin * 2u;
    GPIO_OSPEEDR(port) = (GPIO_OSPEEDR(port) & ~(3u << s2)) | (F4_SPEED_FAST << s2);
    GPIO_PUPDR(port) = (GPIO_PUPDR(port) & ~(3u << s2)) | (pull << s2);
    GPIO_OTYPER(port) &= ~(1u << pin); /* push-pull */
    if (mode == F4_MODE_AF) {
        unsigned s4 = (pin & 7u) * 4u;
        GPIO_AFR(port, pin >> 3) = (GPIO_AFR(port, pin >> 3) & ~(0xFu << s4)) | (af << s4);
    }
    GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << s2)) | (mode << s2);
}

void chip_periph_init(void)
{
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOAEN | RCC_AHB1ENR_GPIOBEN | RCC_AHB1ENR_DMA2EN;
    RCC_APB2ENR |= RCC_APB2ENR_USART1EN | RCC_APB2ENR_SPI1EN;
    (void)RCC_APB2ENR; /* read back: clocks running before the first access */

    GPIO_BSRR(F4_GPIOA_BASE) = 1u << 4; /* chip selects high before they become outputs */
    GPIO_BSRR(F4_GPIOB_BASE) = (1u << 0) | (1u << 1) | (1u << 10);
    pin_cfg(F4_GPIOA_BASE, 4, F4_MODE_OUT, 0, F4_PULL_NONE);
    pin_cfg(F4_GPIOB_BASE, 0, F4_MODE_OUT, 0, F4_PULL_NONE);
    pin_cfg(F4_GPIOB_BASE, 1, F4_MODE_OUT, 0, F4_PULL_NONE);
    pin_cfg(F4_GPIOB_BASE, 10, F4_MODE_OUT, 0, F4_PULL_NONE);
    pin_cfg(F4_GPIOA_BASE, 5, F4_MODE_AF, 5, F4_PULL_NONE);
    pin_cfg(F4_GPIOA_BASE, 6, F4_MODE_AF, 5, F4_PULL_DOWN);
    pin_cfg(F4_GPIOA_BASE, 7, F4_MODE_AF, 5, F4_PULL_NONE);
    pin_cfg(F4_GPIOA_BASE, 9, F4_MODE_AF, 7, F4_PULL_NONE);
    pin_cfg(F4_GPIOA_BASE, 10, F4_MODE_AF, 7, F4_PULL_UP);
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
    /* QEMU 7.2's netduinoplus2 maps nothing at 0x1FFF7A10: a read would BusFault.
     * Report a fixed, recognisable ID instead. */
    static const uint8_t q[12] = {'Q', 'E', 'M', 'U', '-', 'S', 'T', 'M', '3', '2', 'F', '4'};
    memcpy(uid, q, 12);
#else
    for (unsigned i = 0; i < 3u; i++) {
        uint32_t w = IB_REG32(F4_UID_BASE + 4u * i);
        memcpy(uid + 4u * i, &w, 4);
    }
#endif
}

/* ------------------------------------------------------------------ TX DMA */

#if IB_CFG_TX_DMA
#define TX_STREAM 7u /* USART1_TX: DMA2 stream 7 channel 4 (RM0090 10.3.3, table 43) */
#define TX_CHANNEL 4u

static void dma_disable(void)
{
    DMA2_SCR(TX_STREAM) &= ~DMA_SCR_EN;
    for (uint32_t i = 0; i < DMA_WAIT_LOOPS && (DMA2_SCR(TX_STREAM) & DMA_SCR_EN); i++) {
    }
    DMA2_HIFCR = DMA_HIFCR_ALL7;
}

void chip_tx_dma_init(uint32_t usart_dr_addr)
{
    dma_disable();
    DMA2_SPAR(TX_STREAM) = usart_dr_addr;
    DMA2_SFCR(TX_STREAM) = 0; /* direct mode */
    ib_irq_enable(F4_IRQ_DMA2_STREAM7, 0x80u);
}

void chip_tx_dma_start(const uint8_t *p, uint32_t n)
{
    ib_dsb(); /* the queued bytes are in SRAM before the DMA may read them */
    dma_disable();
    DMA2_SM0AR(TX_STREAM) = (uint32_t)(uintptr_t)p;
    DMA2_SNDTR(TX_STREAM) = n;
    DMA2_SCR(TX_STREAM) = DMA_SCR_CHSEL(TX_CHANNEL) | DMA_SCR_PL_HIGH | DMA_SCR_MINC | DMA_SCR_DIR_M2P |
                          DMA_SCR_TCIE | DMA_SCR_TEIE | DMA_SCR_EN;
}

int chip_tx_dma_done(void)
{
    return (DMA2_HISR & (DMA_HISR_TCIF7 | DMA_HISR_TEIF7 | DMA_HISR_DMEIF7)) != 0u;
}

void chip_tx_dma_stop(void) { dma_disable(); }

void DMA2_Stream7_IRQHandler(void) { arm_tx_dma_irq(); }
#endif

/* ----------------------------------------------------------------- SPI DMA */

#if IB_CFG_SPI_DMA
/* SPI_RX_STREAM, SPI_TX_STREAM, SPI_DMA_CHANNEL and chip_spi_dma_start(): chip.h */

static void spi_dma_disable(void)
{
    DMA2_SCR(SPI_RX_STREAM) = 0;
    DMA2_SCR(SPI_TX_STREAM) = 0;
    for (uint32_t i = 0; i < DMA_WAIT_LOOPS && ((DMA2_SCR(SPI_RX_STREAM) | DMA2_SCR(SPI_TX_STREAM)) & DMA_SCR_EN);
         i++) {
    }
    DMA2_LIFCR = DMA_LIFCR_ALL0 | DMA_LIFCR_ALL3;
}

void chip_spi_dma_init(uint32_t spi_dr_addr)
{
    spi_dma_disable();
    DMA2_SPAR(SPI_RX_STREAM) = spi_dr_addr;
    DMA2_SPAR(SPI_TX_STREAM) = spi_dr_addr;
    DMA2_SFCR(SPI_RX_STREAM) = 0; /* direct mode */
    DMA2_SFCR(SPI_TX_STREAM) = 0;
    ib_irq_enable(F4_IRQ_DMA2_STREAM0, 0x80u);
}

/* RX stream complete: in direct mode the TX stream moved its last byte before the RX stream
 * took the last one, and the hardware cleared both streams' EN at the end of their transfers
 * (RM0090 10.3.17, 10.5.5), so only the flags need clearing. A transfer error also clears EN
 * (10.3.18); the streams are stopped anyway then. */
int chip_spi_dma_finish(void)
{
    uint32_t isr = DMA2_LISR;
    DMA2_LIFCR = DMA_LIFCR_ALL0 | DMA_LIFCR_ALL3;
    if (isr & (DMA_LISR_TEIF0 | DMA_LISR_DMEIF0 | DMA_LISR_TEIF3 | DMA_LISR_DMEIF3)) {
        spi_dma_disable();
        return -1;
    }
    return 0;
}

void chip_spi_dma_abort(void) { spi_dma_disable(); }

void DMA2_Stream0_IRQHandler(void) { arm_spi_dma_irq(); }
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

/* Sector number of a sector start address (RM0090 3.3, table 5: 1 MiB devices). */
static int sector_of(uint32_t addr)
{
    uint32_t off = addr - 0x08000000u;
    if (off < 0x10000u) {
        return (off & 0x3FFFu) ? -1 : (int)(off >> 14); /* 0-3: 16 KiB */
    }
    if (off == 0x10000u) {
        return 4; /* 64 KiB */
    }
    if (off >= 0x20000u && off < 0x100000u && (off & 0x1FFFFu) == 0u) {
        return (int)(4u + (off >> 17)); /* 5-11: 128 KiB */
    }
    return -1;
}

static int flash_wait(uint32_t timeout_us)
{
    uint32_t t0 = arm_time_us();
    for (uint32_t i = 0; i < 100000000u; i++) {
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

/* Lock, and reset the data cache so reads see the new flash contents (RM0090 3.5.2). */
static void flash_finish(void)
{
    FLASH_CR |= FLASH_CR_LOCK;
    uint32_t acr = FLASH_ACR;
    if (acr & FLASH_ACR_DCEN) {
        FLASH_ACR = acr & ~FLASH_ACR_DCEN;
        FLASH_ACR = (acr & ~FLASH_ACR_DCEN) | FLASH_ACR_DCRST;
        FLASH_ACR = acr & ~FLASH_ACR_DCEN;
        FLASH_ACR = acr;
    }
}

static int sr_error(uint32_t sr)
{
    if (sr & FLASH_SR_WRPERR) {
        return IB_FLASH_ERR_PROTECTED;
    }
    if (sr & FLASH_SR_PGAERR) {
        return IB_FLASH_ERR_RANGE;
    }
    if (sr & FLASH_SR_ERRORS) {
        return IB_FLASH_ERR; /* PGSERR, PGPERR, OPERR */
    }
    return IB_FLASH_OK;
}

static int f4_erase(void *ctx, uint32_t addr)
{
    (void)ctx;
    int sector = sector_of(addr);
    if ((addr != g_fl->slot_addr[0] && addr != g_fl->slot_addr[1]) || sector < 0) {
        return IB_FLASH_ERR_RANGE;
    }
    flash_unlock();
    if (flash_wait(FLASH_PROG_TIMEOUT_US) != 0) {
        flash_finish();
        return IB_FLASH_ERR_TIMEOUT;
    }
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP; /* write 1 to clear */
    FLASH_CR = (FLASH_CR & FLASH_CR_LOCK) | FLASH_CR_PSIZE_X32 | FLASH_CR_SER | FLASH_CR_SNB((uint32_t)sector);
    FLASH_CR |= FLASH_CR_STRT;
    int rc = flash_wait(FLASH_ERASE_TIMEOUT_US);
    uint32_t sr = FLASH_SR;
    FLASH_CR &= ~(FLASH_CR_SER | FLASH_CR_SNB(0xFu));
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;
    flash_finish();
    return rc != 0 ? IB_FLASH_ERR_TIMEOUT : sr_error(sr);
}

static int f4_program(void *ctx, uint32_t addr, const void *data, size_t len)
{
    (void)ctx;
    if ((addr & 3u) || (len & 3u) || !in_slot(addr, len)) {
        return IB_FLASH_ERR_RANGE;
    }
    const uint8_t *d = (const uint8_t *)data;
    int rc = IB_FLASH_OK;
    flash_unlock();
    if (flash_wait(FLASH_PROG_TIMEOUT_US) != 0) {
        flash_finish();
        return IB_FLASH_ERR_TIMEOUT;
    }
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;
    FLASH_CR = (FLASH_CR & FLASH_CR_LOCK) | FLASH_CR_PSIZE_X32 | FLASH_CR_PG;
    for (size_t i = 0; i < len && rc == IB_FLASH_OK; i += 4u) {
        uint32_t w;
        memcpy(&w, d + i, 4);
        IB_REG32(addr + i) = w;
        ib_dsb();
        if (flash_wait(FLASH_PROG_TIMEOUT_US) != 0) {
            rc = IB_FLASH_ERR_TIMEOUT;
        } else {
            rc = sr_error(FLASH_SR);
        }
    }
    FLASH_CR &= ~FLASH_CR_PG;
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;
    flash_finish();
    return rc;
}

static int f4_read(void *ctx, uint32_t addr, void *data, size_t len)
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
    fl->program_unit = 4u;
    fl->erase = f4_erase;
    fl->program = f4_program;
    fl->read = f4_read;
    fl->ctx = NULL;
}
