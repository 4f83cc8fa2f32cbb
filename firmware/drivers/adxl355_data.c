/* adxl355_data.c - ADXL355-family driver, its data half: samples, the FIFO (read whole or in
 * pieces for a DMA chain) and the self-test; see adxl355.h. Integer math only. */
#include "adxl355_priv.h"

#include <string.h>

/* ---- data ---- */

int ib_adxl355_read_sample(ib_adxl355_t *dev, ib_adxl355_sample_t *s)
{
    uint8_t b[13]; /* STATUS, FIFO_ENTRIES, TEMP2, TEMP1, X3 X2 X1, Y3 Y2 Y1, Z3 Z2 Z1 */
    if (s == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    int r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_STATUS, b, sizeof b);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    s->status = b[0];
    s->fifo_entries = (uint8_t)(b[1] & 0x7Fu);
    s->temp_counts = (uint16_t)(((uint16_t)(b[2] & 0x0Fu) << 8) | b[3]);
    for (int i = 0; i < 3; i++) {
        s->accel_counts[i] = ib_adxl355_counts_from_bytes(b[4 + 3 * i], b[5 + 3 * i], b[6 + 3 * i]);
    }
    /* A STATUS with reserved bits 7:5 or NVM_BUSY set is not a real status (0xFF while
     * the NVM reloads, or MISO floating high): never report new data from it. */
    const uint8_t bogus = IB_ADXL355_STATUS_RESERVED | IB_ADXL355_STATUS_NVM_BUSY;
    s->new_data = (uint8_t)(((b[0] & IB_ADXL355_STATUS_DATA_RDY) != 0u && (b[0] & bogus) == 0u)
                                ? 1u
                                : 0u);
    dev->last_status = b[0];
    return IB_ADXL355_OK;
}

int ib_adxl355_wait_sample(ib_adxl355_t *dev, ib_adxl355_sample_t *s, uint32_t timeout_us)
{
    if (dev == NULL || s == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    uint32_t poll_us = ib_adxl355_odr_period_us(dev->odr_code) / 4u;
    if (poll_us < 20u) {
        poll_us = 20u;
    }
    uint32_t waited = 0;
    for (;;) {
        int r = ib_adxl355_read_sample(dev, s);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        if (s->new_data) {
            return IB_ADXL355_OK;
        }
        if (waited >= timeout_us) {
            return IB_ADXL355_ERR_NO_DATA;
        }
        adxl355_delay_us(dev, poll_us);
        waited += poll_us;
    }
}

/* Pop `n` (<= IB_ADXL355_FIFO_CHUNK) entries in one burst from FIFO_DATA into out. */
static int fifo_pop(ib_adxl355_t *dev, uint8_t *out, size_t n)
{
    uint8_t tx[1u + 3u * IB_ADXL355_FIFO_CHUNK];
    uint8_t rx[1u + 3u * IB_ADXL355_FIFO_CHUNK];
    size_t len = 1u + 3u * n;
    memset(tx, 0, len);
    tx[0] = (uint8_t)((IB_ADXL355_REG_FIFO_DATA << 1) | RW_READ);
    int r = adxl355_xfer(dev, tx, rx, len);
    if (r == IB_ADXL355_OK) {
        memcpy(out, &rx[1], 3u * n);
    }
    return r;
}

size_t ib_adxl355_fifo_entries(ib_adxl355_t *dev, const uint8_t hdr[2], size_t max_sets)
{
    dev->last_status = hdr[0];
    size_t entries = hdr[1] & 0x7Fu;
    if (entries > IB_ADXL355_FIFO_SIZE) {
        entries = IB_ADXL355_FIFO_SIZE;
    }
    entries -= entries % 3u;
    if (max_sets < IB_ADXL355_FIFO_SIZE / 3u && entries > max_sets * 3u) {
        entries = max_sets * 3u;
    }
    return entries;
}

void ib_adxl355_fifo_parse_init(ib_adxl355_fifo_parse_t *p)
{
    p->axis = 0;
    p->empty = 0;
    p->sets = 0;
    p->dropped = 0;
}

void ib_adxl355_fifo_parse(ib_adxl355_t *dev, ib_adxl355_fifo_parse_t *p, const uint8_t *buf, size_t n,
                           int32_t (*xyz)[3], size_t max_sets)
{
    for (size_t k = 0; k < n && !p->empty; k++) {
        const uint8_t *e = &buf[3u * k];
        if (e[2] & IB_ADXL355_FIFO_MARKER_EMPTY) {
            p->empty = 1; /* the rest of this burst is empty too */
            break;
        }
        int32_t v = ib_adxl355_counts_from_bytes(e[0], e[1], e[2]);
        size_t dropped = 0;
        if (e[2] & IB_ADXL355_FIFO_MARKER_X) {
            dropped = p->axis; /* a partial set cut short by a new X */
            p->cur[0] = v;
            p->axis = 1;
        } else if (p->axis == 0) {
            dropped = 1; /* Y or Z without its X: resynchronise */
        } else {
            p->cur[p->axis++] = v;
            if (p->axis == 3u) {
                if (p->sets < max_sets) {
                    xyz[p->sets][0] = p->cur[0];
                    xyz[p->sets][1] = p->cur[1];
                    xyz[p->sets][2] = p->cur[2];
                    p->sets++;
                } else {
                    dropped = 3;
                }
                p->axis = 0;
            }
        }
        if (dropped) {
            dev->fifo_discarded += (uint32_t)dropped;
            p->dropped += dropped;
        }
    }
}

void ib_adxl355_fifo_parse_end(ib_adxl355_t *dev, ib_adxl355_fifo_parse_t *p)
{
    if (p->axis != 0) {
        dev->fifo_discarded += p->axis; /* the FIFO ended inside a set */
        p->axis = 0;
    }
}

int ib_adxl355_read_fifo(ib_adxl355_t *dev, int32_t (*xyz)[3], size_t max_sets,
                         size_t *n_sets)
{
    if (n_sets == NULL || (xyz == NULL && max_sets != 0)) {
        return IB_ADXL355_ERR_ARG;
    }
    *n_sets = 0;
    uint8_t hdr[2];
    int r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_STATUS, hdr, sizeof hdr);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    size_t entries = ib_adxl355_fifo_entries(dev, hdr, max_sets);

    /* `budget` grows by one for every discarded entry, but never beyond `limit`, so a
     * garbage stream cannot keep the loop going. */
    const size_t limit = entries + IB_ADXL355_FIFO_SIZE;
    size_t budget = entries;
    size_t popped = 0;
    ib_adxl355_fifo_parse_t p;
    ib_adxl355_fifo_parse_init(&p);
    uint8_t buf[3u * IB_ADXL355_FIFO_CHUNK];

    while (popped < budget && !p.empty) {
        size_t n = budget - popped;
        if (n > IB_ADXL355_FIFO_CHUNK) {
            n = IB_ADXL355_FIFO_CHUNK;
        }
        r = fifo_pop(dev, buf, n);
        if (r != IB_ADXL355_OK) {
            *n_sets = p.sets;
            return r;
        }
        popped += n;
        size_t before = p.dropped;
        ib_adxl355_fifo_parse(dev, &p, buf, n, xyz, max_sets);
        budget += p.dropped - before;
        if (budget > limit) {
            budget = limit;
        }
    }
    ib_adxl355_fifo_parse_end(dev, &p);
    *n_sets = p.sets;
    return IB_ADXL355_OK;
}

/* ---- self-test ---- */

/* Wait for and sum IB_ADXL355_ST_AVERAGE fresh samples after discarding the settle
 * samples. */
static int st_phase(ib_adxl355_t *dev, int32_t mean[3])
{
    ib_adxl355_sample_t s;
    uint32_t timeout = 4u * ib_adxl355_odr_period_us(dev->odr_code) + 1000u;
    int32_t sum[3] = {0, 0, 0};
    /* Clear a DATA_RDY that may belong to a sample from before the switch. */
    int r = ib_adxl355_read_sample(dev, &s);
    for (uint32_t i = 0; r == IB_ADXL355_OK && i < IB_ADXL355_ST_SETTLE; i++) {
        r = ib_adxl355_wait_sample(dev, &s, timeout);
    }
    for (uint32_t i = 0; r == IB_ADXL355_OK && i < IB_ADXL355_ST_AVERAGE; i++) {
        r = ib_adxl355_wait_sample(dev, &s, timeout);
        if (r == IB_ADXL355_OK) {
            for (int a = 0; a < 3; a++) {
                sum[a] += s.accel_counts[a]; /* 16 * 2^19 fits easily */
            }
        }
    }
    if (r != IB_ADXL355_OK) {
        return r;
    }
    for (int a = 0; a < 3; a++) {
        /* divide rounding to nearest (symmetric) */
        int32_t h = (int32_t)(IB_ADXL355_ST_AVERAGE / 2u);
        int32_t d = (int32_t)IB_ADXL355_ST_AVERAGE;
        mean[a] = sum[a] >= 0 ? (sum[a] + h) / d : -((-sum[a] + h) / d);
    }
    return IB_ADXL355_OK;
}

int ib_adxl355_self_test(ib_adxl355_t *dev, ib_adxl355_selftest_t *res)
{
    if (dev == NULL || dev->bus == NULL || res == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    memset(res, 0, sizeof *res);
    const ib_adxl355_config_t saved = {dev->range, dev->odr_code, dev->hpf_code};
    const uint8_t was_measuring = dev->measuring;
    const ib_adxl355_config_t st_cfg = {IB_ADXL355_ST_RANGE, IB_ADXL355_ST_ODR_CODE, 0u};
    int32_t base[3], forced[3];

    int r = ib_adxl355_standby(dev);
    if (r == IB_ADXL355_OK) {
        r = adxl355_write_config(dev, &st_cfg);
    }
    if (r == IB_ADXL355_OK) {
        r = adxl355_write_reg(dev, IB_ADXL355_REG_SELF_TEST, IB_ADXL355_SELF_TEST_ST1);
    }
    if (r == IB_ADXL355_OK) {
        r = ib_adxl355_measure(dev);
    }
    if (r == IB_ADXL355_OK) {
        r = st_phase(dev, base);
    }
    if (r == IB_ADXL355_OK) {
        r = adxl355_write_reg(dev, IB_ADXL355_REG_SELF_TEST,
                      IB_ADXL355_SELF_TEST_ST1 | IB_ADXL355_SELF_TEST_ST2);
    }
    if (r == IB_ADXL355_OK) {
        r = st_phase(dev, forced);
    }

    /* Restore whatever happened above (a bus error may make this fail too; the first
     * error is the one reported). */
    int r2 = adxl355_write_reg(dev, IB_ADXL355_REG_SELF_TEST, 0x00);
    if (r2 == IB_ADXL355_OK) {
        r2 = ib_adxl355_standby(dev);
    }
    if (r2 == IB_ADXL355_OK) {
        r2 = adxl355_write_config(dev, &saved);
    }
    if (r2 == IB_ADXL355_OK && was_measuring) {
        r2 = ib_adxl355_measure(dev);
    }
    if (r != IB_ADXL355_OK) {
        return r;
    }
    if (r2 != IB_ADXL355_OK) {
        return r2;
    }

    const ib_part_desc_t *part = dev->part ? dev->part : ib_part_by_id(IB_PART_ADXL355);
    const int32_t lsb = ib_adxl355_part_lsb_per_g(part, st_cfg.range);
    res->lsb_per_g = lsb;
    int all = 1;
    for (int a = 0; a < 3; a++) {
        int32_t d = forced[a] - base[a];
        int32_t mag = d < 0 ? -d : d;
        /* the part's limits (protocol/parts.toml, g) in counts of the self-test range */
        int32_t lo = (int32_t)(part->self_test_min[a] * (float)lsb + 0.5f);
        int32_t hi = (int32_t)(part->self_test_max[a] * (float)lsb + 0.5f);
        res->delta_counts[a] = d;
        res->axis_pass[a] = (uint8_t)(mag >= lo && mag <= hi);
        if (!res->axis_pass[a]) {
            all = 0;
        }
    }
    return all ? IB_ADXL355_OK : IB_ADXL355_ERR_SELFTEST;
}
