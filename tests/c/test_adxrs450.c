/*
 * test_adxrs450.c - the ADXRS450 driver (firmware/drivers/adxrs450.c) against the
 * simulator's chip model (firmware/boards/sim/models/adxrs450_model.c).
 *
 * An in-test SPI bus routes IB_CS_GYRO_X/Y/Z to three models (axes 0/1/2); any other
 * chip select has nothing attached (MISO 0x00). delay_us() advances the models' time
 * with the current test world; each transfer can also take `frame_us` of bus time.
 * Expected protocol facts come from /work/shared/reference/sensors.md section 2.
 */
#include <math.h>
#include <string.h>

#include "adxrs450.h"
#include "adxrs450_model.h"
#include "ctest.h"

#define DEG2RAD (3.14159265358979323846 / 180.0)

/* ---- the test bus ---- */

typedef struct frame_rec {
    uint64_t t_us;
    uint8_t cs;
    uint32_t tx;
    uint32_t rx;
} frame_rec_t;

#define LOG_MAX 64

typedef struct test_bus {
    sim_adxrs450_t gyro[3];
    sim_world_t world;
    uint64_t t_us;
    uint32_t frame_us;     /* bus time taken by each transfer */
    int fail_transfers;    /* >0: that many transfers fail with -1 */
    uint32_t nframes;      /* all frames since the last log_reset() */
    frame_rec_t log[LOG_MAX];
    ib_spi_bus_t bus;
} test_bus_t;

static test_bus_t B;

static uint32_t be32(const uint8_t *b)
{
    return ((uint32_t)b[0] << 24) | ((uint32_t)b[1] << 16) | ((uint32_t)b[2] << 8) | b[3];
}

static void advance_all(uint64_t t_us)
{
    B.t_us = t_us;
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_advance(&B.gyro[i], t_us, &B.world);
    }
}

static int bus_transfer(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)ctx;
    if (B.fail_transfers > 0) {
        B.fail_transfers--;
        return -1;
    }
    if (B.frame_us) {
        advance_all(B.t_us + B.frame_us);
    }
    uint8_t txb[8] = {0}, rxb[8] = {0};
    if (tx != NULL && len <= sizeof txb) {
        memcpy(txb, tx, len);
    }
    int ret = 0;
    if (cs >= IB_CS_GYRO_X && cs <= IB_CS_GYRO_Z) {
        ret = sim_adxrs450_spi(&B.gyro[cs - IB_CS_GYRO_X], txb, rxb, len);
    }
    if (rx != NULL && len <= sizeof rxb) {
        memcpy(rx, rxb, len);
    }
    if (B.nframes < LOG_MAX && len == 4) {
        frame_rec_t *f = &B.log[B.nframes];
        f->t_us = B.t_us;
        f->cs = cs;
        f->tx = be32(txb);
        f->rx = be32(rxb);
    }
    B.nframes++;
    return ret;
}

static void bus_delay(void *ctx, uint32_t us)
{
    (void)ctx;
    advance_all(B.t_us + us);
}

static void log_reset(void) { B.nframes = 0; }

/* Fresh bus: three powered-on chips at t = 0, board at rest, 25 degC. */
static void setup(uint64_t seed)
{
    memset(&B, 0, sizeof B);
    B.world.temperature_c = 25.0;
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_init(&B.gyro[i], seed * 16u + (uint64_t)i, i);
    }
    B.bus.transfer = bus_transfer;
    B.bus.delay_us = bus_delay;
    B.bus.ctx = &B;
}

/* Noise-free, drift-free truth for all three chips (identity rows). */
static void make_ideal(void)
{
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_truth_t t = sim_adxrs450_default_truth(i);
        t.noise_n = 0.0;
        t.bias_rw_k = 0.0;
        t.bias_instability_rad_s = 0.0;
        sim_adxrs450_set_truth(&B.gyro[i], &t);
    }
}

/* One raw 32-bit frame on the test bus. */
static uint32_t raw_frame(uint8_t cs, uint32_t cmd)
{
    uint8_t tx[4] = {(uint8_t)(cmd >> 24), (uint8_t)(cmd >> 16), (uint8_t)(cmd >> 8),
                     (uint8_t)cmd};
    uint8_t rx[4] = {0};
    (void)bus_transfer(&B, cs, tx, rx, 4);
    return be32(rx);
}

static void set_rate_dps(double x, double y, double z)
{
    B.world.rate_rad_s[0] = x * DEG2RAD;
    B.world.rate_rad_s[1] = y * DEG2RAD;
    B.world.rate_rad_s[2] = z * DEG2RAD;
}

/* Let the new world fill a whole sample interval, then read. */
static ib_adxrs450_err_t settled_read(ib_adxrs450_t *d, ib_adxrs450_sample_t *s)
{
    bus_delay(&B, 1000);
    (void)ib_adxrs450_read_rate(d, s);
    bus_delay(&B, 1000);
    return ib_adxrs450_read_rate(d, s);
}

static ib_adxrs450_err_t init_chip(ib_adxrs450_t *d, int axis)
{
    return ib_adxrs450_init(d, &B.bus, (uint8_t)(IB_CS_GYRO_X + axis));
}

static int rw_st(uint32_t w) { return (int)((w >> 26) & 3u); }

/* ---- tests ---- */

static void test_parity_examples(void)
{
    /* sensors.md 2.5 computed examples, from the model's encoder */
    CHECK_EQ_INT(sim_adxrs450_encode_sensor(0, 1, 80, 0), 0x14014001u);
    CHECK_EQ_INT(sim_adxrs450_encode_sensor(0, 1, -80, 0), 0x17FEC000u);
    CHECK_EQ_INT(sim_adxrs450_encode_sensor(0, 2, 0, 0xFE), 0x080000FFu);
    /* accepted by the driver's checks, and decoded */
    CHECK(ib_adxrs450_response_parity_ok(0x14014001u));
    CHECK(ib_adxrs450_response_parity_ok(0x17FEC000u));
    CHECK(ib_adxrs450_response_parity_ok(0x080000FFu));
    ib_adxrs450_sample_t s;
    ib_adxrs450_decode_sensor(0x14014001u, &s);
    CHECK_EQ_INT(s.rate_counts, 80);
    CHECK_EQ_INT(s.st, 1);
    CHECK_EQ_INT(s.faults, 0);
    CHECK_EQ_INT(s.good, 1);
    ib_adxrs450_decode_sensor(0x17FEC000u, &s);
    CHECK_EQ_INT(s.rate_counts, -80);
    CHECK_EQ_INT(s.good, 1);
    ib_adxrs450_decode_sensor(0x080000FFu, &s);
    CHECK_EQ_INT(s.st, 2);
    CHECK_EQ_INT(s.faults, 0xFE);
    CHECK_EQ_INT(s.good, 0);
    /* any single flipped bit breaks at least P1; upper-half flips break P0 too */
    for (int b = 0; b < 32; b++) {
        CHECK(!ib_adxrs450_response_parity_ok(0x14014001u ^ (1u << b)));
    }
    ib_adxrs450_decode_sensor(0x14014001u ^ 0x400u, &s);
    CHECK_EQ_INT(s.parity_error, 1);
    CHECK_EQ_INT(s.good, 0);
    /* the power-on word fails P0 (sensors.md 2.5 exception) */
    CHECK(!ib_adxrs450_response_parity_ok(0x00000001u));
    /* model encoder: every generated word passes both checks */
    for (int c = -32768; c <= 32767; c += 97) {
        CHECK(ib_adxrs450_response_parity_ok(
            sim_adxrs450_encode_sensor((uint8_t)(c & 7), (uint8_t)(c & 3), (int16_t)c,
                                       (uint8_t)c)));
    }
}

static void test_command_words(void)
{
    CHECK_EQ_INT(ib_adxrs450_cmd_sensor_data(0), 0x20000000u);
    CHECK_EQ_INT(ib_adxrs450_cmd_sensor_data(1), 0x20000003u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_FAULT), 0x80140000u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_PID), 0x80180000u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_TEM), 0x80040001u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_SNH), 0x801C0001u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_SNL), 0x80200001u);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(IB_ADXRS450_REG_DNC), 0x80240000u);
    CHECK_EQ_INT(ib_adxrs450_cmd_write(IB_ADXRS450_REG_DNC, 0), 0x40240000u);
    /* data in 16:1 and parity: DNC = 0x0001 -> 0x40240002 has 4 ones -> P = 1 */
    CHECK_EQ_INT(ib_adxrs450_cmd_write(IB_ADXRS450_REG_DNC, 1), 0x40240003u);
    CHECK_EQ_INT(ib_adxrs450_cmd_write(IB_ADXRS450_REG_DNC, 0xFFFF), 0x4025FFFEu);
    CHECK_EQ_INT(ib_adxrs450_cmd_read(0x1FF), 0x83FE0001u);
    for (uint32_t a = 0; a < 0x200; a += 7) {
        uint32_t r = ib_adxrs450_cmd_read((uint16_t)a);
        uint32_t w = ib_adxrs450_cmd_write((uint16_t)a, (uint16_t)(a * 331u));
        int pr = 0, pw = 0;
        for (int b = 0; b < 32; b++) {
            pr += (int)((r >> b) & 1u);
            pw += (int)((w >> b) & 1u);
        }
        CHECK(pr % 2 == 1);
        CHECK(pw % 2 == 1);
        CHECK_EQ_INT((r >> 17) & 0x1FFu, a);
        CHECK_EQ_INT((w >> 1) & 0xFFFFu, (a * 331u) & 0xFFFFu);
    }
}

/* The model answers the 2.7 start-up table frame by frame. */
static void test_model_startup_table(void)
{
    setup(1);
    make_ideal();
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000003u), 0); /* before 100 ms: ignored */
    CHECK_EQ_INT(B.gyro[0].ignored_frames, 1);
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000003u), 0x00000001u);
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000000u), 0x04000000u); /* reply to CHK */
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000000u), 0x080000FFu);
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000000u), 0x080000FFu);
    bus_delay(&B, 50000);
    CHECK_EQ_INT(raw_frame(IB_CS_GYRO_X, 0x20000000u), 0x04000000u); /* ST=01, clean */
    /* the FAULT register is 0 after the CHK phase */
    raw_frame(IB_CS_GYRO_X, 0x80140000u);
    uint32_t r = raw_frame(IB_CS_GYRO_X, 0x80140000u);
    CHECK_EQ_INT(r >> 29, 2);
    CHECK_EQ_INT(rw_st(r), 3);
    CHECK_EQ_INT((r >> 5) & 0xFFFFu, 0);
    CHECK(ib_adxrs450_response_parity_ok(r));
    /* SQ echo: SQ1 (bit 31) comes back in bit 30 */
    raw_frame(IB_CS_GYRO_X, ib_adxrs450_with_parity(0xA0000000u));
    r = raw_frame(IB_CS_GYRO_X, 0x20000000u);
    CHECK_EQ_INT(r >> 29, 2);
    CHECK_EQ_INT(rw_st(r), 1);
    CHECK(ib_adxrs450_response_parity_ok(r));
}

static void test_startup_each_chip(void)
{
    setup(2);
    ib_adxrs450_t g[3];
    for (int i = 0; i < 3; i++) {
        uint64_t t0 = B.t_us;
        log_reset();
        CHECK_EQ_INT(init_chip(&g[i], i), IB_ADXRS450_OK);
        CHECK_EQ_INT(g[i].ready, 1);
        CHECK_EQ_INT(g[i].powerup_word, 0x00000001u);
        CHECK_EQ_INT(g[i].powerup_word_ok, 1);
        CHECK_EQ_INT(g[i].pid, 0x5201);
        CHECK_EQ_INT(g[i].serial, B.gyro[i].serial);
        CHECK(g[i].serial != 0u);
        CHECK_EQ_INT(g[i].startup_fault, 0);
        CHECK_EQ_INT(g[i].parity_errors, 0);
        CHECK_EQ_INT(g[i].chk_faults, 0xFE); /* CHK raised all seven fault bits */
        /* frames: CHK, SD x3, FAULT x2, PID x2, SNH x2, SNL x2, all on this chip */
        CHECK_EQ_INT(B.nframes, 12);
        static const uint32_t expect[12] = {0x20000003u, 0x20000000u, 0x20000000u,
                                            0x20000000u, 0x80140000u, 0x80140000u,
                                            0x80180000u, 0x80180000u, 0x801C0001u,
                                            0x801C0001u, 0x80200001u, 0x80200001u};
        for (uint32_t k = 0; k < 12 && k < B.nframes; k++) {
            CHECK_EQ_INT(B.log[k].tx, expect[k]);
            CHECK_EQ_INT(B.log[k].cs, IB_CS_GYRO_X + i);
        }
        CHECK(B.log[0].t_us - t0 >= 100000u);
        for (int k = 1; k <= 4; k++) {
            CHECK(B.log[k].t_us - B.log[k - 1].t_us >= 50000u);
        }
        CHECK(B.t_us - t0 <= 400000u);
        CHECK_EQ_INT(B.gyro[i].chk_remaining, 0);
        CHECK_EQ_INT(B.gyro[i].cmd_parity_errors, 0);
    }
    /* distinct serial numbers from distinct seeds */
    CHECK(g[0].serial != g[1].serial && g[1].serial != g[2].serial);
    /* re-init without a power cycle: the first reply is not the power-on word (warning) */
    CHECK_EQ_INT(init_chip(&g[0], 0), IB_ADXRS450_OK);
    CHECK_EQ_INT(g[0].powerup_word_ok, 0);
    CHECK(g[0].powerup_word != 0x00000001u);
    sim_adxrs450_power_cycle(&B.gyro[0]);
    CHECK_EQ_INT(init_chip(&g[0], 0), IB_ADXRS450_OK);
    CHECK_EQ_INT(g[0].powerup_word_ok, 1);
}

static void test_missing_chip(void)
{
    setup(3);
    ib_adxrs450_t g;
    sim_adxrs450_set_missing(&B.gyro[1], 1);
    uint64_t t0 = B.t_us;
    log_reset();
    CHECK_EQ_INT(init_chip(&g, 1), IB_ADXRS450_ERR_MISSING);
    CHECK_EQ_INT(g.ready, 0);
    CHECK(B.nframes <= 12u);
    CHECK(B.t_us - t0 <= 400000u);
    ib_adxrs450_sample_t s;
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_MISSING);
    CHECK_EQ_INT(s.good, 0);
    uint16_t v;
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_PID, &v), IB_ADXRS450_ERR_MISSING);
    /* nothing at all on the accelerometer's chip select */
    log_reset();
    CHECK_EQ_INT(ib_adxrs450_init(&g, &B.bus, IB_CS_ACCEL), IB_ADXRS450_ERR_MISSING);
    CHECK(B.nframes <= 12u);
    /* the other chips are unaffected */
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_OK);
}

static void test_wrong_pid(void)
{
    setup(4);
    ib_adxrs450_t g;
    sim_adxrs450_set_pid(&B.gyro[2], 0x4201);
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_ERR_BAD_PID);
    CHECK_EQ_INT(g.pid, 0x4201);
    CHECK_EQ_INT(g.ready, 0);
    sim_adxrs450_set_pid(&B.gyro[2], 0x5202); /* an ADXRS453: accepted, and named */
    sim_adxrs450_power_cycle(&B.gyro[2]);
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_OK);
    CHECK_EQ_INT(g.pid, 0x5202);
    CHECK(g.part != NULL && g.part->part == IB_PART_ADXRS453);
    sim_adxrs450_set_pid(&B.gyro[2], 0x5207); /* another revision of the family: an ADXRS450 */
    sim_adxrs450_power_cycle(&B.gyro[2]);
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_OK);
    CHECK(g.part != NULL && g.part->part == IB_PART_ADXRS450);
}

/* The ADXRS453 model (protocol/parts.toml): PID 0x5202 and its 16 deg/h bias instability; the
 * default chip keeps PID 0x5201 and 25 deg/h. */
static void test_adxrs453_sibling(void)
{
    setup(5);
    sim_adxrs450_set_part(&B.gyro[1], ib_part_by_id(IB_PART_ADXRS453));
    ib_adxrs450_t g0, g1;
    CHECK_EQ_INT(init_chip(&g0, 0), IB_ADXRS450_OK);
    CHECK_EQ_INT(init_chip(&g1, 1), IB_ADXRS450_OK);
    CHECK_EQ_INT(g0.pid, 0x5201);
    CHECK_EQ_INT(g1.pid, 0x5202);
    CHECK(g0.part->part == IB_PART_ADXRS450 && g1.part->part == IB_PART_ADXRS453);
    CHECK_NEAR(B.gyro[1].truth.bias_instability_rad_s * 180.0 / 3.14159265358979 * 3600.0, 16.0, 1e-3);
    CHECK_NEAR(B.gyro[0].truth.bias_instability_rad_s * 180.0 / 3.14159265358979 * 3600.0, 25.0, 1e-3);
    CHECK_EQ_INT((int)g1.part->ranges[0].lsb_per_unit, 80);
}

static void test_startup_faults(void)
{
    setup(5);
    ib_adxrs450_t g;
    /* a persistent NVM fault: the CHK phase passes, the clean-sample/FAULT check fails */
    sim_adxrs450_set_persistent_faults(&B.gyro[0], SIM_ADXRS450_FAULT_NVM);
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(g.startup_fault, IB_ADXRS450_FAULT_NVM);
    CHECK(g.faults_seen & IB_ADXRS450_FAULT_NVM);
    /* corrupted CHK-phase replies: parity error */
    sim_adxrs450_set_persistent_faults(&B.gyro[1], 0);
    sim_adxrs450_corrupt_responses(&B.gyro[1], 3, 0x00000001u);
    CHECK_EQ_INT(init_chip(&g, 1), IB_ADXRS450_ERR_PARITY);
    /* a chip that never enters the CHK state: the CHK command is lost (sent during the
     * start-up dead time of a chip powered on just now) */
    sim_adxrs450_power_cycle(&B.gyro[2]);
    B.gyro[2].startup_us = 150000u;
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_ERR_CHK_FAILED);
}

static void test_rate_sign_and_scale(void)
{
    setup(6);
    make_ideal();
    ib_adxrs450_t g[3];
    for (int i = 0; i < 3; i++) {
        CHECK_EQ_INT(init_chip(&g[i], i), IB_ADXRS450_OK);
    }
    ib_adxrs450_sample_t s;
    set_rate_dps(1.0, 0.0, 0.0);
    CHECK_EQ_INT(settled_read(&g[0], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 80);
    CHECK_EQ_INT(s.st, 1);
    CHECK_EQ_INT(s.faults, 0);
    CHECK_EQ_INT(s.good, 1);
    CHECK_EQ_INT(s.raw, 0x14014001u); /* the 2.5 example, on the wire */
    set_rate_dps(-1.0, 0.0, 0.0);
    CHECK_EQ_INT(settled_read(&g[0], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, -80);
    CHECK_EQ_INT(s.raw, 0x17FEC000u);
    /* each chip sees only its own axis with identity rows */
    set_rate_dps(1.0, 2.0, -3.0);
    int16_t expect[3] = {80, 160, -240};
    for (int i = 0; i < 3; i++) {
        CHECK_EQ_INT(settled_read(&g[i], &s), IB_ADXRS450_OK);
        CHECK_EQ_INT(s.rate_counts, expect[i]);
    }
    /* a sensitivity row with scale and cross-axis terms */
    sim_adxrs450_truth_t t = *sim_adxrs450_get_truth(&B.gyro[0]);
    t.sens[0] = 1.02;
    t.sens[1] = 0.01;
    t.sens[2] = -0.01;
    sim_adxrs450_set_truth(&B.gyro[0], &t);
    set_rate_dps(10.0, 20.0, 30.0);
    CHECK_EQ_INT(settled_read(&g[0], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 808); /* 10.2 + 0.2 - 0.3 = 10.1 deg/s */
    /* saturation at the int16 limits (+-409.6 deg/s) */
    set_rate_dps(500.0, 0.0, 0.0);
    CHECK_EQ_INT(settled_read(&g[1], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 0);
    set_rate_dps(0.0, 500.0, -500.0);
    CHECK_EQ_INT(settled_read(&g[1], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 32767);
    CHECK_EQ_INT(settled_read(&g[2], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, -32768);
    /* freshness: the sample of this call, not the previous one */
    set_rate_dps(0.0, 0.0, 10.0);
    CHECK_EQ_INT(settled_read(&g[2], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 800);
    set_rate_dps(0.0, 0.0, 20.0);
    bus_delay(&B, 1000);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g[2], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 1600);
    /* the RATE register latches like a sensor-data command */
    bus_delay(&B, 1000);
    uint16_t v = 0;
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g[2], IB_ADXRS450_REG_RATE, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT((int16_t)v, 1600);
    /* the mean over the interval: half at 20, half at 30 deg/s */
    bus_delay(&B, 500);
    set_rate_dps(0.0, 0.0, 30.0);
    bus_delay(&B, 500);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g[2], &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 2000);
}

static void test_faults(void)
{
    setup(7);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    sim_adxrs450_t *m = &B.gyro[0];
    ib_adxrs450_sample_t s;
    uint16_t f = 0;
    set_rate_dps(1.0, 0.0, 0.0);
    CHECK_EQ_INT(settled_read(&g, &s), IB_ADXRS450_OK);

    /* persistent Q: every sample, ST stays 01, then once more after the cause goes */
    sim_adxrs450_set_persistent_faults(m, SIM_ADXRS450_FAULT_Q);
    for (int k = 0; k < 3; k++) {
        CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
        CHECK_EQ_INT(s.faults, IB_ADXRS450_FAULT_Q);
        CHECK_EQ_INT(s.st, 1);
        CHECK_EQ_INT(s.rate_counts, 80);
        CHECK_EQ_INT(s.good, 0);
    }
    uint16_t quad = 0;
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_QUAD, &quad), IB_ADXRS450_OK);
    CHECK(quad > 4096u);
    sim_adxrs450_set_persistent_faults(m, 0);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.faults, IB_ADXRS450_FAULT_Q); /* re-asserted after the last report */
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.faults, 0);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, 0);

    /* a one-shot fault: reported once, then gone */
    sim_adxrs450_inject_faults(m, SIM_ADXRS450_FAULT_CST);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.faults, IB_ADXRS450_FAULT_CST);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);

    /* PLL forces ST = 00 */
    sim_adxrs450_set_persistent_faults(m, SIM_ADXRS450_FAULT_PLL);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.st, 0);
    CHECK_EQ_INT(s.faults, IB_ADXRS450_FAULT_PLL);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_PLL);
    sim_adxrs450_set_persistent_faults(m, 0);
    (void)ib_adxrs450_read_rate(&g, &s);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.st, 1);

    /* FAIL (FAULT register only) also forces ST = 00; only a FAULT read clears it */
    sim_adxrs450_set_persistent_faults(m, SIM_ADXRS450_FAULT_FAIL);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.st, 0);
    CHECK_EQ_INT(s.faults, 0);
    sim_adxrs450_set_persistent_faults(m, 0);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.st, 0);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_FAIL);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);

    /* undervoltage: PWR in the sample, UV stays in the FAULT register until read */
    sim_adxrs450_inject_faults(m, SIM_ADXRS450_FAULT_UV);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.faults, IB_ADXRS450_FAULT_PWR);
    CHECK_EQ_INT(s.st, 1);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_UV);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, 0);

    /* a fault read through the FAULT register only, persistent: every read shows it */
    sim_adxrs450_set_persistent_faults(m, SIM_ADXRS450_FAULT_OV);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_OV | IB_ADXRS450_FAULT_PWR);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_OV | IB_ADXRS450_FAULT_PWR);
    sim_adxrs450_set_persistent_faults(m, 0);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK); /* latched once more */
    CHECK_EQ_INT(f, IB_ADXRS450_FAULT_OV | IB_ADXRS450_FAULT_PWR);
    CHECK_EQ_INT(ib_adxrs450_read_fault(&g, &f), IB_ADXRS450_OK);
    CHECK_EQ_INT(f, 0);
    (void)ib_adxrs450_read_rate(&g, &s);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);

    /* sticky record of everything seen */
    CHECK((g.faults_seen & (IB_ADXRS450_FAULT_Q | IB_ADXRS450_FAULT_PLL |
                            IB_ADXRS450_FAULT_CST | IB_ADXRS450_FAULT_FAIL |
                            IB_ADXRS450_FAULT_UV)) ==
          (IB_ADXRS450_FAULT_Q | IB_ADXRS450_FAULT_PLL | IB_ADXRS450_FAULT_CST |
           IB_ADXRS450_FAULT_FAIL | IB_ADXRS450_FAULT_UV));
    ib_adxrs450_clear_faults_seen(&g);
    CHECK_EQ_INT(g.faults_seen, 0);

    /* after a power cycle and a new start-up, a persistent cause is still there */
    sim_adxrs450_set_persistent_faults(m, SIM_ADXRS450_FAULT_Q);
    sim_adxrs450_power_cycle(m);
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(g.startup_fault, IB_ADXRS450_FAULT_Q);
}

static void test_parity_injection(void)
{
    setup(8);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 1), IB_ADXRS450_OK);
    sim_adxrs450_t *m = &B.gyro[1];
    ib_adxrs450_sample_t s;
    set_rate_dps(0.0, 1.0, 0.0);
    CHECK_EQ_INT(settled_read(&g, &s), IB_ADXRS450_OK);

    /* only the discarded reply corrupted: harmless */
    sim_adxrs450_corrupt_responses(m, 1, 0x00000001u);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(g.parity_errors, 0);
    /* P1 only, P0 and P1, a data bit */
    static const uint32_t masks[3] = {0x00000001u, 0x10000000u, 0x00000400u};
    for (int k = 0; k < 3; k++) {
        sim_adxrs450_corrupt_responses(m, 2, masks[k]);
        CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_PARITY);
        CHECK_EQ_INT(s.parity_error, 1);
        CHECK_EQ_INT(s.good, 0);
        CHECK_EQ_INT(g.parity_errors, (uint32_t)k + 1u);
        CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
        CHECK_EQ_INT(s.rate_counts, 80);
    }
    /* register replies are checked too */
    uint16_t v = 0;
    sim_adxrs450_corrupt_responses(m, 2, 0x00010000u);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_PID, &v), IB_ADXRS450_ERR_PARITY);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_PID, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, 0x5201);
    CHECK_EQ_INT(g.parity_errors, 4);
    /* a bus error */
    B.fail_transfers = 1;
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_BUS);
    CHECK_EQ_INT(g.bus_errors, 1);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
}

static void test_invalid_commands(void)
{
    setup(9);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    set_rate_dps(2.0, 0.0, 0.0);
    bus_delay(&B, 1000);
    /* Linux-style register read: command, then 0x00000000 as the fetch frame */
    raw_frame(IB_CS_GYRO_X, 0x80180000u);
    uint32_t r = raw_frame(IB_CS_GYRO_X, 0x00000000u);
    CHECK_EQ_INT(r >> 29, 2);
    CHECK_EQ_INT(rw_st(r), 3);
    CHECK_EQ_INT((r >> 5) & 0xFFFFu, 0x5201);
    CHECK(ib_adxrs450_response_parity_ok(r));
    /* the 0x00000000 itself is answered on the next frame: R/W error, RE (+ SPI: its
     * parity is even) */
    r = raw_frame(IB_CS_GYRO_X, 0x20000000u);
    CHECK_EQ_INT(r >> 29, 0);
    CHECK_EQ_INT(rw_st(r), 3);
    CHECK(r & IB_ADXRS450_RESP_ERR_RE);
    CHECK(r & IB_ADXRS450_RESP_ERR_SPI);
    CHECK(ib_adxrs450_response_parity_ok(r));
    /* Linux-style rate read */
    bus_delay(&B, 1000);
    raw_frame(IB_CS_GYRO_X, 0x20000000u);
    r = raw_frame(IB_CS_GYRO_X, 0x00000000u);
    CHECK(ib_adxrs450_response_parity_ok(r));
    CHECK_EQ_INT(rw_st(r), 1);
    CHECK_EQ_INT((r >> 10) & 0xFFFFu, 160);
    /* a valid-parity but meaningless command: RE only */
    raw_frame(IB_CS_GYRO_X, 0x00000001u);
    r = raw_frame(IB_CS_GYRO_X, 0x20000000u);
    CHECK_EQ_INT(r >> 29, 0);
    CHECK_EQ_INT(rw_st(r), 3);
    CHECK_EQ_INT(r & 0x00070000u, IB_ADXRS450_RESP_ERR_RE);
    CHECK(ib_adxrs450_response_parity_ok(r));
    /* a sensor-data command with bad parity: SPI only, and it is not executed */
    uint32_t perr = B.gyro[0].cmd_parity_errors;
    raw_frame(IB_CS_GYRO_X, 0x20000001u);
    r = raw_frame(IB_CS_GYRO_X, 0x20000000u);
    CHECK_EQ_INT(r & 0x00070000u, IB_ADXRS450_RESP_ERR_SPI);
    CHECK_EQ_INT(rw_st(r), 3);
    CHECK_EQ_INT(B.gyro[0].cmd_parity_errors, perr + 1u);
    /* the driver reads normally afterwards */
    ib_adxrs450_sample_t s;
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 160);
    /* a frame of the wrong length is no command; the next reply is SPI error */
    uint8_t tx[2] = {0x20, 0x00}, rx[2];
    CHECK_EQ_INT(sim_adxrs450_spi(&B.gyro[0], tx, rx, 2), -1);
    r = raw_frame(IB_CS_GYRO_X, 0x20000000u);
    CHECK_EQ_INT(r & 0x00070000u, IB_ADXRS450_RESP_ERR_SPI);
    CHECK_EQ_INT(rw_st(r), 3);
    /* wrong status / response type in a rate reply (forced by corruption that keeps
     * the parity right) */
    sim_adxrs450_corrupt_responses(&B.gyro[0], 2, 0x0C000000u); /* ST 01 -> 10 */
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_FAULT);
    CHECK_EQ_INT(s.st, 2);
    /* ST 01 -> 11 plus rate bit 14: two flips in 31:16 keep both parities */
    sim_adxrs450_corrupt_responses(&B.gyro[0], 2, 0x09000000u);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
}

static void test_registers(void)
{
    setup(10);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 2), IB_ADXRS450_OK);
    uint16_t v = 0;
    /* DNC: writable, 10-bit signed */
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, IB_ADXRS450_REG_DNC, 5), IB_ADXRS450_OK);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_DNC, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, 5);
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, IB_ADXRS450_REG_DNC, 0xFFFF), IB_ADXRS450_OK);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_DNC, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, 0xFFFF);
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, IB_ADXRS450_REG_DNC, 0x03FF),
                 IB_ADXRS450_ERR_BAD_RESPONSE); /* echo is sign-extended: 0xFFFF */
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, IB_ADXRS450_REG_DNC, 0), IB_ADXRS450_OK);
    /* read-only: the echo shows the unchanged value */
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, IB_ADXRS450_REG_PID, 0x1234),
                 IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_PID, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, 0x5201);
    /* unknown and odd addresses: R/W error with RE */
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, 0x14, &v), IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(g.last_rw_error, 2);
    g.last_rw_error = 0;
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, 0x0D, &v), IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(g.last_rw_error, 2);
    CHECK_EQ_INT(ib_adxrs450_write_reg(&g, 0x40, 1), IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, 0x200, &v), IB_ADXRS450_ERR_ARG);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, 0x00, NULL), IB_ADXRS450_ERR_ARG);
    /* the rest of the map */
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_SNH, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, B.gyro[2].serial >> 16);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_SNL, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(v, B.gyro[2].serial & 0xFFFFu);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_LOCST, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_HICST, &v), IB_ADXRS450_OK);
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_QUAD, &v), IB_ADXRS450_OK);
    CHECK(v <= 4096u);
    /* the reply carries ST = 11, type 010 and bits 25:21 = 10000 on the wire */
    raw_frame(IB_CS_GYRO_Z, 0x80180000u);
    uint32_t r = raw_frame(IB_CS_GYRO_Z, 0x80180000u);
    CHECK_EQ_INT(r & 0xEFE0001Eu, 0x4E000000u);
    CHECK_EQ_INT((r >> 5) & 0xFFFFu, 0x5201);
}

static void test_temperature(void)
{
    setup(11);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    static const double temps[] = {45.0, 25.0, 85.0, -40.0, 105.0, 46.0, 44.0, 200.0, -100.0};
    static const int raw[] = {0, -100, 200, -425, 300, 5, -5, 511, -512};
    for (size_t k = 0; k < sizeof temps / sizeof temps[0]; k++) {
        B.world.temperature_c = temps[k];
        bus_delay(&B, 10);
        int16_t r10 = 1234;
        CHECK_EQ_INT(ib_adxrs450_read_temp(&g, &r10), IB_ADXRS450_OK);
        CHECK_EQ_INT(r10, raw[k]);
        CHECK_EQ_INT(sim_adxrs450_tem_register(temps[k]), (uint16_t)((raw[k] & 0x3FF) << 6));
    }
    CHECK_EQ_INT(ib_adxrs450_temp_centi_c(-100), 2500);
    CHECK_EQ_INT(ib_adxrs450_temp_centi_c(0), 4500);
    CHECK_EQ_INT(ib_adxrs450_temp_centi_c(-425), -4000);
    CHECK_EQ_INT(ib_adxrs450_temp_centi_c(301), 10520);
}

/* std (counts) of n reads at `rate_hz` with `frame_us` of bus time per frame */
static double noise_std(ib_adxrs450_t *g, double rate_hz, int n, uint32_t frame_us,
                        int block, double *block_std)
{
    uint32_t period = (uint32_t)(1e6 / rate_hz + 0.5);
    B.frame_us = frame_us;
    ib_adxrs450_sample_t s;
    /* one read to start a regular interval */
    bus_delay(&B, period);
    (void)ib_adxrs450_read_rate(g, &s);
    double sum = 0, sum2 = 0, bsum = 0, bsum2 = 0, acc = 0;
    int bad = 0, nb = 0;
    for (int k = 0; k < n; k++) {
        bus_delay(&B, period - 2u * frame_us);
        if (ib_adxrs450_read_rate(g, &s) != IB_ADXRS450_OK) {
            bad++;
        }
        double c = s.rate_counts;
        sum += c;
        sum2 += c * c;
        acc += c;
        if ((k + 1) % block == 0) {
            acc /= block;
            bsum += acc;
            bsum2 += acc * acc;
            nb++;
            acc = 0;
        }
    }
    CHECK_EQ_INT(bad, 0);
    B.frame_us = 0;
    double mean = sum / n;
    if (block_std != NULL) {
        double bm = bsum / nb;
        *block_std = sqrt(bsum2 / nb - bm * bm);
    }
    return sqrt(sum2 / n - mean * mean);
}

static void test_white_noise(void)
{
    setup(12);
    ib_adxrs450_t g;
    sim_adxrs450_truth_t t = sim_adxrs450_default_truth(0);
    t.bias_rw_k = 0.0;
    t.bias_instability_rad_s = 0.0;
    sim_adxrs450_set_truth(&B.gyro[0], &t);
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    const double n_counts = t.noise_n / DEG2RAD * 80.0; /* N in counts/sqrt(Hz) */
    double bstd = 0;
    double s1 = noise_std(&g, 1000.0, 20000, 0, 1, NULL);
    CHECK_NEAR(s1 / (n_counts * sqrt(1000.0)), 1.0, 0.05);
    double s4 = noise_std(&g, 4000.0, 20000, 8, 4, &bstd);
    CHECK_NEAR(s4 / (n_counts * sqrt(4000.0)), 1.0, 0.05);
    /* averaging 4 samples at 4 kHz is the same as sampling at 1 kHz */
    CHECK_NEAR(bstd / (n_counts * sqrt(1000.0)), 1.0, 0.05);
    /* a slow bus (40 us per frame) still gives whole-period samples */
    double s4b = noise_std(&g, 4000.0, 20000, 40, 1, NULL);
    CHECK_NEAR(s4b / (n_counts * sqrt(4000.0)), 1.0, 0.05);
    printf("     noise: 1 kHz %.2f counts (expect %.2f), 4 kHz %.2f (expect %.2f)\n", s1,
           n_counts * sqrt(1000.0), s4, n_counts * sqrt(4000.0));
}

static void test_bias_random_walk(void)
{
    /* across many chips, the random-walk bias after T has sigma K*sqrt(T) */
    static sim_adxrs450_t m[400];
    const double k = 0.01 * DEG2RAD;
    const double T = 100.0;
    sim_world_t w;
    memset(&w, 0, sizeof w);
    w.temperature_c = 25.0;
    double sum2 = 0.0;
    for (int i = 0; i < 400; i++) {
        sim_adxrs450_init(&m[i], 1000u + (uint64_t)i, 0);
        sim_adxrs450_truth_t t = sim_adxrs450_default_truth(0);
        t.noise_n = 0.0;
        t.bias_rw_k = k;
        t.bias_instability_rad_s = 0.0;
        sim_adxrs450_set_truth(&m[i], &t);
        for (int s = 1; s <= 200; s++) {
            sim_adxrs450_advance(&m[i], (uint64_t)s * 500000u, &w);
        }
        double b = sim_adxrs450_true_bias_rad_s(&m[i]);
        sum2 += b * b;
    }
    CHECK_NEAR(sqrt(sum2 / 400.0) / (k * sqrt(T)), 1.0, 0.12);

    /* and the driver sees the wandering bias of one chip */
    setup(13);
    sim_adxrs450_truth_t t = sim_adxrs450_default_truth(1);
    t.noise_n = 0.0;
    t.bias_rw_k = 0.2 * DEG2RAD;
    sim_adxrs450_set_truth(&B.gyro[1], &t);
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 1), IB_ADXRS450_OK);
    ib_adxrs450_sample_t s;
    int moved = 0;
    for (int step = 0; step < 20; step++) {
        for (int k2 = 0; k2 < 100; k2++) {
            bus_delay(&B, 10000); /* 1 s in 10 ms steps */
        }
        double truth_before = sim_adxrs450_true_bias_rad_s(&B.gyro[1]);
        bus_delay(&B, 100); /* the >100 ms interval: the sample is the current rate */
        CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_OK);
        double expect = truth_before / DEG2RAD * 80.0;
        CHECK_NEAR(s.rate_counts, expect, 2.0);
        if (fabs(expect) > 20.0) {
            moved = 1;
        }
    }
    CHECK(moved);
}

static void test_bias_instability_bank(void)
{
    /* across many chips, each process of the bank is stationary with sigma W*B, so the
     * bias-instability part has sigma W*B*sqrt(5) at any time, and its increments over a
     * short step are those of the processes' correlation (the rng is the chip's own: the
     * white noise's sequence does not change with B) */
    static sim_adxrs450_t m[400];
    const double b = 25.0 / 3600.0 * DEG2RAD;
    const double w = sim_adxrs450_flicker_weight();
    sim_world_t wd;
    memset(&wd, 0, sizeof wd);
    wd.temperature_c = 25.0;
    double sum2_0 = 0.0, sum2_1 = 0.0, dsum2 = 0.0;
    for (int i = 0; i < 400; i++) {
        sim_adxrs450_init(&m[i], 5000u + (uint64_t)i, 0);
        double b0 = sim_adxrs450_flicker_bias_rad_s(&m[i]);
        for (int s = 1; s <= 1000; s++) { /* 1000 s in 1 s steps */
            sim_adxrs450_advance(&m[i], (uint64_t)s * 1000000u, &wd);
        }
        double b1 = sim_adxrs450_flicker_bias_rad_s(&m[i]);
        sum2_0 += b0 * b0;
        sum2_1 += b1 * b1;
        dsum2 += (b1 - b0) * (b1 - b0);
    }
    const double sd = w * b * sqrt((double)SIM_ADXRS450_FLICKER_N);
    CHECK_NEAR(sqrt(sum2_0 / 400.0) / sd, 1.0, 0.12);
    CHECK_NEAR(sqrt(sum2_1 / 400.0) / sd, 1.0, 0.12);
    /* over 1000 s: var of the change = 2*(W*B)^2 * sum(1 - exp(-1000/T)) */
    const double *tau = sim_adxrs450_flicker_taus();
    double want = 0.0;
    for (int k = 0; k < SIM_ADXRS450_FLICKER_N; k++) {
        want += 2.0 * (w * b) * (w * b) * (1.0 - exp(-1000.0 / tau[k]));
    }
    CHECK_NEAR(sqrt(dsum2 / 400.0) / sqrt(want), 1.0, 0.12);

    /* the default chip carries the data sheet's B; B = 0 takes the part out, at once */
    sim_adxrs450_t *c = &m[0];
    CHECK_NEAR(sim_adxrs450_get_truth(c)->bias_instability_rad_s, b, 1e-15);
    double before = sim_adxrs450_true_bias_rad_s(c);
    double part = sim_adxrs450_flicker_bias_rad_s(c);
    CHECK(part != 0.0);
    sim_adxrs450_truth_t t = *sim_adxrs450_get_truth(c);
    t.bias_instability_rad_s = 0.0;
    sim_adxrs450_set_truth(c, &t);
    CHECK_NEAR(sim_adxrs450_true_bias_rad_s(c), before - part, 1e-15);
    CHECK_NEAR(sim_adxrs450_flicker_bias_rad_s(c), 0.0, 1e-15);

    /* same seed, same drift: deterministic per seed, different per seed */
    sim_adxrs450_t a1, a2, a3;
    sim_adxrs450_init(&a1, 77u, 1);
    sim_adxrs450_init(&a2, 77u, 1);
    sim_adxrs450_init(&a3, 78u, 1);
    for (int s = 1; s <= 500; s++) {
        sim_adxrs450_advance(&a1, (uint64_t)s * 7000u, &wd);
        sim_adxrs450_advance(&a2, (uint64_t)s * 7000u, &wd);
        sim_adxrs450_advance(&a3, (uint64_t)s * 7000u, &wd);
    }
    CHECK(sim_adxrs450_true_bias_rad_s(&a1) == sim_adxrs450_true_bias_rad_s(&a2));
    CHECK(sim_adxrs450_true_bias_rad_s(&a1) != sim_adxrs450_true_bias_rad_s(&a3));
}

static void test_tempco(void)
{
    setup(14);
    make_ideal();
    sim_adxrs450_truth_t t = *sim_adxrs450_get_truth(&B.gyro[0]);
    t.bias_tempco_rad_s_per_c = 0.1 * DEG2RAD;
    t.scale_tempco_per_c = 1e-3;
    t.bias_rad_s = 0.5 * DEG2RAD;
    sim_adxrs450_set_truth(&B.gyro[0], &t);
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    ib_adxrs450_sample_t s;
    set_rate_dps(100.0, 0.0, 0.0);
    static const double temps[] = {25.0, 65.0, -15.0};
    /* (1 + 1e-3 dT) * 100 + 0.5 + 0.1 dT deg/s */
    static const int expect[] = {8040, 8680, 7400};
    for (int k = 0; k < 3; k++) {
        B.world.temperature_c = temps[k];
        CHECK_EQ_INT(settled_read(&g, &s), IB_ADXRS450_OK);
        CHECK_EQ_INT(s.rate_counts, expect[k]);
        CHECK_NEAR(sim_adxrs450_true_bias_rad_s(&B.gyro[0]) / DEG2RAD,
                   0.5 + 0.1 * (temps[k] - 25.0), 1e-9);
    }
}

/* Curved bias and the play-operator hysteresis (adxrs450_model.h). */
static void test_curve_and_hysteresis(void)
{
    setup(15);
    make_ideal();
    sim_adxrs450_truth_t t = *sim_adxrs450_get_truth(&B.gyro[0]);
    t.bias_tc2 = 2e-3 * DEG2RAD;
    t.bias_tc3 = -1e-5 * DEG2RAD;
    t.hysteresis = 0.05 * DEG2RAD;
    t.hysteresis_width_c = 2.0;
    sim_adxrs450_set_truth(&B.gyro[0], &t);
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    ib_adxrs450_sample_t s;
    static const double temps[] = {25.0, 45.0, 44.0, 5.0, 5.5, 25.0};
    static const double h[] = {0.0, 1.0, 0.0, -1.0, -0.5, 1.0};
    for (int k = 0; k < 6; k++) {
        B.world.temperature_c = temps[k];
        CHECK_EQ_INT(settled_read(&g, &s), IB_ADXRS450_OK);
        double d = temps[k] - 25.0;
        double want = 2e-3 * d * d - 1e-5 * d * d * d + 0.05 * h[k]; /* deg/s */
        CHECK_NEAR(B.gyro[0].hyst_h, h[k], 1e-12);
        CHECK_NEAR(sim_adxrs450_true_bias_rad_s(&B.gyro[0]) / DEG2RAD, want, 1e-9);
        CHECK_NEAR(sim_adxrs450_truth_thermal_bias(&t, temps[k], h[k]) / DEG2RAD, want, 1e-9);
        CHECK_EQ_INT(s.rate_counts, (int)lround(want * 80.0));
    }
}

static void test_random_truth(void)
{
    sim_rng_t rng;
    sim_rng_seed(&rng, 77);
    double max_bias = 0, sum2 = 0;
    for (int i = 0; i < 2000; i++) {
        int axis = i % 3;
        sim_adxrs450_truth_t t;
        sim_adxrs450_random_truth(&t, &rng, axis);
        for (int j = 0; j < 3; j++) {
            if (j == axis) {
                CHECK(fabs(t.sens[j] - 1.0) <= 0.03);
            } else {
                CHECK(fabs(t.sens[j]) <= 0.01);
            }
        }
        double b = t.bias_rad_s / DEG2RAD;
        CHECK(fabs(b) <= 3.0);
        max_bias = fmax(max_bias, fabs(b));
        sum2 += b * b;
        CHECK(t.noise_n > 0.0);
        CHECK(fabs(t.bias_tempco_rad_s_per_c / DEG2RAD) <= 0.01);
        CHECK(fabs(t.scale_tempco_per_c) <= 1e-4);
        CHECK(fabs(t.bias_tc2 / DEG2RAD) <= 1e-4 && fabs(t.bias_tc3 / DEG2RAD) <= 1e-6);
        CHECK(fabs(t.hysteresis / DEG2RAD) <= 0.01);
        CHECK(t.hysteresis_width_c >= 1.0 && t.hysteresis_width_c <= 4.0);
        /* the bound the ranges come from: the null moves by at most 2 deg/s on -40..105 degC */
        for (double d = -65.0; d <= 80.0; d += 5.0) {
            CHECK(fabs(sim_adxrs450_truth_thermal_bias(&t, 25.0 + d, 0.0) / DEG2RAD) <= 2.0);
        }
    }
    CHECK_NEAR(sqrt(sum2 / 2000.0), 0.5, 0.05);
    CHECK(max_bias > 1.0);
    sim_adxrs450_truth_t d = sim_adxrs450_default_truth(1);
    CHECK(d.sens[0] == 0.0 && d.sens[1] == 1.0 && d.sens[2] == 0.0);
    CHECK(d.bias_rad_s == 0.0);
    CHECK_NEAR(d.noise_n, 0.015 * DEG2RAD, 1e-12);
}

static void test_bad_args(void)
{
    ib_adxrs450_t g;
    memset(&g, 0, sizeof g);
    ib_adxrs450_sample_t s;
    ib_spi_bus_t empty;
    memset(&empty, 0, sizeof empty);
    CHECK_EQ_INT(ib_adxrs450_init(NULL, &B.bus, 1), IB_ADXRS450_ERR_ARG);
    CHECK_EQ_INT(ib_adxrs450_init(&g, NULL, 1), IB_ADXRS450_ERR_ARG);
    CHECK_EQ_INT(ib_adxrs450_init(&g, &empty, 1), IB_ADXRS450_ERR_ARG);
    CHECK_EQ_INT(ib_adxrs450_read_rate(&g, &s), IB_ADXRS450_ERR_ARG); /* no bus */
    CHECK_EQ_INT(ib_adxrs450_read_rate(NULL, &s), IB_ADXRS450_ERR_ARG);
}

/* The pieces a DMA board uses (one frame per sample): prime, then every frame's reply is the
 * rate latched by the frame before, decoded exactly as ib_adxrs450_read_rate does; "read TEM"
 * then a sensor-data frame gives the pending rate and the temperature. */
static void test_pipelined_pieces(void)
{
    setup(9);
    make_ideal();
    ib_adxrs450_t g;
    CHECK_EQ_INT(init_chip(&g, 0), IB_ADXRS450_OK);
    uint8_t sd[4], tem[4], rx[4];
    ib_adxrs450_rate_cmd_bytes(sd);
    ib_adxrs450_temp_cmd_bytes(tem);
    CHECK_EQ_INT(be32(sd), ib_adxrs450_cmd_sensor_data(0));
    CHECK_EQ_INT(be32(tem), ib_adxrs450_cmd_read(IB_ADXRS450_REG_TEM));
    /* after a register read the first reply would be a register reply: prime */
    uint16_t pid = 0;
    ib_adxrs450_sample_t s0;
    set_rate_dps(1.0, 0.0, 0.0);
    (void)settled_read(&g, &s0); /* the model's output filter settles */
    CHECK_EQ_INT(ib_adxrs450_read_reg(&g, IB_ADXRS450_REG_PID, &pid), IB_ADXRS450_OK);
    bus_delay(&B, 1000);
    CHECK_EQ_INT(ib_adxrs450_prime_rate(&g), IB_ADXRS450_OK);
    ib_adxrs450_sample_t s;
    bus_delay(&B, 250);
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, sd, rx, 4), 0);
    CHECK_EQ_INT(ib_adxrs450_rate_from_reply(&g, ib_adxrs450_word(rx), &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 80);
    CHECK_EQ_INT(s.good, 1);
    /* the rate changes: the next reply still carries the one latched before the change */
    set_rate_dps(-2.0, 0.0, 0.0);
    bus_delay(&B, 20000);
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, tem, rx, 4), 0);
    CHECK_EQ_INT(ib_adxrs450_rate_from_reply(&g, ib_adxrs450_word(rx), &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 80);
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, sd, rx, 4), 0);
    int16_t raw10 = 99;
    CHECK_EQ_INT(ib_adxrs450_temp_from_reply(&g, ib_adxrs450_word(rx), &raw10), IB_ADXRS450_OK);
    int16_t direct = 0;
    CHECK_EQ_INT(ib_adxrs450_read_temp(&g, &direct), IB_ADXRS450_OK);
    CHECK_EQ_INT(raw10, direct);
    /* a register reply where a rate is expected, and a rate where a register reply is */
    CHECK_EQ_INT(ib_adxrs450_prime_rate(&g), IB_ADXRS450_OK); /* its reply: the TEM read's */
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, sd, rx, 4), 0);
    CHECK_EQ_INT(ib_adxrs450_temp_from_reply(&g, ib_adxrs450_word(rx), &raw10), IB_ADXRS450_ERR_BAD_RESPONSE);
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, tem, rx, 4), 0);
    CHECK_EQ_INT(B.bus.transfer(B.bus.ctx, IB_CS_GYRO_X, sd, rx, 4), 0);
    CHECK_EQ_INT(ib_adxrs450_rate_from_reply(&g, ib_adxrs450_word(rx), &s), IB_ADXRS450_ERR_BAD_RESPONSE);
    /* a flipped bit is a parity error, as in the blocking read */
    CHECK_EQ_INT(ib_adxrs450_rate_from_reply(&g, 0x14014001u ^ 0x00000400u, &s), IB_ADXRS450_ERR_PARITY);
    CHECK_EQ_INT(ib_adxrs450_rate_from_reply(&g, 0x14014001u, &s), IB_ADXRS450_OK);
    CHECK_EQ_INT(s.rate_counts, 80);
}

int main(void)
{
    RUN(test_pipelined_pieces);
    RUN(test_parity_examples);
    RUN(test_command_words);
    RUN(test_model_startup_table);
    RUN(test_startup_each_chip);
    RUN(test_missing_chip);
    RUN(test_wrong_pid);
    RUN(test_adxrs453_sibling);
    RUN(test_startup_faults);
    RUN(test_rate_sign_and_scale);
    RUN(test_faults);
    RUN(test_parity_injection);
    RUN(test_invalid_commands);
    RUN(test_registers);
    RUN(test_temperature);
    RUN(test_white_noise);
    RUN(test_bias_random_walk);
    RUN(test_bias_instability_bank);
    RUN(test_tempco);
    RUN(test_curve_and_hysteresis);
    RUN(test_random_truth);
    RUN(test_bad_args);
    return ctest_summary();
}
