/* adxl355_ops.c - the ADXL355 family (ADXL355, ADXL359) behind the accelerometer ops of
 * sensor.h: the core's generic accelerometer, one context per slot kept here. */
#include <string.h>

#include "adxl355.h"
#include "sensor.h"

/* the driver's codes pass through the ops unchanged where sensor.h gives them a meaning */
_Static_assert(IB_ADXL355_OK == IB_SENSOR_OK && IB_ADXL355_ERR_BUS == IB_SENSOR_ERR_BUS, "adxl355 codes");

/* The whole FIFO in one chain: 160 Hz takes 25 sets a tick. */
#define CHAIN_FIFO_SETS (IB_ADXL355_FIFO_SIZE / 3u)
enum { STEP_HDR = 0, STEP_FIFO = 1 };

typedef struct {
    ib_adxl355_t dev;
    /* the chain's buffers: STATUS, FIFO_ENTRIES, TEMP2, TEMP1 in one burst, then the FIFO pop */
    uint8_t hdr_tx[5], hdr_rx[5];
    uint8_t fifo_n; /* entries the header counted (whole sets) */
    uint8_t fifo_rx[1u + 3u * IB_ADXL355_FIFO_SIZE];
} accel_inst_t;

static accel_inst_t g_inst[IB_ACCEL_SLOTS];

static void *instance(uint8_t slot) { return slot < IB_ACCEL_SLOTS ? &g_inst[slot] : NULL; }

static int init(void *ctx, const ib_spi_bus_t *bus, uint8_t cs)
{
    accel_inst_t *a = ctx;
    memset(a, 0, sizeof *a);
    a->hdr_tx[0] = ib_adxl355_read_cmd(IB_ADXL355_REG_STATUS);
    ib_adxl355_config_t cfg = {1u, 2u, 0u}; /* code 1: every part's lowest range */
    return ib_adxl355_init(&a->dev, bus, cs, &cfg) == IB_ADXL355_OK ? IB_SENSOR_OK : IB_ADXL355_ERR_ID;
}

static const ib_part_desc_t *part(void *ctx) { return ((accel_inst_t *)ctx)->dev.part; }

static void ids(void *ctx, uint8_t id[4])
{
    const ib_adxl355_t *d = &((accel_inst_t *)ctx)->dev;
    id[0] = d->devid_ad;
    id[1] = d->devid_mst;
    id[2] = d->partid;
    id[3] = d->revid;
}

/* Empty the FIFO in chunks of 8 sets (small stack), at most max_sets. */
static int start(void *ctx, uint8_t range_code, uint8_t odr_code, uint32_t max_sets)
{
    ib_adxl355_t *d = &((accel_inst_t *)ctx)->dev;
    ib_adxl355_config_t cfg = {range_code, odr_code, 0u};
    int rc = ib_adxl355_configure(d, &cfg) == IB_ADXL355_OK ? IB_SENSOR_OK : IB_SENSOR_ERR_BUS;
    int32_t sink[8][3];
    size_t n = 0, left = max_sets;
    do {
        if (ib_adxl355_read_fifo(d, sink, 8u, &n) != IB_ADXL355_OK) {
            break;
        }
        left = left > n ? left - n : 0;
    } while (n == 8u && left);
    return rc;
}

static int read_temp(void *ctx, uint16_t *counts)
{
    uint8_t t[2];
    int r = ib_adxl355_read_regs(&((accel_inst_t *)ctx)->dev, IB_ADXL355_REG_TEMP2, t, 2);
    if (r == IB_ADXL355_OK) {
        *counts = (uint16_t)(((t[0] & 0x0Fu) << 8) | t[1]);
    }
    return r;
}

/* Every set the FIFO collected since the last tick, in chunks of 8 (small stack). */
static void read(void *ctx, uint32_t max_sets, ib_accel_read_t *out)
{
    ib_adxl355_t *d = &((accel_inst_t *)ctx)->dev;
    int32_t sets[8][3];
    size_t n = 0;
    int err = IB_ADXL355_OK;
    do {
        err = ib_adxl355_read_fifo(d, sets, 8u, &n);
        out->status |= d->last_status;
        for (size_t i = 0; err == IB_ADXL355_OK && i < n; i++) {
            out->sum[0] += sets[i][0];
            out->sum[1] += sets[i][1];
            out->sum[2] += sets[i][2];
        }
        out->sets += (uint32_t)n;
    } while (err == IB_ADXL355_OK && n == 8u && out->sets < max_sets + 8u);
    out->err = err;
}

/* ---- the chain: 0 the header burst (3 bytes, 5 with the temperature), 1 pop the sets it
 * counted (the read of ib_adxl355_read_fifo in pieces, adxl355.h) ---- */

static uint8_t plan(void *ctx, uint8_t temps, ib_xfer_t *out)
{
    accel_inst_t *a = ctx;
    out[0].tx = a->hdr_tx;
    out[0].rx = a->hdr_rx;
    out[0].len = temps ? (uint8_t)sizeof a->hdr_tx : 3u;
    out[0].tag = IB_XFER_NOTIFY; /* STEP_HDR (0), and chain_done after it */
    out[1].tx = ib_adxl355_fifo_read_tx;
    out[1].rx = a->fifo_rx;
    out[1].len = 0u;
    out[1].tag = STEP_FIFO;
    return 2u;
}

static size_t chain_len(void *ctx, const ib_xfer_t *x)
{
    const accel_inst_t *a = ctx;
    return x->tag == STEP_FIFO && a->fifo_n ? 1u + 3u * (size_t)a->fifo_n : 0u;
}

static void chain_done(void *ctx, const ib_xfer_t *x)
{
    accel_inst_t *a = ctx;
    (void)x; /* only the header notifies */
    a->fifo_n = (uint8_t)ib_adxl355_fifo_entries(&a->dev, &a->hdr_rx[1], CHAIN_FIFO_SETS);
}

/* Every field of out is written (the core does not clear it: once a sample). */
static void finish(void *ctx, int rc, uint8_t temps, ib_accel_read_t *out)
{
    accel_inst_t *a = ctx;
    out->err = rc != 0 ? IB_SENSOR_ERR_BUS : IB_SENSOR_OK;
    out->sets = 0;
    out->sum[0] = out->sum[1] = out->sum[2] = 0;
    out->status = 0;
    out->temp_ok = 0;
    out->temp_counts = 0;
    if (rc != 0) {
        return;
    }
    out->status = a->dev.last_status;
    if (temps) {
        out->temp_counts = (uint16_t)(((a->hdr_rx[3] & 0x0Fu) << 8) | a->hdr_rx[4]);
        out->temp_ok = 1;
    }
    if (a->fifo_n == 0u) {
        return;
    }
    int32_t sets[8][3]; /* in chunks of 8 sets (small stack) */
    ib_adxl355_fifo_parse_t p;
    ib_adxl355_fifo_parse_init(&p);
    size_t total = 0;
    for (size_t e0 = 0; e0 < a->fifo_n && !p.empty; e0 += 24u) {
        size_t n = a->fifo_n - e0 < 24u ? a->fifo_n - e0 : 24u;
        p.sets = 0;
        ib_adxl355_fifo_parse(&a->dev, &p, &a->fifo_rx[1u + 3u * e0], n, sets, 8u);
        for (size_t i = 0; i < p.sets; i++) {
            out->sum[0] += sets[i][0];
            out->sum[1] += sets[i][1];
            out->sum[2] += sets[i][2];
        }
        total += p.sets;
    }
    ib_adxl355_fifo_parse_end(&a->dev, &p);
    out->sets = (uint32_t)total;
}

static int self_test(void *ctx, int32_t delta_counts[3])
{
    ib_adxl355_selftest_t st;
    int e = ib_adxl355_self_test(&((accel_inst_t *)ctx)->dev, &st);
    for (int k = 0; k < 3; k++) {
        delta_counts[k] = st.delta_counts[k];
    }
    return e;
}

const ib_accel_ops_t ib_adxl355_accel_ops = {
    {plan, chain_len, chain_done},
    instance,
    init,
    part,
    ids,
    IB_ADXL355_ODR_CODE_MAX,
    ib_adxl355_odr_period_us,
    start,
    read_temp,
    read,
    finish,
    self_test,
    IB_ADXL355_STATUS_FIFO_OVR,
    IB_PART_ADXL355,
};
