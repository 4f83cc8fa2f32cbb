/* adxrs450_ops.c - the ADXRS450 family (ADXRS450, ADXRS453) behind the gyro ops of sensor.h:
 * the core's generic single-axis gyro, one context per slot kept here. */
#include "adxrs450.h"
#include "sensor.h"

/* the driver's codes pass through the ops unchanged where sensor.h gives them a meaning */
_Static_assert(IB_ADXRS450_OK == IB_SENSOR_OK && IB_ADXRS450_ERR_BUS == IB_SENSOR_ERR_BUS, "adxrs450 codes");

typedef struct {
    ib_adxrs450_t dev;
    uint8_t rx[2][4]; /* the chain's replies: the rate (or the pending rate), the temperature */
} gyro_inst_t;

static gyro_inst_t g_inst[IB_GYRO_SLOTS];
/* the sensor-data and "read TEM" commands, the same for every part of the family */
static uint8_t g_rate_tx[4], g_tem_tx[4];

static void *instance(uint8_t slot) { return slot < IB_GYRO_SLOTS ? &g_inst[slot] : NULL; }

static int init(void *ctx, const ib_spi_bus_t *bus, uint8_t cs)
{
    gyro_inst_t *g = ctx;
    const gyro_inst_t zero = {0};
    *g = zero;
    ib_adxrs450_rate_cmd_bytes(g_rate_tx);
    ib_adxrs450_temp_cmd_bytes(g_tem_tx);
    return ib_adxrs450_init(&g->dev, bus, cs);
}

static const ib_part_desc_t *part(void *ctx) { return ((gyro_inst_t *)ctx)->dev.part; }

static void ids(void *ctx, uint16_t *id, uint32_t *serial)
{
    const ib_adxrs450_t *d = &((gyro_inst_t *)ctx)->dev;
    *id = d->pid;
    *serial = d->serial;
}

/* The pipelined read's first frame: its reply is discarded, the next one is a rate. */
static int start(void *ctx, int pipelined)
{
    return pipelined ? ib_adxrs450_prime_rate(&((gyro_inst_t *)ctx)->dev) : IB_SENSOR_OK;
}

static int read_temp(void *ctx, int16_t *counts) { return ib_adxrs450_read_temp(&((gyro_inst_t *)ctx)->dev, counts); }

static void from_sample(int err, const ib_adxrs450_sample_t *s, ib_gyro_read_t *out)
{
    out->err = err;
    out->rate_counts = s->rate_counts;
    out->faults = (uint8_t)(s->faults | (s->parity_error ? 1u : 0u));
    out->status_bad = s->st != IB_ADXRS450_ST_VALID ? (uint8_t)(s->st | 0x80u) : 0u;
    out->good = s->good;
}

static void read(void *ctx, ib_gyro_read_t *out)
{
    ib_adxrs450_sample_t s = {0};
    from_sample(ib_adxrs450_read_rate(&((gyro_inst_t *)ctx)->dev, &s), &s, out);
}

/* ---- the chain: one frame a sample (the pipelined read of adxrs450.h: its reply is the rate
 * the previous sample's frame latched); at a batch's first, "read TEM" instead and a
 * sensor-data frame whose reply is the temperature ---- */

static uint8_t plan(void *ctx, uint8_t temps, ib_xfer_t *out)
{
    gyro_inst_t *g = ctx;
    out[0].tx = temps ? g_tem_tx : g_rate_tx;
    out[0].rx = g->rx[0];
    out[0].len = 4u;
    out[0].tag = 0u;
    if (!temps) {
        return 1u;
    }
    out[1].tx = g_rate_tx;
    out[1].rx = g->rx[1];
    out[1].len = 4u;
    out[1].tag = 1u;
    return 2u;
}

/* Every field of out is written (the core does not clear it: once a sample). */
static void finish(void *ctx, int rc, uint8_t temps, ib_gyro_read_t *out)
{
    gyro_inst_t *g = ctx;
    out->temp_ok = 0;
    out->temp_counts = 0;
    if (rc != 0) {
        ib_adxrs450_note_bus_error(&g->dev);
        out->err = IB_SENSOR_ERR_BUS;
        out->rate_counts = 0;
        out->faults = out->status_bad = out->good = 0;
        return;
    }
    ib_adxrs450_sample_t s;
    from_sample(ib_adxrs450_rate_from_reply(&g->dev, ib_adxrs450_word(g->rx[0]), &s), &s, out);
    int16_t raw10;
    if (temps && ib_adxrs450_temp_from_reply(&g->dev, ib_adxrs450_word(g->rx[1]), &raw10) == IB_ADXRS450_OK) {
        out->temp_counts = raw10;
        out->temp_ok = 1;
    }
}

/* The CHK sequence is part of the start-up: run it again. */
static int self_test(void *ctx, uint8_t *detail)
{
    ib_adxrs450_t *d = &((gyro_inst_t *)ctx)->dev;
    ib_adxrs450_err_t e = ib_adxrs450_init(d, d->bus, d->cs);
    *detail = d->chk_faults;
    return e;
}

const ib_gyro_ops_t ib_adxrs450_gyro_ops = {
    {plan, NULL, NULL},
    instance,
    init,
    part,
    ids,
    start,
    read_temp,
    read,
    finish,
    self_test,
    IB_PART_ADXRS450,
};
