/*
 * arm_board.c - the ib_board_t of the STM32 boards (F1 and F4, hardware and QEMU images);
 * see arm_board.h. Everything chip specific is behind chip_*().
 *
 * Time: SysTick interrupts at 1 kHz from the CPU clock (the one timer QEMU models on both
 * machines) and counts milliseconds; time_us() adds the elapsed part of the current
 * millisecond from SysTick VAL, so it has 1 us resolution. Not the DWT: QEMU does not
 * model it (CYCCNT reads 0).
 *
 * Sample tick: the main loop compares time_us() with the next due time of the period
 * the core asked for (set_tick_hz) and calls ib_core_tick(missed, due) from the main loop,
 * never from an interrupt; due is the tick's place on the period grid (the batch stamp), not
 * the moment the main loop got to it.
 *
 * Link: USART1 8N1. RX: RXNE interrupt into a ring (ORE/FE/NE cleared by the SR-then-DR
 * read). TX: a ring the core fills through link_write(); drained by DMA (hardware builds:
 * one contiguous chunk per transfer, restarted from the DMA interrupt and from the main
 * loop) or by polling TXE from link_write()/link_tx_free()/the main loop/delays (QEMU:
 * no DMA model and no TXE interrupt; TXE is always 1 there, so the ring empties at once).
 *
 * SPI1: mode 0, 8 bit, MSB first, software NSS. transfer(): polled byte by byte (start-up,
 * configuration, commands, the once-per-batch temperatures); every wait bounded, a timeout
 * is a bus error (-1). start() (IB_CFG_SPI_DMA, hardware builds): chip select low, SPI1
 * RX and TX by DMA, and from the RX channel's completion interrupt chip select high and the
 * caller's done(); the core chains a sample's transfers from there (core.c, job_next).
 * With no sensor (QEMU) every byte reads 0x00 and the drivers report the parts missing;
 * the firmware keeps serving commands.
 */
#include <string.h>

#include "arm_board.h"
#include "chip.h"
#include "core.h"

/* Bounded busy waits (loop passes, each several cycles). */
#define SPI_WAIT_LOOPS 20000u
#define TC_WAIT_US 2000u
#define REBOOT_DRAIN_US 200000u

static ib_core_t g_core;
static ib_board_t g_board;
static ib_spi_bus_t g_spi;
static ib_flash_if_t g_flash;
static arm_clocks_t g_clk;

/* ------------------------------------------------------------------ time */

static volatile uint32_t g_ms;
static uint32_t g_systick_load;  /* cycles per ms - 1 */
static uint32_t g_cycles_per_us;

void SysTick_Handler(void) { g_ms++; }

uint32_t arm_time_us(void)
{
    uint32_t ms, val, p1, p2;
    unsigned tries = 0;
    /* Consistent (ms, VAL) pair: retry if the SysTick interrupt ran or became pending in
     * between. With interrupts masked the ISR cannot run: a pending SysTick means VAL has
     * wrapped since g_ms was last incremented, so count that millisecond here. */
    do {
        ms = g_ms;
        p1 = SCB_ICSR & SCB_ICSR_PENDSTSET;
        val = STK_VAL;
        p2 = SCB_ICSR & SCB_ICSR_PENDSTSET;
    } while ((ms != g_ms || p1 != p2) && ++tries < 4u);
    if (p1) {
        ms++;
    }
    uint32_t elapsed = val <= g_systick_load ? g_systick_load - val : 0u;
    return ms * 1000u + elapsed / g_cycles_per_us;
}

static void systick_init(uint32_t sysclk_hz)
{
    g_cycles_per_us = sysclk_hz / 1000000u;
    if (g_cycles_per_us == 0u) {
        g_cycles_per_us = 1u;
    }
    g_systick_load = sysclk_hz / 1000u - 1u;
    STK_CTRL = 0;
    STK_LOAD = g_systick_load;
    STK_VAL = 0;
    SCB_SHPR3 = (SCB_SHPR3 & 0x00FFFFFFu) | (0x40u << 24); /* below the USART RX interrupt */
    STK_CTRL = STK_CTRL_CLKSOURCE | STK_CTRL_TICKINT | STK_CTRL_ENABLE;
}

static uint32_t b_time_us(void *ctx)
{
    (void)ctx;
    return arm_time_us();
}

/* Sample tick, polled by the main loop. */
static uint32_t g_tick_period_us; /* 0 = no tick */
static uint32_t g_tick_next_us;

static void b_set_tick_hz(void *ctx, uint32_t rate_hz)
{
    (void)ctx;
    if (rate_hz == 0u || rate_hz > 1000000u) {
        g_tick_period_us = 0;
        return;
    }
    g_tick_period_us = 1000000u / rate_hz;
    g_tick_next_us = arm_time_us() + g_tick_period_us;
}

/* ------------------------------------------------------------------ link */

#define TX_MASK (IB_CFG_TX_RING - 1u)
#define RX_MASK (IB_CFG_RX_RING - 1u)

static uint8_t g_rx[IB_CFG_RX_RING];
static volatile uint32_t g_rx_head; /* written by the ISR */
static volatile uint32_t g_rx_tail; /* written by the main loop */
static volatile uint32_t g_rx_dropped;

static uint8_t g_tx[IB_CFG_TX_RING] __attribute__((aligned(4)));
static volatile uint32_t g_tx_head; /* written by the main loop */
static volatile uint32_t g_tx_tail; /* advanced when bytes have left */
static uint32_t g_baud;

void USART1_IRQHandler(void)
{
    const uint32_t b = CHIP_USART1_BASE;
    uint32_t sr = USART_SR(b);
    if (sr & (USART_SR_RXNE | USART_SR_ORE | USART_SR_FE | USART_SR_NE | USART_SR_PE)) {
        uint8_t byte = (uint8_t)USART_DR(b); /* SR then DR read clears RXNE, ORE, FE, NE */
        if (sr & USART_SR_ORE) {
            g_rx_dropped++;
        }
        if (sr & USART_SR_RXNE) {
            uint32_t h = g_rx_head;
            if (((h + 1u) & RX_MASK) != g_rx_tail) {
                g_rx[h] = byte;
                g_rx_head = (h + 1u) & RX_MASK;
            } else {
                g_rx_dropped++;
            }
        }
    }
}

#if IB_CFG_TX_DMA
static volatile uint32_t g_tx_inflight; /* bytes of the running DMA transfer, 0 = idle */

/* Called from the DMA interrupt or with interrupts masked: finish the running transfer
 * if it is done, start the next contiguous chunk. */
static void tx_kick(void)
{
    if (g_tx_inflight) {
        if (!chip_tx_dma_done()) {
            return;
        }
        chip_tx_dma_stop();
        g_tx_tail = (g_tx_tail + g_tx_inflight) & TX_MASK;
        g_tx_inflight = 0;
    }
    uint32_t head = g_tx_head, tail = g_tx_tail;
    if (head == tail) {
        return;
    }
    uint32_t n = head > tail ? head - tail : IB_CFG_TX_RING - tail;
    g_tx_inflight = n;
    chip_tx_dma_start(&g_tx[tail], n);
}

void arm_tx_dma_irq(void) { tx_kick(); }

static void tx_service(void)
{
    uint32_t pm = ib_irq_save();
    tx_kick();
    ib_irq_restore(pm);
}
#else
/* Polled TX: send what the transmitter takes now (all of it under QEMU). Bounded by the
 * ring size. */
static void tx_service(void)
{
    const uint32_t b = CHIP_USART1_BASE;
    uint32_t tail = g_tx_tail, head = g_tx_head;
    for (uint32_t n = 0; tail != head && n < IB_CFG_TX_RING; n++) {
        if (!(USART_SR(b) & USART_SR_TXE)) {
            break;
        }
        USART_DR(b) = g_tx[tail];
        tail = (tail + 1u) & TX_MASK;
    }
    g_tx_tail = tail;
}
#endif

static uint32_t tx_used(void) { return (g_tx_head - g_tx_tail) & TX_MASK; }

static size_t b_link_tx_free(void *ctx)
{
    (void)ctx;
    tx_service();
    return (size_t)(TX_MASK - tx_used());
}

static size_t b_link_write(void *ctx, const uint8_t *data, size_t len)
{
    (void)ctx;
    size_t room = TX_MASK - tx_used();
    size_t n = len < room ? len : room;
    uint32_t h = g_tx_head;
    size_t first = IB_CFG_TX_RING - h; /* up to the ring's end, then from its start */
    if (first > n) {
        first = n;
    }
    memcpy(&g_tx[h], data, first);
    memcpy(g_tx, data + first, n - first);
    h = (h + (uint32_t)n) & TX_MASK;
    ib_compiler_barrier();
    g_tx_head = h;
    tx_service();
    return n;
}

static size_t b_link_read(void *ctx, uint8_t *buf, size_t cap)
{
    (void)ctx;
    size_t n = 0;
    uint32_t t = g_rx_tail;
    const uint32_t h = g_rx_head;
    while (t != h && n < cap) {
        buf[n++] = g_rx[t];
        t = (t + 1u) & RX_MASK;
    }
    g_rx_tail = t;
    return n;
}

static void usart_init(uint32_t pclk_hz)
{
    const uint32_t b = CHIP_USART1_BASE;
    /* 16x oversampling: BRR = f_PCLK / baud (mantissa.fraction = USARTDIV, 4 fraction
     * bits); USARTDIV must be >= 1, i.e. BRR >= 16: a slow fallback clock lowers the baud
     * rate to f_PCLK / 16 (reported in info.baud). 72 MHz -> 0x24, 84 MHz -> 0x2A. */
    uint32_t brr = (pclk_hz + IB_CFG_BAUD / 2u) / IB_CFG_BAUD;
    if (brr < 16u) {
        brr = 16u;
    }
    g_baud = IB_CFG_QEMU ? IB_CFG_BAUD : (pclk_hz + brr / 2u) / brr;
    USART_CR1(b) = 0;
    USART_BRR(b) = brr;
    USART_CR2(b) = 0; /* 1 stop bit */
    USART_CR3(b) = IB_CFG_TX_DMA ? USART_CR3_DMAT : 0u;
    USART_CR1(b) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    ib_irq_enable(CHIP_USART1_IRQ, 0x00u); /* highest: 5 us per byte at 2 Mbaud */
#if IB_CFG_TX_DMA
    chip_tx_dma_init(CHIP_USART1_BASE + 0x04u);
#endif
}

/* ------------------------------------------------------------------- SPI */

static int spi_wait(uint32_t mask, uint32_t want)
{
    const uint32_t b = CHIP_SPI1_BASE;
    for (uint32_t i = 0; i < SPI_WAIT_LOOPS; i++) {
        if ((SPI_SR(b) & mask) == want) {
            return 0;
        }
    }
    return -1;
}

static int spi_transfer(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)ctx;
    const uint32_t b = CHIP_SPI1_BASE;
    if (cs >= IB_CS_COUNT) {
        return -1;
    }
    if (SPI_SR(b) & SPI_SR_MODF) { /* mode fault cleared MSTR/SPE: re-arm */
        SPI_CR1(b) = SPI_CR1(b) | SPI_CR1_MSTR | SPI_CR1_SPE;
    }
    if (SPI_SR(b) & SPI_SR_RXNE) {
        (void)SPI_DR(b); /* stale byte */
    }
    chip_cs_write(cs, 0);
    int rc = 0;
    for (size_t i = 0; i < len; i++) {
        if (spi_wait(SPI_SR_TXE, SPI_SR_TXE) != 0) {
            rc = -1;
            break;
        }
        SPI_DR(b) = tx ? tx[i] : 0u;
        if (spi_wait(SPI_SR_RXNE, SPI_SR_RXNE) != 0) {
            rc = -1;
            break;
        }
        uint8_t v = (uint8_t)SPI_DR(b);
        if (rx) {
            rx[i] = v;
        }
    }
    if (spi_wait(SPI_SR_BSY, 0u) != 0) {
        rc = -1;
    }
    chip_cs_write(cs, 1);
    return rc;
}

#if IB_CFG_SPI_DMA
#define SPI_DMA_TIMEOUT_MS 3u /* the longest transfer (97 bytes) takes ~0.2 ms */

static struct {
    void (*done)(void *arg, int rc);
    void *arg;
    volatile uint32_t *cs_bsrr; /* chip select of the running transfer: its BSRR */
    uint32_t cs_bit;            /* and its pin's bit there (written: released) */
    uint32_t t0_ms;
    volatile uint8_t busy;
} g_spi_job;
static const uint8_t g_spi_zero = 0; /* sent when tx is NULL */
static uint8_t g_spi_sink;           /* received into when rx is NULL */

/* Rare: a mode fault (it cleared MSTR/SPE: re-arm) or a stale received byte. Out of line so
 * the per-transfer path is one SR read and a branch. */
__attribute__((noinline)) static void spi_recover(uint32_t sr)
{
    const uint32_t b = CHIP_SPI1_BASE;
    if (sr & SPI_SR_MODF) {
        SPI_CR1(b) = SPI_CR1(b) | SPI_CR1_MSTR | SPI_CR1_SPE;
    }
    if (SPI_SR(b) & SPI_SR_RXNE) {
        (void)SPI_DR(b);
    }
}

/* Runs ~5 times a sample (the chain's transfers), mostly from the previous transfer's
 * completion interrupt: kept lean (one SR read, chip select inline, no flag re-reads). */
static int spi_start(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len,
                     void (*done)(void *arg, int rc), void *arg)
{
    (void)ctx;
    const uint32_t b = CHIP_SPI1_BASE;
    if (cs >= IB_CS_COUNT || len - 1u >= 0xFFFFu || g_spi_job.busy || done == NULL) {
        return -1;
    }
    uint32_t sr = SPI_SR(b);
    if (sr & (SPI_SR_MODF | SPI_SR_RXNE)) {
        spi_recover(sr);
    }
    volatile uint32_t *bsrr = chip_cs_bsrr(cs);
    uint32_t bit = chip_cs_bit(cs);
    g_spi_job.done = done;
    g_spi_job.arg = arg;
    g_spi_job.cs_bsrr = bsrr;
    g_spi_job.cs_bit = bit;
    g_spi_job.t0_ms = g_ms;
    g_spi_job.busy = 1;
    *bsrr = bit << 16; /* select */
    ib_dsb(); /* tx bytes in SRAM before the DMA reads them */
    chip_spi_dma_start(tx ? tx : &g_spi_zero, tx != NULL, rx ? rx : &g_spi_sink, rx != NULL, (uint32_t)len);
    SPI_CR2(b) = SPI_CR2_RXDMAEN | SPI_CR2_TXDMAEN; /* RM: channels enabled, then the requests */
    return 0;
}

/* RX channel complete (the last byte is in memory, so its frame has been clocked). */
void arm_spi_dma_irq(void)
{
    const uint32_t b = CHIP_SPI1_BASE;
    int rc = chip_spi_dma_finish();
    SPI_CR2(b) = 0;
    if (SPI_SR(b) & SPI_SR_BSY) { /* clear by now: the last frame's byte is in memory */
        if (spi_wait(SPI_SR_BSY, 0u) != 0) {
            rc = -1;
        }
    }
    *g_spi_job.cs_bsrr = g_spi_job.cs_bit; /* release */
    g_spi_job.busy = 0;
    g_spi_job.done(g_spi_job.arg, rc);
}
#endif

#if IB_CFG_SPI_DMA
/* While a chain of DMA transfers runs and no byte waits to be read, sleep: each completion
 * interrupt runs the next step of the chain and wakes us; we go back to sleep until the
 * chain is over or a byte arrives (then the main loop serves it at once). Interrupts are
 * masked around the check so a completion between check and WFI still wakes the WFI
 * (ARMv7-M: WFI wakes on a pending interrupt whatever PRIMASK says); the interrupt runs
 * when PRIMASK is restored. */
static void spi_job_sleep(void)
{
    for (;;) {
        uint32_t pm = ib_irq_save();
        int sleep = g_spi_job.busy && g_rx_head == g_rx_tail;
        if (sleep && g_ms - g_spi_job.t0_ms > SPI_DMA_TIMEOUT_MS) {
            /* the completion never came (bounded like every other wait): stop the channels,
             * release chip select and report a bus error to the chain (it goes on with the
             * next step; the sample is flagged SPI_ERROR) */
            chip_spi_dma_abort();
            SPI_CR2(CHIP_SPI1_BASE) = 0;
            *g_spi_job.cs_bsrr = g_spi_job.cs_bit;
            g_spi_job.busy = 0;
            g_spi_job.done(g_spi_job.arg, -1);
            sleep = 0;
        }
        if (sleep) {
            ib_wfi();
        }
        ib_irq_restore(pm);
        if (!sleep) {
            return;
        }
    }
}
#endif

static void b_delay_us(void *ctx, uint32_t us)
{
    (void)ctx;
    uint32_t t0 = arm_time_us();
    /* Backstop in case SysTick were not running: a pass takes far more than 1 cycle. */
    uint32_t clamp = us > 20000000u ? 20000000u : us;
    uint32_t guard = clamp * g_cycles_per_us + 1000u;
    for (uint32_t i = 0; i < guard; i++) {
        if (arm_time_us() - t0 >= us) {
            break;
        }
        tx_service();
    }
}

static void spi_init(uint32_t pclk_hz)
{
    const uint32_t b = CHIP_SPI1_BASE;
    uint32_t br = 0; /* f_SCK = f_PCLK / 2^(br+1) <= IB_CFG_SPI_MAX_HZ */
    while (br < 7u && (pclk_hz >> (br + 1u)) > IB_CFG_SPI_MAX_HZ) {
        br++;
    }
    SPI_CR1(b) = 0;
    SPI_CR2(b) = 0;
    /* mode 0 (CPOL = 0, CPHA = 0), 8 bit, MSB first, master, software NSS held high */
    SPI_CR1(b) = SPI_CR1_MSTR | (br << SPI_CR1_BR_SHIFT) | SPI_CR1_SSM | SPI_CR1_SSI;
    SPI_CR1(b) = SPI_CR1(b) | SPI_CR1_SPE;
#if IB_CFG_SPI_DMA
    chip_spi_dma_init(CHIP_SPI1_BASE + 0x0Cu);
#endif
}

/* ---------------------------------------------------------------- reboot */

static void b_reboot(void *ctx)
{
    (void)ctx;
    uint32_t t0 = arm_time_us();
    while (tx_used() != 0u && arm_time_us() - t0 < REBOOT_DRAIN_US) {
        tx_service();
    }
    t0 = arm_time_us();
    while (!(USART_SR(CHIP_USART1_BASE) & USART_SR_TC) && arm_time_us() - t0 < TC_WAIT_US) {
    }
    (void)ib_irq_save();
    ib_dsb();
    SCB_AIRCR = SCB_AIRCR_VECTKEY | SCB_AIRCR_SYSRESETREQ;
    ib_dsb();
    for (;;) {
    }
}

/* The image's own tag: the board it is built for and its build id, found by `imubench flash`
 * in the .bin/.hex/.elf it is given (an F4 image is refused for an F103 before anything is
 * erased). KEEP in sections.ld keeps it in spite of --gc-sections. */
__attribute__((used, section(".ib_image_tag"))) const char ib_image_tag[] =
    "imubench-image board=" CHIP_BOARD_NAME " build=" IB_BUILD_ID;

/* ------------------------------------------------------------------ main */

int main(void)
{
    chip_clock_init(&g_clk);
    systick_init(g_clk.sysclk_hz);
    chip_periph_init();
    usart_init(g_clk.pclk2_hz);
    spi_init(g_clk.pclk2_hz);
    chip_flash_init(&g_flash);

    g_spi.transfer = spi_transfer;
    g_spi.delay_us = b_delay_us;
    g_spi.ctx = NULL;
#if IB_CFG_SPI_DMA
    g_spi.start = spi_start;
#else
    g_spi.start = NULL;
#endif

    g_board.board_id = CHIP_BOARD_ID;
    g_board.clock_source = g_clk.clock_source;
    g_board.baud = g_baud;
    chip_read_uid(g_board.uid);
    g_board.build = IB_BUILD_ID;
    g_board.time_us = b_time_us;
    g_board.set_tick_hz = b_set_tick_hz;
    g_board.link_tx_free = b_link_tx_free;
    g_board.link_write = b_link_write;
    g_board.link_read = b_link_read;
    g_board.spi = &g_spi;
    g_board.flash = &g_flash;
    g_board.reboot = b_reboot;
    g_board.ctx = NULL;

    ib_core_init(&g_core, &g_board);

    for (;;) {
        tx_service();
        if (g_tick_period_us) {
            uint32_t late = arm_time_us() - g_tick_next_us;
            if (late < 0x80000000u) { /* due (serial-number comparison) */
                uint32_t missed = late / g_tick_period_us;
                uint32_t due_us = g_tick_next_us + missed * g_tick_period_us;
                g_tick_next_us = due_us + g_tick_period_us;
                ib_core_tick(&g_core, missed, due_us);
            }
        }
#if IB_CFG_SPI_DMA
        /* sleep through the sample's DMA chain, then poll: the sample is finished in the
         * pass that started it, not in a later one (one main-loop pass less per sample) */
        spi_job_sleep();
#endif
        ib_core_poll(&g_core);
        if (!g_tick_period_us && g_rx_head == g_rx_tail && tx_used() == 0u) {
            ib_wfi(); /* idle: SysTick (1 ms) or a received byte wakes us */
        }
    }
}
