/*
 * core_cost.c - the firmware core's cost per sample, for callgrind (bench/core_instructions.py).
 *
 * Links the real core and drivers with a minimal in-process board: SPI goes to the sensor
 * models (board_spi_transfer), the link discards what it is given (board_link_write), time
 * advances one sample period per tick. Boots, starts a stream with a start_stream command
 * frame, then runs N ticks. Callgrind's inclusive count of ib_core_tick minus the inclusive
 * counts of the board's SPI and link functions is the core's own work (drivers included,
 * sensor models and link excluded).
 *
 *   core_cost RATE_HZ MODE(0 raw, 1 calibrated) TICKS
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "adxl355_model.h"
#include "adxrs450_model.h"
#include "core.h"
#include "frame.h"

static uint64_t t_us;
static adxl355_model_t acc;
static sim_adxrs450_t gyr[3];
static sim_world_t world = {{0.0, 0.0, SIM_G0_MPS2}, {0.0, 0.0, 0.0}, 25.0};
static uint8_t rxq[512];
static size_t rxq_n, rxq_pos;
static unsigned long long link_bytes;

__attribute__((noinline)) int board_spi_transfer(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)ctx;
    static uint8_t zeros[64];
    if (!tx) {
        tx = zeros;
    }
    uint8_t tmp[64];
    if (!rx) {
        rx = tmp;
    }
    if (cs == IB_CS_ACCEL) {
        adxl355_model_advance(&acc, t_us, &world);
        adxl355_model_spi(&acc, tx, rx, len);
    } else {
        sim_adxrs450_advance(&gyr[cs - 1], t_us, &world);
        sim_adxrs450_spi(&gyr[cs - 1], tx, rx, len);
    }
    return 0;
}

static void delay_us(void *ctx, uint32_t us)
{
    (void)ctx;
    t_us += us;
}

static uint32_t time_us(void *ctx)
{
    (void)ctx;
    return (uint32_t)t_us;
}

static void set_tick_hz(void *ctx, uint32_t hz)
{
    (void)ctx;
    (void)hz;
}

static size_t tx_free(void *ctx)
{
    (void)ctx;
    return 8192;
}

__attribute__((noinline)) size_t board_link_write(void *ctx, const uint8_t *d, size_t n)
{
    (void)ctx;
    (void)d;
    link_bytes += n;
    return n;
}

__attribute__((noinline)) size_t board_link_read(void *ctx, uint8_t *buf, size_t cap)
{
    (void)ctx;
    size_t n = rxq_n - rxq_pos < cap ? rxq_n - rxq_pos : cap;
    memcpy(buf, rxq + rxq_pos, n);
    rxq_pos += n;
    return n;
}

static void reboot(void *ctx) { (void)ctx; }

int main(int argc, char **argv)
{
    if (argc != 4) {
        fprintf(stderr, "usage: core_cost RATE_HZ MODE TICKS\n");
        return 2;
    }
    unsigned rate = (unsigned)atoi(argv[1]);
    unsigned mode = (unsigned)atoi(argv[2]);
    unsigned long ticks = strtoul(argv[3], NULL, 10);
    adxl355_model_init(&acc, 1);
    for (int k = 0; k < 3; k++) {
        sim_adxrs450_init(&gyr[k], 100u + (unsigned)k, k);
    }
    static const ib_spi_bus_t bus = {board_spi_transfer, delay_us, NULL, NULL}; /* no start(): synchronous reads */
    ib_board_t b;
    memset(&b, 0, sizeof b);
    b.board_id = IB_BOARD_SIM;
    b.build = "core-cost";
    b.time_us = time_us;
    b.set_tick_hz = set_tick_hz;
    b.link_tx_free = tx_free;
    b.link_write = board_link_write;
    b.link_read = board_link_read;
    b.spi = &bus;
    b.flash = NULL;
    b.reboot = reboot;
    static ib_core_t core;
    ib_core_init(&core, &b);
    /* start_stream command */
    uint8_t raw[IB_MAX_FRAME];
    ib_msg_start_stream_t m = {(uint16_t)rate, (uint8_t)mode, 0, 2, {0, 0, 0}};
    size_t n = ib_msg_start_stream_pack(&m, raw + IB_HEADER_SIZE);
    rxq_n = ib_frame_encode(raw, IB_MSG_START_STREAM, 1, 0, n, rxq);
    ib_core_poll(&core);
    if (core.stream_state == IB_STREAM_STATE_STOPPED) {
        fprintf(stderr, "stream did not start\n");
        return 1;
    }
    uint32_t period = 1000000u / rate;
    unsigned long long before = link_bytes;
    for (unsigned long i = 0; i < ticks; i++) {
        t_us += period;
        ib_core_tick(&core, 0, t_us);
        ib_core_poll(&core);
    }
    printf("{\"ticks\": %lu, \"samples_produced\": %lu, \"samples_dropped\": %lu, \"link_bytes\": %llu, "
           "\"present\": %u}\n",
           ticks, (unsigned long)core.stats.samples_produced, (unsigned long)core.stats.samples_dropped,
           link_bytes - before, core.present);
    return core.present == 0x0F ? 0 : 1;
}
