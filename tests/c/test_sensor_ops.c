/*
 * test_sensor_ops.c - the core holds generic sensors (firmware/core/sensor.h): it runs on any
 * driver that fills the ops tables, and picks each slot's driver from the part table at boot.
 *
 * This program brings its own part table of drivers (ib_sensor_drivers: it defines the symbol, so
 * the generated one in libfw.a is not linked) with fake drivers that speak no real protocol: an
 * accelerometer (the ADXL359's part) and two gyro drivers, the first finding an ADXRS450 on
 * chip select X only, the second an ADXRS453 on Y only, and on Z an ADXRS453 the first driver
 * claims by mistake (a part the table gives to another driver: refused). Then a stream on a
 * board without bus->start (the blocking reads) and one with it (the chain of transfers,
 * completed at once from start()), and the self-test, all through the ops.
 */
#include <string.h>

#include "core.h"
#include "ctest.h"
#include "frame.h"
#include "protocol_gen.h"
#include "sensor.h"

/* ------------------------------------------------------------ the fake drivers */

typedef struct {
    uint8_t cs;
    const ib_part_desc_t *part;
    uint8_t tx[4], rx[2][4];
    uint8_t n_len_asked, n_done;
    uint32_t n_read, n_finish, n_start;
} fake_t;

static fake_t g_acc[IB_ACCEL_SLOTS], g_g1[IB_GYRO_SLOTS], g_g2[IB_GYRO_SLOTS];

static void *acc_instance(uint8_t slot) { return &g_acc[slot]; }
static void *g1_instance(uint8_t slot) { return &g_g1[slot]; }
static void *g2_instance(uint8_t slot) { return &g_g2[slot]; }

static int acc_init(void *ctx, const ib_spi_bus_t *bus, uint8_t cs)
{
    fake_t *f = ctx;
    (void)bus;
    memset(f, 0, sizeof *f);
    f->cs = cs;
    f->part = ib_part_by_id(IB_PART_ADXL359);
    return IB_SENSOR_OK;
}
/* gyro driver 1: an ADXRS450 on X; on Z it "finds" an ADXRS453 (not its part: refused) */
static int g1_init(void *ctx, const ib_spi_bus_t *bus, uint8_t cs)
{
    fake_t *f = ctx;
    (void)bus;
    memset(f, 0, sizeof *f);
    f->cs = cs;
    f->part = cs == IB_CS_GYRO_X ? ib_part_by_id(IB_PART_ADXRS450)
              : cs == IB_CS_GYRO_Z ? ib_part_by_id(IB_PART_ADXRS453) : NULL;
    return f->part ? IB_SENSOR_OK : -2;
}
/* gyro driver 2: an ADXRS453 on Y */
static int g2_init(void *ctx, const ib_spi_bus_t *bus, uint8_t cs)
{
    fake_t *f = ctx;
    (void)bus;
    memset(f, 0, sizeof *f);
    f->cs = cs;
    f->part = cs == IB_CS_GYRO_Y ? ib_part_by_id(IB_PART_ADXRS453) : NULL;
    return f->part ? IB_SENSOR_OK : -2;
}
static const ib_part_desc_t *fake_part(void *ctx) { return ((fake_t *)ctx)->part; }
static void acc_ids(void *ctx, uint8_t id[4])
{
    id[0] = 0xAD;
    id[1] = 0x1D;
    id[2] = 0xE9;
    id[3] = ((fake_t *)ctx)->cs;
}
static void g1_ids(void *ctx, uint16_t *id, uint32_t *serial)
{
    *id = (uint16_t)(0x5100u + ((fake_t *)ctx)->cs);
    *serial = 1000u + ((fake_t *)ctx)->cs;
}
static void g2_ids(void *ctx, uint16_t *id, uint32_t *serial)
{
    *id = (uint16_t)(0x5200u + ((fake_t *)ctx)->cs);
    *serial = 2000u + ((fake_t *)ctx)->cs;
}
static uint32_t odr_period_us(uint8_t code) { return 250u << code; }
static int acc_start(void *ctx, uint8_t range_code, uint8_t odr_code, uint32_t max_sets)
{
    fake_t *f = ctx;
    f->n_start++;
    f->rx[0][0] = range_code;
    f->rx[0][1] = odr_code;
    (void)max_sets;
    return IB_SENSOR_OK;
}
static int g_start(void *ctx, int pipelined)
{
    ((fake_t *)ctx)->n_start += pipelined ? 100u : 1u;
    return IB_SENSOR_OK;
}
static int acc_temp(void *ctx, uint16_t *counts)
{
    (void)ctx;
    *counts = 1852u; /* 25 degC on the ADXL359 */
    return IB_SENSOR_OK;
}
static int g_temp(void *ctx, int16_t *counts)
{
    *counts = (int16_t)(10 * ((fake_t *)ctx)->cs);
    return IB_SENSOR_OK;
}
/* four sets a period: X 1000, Y -1001, Z 25600 + cs (the mean is what the stream carries) */
static void acc_fill(ib_accel_read_t *out)
{
    out->sets = 4u;
    out->sum[0] = 4 * 1000;
    out->sum[1] = 4 * -1001;
    out->sum[2] = 4 * 25600;
    out->status = 0x01u;
}
static void acc_read(void *ctx, uint32_t max_sets, ib_accel_read_t *out)
{
    ((fake_t *)ctx)->n_read++;
    (void)max_sets;
    acc_fill(out);
}
/* finish writes every field of out (sensor.h: the core does not clear it) */
static void acc_finish(void *ctx, int rc, uint8_t temps, ib_accel_read_t *out)
{
    fake_t *f = ctx;
    memset(out, 0, sizeof *out);
    f->n_finish++;
    if (rc != 0) {
        out->err = IB_SENSOR_ERR_BUS;
        return;
    }
    acc_fill(out);
    if (temps) {
        out->temp_ok = 1;
        out->temp_counts = 1852u;
    }
}
static void g_fill(const fake_t *f, ib_gyro_read_t *out)
{
    out->rate_counts = (int16_t)(80 * f->cs); /* cs deg/s */
    out->good = 1;
}
static void g_read(void *ctx, ib_gyro_read_t *out)
{
    ((fake_t *)ctx)->n_read++;
    g_fill(ctx, out);
}
static void g_finish(void *ctx, int rc, uint8_t temps, ib_gyro_read_t *out)
{
    fake_t *f = ctx;
    memset(out, 0, sizeof *out);
    f->n_finish++;
    if (rc != 0) {
        out->err = IB_SENSOR_ERR_BUS;
        return;
    }
    g_fill(f, out);
    if (temps) {
        out->temp_ok = 1;
        out->temp_counts = (int16_t)(10 * f->cs);
    }
}
static int acc_self_test(void *ctx, int32_t delta[3])
{
    (void)ctx;
    delta[0] = 11;
    delta[1] = 22;
    delta[2] = 33;
    return IB_SENSOR_OK;
}
static int g_self_test(void *ctx, uint8_t *detail)
{
    *detail = (uint8_t)(0xF0u | ((fake_t *)ctx)->cs);
    return IB_SENSOR_OK;
}

/* the chain: the accelerometer a header (notifying) and a body whose length it asks for;
 * a gyro one frame, two at a batch's start */
static uint8_t acc_plan(void *ctx, uint8_t temps, ib_xfer_t *out)
{
    fake_t *f = ctx;
    out[0].tx = f->tx;
    out[0].rx = f->rx[0];
    out[0].len = temps ? 4u : 3u;
    out[0].tag = IB_XFER_NOTIFY; /* step 0 */
    out[1].tx = f->tx;
    out[1].rx = f->rx[1];
    out[1].len = 0u;
    out[1].tag = 1u;
    return 2u;
}
static size_t acc_len(void *ctx, const ib_xfer_t *x)
{
    fake_t *f = ctx;
    f->n_len_asked++;
    return x->tag == 1u ? 4u : 0u;
}
static void acc_done(void *ctx, const ib_xfer_t *x)
{
    ((fake_t *)ctx)->n_done++;
    (void)x;
}
static uint8_t g_plan(void *ctx, uint8_t temps, ib_xfer_t *out)
{
    fake_t *f = ctx;
    for (uint8_t i = 0; i < 1u + (temps ? 1u : 0u); i++) {
        out[i].tx = f->tx;
        out[i].rx = f->rx[i];
        out[i].len = 4u;
        out[i].tag = i;
    }
    return temps ? 2u : 1u;
}

static const ib_accel_ops_t acc_ops = {
    {acc_plan, acc_len, acc_done}, acc_instance, acc_init, fake_part, acc_ids, 10u, odr_period_us,
    acc_start, acc_temp, acc_read, acc_finish, acc_self_test, 0x04u, IB_PART_ADXL359};
static const ib_gyro_ops_t g1_ops = {
    {g_plan, NULL, NULL}, g1_instance, g1_init, fake_part, g1_ids, g_start, g_temp, g_read, g_finish,
    g_self_test, IB_PART_ADXRS450};
static const ib_gyro_ops_t g2_ops = {
    {g_plan, NULL, NULL}, g2_instance, g2_init, fake_part, g2_ids, g_start, g_temp, g_read, g_finish,
    g_self_test, IB_PART_ADXRS453};

/* this program's part table of drivers (the generated one is drivers_gen.c) */
const ib_sensor_driver_t ib_sensor_drivers[] = {
    {IB_PART_ADXL359, &acc_ops, NULL},
    {IB_PART_ADXRS450, NULL, &g1_ops},
    {IB_PART_ADXRS453, NULL, &g2_ops},
};
const size_t ib_sensor_driver_count = 3u;

/* ------------------------------------------------------------------ the board */

typedef struct {
    uint8_t in[512];
    size_t in_len, in_pos;
    uint8_t out[16384];
    size_t out_len;
    uint32_t t_us;
    uint8_t xfer_cs[64];
    uint8_t xfer_len[64];
    size_t n_xfer;
} tb_t;

static tb_t g_tb;

static uint32_t tb_time(void *ctx) { return ((tb_t *)ctx)->t_us += 10u; }
static void tb_tick(void *ctx, uint32_t hz) { (void)ctx; (void)hz; }
static size_t tb_free(void *ctx) { return sizeof ((tb_t *)ctx)->out - ((tb_t *)ctx)->out_len; }
static size_t tb_write(void *ctx, const uint8_t *d, size_t n)
{
    tb_t *t = ctx;
    if (n > tb_free(t)) {
        return 0;
    }
    memcpy(t->out + t->out_len, d, n);
    t->out_len += n;
    return n;
}
static size_t tb_read(void *ctx, uint8_t *buf, size_t cap)
{
    tb_t *t = ctx;
    size_t n = t->in_len - t->in_pos < cap ? t->in_len - t->in_pos : cap;
    memcpy(buf, t->in + t->in_pos, n);
    t->in_pos += n;
    return n;
}
static int tb_spi(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)ctx; (void)cs; (void)tx; (void)rx; (void)len;
    return -1; /* the fake drivers never use the bus themselves */
}
static void tb_delay(void *ctx, uint32_t us) { ((tb_t *)ctx)->t_us += us; }
static void tb_reboot(void *ctx) { (void)ctx; }
/* the chain: note the transfer, complete it at once (done() starts the next) */
static int tb_start(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len, void (*done)(void *, int),
                    void *arg)
{
    tb_t *t = ctx;
    (void)tx;
    (void)rx;
    if (t->n_xfer < sizeof t->xfer_cs) {
        t->xfer_cs[t->n_xfer] = cs;
        t->xfer_len[t->n_xfer] = (uint8_t)len;
    }
    t->n_xfer++;
    done(arg, 0);
    return 0;
}

static const ib_spi_bus_t g_bus_sync = {tb_spi, tb_delay, &g_tb, NULL};
static const ib_spi_bus_t g_bus_dma = {tb_spi, tb_delay, &g_tb, tb_start};
static const ib_board_t g_board_sync = {
    IB_BOARD_SIM, IB_CLOCK_SOURCE_NONE, 0, {0}, "test", tb_time, tb_tick, tb_free, tb_write, tb_read,
    &g_bus_sync, NULL, tb_reboot, &g_tb};
static const ib_board_t g_board_dma = {
    IB_BOARD_SIM, IB_CLOCK_SOURCE_NONE, 0, {0}, "test", tb_time, tb_tick, tb_free, tb_write, tb_read,
    &g_bus_dma, NULL, tb_reboot, &g_tb};

static ib_core_t g_core;

/* ------------------------------------------------------------------ helpers */

static void command(uint8_t type, uint16_t rid, const uint8_t *payload, size_t len)
{
    uint8_t raw[IB_MAX_FRAME];
    uint8_t enc[IB_MAX_ENCODED + 1];
    memcpy(raw + IB_HEADER_SIZE, payload, len);
    size_t n = ib_frame_encode(raw, type, rid, 0, len, enc);
    enc[n++] = 0;
    memcpy(g_tb.in, enc, n);
    g_tb.in_len = n;
    g_tb.in_pos = 0;
    for (int i = 0; i < 8; i++) {
        ib_core_poll(&g_core);
    }
}

/* Walk the frames the core wrote; call fn for each. */
static void frames(void (*fn)(const ib_frame_t *f, void *arg), void *arg)
{
    ib_frame_rx_t rx;
    ib_frame_rx_init(&rx);
    for (size_t i = 0; i < g_tb.out_len; i++) {
        ib_frame_t f;
        if (ib_frame_rx_push(&rx, g_tb.out[i], &f) == IB_FRAME_OK) {
            fn(&f, arg);
        }
    }
}

typedef struct {
    ib_msg_info_t info;
    int n_info;
    ib_msg_fault_event_t fault[8];
    int n_fault;
    ib_raw_sample_t sample[64];
    ib_batch_header_t hdr;
    int n_samples;
    ib_msg_self_test_result_t st;
    int n_st;
} seen_t;

static void collect(const ib_frame_t *f, void *arg)
{
    seen_t *s = arg;
    if (f->type == IB_MSG_INFO) {
        ib_msg_info_unpack(f->payload, &s->info);
        s->n_info++;
    } else if (f->type == IB_MSG_FAULT_EVENT && s->n_fault < 8) {
        ib_msg_fault_event_unpack(f->payload, &s->fault[s->n_fault++]);
    } else if (f->type == IB_MSG_RAW_BATCH) {
        ib_batch_header_unpack(f->payload, &s->hdr);
        for (int i = 0; i < s->hdr.count && s->n_samples < 64; i++) {
            ib_raw_sample_unpack(f->payload + IB_BATCH_HEADER_SIZE + (size_t)i * IB_RAW_SAMPLE_SIZE,
                                 &s->sample[s->n_samples++]);
        }
    } else if (f->type == IB_MSG_SELF_TEST_RESULT) {
        ib_msg_self_test_result_unpack(f->payload, &s->st);
        s->n_st++;
    }
}

static void boot(const ib_board_t *b, seen_t *s)
{
    memset(&g_tb, 0, sizeof g_tb);
    ib_core_init(&g_core, b);
    memset(s, 0, sizeof *s);
    frames(collect, s);
}

/* 20 raw samples at 1 kHz in batches of 4 (ticks due every 1000 us). */
static void stream(seen_t *s)
{
    ib_msg_start_stream_t m = {1000u, IB_STREAM_MODE_RAW, 4u, 20u, {0, 0, 0}};
    uint8_t p[IB_MSG_START_STREAM_SIZE];
    ib_msg_start_stream_pack(&m, p);
    command(IB_MSG_START_STREAM, 7, p, sizeof p);
    for (uint32_t k = 0; k < 20u; k++) {
        ib_core_tick(&g_core, 0, 1000u * k);
        ib_core_poll(&g_core);
    }
    command(IB_MSG_STOP_STREAM, 8, NULL, 0);
    memset(s, 0, sizeof *s);
    frames(collect, s);
}

/* ------------------------------------------------------------------ tests */

static void test_boot_picks_each_slots_driver_from_the_part_table(void)
{
    seen_t s;
    boot(&g_board_sync, &s);
    CHECK_EQ_INT(s.n_info, 1);
    CHECK_EQ_INT(s.info.sensors_present, 0x07);
    CHECK_EQ_INT(s.info.parts[0], IB_PART_ADXL359);
    CHECK_EQ_INT(s.info.parts[1], IB_PART_ADXRS450);
    CHECK_EQ_INT(s.info.parts[2], IB_PART_ADXRS453); /* the second driver, after the first's refusal */
    CHECK_EQ_INT(s.info.parts[3], IB_PART_NONE);     /* driver 1's ADXRS453 is driver 2's part */
    CHECK_EQ_INT(s.info.accel_range_g, 10);           /* the ADXL359's default full scale */
    CHECK_EQ_INT(s.info.accel_ids[2], 0xE9);
    CHECK_EQ_INT(s.info.gyro_pid[0], 0x5101);         /* each slot's driver reports its IDs */
    CHECK_EQ_INT(s.info.gyro_pid[1], 0x5202);
    CHECK_EQ_INT(s.info.gyro_pid[2], 0x5203);         /* Z: the last driver tried */
    CHECK_EQ_INT(s.info.gyro_sn[0], 1001);
    /* the missing Z gyro: one fault event, its detail the ID the slot read */
    CHECK_EQ_INT(s.n_fault, 1);
    CHECK_EQ_INT(s.fault[0].sensor, IB_SENSOR_GYRO_Z);
    CHECK_EQ_INT(s.fault[0].kind, IB_FAULT_KIND_MISSING);
    CHECK_EQ_INT(s.fault[0].detail, 0x5203);
}

static void test_a_stream_through_the_blocking_reads(void)
{
    seen_t s;
    boot(&g_board_sync, &s);
    stream(&s);
    CHECK_EQ_INT(g_acc[0].n_start, 1);
    CHECK_EQ_INT(g_acc[0].rx[0][0], 2);   /* the ADXL359's code of +-20 g */
    CHECK_EQ_INT(g_acc[0].rx[0][1], 2);   /* 1 kHz from 4 kHz / 2^2 ... */
    CHECK_EQ_INT(g_g1[0].n_start, 1);     /* ... and no pipelined read without bus->start */
    CHECK_EQ_INT(g_acc[0].n_read, 20);
    CHECK_EQ_INT(g_g1[0].n_read, 20);
    CHECK_EQ_INT(g_g2[1].n_read, 20);
    CHECK_EQ_INT(g_acc[0].n_finish, 0);
    CHECK_EQ_INT(s.n_samples, 20);
    CHECK_EQ_INT(s.hdr.accel_range_g, 20);
    CHECK_EQ_INT(s.hdr.gyro_temp_counts[0], 10);
    CHECK_EQ_INT(s.hdr.gyro_temp_counts[1], 20);
    CHECK_EQ_INT(s.hdr.accel_temp_counts, 1852);
    CHECK_EQ_INT(s.sample[5].accel_x_counts, 1000);
    CHECK_EQ_INT(s.sample[5].accel_y_counts, -1001);
    CHECK_EQ_INT(s.sample[5].accel_z_counts, 25600);
    CHECK_EQ_INT(s.sample[5].gyro_counts[0], 80);
    CHECK_EQ_INT(s.sample[5].gyro_counts[1], 160);
    CHECK_EQ_INT(s.sample[5].gyro_counts[2], 0);
    CHECK_EQ_INT(s.sample[5].status, IB_SAMPLE_STATUS_GYRO_Z_BAD);
}

static void test_a_stream_through_the_chain_of_transfers(void)
{
    seen_t s;
    boot(&g_board_dma, &s);
    stream(&s);
    CHECK_EQ_INT(g_g1[0].n_start, 100);   /* the pipelined read primed */
    CHECK_EQ_INT(g_acc[0].n_read, 0);     /* every sample from the chain */
    CHECK_EQ_INT(g_acc[0].n_finish, 20);
    CHECK_EQ_INT(g_g2[1].n_finish, 20);
    CHECK_EQ_INT(g_acc[0].n_done, 20);    /* the notifying header, once a sample */
    CHECK_EQ_INT(g_acc[0].n_len_asked, 20);
    /* a batch's first sample: accel header 4 + body 4, gyro X 4 + 4, gyro Y 4 + 4; then 3 + 4, 4, 4 */
    CHECK_EQ_INT(g_tb.n_xfer, 5 * 6 + 15 * 4);
    static const uint8_t cs0[6] = {IB_CS_ACCEL, IB_CS_ACCEL, IB_CS_GYRO_X, IB_CS_GYRO_X, IB_CS_GYRO_Y, IB_CS_GYRO_Y};
    static const uint8_t len0[6] = {4, 4, 4, 4, 4, 4};
    static const uint8_t cs1[4] = {IB_CS_ACCEL, IB_CS_ACCEL, IB_CS_GYRO_X, IB_CS_GYRO_Y};
    static const uint8_t len1[4] = {3, 4, 4, 4};
    for (int i = 0; i < 6; i++) {
        CHECK_EQ_INT(g_tb.xfer_cs[i], cs0[i]);
        CHECK_EQ_INT(g_tb.xfer_len[i], len0[i]);
    }
    for (int i = 0; i < 4; i++) {
        CHECK_EQ_INT(g_tb.xfer_cs[6 + i], cs1[i]);
        CHECK_EQ_INT(g_tb.xfer_len[6 + i], len1[i]);
    }
    CHECK_EQ_INT(s.n_samples, 20);
    CHECK_EQ_INT(s.sample[19].accel_z_counts, 25600);
    CHECK_EQ_INT(s.sample[19].gyro_counts[1], 160);
    CHECK_EQ_INT(s.hdr.gyro_temp_counts[1], 20);
}

static void test_the_self_test_goes_through_the_ops(void)
{
    seen_t s;
    boot(&g_board_sync, &s);
    command(IB_MSG_SELF_TEST, 9, NULL, 0);
    memset(&s, 0, sizeof s);
    frames(collect, &s);
    CHECK_EQ_INT(s.n_st, 1);
    CHECK_EQ_INT(s.st.tested, 0x07);
    CHECK_EQ_INT(s.st.passed, 0x07);
    CHECK_EQ_INT(s.st.accel_delta_counts[2], 33);
    CHECK_EQ_INT(s.st.gyro_chk_faults[0], 0xF1);
    CHECK_EQ_INT(s.st.gyro_chk_faults[1], 0xF2);
    CHECK_EQ_INT(s.st.gyro_chk_faults[2], 0);
}

int main(void)
{
    RUN(test_boot_picks_each_slots_driver_from_the_part_table);
    RUN(test_a_stream_through_the_blocking_reads);
    RUN(test_a_stream_through_the_chain_of_transfers);
    RUN(test_the_self_test_goes_through_the_ops);
    return ctest_summary();
}
