/*
 * test_adxl355.c - the ADXL355 driver against the register-level model.
 *
 * A tiny in-test SPI bus routes chip select IB_CS_ACCEL to the model; delay_us()
 * advances device time (and so the model) by exactly the requested microseconds. SPI
 * transactions take no device time.
 */
#include <stdlib.h>
#include <string.h>

#include "adxl355.h"
#include "adxl355_model.h"
#include "ctest.h"

#define G0 SIM_G0_MPS2

typedef struct bench {
    adxl355_model_t model;
    sim_world_t world;
    uint64_t t_us;
    int bus_fail;  /* transfer() returns -1 */
    int miso_high; /* nothing on IB_CS_ACCEL and MISO floats high: every byte 0xFF */
    unsigned transfers;
    ib_spi_bus_t bus;
} bench_t;

static int bench_transfer(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    bench_t *b = (bench_t *)ctx;
    b->transfers++;
    if (b->bus_fail) {
        return -1;
    }
    if (cs == IB_CS_ACCEL && !b->miso_high) {
        adxl355_model_spi(&b->model, tx, rx, len);
    } else if (rx != NULL) {
        memset(rx, b->miso_high ? 0xFF : 0x00, len);
    }
    return 0;
}

static void bench_delay(void *ctx, uint32_t us)
{
    bench_t *b = (bench_t *)ctx;
    b->t_us += us;
    adxl355_model_advance(&b->model, b->t_us, &b->world);
}

/* A bench with a level board (f = 0, 0, +g0) at 25 degC; noise_free also removes the
 * white noise and the random walk from the default truth. */
static void bench_init(bench_t *b, uint64_t seed, int noise_free)
{
    memset(b, 0, sizeof *b);
    adxl355_model_init(&b->model, seed);
    if (noise_free) {
        for (int i = 0; i < 3; i++) {
            b->model.truth.noise_n[i] = 0.0;
            b->model.truth.rw_k[i] = 0.0;
        }
    }
    b->world.specific_force_mps2[2] = G0;
    b->world.temperature_c = 25.0;
    b->bus.transfer = bench_transfer;
    b->bus.delay_us = bench_delay;
    b->bus.ctx = b;
}

static void wait_us(bench_t *b, uint32_t us) { bench_delay(b, us); }

static void raw_read(bench_t *b, uint8_t addr, uint8_t *buf, size_t n)
{
    uint8_t tx[300] = {0}, rx[300];
    tx[0] = (uint8_t)((addr << 1) | 1u);
    adxl355_model_spi(&b->model, tx, rx, n + 1);
    memcpy(buf, rx + 1, n);
}

static uint8_t raw_read1(bench_t *b, uint8_t addr)
{
    uint8_t v;
    raw_read(b, addr, &v, 1);
    return v;
}

static void raw_write1(bench_t *b, uint8_t addr, uint8_t v)
{
    uint8_t tx[2] = {(uint8_t)(addr << 1), v};
    adxl355_model_spi(&b->model, tx, NULL, 2);
}

/* ------------------------------------------------------------------------------------ */

static void test_helpers(void)
{
    CHECK_EQ_INT(ib_adxl355_lsb_per_g(IB_ADXL355_RANGE_2G), 256000);
    CHECK_EQ_INT(ib_adxl355_lsb_per_g(IB_ADXL355_RANGE_4G), 128000);
    CHECK_EQ_INT(ib_adxl355_lsb_per_g(IB_ADXL355_RANGE_8G), 64000);
    CHECK_EQ_INT(ib_adxl355_lsb_per_g(0), 0);
    CHECK_EQ_INT(ib_adxl355_odr_period_us(0), 250);
    CHECK_EQ_INT(ib_adxl355_odr_period_us(10), 256000);
    CHECK_EQ_INT(ib_adxl355_odr_period_us(11), 0);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0x3E, 0x80, 0x00), 256000);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0xC1, 0x80, 0x00), -256000);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0x1F, 0x40, 0x00), 128000);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0x7F, 0xFF, 0xF3), 524287);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0x80, 0x00, 0x01), -524288);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(0xFF, 0xFF, 0xF0), -1);
}

/* sensors.md 1.9 computed vectors, through the model's registers and the driver. */
static void test_vectors_1_9(void)
{
    bench_t b;
    bench_init(&b, 1, 1);
    b.world.specific_force_mps2[0] = G0;
    b.world.specific_force_mps2[1] = -G0;
    b.world.specific_force_mps2[2] = 0.5 * G0;
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    wait_us(&b, 250);
    uint8_t r[11];
    raw_read(&b, 0x06, r, sizeof r);
    CHECK_EQ_INT(r[0], 0x07);
    CHECK_EQ_INT(r[1], 0x5D);
    CHECK_EQ_INT(r[2], 0x3E);
    CHECK_EQ_INT(r[3], 0x80);
    CHECK_EQ_INT(r[4], 0x00);
    CHECK_EQ_INT(r[5], 0xC1);
    CHECK_EQ_INT(r[6], 0x80);
    CHECK_EQ_INT(r[7], 0x00);
    CHECK_EQ_INT(r[8], 0x1F);
    CHECK_EQ_INT(r[9], 0x40);
    CHECK_EQ_INT(r[10], 0x00);

    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], 256000);
    CHECK_EQ_INT(s.accel_counts[1], -256000);
    CHECK_EQ_INT(s.accel_counts[2], 128000);
    CHECK_EQ_INT(s.temp_counts, 1885);
}

static void test_init_measuring(void)
{
    bench_t b;
    bench_init(&b, 2, 1);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    CHECK_EQ_INT(dev.devid_ad, 0xAD);
    CHECK_EQ_INT(dev.devid_mst, 0x1D);
    CHECK_EQ_INT(dev.partid, 0xED);
    CHECK_EQ_INT(dev.revid, 0x01);
    CHECK_EQ_INT(dev.measuring, 1);
    CHECK_EQ_INT(dev.range, IB_ADXL355_RANGE_2G);
    CHECK(memcmp(dev.shadow, b.model.shadow, 5) == 0);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x00); /* POWER_CTL: measuring */
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81); /* RANGE: +-2 g, I2C_HS kept */
    CHECK_EQ_INT(raw_read1(&b, 0x28), 0x00); /* FILTER: 4 kHz, HPF off */
    /* first sample one period after leaving standby */
    uint64_t before = b.model.samples;
    wait_us(&b, 249);
    CHECK_EQ_INT(b.model.samples, before);
    wait_us(&b, 1);
    CHECK_EQ_INT(b.model.samples, before + 1);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
    CHECK_EQ_INT(s.new_data, 1);
    CHECK_EQ_INT(s.accel_counts[0], 0);
    CHECK_EQ_INT(s.accel_counts[1], 0);
    CHECK_EQ_INT(s.accel_counts[2], 256000);

    /* config with another ODR: 500 Hz -> 5 samples in 10 ms */
    ib_adxl355_config_t cfg = {IB_ADXL355_RANGE_4G, 3, 0};
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    CHECK_EQ_INT(raw_read1(&b, 0x28), 0x03);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x82);
    before = b.model.samples;
    wait_us(&b, 10000);
    CHECK_EQ_INT(b.model.samples, before + 5);
}

static void test_ranges(void)
{
    bench_t b;
    bench_init(&b, 3, 1);
    b.world.specific_force_mps2[0] = G0;
    b.world.specific_force_mps2[1] = -G0;
    b.world.specific_force_mps2[2] = 0.5 * G0;
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    const uint8_t ranges[3] = {IB_ADXL355_RANGE_2G, IB_ADXL355_RANGE_4G, IB_ADXL355_RANGE_8G};
    for (int k = 0; k < 3; k++) {
        CHECK_EQ_INT(ib_adxl355_set_range(&dev, ranges[k]), IB_ADXL355_OK);
        CHECK_EQ_INT(dev.measuring, 1);
        CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x80 | ranges[k]);
        CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x00);
        ib_adxl355_sample_t s;
        CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
        int32_t lsb = ib_adxl355_lsb_per_g(ranges[k]);
        CHECK_EQ_INT(s.accel_counts[0], lsb);
        CHECK_EQ_INT(s.accel_counts[1], -lsb);
        CHECK_EQ_INT(s.accel_counts[2], lsb / 2);
    }
    /* saturation at the 20-bit limits */
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, IB_ADXL355_RANGE_2G), IB_ADXL355_OK);
    b.world.specific_force_mps2[0] = 3.0 * G0;
    b.world.specific_force_mps2[1] = -3.0 * G0;
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], 524287);
    CHECK_EQ_INT(s.accel_counts[1], -524288);

    /* bad arguments */
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, 0), IB_ADXL355_ERR_ARG);
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, 4), IB_ADXL355_ERR_ARG);
    CHECK_EQ_INT(ib_adxl355_set_filter(&dev, 11, 0), IB_ADXL355_ERR_ARG);
    CHECK_EQ_INT(ib_adxl355_set_filter(&dev, 0, 7), IB_ADXL355_ERR_ARG);
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, NULL), IB_ADXL355_ERR_ARG);
    CHECK_EQ_INT(ib_adxl355_init(NULL, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_ARG);
    ib_adxl355_config_t bad = {IB_ADXL355_RANGE_2G, 12, 0};
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &bad), IB_ADXL355_ERR_ARG);
}

static void test_filter_hpf(void)
{
    bench_t b;
    bench_init(&b, 4, 1);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_set_filter(&dev, 2, 1), IB_ADXL355_OK); /* 1 kHz, HPF 2.47 Hz */
    CHECK_EQ_INT(raw_read1(&b, 0x28), 0x12);
    CHECK_EQ_INT(dev.odr_code, 2);
    CHECK_EQ_INT(dev.hpf_code, 1);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 5000), IB_ADXL355_OK);
    int32_t first = s.accel_counts[2];
    CHECK(first > 250000); /* step response starts near the input */
    wait_us(&b, 2000000);  /* 2 s >> 1/(2 pi 2.47 Hz) */
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
    CHECK(abs(s.accel_counts[2]) < 10); /* DC removed */

    /* FILTER written while measuring (without standby) does not change the ODR in
     * effect (model choice: LPF/ODR latched when measurement starts) */
    raw_write1(&b, 0x28, 0x03);
    uint64_t before = b.model.samples;
    wait_us(&b, 10000);
    CHECK_EQ_INT(b.model.samples, before + 10);
}

static void test_wrong_ids_and_missing(void)
{
    /* 0xE9 is the ADXL359 (test_adxl359_sibling); 0xEA names no part of protocol/parts.toml */
    const uint8_t bad[3][3] = {{0xAC, 0x1D, 0xED}, {0xAD, 0x1E, 0xED}, {0xAD, 0x1D, 0xEA}};
    for (int k = 0; k < 3; k++) {
        bench_t b;
        bench_init(&b, 5, 1);
        adxl355_model_set_ids(&b.model, bad[k][0], bad[k][1], bad[k][2]);
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_ID);
        CHECK_EQ_INT(dev.devid_ad, bad[k][0]);
        CHECK_EQ_INT(dev.devid_mst, bad[k][1]);
        CHECK_EQ_INT(dev.partid, bad[k][2]);
        CHECK_EQ_INT(b.t_us, 0);          /* no waiting at all */
        CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01); /* left alone: still standby */
    }
    {
        bench_t b;
        bench_init(&b, 6, 1);
        adxl355_model_set_missing(&b.model, 1);
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_ID);
        CHECK_EQ_INT(dev.devid_ad, 0x00);
        CHECK_EQ_INT(dev.devid_mst, 0x00);
        CHECK_EQ_INT(dev.partid, 0x00);
        CHECK_EQ_INT(dev.revid, 0x00);
        CHECK(b.t_us < 1000);
        CHECK(b.transfers < 5);
    }
    {
        /* nothing on the bus and MISO floating high: bounded wait, then bad ID */
        bench_t b;
        bench_init(&b, 7, 1);
        b.miso_high = 1;
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_ID);
        CHECK_EQ_INT(dev.devid_ad, 0xFF);
        CHECK(b.t_us <= 110000);
        CHECK(b.transfers < 110);
    }
    {
        bench_t b;
        bench_init(&b, 8, 1);
        b.bus_fail = 1;
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_BUS);
        b.bus_fail = 0;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
        b.bus_fail = 1;
        ib_adxl355_sample_t s;
        CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_ERR_BUS);
        int32_t xyz[4][3];
        size_t n = 99;
        CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 4, &n), IB_ADXL355_ERR_BUS);
        CHECK_EQ_INT(n, 0);
        ib_adxl355_selftest_t st;
        CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_ERR_BUS);
        /* the part vanishes after init (MISO high): all-0xFF STATUS is not new data */
        b.bus_fail = 0;
        b.miso_high = 1;
        CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
        CHECK_EQ_INT(s.status, 0xFF);
        CHECK_EQ_INT(s.new_data, 0);
        CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 5000), IB_ADXL355_ERR_NO_DATA);
    }
}

static void test_nvm_timeout_and_shadow(void)
{
    {
        bench_t b;
        bench_init(&b, 9, 1);
        b.model.reset_busy_us = 5000000; /* NVM never finishes within the driver's patience */
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL),
                     IB_ADXL355_ERR_NVM_TIMEOUT);
        CHECK(b.t_us >= 100000 && b.t_us <= 110000);
    }
    {
        bench_t b;
        bench_init(&b, 10, 1);
        uint8_t orig = b.model.shadow[2];
        adxl355_model_set_shadow_corrupt(&b.model, 1);
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_ERR_SHADOW);
        CHECK_EQ_INT(dev.shadow[2], orig);                    /* the pre-reset copy */
        CHECK_EQ_INT(b.model.shadow[2], (uint8_t)(orig + 3));  /* 3 reset tries */
        CHECK(b.t_us < 20000);
    }
    {
        /* the driver waits out a longer but finite NVM reload */
        bench_t b;
        bench_init(&b, 11, 1);
        b.model.reset_busy_us = 7500;
        ib_adxl355_t dev;
        CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
        CHECK(b.t_us >= 7500 && b.t_us <= 9000);
    }
}

static void test_soft_reset_model(void)
{
    bench_t b;
    bench_init(&b, 12, 1);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    int16_t off[3] = {5, 6, 7};
    CHECK_EQ_INT(ib_adxl355_set_offset(&dev, off), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_set_filter(&dev, 4, 2), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, IB_ADXL355_RANGE_8G), IB_ADXL355_OK);
    raw_write1(&b, 0x29, 0x10);
    raw_write1(&b, 0x27, 0x05);
    wait_us(&b, 20000);
    CHECK(raw_read1(&b, 0x05) > 0);
    uint8_t shadow_before[5];
    raw_read(&b, 0x50, shadow_before, 5);

    raw_write1(&b, 0x2F, 0x51); /* not the reset code: ignored */
    CHECK_EQ_INT(raw_read1(&b, 0x00), 0xAD);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x83);

    raw_write1(&b, 0x2F, 0x52);
    uint8_t r[4];
    raw_read(&b, 0x00, r, 4);
    CHECK_EQ_INT(r[0], 0xFF);
    CHECK_EQ_INT(r[3], 0xFF);
    uint8_t st = raw_read1(&b, 0x04);
    CHECK_EQ_INT(st & IB_ADXL355_STATUS_NVM_BUSY, IB_ADXL355_STATUS_NVM_BUSY);
    raw_write1(&b, 0x28, 0x05); /* ignored while busy */
    wait_us(&b, ADXL355_MODEL_RESET_BUSY_US - 1);
    CHECK_EQ_INT(raw_read1(&b, 0x04), 0xFF);
    wait_us(&b, 1);
    CHECK_EQ_INT(raw_read1(&b, 0x04), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x00), 0xAD);
    CHECK_EQ_INT(raw_read1(&b, 0x28), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x29), 0x60);
    CHECK_EQ_INT(raw_read1(&b, 0x27), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x1E), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x23), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 0x00);
    uint8_t shadow_after[5];
    raw_read(&b, 0x50, shadow_after, 5);
    CHECK(memcmp(shadow_before, shadow_after, 5) == 0);
    CHECK(shadow_after[0] != 0x00 || shadow_after[1] != 0x00);
    uint64_t before = b.model.samples;
    wait_us(&b, 10000); /* standby after reset: nothing */
    CHECK_EQ_INT(b.model.samples, before);

    /* the driver's reset from a running configuration */
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, IB_ADXL355_RANGE_4G), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_soft_reset(&dev), IB_ADXL355_OK);
    CHECK_EQ_INT(dev.measuring, 0);
    CHECK_EQ_INT(dev.range, IB_ADXL355_RANGE_2G);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
}

static void test_model_registers(void)
{
    bench_t b;
    bench_init(&b, 13, 1);
    /* power-on values */
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x29), 0x60);
    CHECK_EQ_INT(raw_read1(&b, 0x27), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x03), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x04), 0x00);
    /* read-only registers ignore writes */
    raw_write1(&b, 0x00, 0x12);
    raw_write1(&b, 0x08, 0x12);
    raw_write1(&b, 0x50, 0x12);
    CHECK_EQ_INT(raw_read1(&b, 0x00), 0xAD);
    CHECK_EQ_INT(raw_read1(&b, 0x08), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x50), b.model.shadow[0]);
    /* burst write auto-increments */
    uint8_t tx[3] = {0x1E << 1, 0x12, 0x34};
    adxl355_model_spi(&b.model, tx, NULL, 3);
    CHECK_EQ_INT(raw_read1(&b, 0x1E), 0x12);
    CHECK_EQ_INT(raw_read1(&b, 0x1F), 0x34);
    /* the command bytes of sensors.md 1.1 */
    uint8_t t2[2] = {0x01, 0}, r2[2];
    adxl355_model_spi(&b.model, t2, r2, 2);
    CHECK_EQ_INT(r2[1], 0xAD);

    /* STATUS read clears DATA_RDY; FIFO_FULL follows the watermark */
    raw_write1(&b, 0x1E, 0);
    raw_write1(&b, 0x1F, 0);
    raw_write1(&b, 0x29, 6);
    raw_write1(&b, 0x2D, 0x00);
    wait_us(&b, 250);
    uint8_t st = raw_read1(&b, 0x04);
    CHECK_EQ_INT(st, IB_ADXL355_STATUS_DATA_RDY);
    CHECK_EQ_INT(raw_read1(&b, 0x04), 0x00);
    wait_us(&b, 250);
    CHECK_EQ_INT(raw_read1(&b, 0x04), IB_ADXL355_STATUS_DATA_RDY | IB_ADXL355_STATUS_FIFO_FULL);
    CHECK_EQ_INT(raw_read1(&b, 0x04), IB_ADXL355_STATUS_FIFO_FULL);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 6);

    /* activity on Z: |256000| >> 3 = 32000 > 30000, three samples in a row */
    raw_write1(&b, 0x2D, 0x01);
    raw_write1(&b, 0x24, 0x04);
    raw_write1(&b, 0x25, 30000 >> 8);
    raw_write1(&b, 0x26, 30000 & 0xFF);
    raw_write1(&b, 0x27, 3);
    raw_write1(&b, 0x2D, 0x00);
    wait_us(&b, 500);
    CHECK_EQ_INT(raw_read1(&b, 0x04) & IB_ADXL355_STATUS_ACTIVITY, 0);
    wait_us(&b, 250);
    CHECK_EQ_INT(raw_read1(&b, 0x04) & IB_ADXL355_STATUS_ACTIVITY, IB_ADXL355_STATUS_ACTIVITY);
    CHECK_EQ_INT(raw_read1(&b, 0x04) & IB_ADXL355_STATUS_ACTIVITY, 0); /* cleared by read */
    wait_us(&b, 250);
    CHECK_EQ_INT(raw_read1(&b, 0x04) & IB_ADXL355_STATUS_ACTIVITY, IB_ADXL355_STATUS_ACTIVITY);

    /* TEMP_OFF freezes the temperature registers */
    b.world.temperature_c = 50.0;
    raw_write1(&b, 0x2D, 0x02);
    wait_us(&b, 250);
    CHECK_EQ_INT(raw_read1(&b, 0x07), 0x5D);
    raw_write1(&b, 0x2D, 0x00);
    wait_us(&b, 250);
    CHECK_EQ_INT((raw_read1(&b, 0x06) << 8) | raw_read1(&b, 0x07), 1885 - 226); /* -226.25 */
}

static void test_data_ready_flag(void)
{
    bench_t b;
    bench_init(&b, 14, 0);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    ib_adxl355_sample_t s1, s2, s3;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s1), IB_ADXL355_OK);
    CHECK_EQ_INT(s1.new_data, 0); /* nothing produced yet */
    wait_us(&b, 250);
    unsigned tr = b.transfers;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s1), IB_ADXL355_OK);
    CHECK_EQ_INT(b.transfers - tr, 1); /* one burst */
    CHECK_EQ_INT(s1.new_data, 1);
    CHECK_EQ_INT(s1.status & IB_ADXL355_STATUS_DATA_RDY, IB_ADXL355_STATUS_DATA_RDY);
    CHECK_EQ_INT(s1.fifo_entries, 3);
    CHECK_EQ_INT(s1.temp_counts, 1885);
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s2), IB_ADXL355_OK);
    CHECK_EQ_INT(s2.new_data, 0);
    CHECK(memcmp(s1.accel_counts, s2.accel_counts, sizeof s1.accel_counts) == 0);
    wait_us(&b, 250);
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s3), IB_ADXL355_OK);
    CHECK_EQ_INT(s3.new_data, 1);
    CHECK(memcmp(s1.accel_counts, s3.accel_counts, sizeof s1.accel_counts) != 0); /* noise */

    /* stuck data: no DATA_RDY ever, bounded wait */
    adxl355_model_set_stuck_data(&b.model, 1);
    uint64_t t0 = b.t_us;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s1, 10000), IB_ADXL355_ERR_NO_DATA);
    CHECK(b.t_us - t0 <= 10100);
    CHECK_EQ_INT(s1.new_data, 0);
    CHECK(memcmp(s1.accel_counts, s3.accel_counts, sizeof s1.accel_counts) == 0);
    ib_adxl355_selftest_t st;
    t0 = b.t_us;
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_ERR_NO_DATA);
    CHECK(b.t_us - t0 < 20000);
    CHECK_EQ_INT(dev.measuring, 1);
    CHECK_EQ_INT(raw_read1(&b, 0x2E), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81);
}

static int set_ok(const int32_t v[3], int32_t x, int32_t y, int32_t z)
{
    return v[0] == x && v[1] == y && v[2] == z;
}

static void test_fifo(void)
{
    bench_t b;
    bench_init(&b, 15, 1);
    b.world.specific_force_mps2[0] = 0.25 * G0;
    b.world.specific_force_mps2[1] = -0.5 * G0;
    b.world.specific_force_mps2[2] = G0;
    const int32_t X = 64000, Y = -128000, Z = 256000;
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    int32_t xyz[40][3];
    size_t n = 0;

    /* overflow: 40 samples into a 32-set FIFO */
    wait_us(&b, 40 * 250);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 96);
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 40, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 32);
    CHECK(dev.last_status & IB_ADXL355_STATUS_FIFO_OVR);
    CHECK(dev.last_status & IB_ADXL355_STATUS_FIFO_FULL);
    int all = 1;
    for (size_t i = 0; i < n; i++) {
        all &= set_ok(xyz[i], X, Y, Z);
    }
    CHECK(all);
    CHECK_EQ_INT(dev.fifo_discarded, 0);
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 40, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(dev.last_status & IB_ADXL355_STATUS_FIFO_OVR, 0); /* cleared by the read */

    /* smaller caller buffer: the rest stays for the next call */
    wait_us(&b, 10 * 250);
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 4, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 4);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 18);
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 40, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 6);
    CHECK(set_ok(xyz[5], X, Y, Z));

    /* started mid-set: somebody popped one entry (the X) */
    wait_us(&b, 5 * 250);
    uint8_t e[3];
    raw_read(&b, 0x11, e, 3);
    CHECK_EQ_INT(e[2] & 0x03, 0x01); /* that was an X entry */
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(e[0], e[1], e[2]), X);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 14);
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 40, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 4);
    CHECK_EQ_INT(dev.fifo_discarded, 2);
    all = 1;
    for (size_t i = 0; i < n; i++) {
        all &= set_ok(xyz[i], X, Y, Z);
    }
    CHECK(all);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 0);

    /* misaligned by an overflow: full FIFO, one entry popped, one more sample (X fits,
     * Y and Z are dropped) -> Y Z [31 sets] X */
    wait_us(&b, 40 * 250);
    raw_read(&b, 0x11, e, 3);
    wait_us(&b, 250);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 96);
    dev.fifo_discarded = 0;
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 40, &n), IB_ADXL355_OK);
    CHECK_EQ_INT(n, 31);
    CHECK_EQ_INT(dev.fifo_discarded, 3);
    all = 1;
    for (size_t i = 0; i < n; i++) {
        all &= set_ok(xyz[i], X, Y, Z);
    }
    CHECK(all);

    /* the empty indicator */
    raw_read(&b, 0x11, e, 3);
    CHECK_EQ_INT(e[2] & 0x03, 0x02);
    /* address does not advance at FIFO_DATA: a 6-byte read pops 2 entries */
    wait_us(&b, 250);
    uint8_t e6[6];
    raw_read(&b, 0x11, e6, 6);
    CHECK_EQ_INT(e6[2] & 0x03, 0x01);
    CHECK_EQ_INT(e6[5] & 0x03, 0x00);
    CHECK_EQ_INT(ib_adxl355_counts_from_bytes(e6[3], e6[4], e6[5]), Y);
    CHECK_EQ_INT(raw_read1(&b, 0x05), 1);

    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, NULL, 3, &n), IB_ADXL355_ERR_ARG);
}

static void test_offset(void)
{
    bench_t b;
    bench_init(&b, 16, 1);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    const int16_t off[3] = {100, -200, -32768};
    CHECK_EQ_INT(ib_adxl355_set_offset(&dev, off), IB_ADXL355_OK);
    CHECK_EQ_INT(dev.measuring, 1);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x00);
    uint8_t r[6];
    raw_read(&b, 0x1E, r, 6);
    CHECK_EQ_INT(r[0], 0x00);
    CHECK_EQ_INT(r[1], 0x64);
    CHECK_EQ_INT(r[2], 0xFF);
    CHECK_EQ_INT(r[3], 0x38);
    CHECK_EQ_INT(r[4], 0x80);
    CHECK_EQ_INT(r[5], 0x00);
    int16_t back[3];
    CHECK_EQ_INT(ib_adxl355_get_offset(&dev, back), IB_ADXL355_OK);
    CHECK_EQ_INT(back[0], 100);
    CHECK_EQ_INT(back[1], -200);
    CHECK_EQ_INT(back[2], -32768);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], 1600);
    CHECK_EQ_INT(s.accel_counts[1], -3200);
    CHECK_EQ_INT(s.accel_counts[2], 256000 - 524288);
    /* FIFO carries the same (offset) values */
    int32_t xyz[2][3];
    size_t n;
    CHECK_EQ_INT(ib_adxl355_read_fifo(&dev, xyz, 2, &n), IB_ADXL355_OK);
    CHECK(n >= 1);
    CHECK_EQ_INT(xyz[0][0], 1600);
    /* offset pushes past full scale -> saturation */
    const int16_t big[3] = {32767, 0, 0};
    b.world.specific_force_mps2[0] = 1.5 * G0;
    CHECK_EQ_INT(ib_adxl355_set_offset(&dev, big), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], 524287);
}

static void test_standby(void)
{
    bench_t b;
    bench_init(&b, 17, 0);
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    wait_us(&b, 1000);
    CHECK_EQ_INT(ib_adxl355_standby(&dev), IB_ADXL355_OK);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK); /* clears DATA_RDY */
    uint64_t before = b.model.samples;
    wait_us(&b, 100000);
    CHECK_EQ_INT(b.model.samples, before);
    ib_adxl355_sample_t s2;
    CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s2), IB_ADXL355_OK);
    CHECK_EQ_INT(s2.new_data, 0);
    CHECK_EQ_INT(s2.fifo_entries, s.fifo_entries);
    CHECK(memcmp(s.accel_counts, s2.accel_counts, sizeof s.accel_counts) == 0);
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s2, 5000), IB_ADXL355_ERR_NO_DATA);
    /* configuration changes in standby stay in standby */
    CHECK_EQ_INT(ib_adxl355_set_range(&dev, IB_ADXL355_RANGE_8G), IB_ADXL355_OK);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
    CHECK_EQ_INT(ib_adxl355_measure(&dev), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s2, 2000), IB_ADXL355_OK);
    CHECK(abs(s2.accel_counts[2] - 64000) < 500);
}

/* The ADXL359 (protocol/parts.toml): identified by PARTID 0xE9 through the parts table, its
 * +-10/20/40 g ranges at 51200/25600/12800 LSB/g on RANGE codes 1..3, self-test at code 3
 * (+-40 g) against the part's limits, 1 g reads 51200 counts at +-10 g. */
static void test_adxl359_sibling(void)
{
    bench_t b;
    bench_init(&b, 19, 0);
    adxl355_model_set_part(&b.model, ib_part_by_id(IB_PART_ADXL359));
    ib_adxl355_t dev;
    ib_adxl355_config_t cfg = {1u, 1, 0};
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    CHECK(dev.part != NULL && dev.part->part == IB_PART_ADXL359);
    CHECK_EQ_INT(dev.partid, 0xE9);
    CHECK_EQ_INT(ib_adxl355_part_lsb_per_g(dev.part, 1), 51200);
    CHECK_EQ_INT(ib_adxl355_part_lsb_per_g(dev.part, 2), 25600);
    CHECK_EQ_INT(ib_adxl355_part_lsb_per_g(dev.part, 3), 12800);
    CHECK_EQ_INT(ib_part_range(dev.part, 10)->code, 1);
    CHECK(ib_part_range(dev.part, 2) == NULL); /* an ADXL355 range is none of the ADXL359's */
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK(abs(s.accel_counts[2] - 51200) < 400);
    ib_adxl355_selftest_t st;
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_OK);
    CHECK_EQ_INT(st.lsb_per_g, 12800);
    CHECK_NEAR(st.delta_counts[2], 1.5 * 12800, 100);
    /* the ADXL355 stays the ADXL355 */
    bench_t b2;
    bench_init(&b2, 20, 0);
    ib_adxl355_t dev2;
    CHECK_EQ_INT(ib_adxl355_init(&dev2, &b2.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    CHECK(dev2.part != NULL && dev2.part->part == IB_PART_ADXL355);
}

static void test_self_test(void)
{
    bench_t b;
    bench_init(&b, 18, 0);
    ib_adxl355_t dev;
    ib_adxl355_config_t cfg = {IB_ADXL355_RANGE_2G, 1, 0};
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    ib_adxl355_selftest_t st;
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_OK);
    CHECK_EQ_INT(st.lsb_per_g, 64000);
    CHECK_NEAR(st.delta_counts[0], 0.3 * 64000, 200);
    CHECK_NEAR(st.delta_counts[1], 0.3 * 64000, 200);
    CHECK_NEAR(st.delta_counts[2], 1.5 * 64000, 200);
    CHECK(st.axis_pass[0] && st.axis_pass[1] && st.axis_pass[2]);
    /* configuration and state restored */
    CHECK_EQ_INT(dev.measuring, 1);
    CHECK_EQ_INT(dev.range, IB_ADXL355_RANGE_2G);
    CHECK_EQ_INT(dev.odr_code, 1);
    CHECK_EQ_INT(raw_read1(&b, 0x2C), 0x81);
    CHECK_EQ_INT(raw_read1(&b, 0x28), 0x01);
    CHECK_EQ_INT(raw_read1(&b, 0x2E), 0x00);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x00);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK(abs(s.accel_counts[2] - 256000) < 2000);

    /* no self-test force: fails, every axis */
    b.model.st_force_g[0] = b.model.st_force_g[1] = b.model.st_force_g[2] = 0.0;
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_ERR_SELFTEST);
    CHECK(!st.axis_pass[0] && !st.axis_pass[1] && !st.axis_pass[2]);
    CHECK(abs(st.delta_counts[2]) < 200);
    /* a weak Z only */
    b.model.st_force_g[0] = b.model.st_force_g[1] = -0.3; /* sign does not matter */
    b.model.st_force_g[2] = 0.2;
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_ERR_SELFTEST);
    CHECK(st.axis_pass[0] && st.axis_pass[1] && !st.axis_pass[2]);
    /* from standby: stays in standby */
    b.model.st_force_g[0] = b.model.st_force_g[1] = 0.3;
    b.model.st_force_g[2] = 1.5;
    CHECK_EQ_INT(ib_adxl355_standby(&dev), IB_ADXL355_OK);
    CHECK_EQ_INT(ib_adxl355_self_test(&dev, &st), IB_ADXL355_OK);
    CHECK_EQ_INT(dev.measuring, 0);
    CHECK_EQ_INT(raw_read1(&b, 0x2D), 0x01);
}

static void test_noise(void)
{
    bench_t b;
    bench_init(&b, 19, 0);
    for (int i = 0; i < 3; i++) {
        b.model.truth.rw_k[i] = 0.0;
    }
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    const int n = 20000;
    double sum[3] = {0}, sum2[3] = {0};
    int fresh = 1;
    for (int k = 0; k < n; k++) {
        ib_adxl355_sample_t s;
        wait_us(&b, 250);
        CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
        fresh &= s.new_data;
        for (int i = 0; i < 3; i++) {
            sum[i] += s.accel_counts[i];
            sum2[i] += (double)s.accel_counts[i] * s.accel_counts[i];
        }
    }
    CHECK(fresh);
    const double expect = ADXL355_MODEL_NOISE_MPS2_RTHZ * sqrt(4000.0) / G0 * 256000.0;
    for (int i = 0; i < 3; i++) {
        double mean = sum[i] / n;
        double sd = sqrt((sum2[i] - n * mean * mean) / (n - 1));
        CHECK_NEAR(sd / expect, 1.0, 0.05);
        CHECK_NEAR(mean, i == 2 ? 256000.0 : 0.0, 5.0 * expect / sqrt((double)n));
    }
}

static void test_random_walk(void)
{
    const double k_rw = 0.01; /* m/s^2 * sqrt(Hz): large, to see it in 10 s */
    bench_t b;
    bench_init(&b, 20, 1);
    for (int i = 0; i < 3; i++) {
        b.model.truth.rw_k[i] = k_rw;
    }
    ib_adxl355_t dev;
    ib_adxl355_config_t cfg = {IB_ADXL355_RANGE_2G, 2, 0}; /* 1 kHz */
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    const int n = 10000;
    double prev[3] = {0}, sd_sum[3] = {0}, sd_sum2[3] = {0};
    int match = 1;
    for (int k = 0; k < n; k++) {
        ib_adxl355_sample_t s;
        wait_us(&b, 1000);
        CHECK_EQ_INT(ib_adxl355_read_sample(&dev, &s), IB_ADXL355_OK);
        double bias[3];
        adxl355_model_true_bias(&b.model, bias);
        for (int i = 0; i < 3; i++) {
            double expect = (b.world.specific_force_mps2[i] + bias[i]) / G0 * 256000.0;
            if (fabs(s.accel_counts[i] - expect) > 0.51) {
                match = 0;
            }
            if (k > 0) {
                double d = s.accel_counts[i] - prev[i];
                sd_sum[i] += d;
                sd_sum2[i] += d * d;
            }
            prev[i] = s.accel_counts[i];
        }
    }
    CHECK(match);
    const double step = k_rw * sqrt(1e-3) / G0 * 256000.0; /* per-sample increment sigma */
    for (int i = 0; i < 3; i++) {
        double m = sd_sum[i] / (n - 1);
        double sd = sqrt(sd_sum2[i] / (n - 1) - m * m);
        CHECK_NEAR(sd / step, 1.0, 0.05);
    }
    double bias[3];
    adxl355_model_true_bias(&b.model, bias);
    CHECK(fabs(bias[0]) + fabs(bias[1]) + fabs(bias[2]) > 1e-3);

    /* K = 0: the bias does not move */
    bench_init(&b, 21, 1);
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, &cfg), IB_ADXL355_OK);
    wait_us(&b, 1000000);
    adxl355_model_true_bias(&b.model, bias);
    CHECK_EQ_INT(bias[0] == 0.0 && bias[1] == 0.0 && bias[2] == 0.0, 1);
}

static void test_temperature(void)
{
    bench_t b;
    bench_init(&b, 22, 1);
    b.model.truth.bias_tc[0] = 1e-3;
    b.model.truth.bias_tc[1] = -2e-3;
    b.model.truth.scale_tc[2] = 1e-3;
    b.model.truth.bias_mps2[0] = 0.05;
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], lround(0.05 / G0 * 256000.0));
    CHECK_EQ_INT(s.accel_counts[1], 0);
    CHECK_EQ_INT(s.accel_counts[2], 256000);
    CHECK_EQ_INT(s.temp_counts, 1885);

    b.world.temperature_c = 45.0;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.accel_counts[0], lround((0.05 + 0.02) / G0 * 256000.0));
    CHECK_EQ_INT(s.accel_counts[1], lround(-0.04 / G0 * 256000.0));
    CHECK_EQ_INT(s.accel_counts[2], 261120); /* (1 + 20e-3) * 256000 */
    CHECK_EQ_INT(s.temp_counts, 1704);       /* 1885 - 9.05 * 20 = 1704 */
    double bias[3];
    adxl355_model_true_bias(&b.model, bias);
    CHECK_NEAR(bias[0], 0.07, 1e-12);
    CHECK_NEAR(bias[1], -0.04, 1e-12);
    CHECK_NEAR(bias[2], 0.0, 1e-12);

    b.world.temperature_c = -40.0;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    CHECK_EQ_INT(s.temp_counts, 2473); /* 1885 + 9.05 * 65 = 2473.25 */
}

/* Curved bias and the play-operator hysteresis (adxl355_model.h): the branch follows the
 * direction the die last moved by more than the dead band. */
static void test_curve_and_hysteresis(void)
{
    bench_t b;
    bench_init(&b, 24, 1);
    b.model.truth.bias_tc2[0] = 1e-4;
    b.model.truth.bias_tc3[0] = 2e-6;
    b.model.truth.hysteresis[0] = 2e-3;
    b.model.truth.hysteresis_width_c[0] = 2.0;
    b.model.truth.hysteresis[1] = -1e-3;  /* width 0: the sign of the last change */
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    ib_adxl355_sample_t s;
    /* temperature, branch of X, branch of Y after it */
    static const double temps[] = {25.0, 35.0, 34.5, 30.0, 30.5, 40.0};
    static const double hx[] = {0.0, 1.0, 0.5, -1.0, -0.5, 1.0};
    static const double hy[] = {0.0, 1.0, -1.0, -1.0, 1.0, 1.0};
    for (int k = 0; k < 6; k++) {
        b.world.temperature_c = temps[k];
        CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
        double d = temps[k] - 25.0;
        double want_x = 1e-4 * d * d + 2e-6 * d * d * d + 2e-3 * hx[k];
        double want_y = -1e-3 * hy[k];
        CHECK_NEAR(b.model.hyst_h[0], hx[k], 1e-12);
        CHECK_NEAR(b.model.hyst_h[1], hy[k], 1e-12);
        CHECK_NEAR(adxl355_truth_thermal_bias(&b.model.truth, 0, temps[k], hx[k]), want_x, 1e-15);
        double bias[3];
        adxl355_model_true_bias(&b.model, bias);
        CHECK_NEAR(bias[0], want_x, 1e-12);
        CHECK_NEAR(bias[1], want_y, 1e-12);
        CHECK_EQ_INT(s.accel_counts[0], lround(want_x / G0 * 256000.0));
        CHECK_EQ_INT(s.accel_counts[1], lround(want_y / G0 * 256000.0));
    }
}

static void test_truths(void)
{
    adxl355_truth_t t;
    adxl355_model_default_truth(&t);
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            CHECK_EQ_INT(t.m[i][j] == (i == j ? 1.0 : 0.0), 1);
        }
        CHECK_EQ_INT(t.bias_mps2[i] == 0.0, 1);
        CHECK_NEAR(t.noise_n[i], 22.5e-6 * G0, 1e-12);
    }
    sim_rng_t rng;
    sim_rng_seed(&rng, 99);
    int ok = 1;
    for (int k = 0; k < 200; k++) {
        adxl355_model_random_truth(&t, &rng);
        for (int i = 0; i < 3; i++) {
            ok &= fabs(t.bias_mps2[i]) <= 25e-3 * G0;
            ok &= fabs(t.m[i][i] - 1.0) <= 0.01;
            ok &= fabs(t.m[i][(i + 1) % 3]) <= 0.01 && fabs(t.m[i][(i + 2) % 3]) <= 0.01;
            ok &= t.noise_n[i] > 0.0 && fabs(t.noise_n[i] / (22.5e-6 * G0) - 1.0) <= 0.1;
            ok &= t.rw_k[i] > 0.0 && t.rw_k[i] <= 2e-6 * G0;
            ok &= fabs(t.bias_tc[i]) <= 0.1e-3 * G0;
            ok &= fabs(t.scale_tc[i]) <= 1e-4;
            ok &= fabs(t.bias_tc2[i]) <= 2e-7 * G0 && fabs(t.bias_tc3[i]) <= 2e-9 * G0;
            ok &= fabs(t.hysteresis[i]) <= 20e-6 * G0;
            ok &= t.hysteresis_width_c[i] >= 1.0 && t.hysteresis_width_c[i] <= 4.0;
            /* the data-sheet bound the ranges come from: slope <= 0.15 mg/degC on -40..85 */
            for (double d = -65.0; d <= 60.0; d += 5.0) {
                ok &= fabs(t.bias_tc[i] + 2.0 * t.bias_tc2[i] * d + 3.0 * t.bias_tc3[i] * d * d) <=
                      0.15e-3 * G0;
            }
        }
    }
    CHECK(ok);
    /* random truth through the whole chain: the reading matches M f + b */
    bench_t b;
    bench_init(&b, 23, 1);
    adxl355_model_random_truth(&t, &rng);
    for (int i = 0; i < 3; i++) {
        t.noise_n[i] = 0.0;
        t.rw_k[i] = 0.0;
    }
    adxl355_model_set_truth(&b.model, &t);
    adxl355_truth_t back;
    adxl355_model_get_truth(&b.model, &back);
    CHECK(memcmp(&back, &t, sizeof t) == 0);
    b.world.specific_force_mps2[0] = 0.3 * G0;
    b.world.specific_force_mps2[1] = -0.2 * G0;
    b.world.specific_force_mps2[2] = 0.9 * G0;
    ib_adxl355_t dev;
    CHECK_EQ_INT(ib_adxl355_init(&dev, &b.bus, IB_CS_ACCEL, NULL), IB_ADXL355_OK);
    ib_adxl355_sample_t s;
    CHECK_EQ_INT(ib_adxl355_wait_sample(&dev, &s, 2000), IB_ADXL355_OK);
    for (int i = 0; i < 3; i++) {
        double u = t.bias_mps2[i];
        for (int j = 0; j < 3; j++) {
            u += t.m[i][j] * b.world.specific_force_mps2[j];
        }
        CHECK_NEAR(s.accel_counts[i], u / G0 * 256000.0, 0.51);
    }
}

int main(void)
{
    RUN(test_helpers);
    RUN(test_vectors_1_9);
    RUN(test_init_measuring);
    RUN(test_ranges);
    RUN(test_filter_hpf);
    RUN(test_wrong_ids_and_missing);
    RUN(test_nvm_timeout_and_shadow);
    RUN(test_soft_reset_model);
    RUN(test_model_registers);
    RUN(test_data_ready_flag);
    RUN(test_fifo);
    RUN(test_offset);
    RUN(test_standby);
    RUN(test_self_test);
    RUN(test_adxl359_sibling);
    RUN(test_noise);
    RUN(test_random_walk);
    RUN(test_temperature);
    RUN(test_curve_and_hysteresis);
    RUN(test_truths);
    return ctest_summary();
}
