/* adxl355.c - ADXL355 driver; see adxl355.h. Integer math only. */
#include "adxl355.h"

#include <string.h>

#define RW_READ 0x01u
#define REGS_MAX 16u

/* ---- helpers without bus access ---- */

int32_t ib_adxl355_part_lsb_per_g(const ib_part_desc_t *part, uint8_t range)
{
    if (part == NULL) {
        part = ib_part_by_id(IB_PART_ADXL355);
    }
    for (size_t i = 0; i < part->n_ranges; i++) {
        if (range != 0u && part->ranges[i].code == range) {
            return (int32_t)part->ranges[i].lsb_per_unit;
        }
    }
    return 0;
}

int32_t ib_adxl355_lsb_per_g(uint8_t range) { return ib_adxl355_part_lsb_per_g(NULL, range); }

uint32_t ib_adxl355_odr_period_us(uint8_t odr_code)
{
    if (odr_code > IB_ADXL355_ODR_CODE_MAX) {
        return 0;
    }
    return 250u << odr_code;
}

int32_t ib_adxl355_counts_from_bytes(uint8_t b3, uint8_t b2, uint8_t b1)
{
    uint32_t u = ((uint32_t)b3 << 12) | ((uint32_t)b2 << 4) | ((uint32_t)b1 >> 4);
    int32_t v = (int32_t)u;
    if (u & 0x80000u) {
        v -= 0x100000; /* sign-extend from bit 19 without shifting a negative value */
    }
    return v;
}

uint8_t ib_adxl355_read_cmd(uint8_t addr) { return (uint8_t)((addr << 1) | RW_READ); }

const uint8_t ib_adxl355_fifo_read_tx[1u + 3u * IB_ADXL355_FIFO_SIZE] = {(IB_ADXL355_REG_FIFO_DATA << 1) | RW_READ};

/* ---- raw register access ---- */

static int xfer(ib_adxl355_t *dev, const uint8_t *tx, uint8_t *rx, size_t len)
{
    int r = dev->bus->transfer(dev->bus->ctx, dev->cs, tx, rx, len);
    return r < 0 ? IB_ADXL355_ERR_BUS : IB_ADXL355_OK;
}

static void delay_us(const ib_adxl355_t *dev, uint32_t us)
{
    dev->bus->delay_us(dev->bus->ctx, us);
}

int ib_adxl355_read_regs(ib_adxl355_t *dev, uint8_t addr, uint8_t *buf, size_t n)
{
    uint8_t tx[REGS_MAX + 1u];
    uint8_t rx[REGS_MAX + 1u];
    if (dev == NULL || dev->bus == NULL || buf == NULL || n == 0 || n > REGS_MAX ||
        addr > 0x7Fu) {
        return IB_ADXL355_ERR_ARG;
    }
    memset(tx, 0, n + 1u);
    tx[0] = (uint8_t)((addr << 1) | RW_READ);
    int r = xfer(dev, tx, rx, n + 1u);
    if (r == IB_ADXL355_OK) {
        memcpy(buf, &rx[1], n);
    }
    return r;
}

int ib_adxl355_write_regs(ib_adxl355_t *dev, uint8_t addr, const uint8_t *buf, size_t n)
{
    uint8_t tx[REGS_MAX + 1u];
    if (dev == NULL || dev->bus == NULL || buf == NULL || n == 0 || n > REGS_MAX ||
        addr > 0x7Fu) {
        return IB_ADXL355_ERR_ARG;
    }
    tx[0] = (uint8_t)(addr << 1);
    memcpy(&tx[1], buf, n);
    return xfer(dev, tx, NULL, n + 1u);
}

static int read_reg(ib_adxl355_t *dev, uint8_t addr, uint8_t *val)
{
    return ib_adxl355_read_regs(dev, addr, val, 1);
}

static int write_reg(ib_adxl355_t *dev, uint8_t addr, uint8_t val)
{
    return ib_adxl355_write_regs(dev, addr, &val, 1);
}

/* ---- identification, reset ---- */

/* Identify the part from its ID registers against protocol/parts.toml (ADXL355, ADXL359). */
static int ids_ok(ib_adxl355_t *dev)
{
    static const uint16_t regs[4] = {IB_ADXL355_REG_DEVID_AD, IB_ADXL355_REG_DEVID_MST, IB_ADXL355_REG_PARTID,
                                     IB_ADXL355_REG_REVID};
    const uint16_t vals[4] = {dev->devid_ad, dev->devid_mst, dev->partid, dev->revid};
    dev->part = ib_part_identify(IB_PART_KIND_ACCEL_TRIAD, regs, vals, 4u);
    return dev->part != NULL;
}

static int read_ids(ib_adxl355_t *dev)
{
    uint8_t id[4];
    int r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_DEVID_AD, id, sizeof id);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    dev->devid_ad = id[0];
    dev->devid_mst = id[1];
    dev->partid = id[2];
    dev->revid = id[3];
    return IB_ADXL355_OK;
}

int ib_adxl355_check_id(ib_adxl355_t *dev)
{
    if (dev == NULL || dev->bus == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    int r = read_ids(dev);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    if (!ids_ok(dev) && dev->devid_ad == 0xFFu && dev->devid_mst == 0xFFu &&
        dev->partid == 0xFFu && dev->revid == 0xFFu) {
        /* Everything reads 0xFF: either the part is reloading its NVM after a reset,
         * or MISO floats high with no part. Wait (bounded), then look once more. */
        r = ib_adxl355_wait_nvm(dev);
        if (r == IB_ADXL355_ERR_BUS) {
            return r;
        }
        r = read_ids(dev);
        if (r != IB_ADXL355_OK) {
            return r;
        }
    }
    return ids_ok(dev) ? IB_ADXL355_OK : IB_ADXL355_ERR_ID;
}

int ib_adxl355_wait_nvm(ib_adxl355_t *dev)
{
    if (dev == NULL || dev->bus == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    for (uint32_t i = 0; i <= IB_ADXL355_NVM_POLL_MAX; i++) {
        uint8_t status;
        int r = read_reg(dev, IB_ADXL355_REG_STATUS, &status);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        if ((status & IB_ADXL355_STATUS_NVM_BUSY) == 0) {
            return IB_ADXL355_OK;
        }
        if (i < IB_ADXL355_NVM_POLL_MAX) {
            delay_us(dev, IB_ADXL355_NVM_POLL_US);
        }
    }
    return IB_ADXL355_ERR_NVM_TIMEOUT;
}

static void set_reset_config(ib_adxl355_t *dev)
{
    dev->range = IB_ADXL355_RANGE_2G;
    dev->odr_code = 0;
    dev->hpf_code = 0;
    dev->measuring = 0;
}

int ib_adxl355_soft_reset(ib_adxl355_t *dev)
{
    if (dev == NULL || dev->bus == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    int r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_SHADOW, dev->shadow, IB_ADXL355_SHADOW_LEN);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    for (uint32_t attempt = 0; attempt < IB_ADXL355_RESET_TRIES; attempt++) {
        uint8_t after[IB_ADXL355_SHADOW_LEN];
        r = write_reg(dev, IB_ADXL355_REG_RESET, IB_ADXL355_RESET_CODE);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        set_reset_config(dev);
        delay_us(dev, IB_ADXL355_NVM_POLL_US);
        r = ib_adxl355_wait_nvm(dev);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_SHADOW, after, IB_ADXL355_SHADOW_LEN);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        if (memcmp(after, dev->shadow, IB_ADXL355_SHADOW_LEN) == 0) {
            return IB_ADXL355_OK;
        }
    }
    return IB_ADXL355_ERR_SHADOW;
}

/* ---- power and configuration ---- */

int ib_adxl355_standby(ib_adxl355_t *dev)
{
    if (dev == NULL || dev->bus == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    int r = write_reg(dev, IB_ADXL355_REG_POWER_CTL, IB_ADXL355_POWER_STANDBY);
    if (r == IB_ADXL355_OK) {
        dev->measuring = 0;
    }
    return r;
}

int ib_adxl355_measure(ib_adxl355_t *dev)
{
    if (dev == NULL || dev->bus == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    int r = write_reg(dev, IB_ADXL355_REG_POWER_CTL, 0x00);
    if (r == IB_ADXL355_OK) {
        dev->measuring = 1;
    }
    return r;
}

/* Standby around a configuration change: enter, and leave again if it was measuring. */
static int enter_config(ib_adxl355_t *dev, uint8_t *was_measuring)
{
    *was_measuring = dev->measuring;
    return ib_adxl355_standby(dev);
}

static int leave_config(ib_adxl355_t *dev, uint8_t was_measuring, int r)
{
    if (r == IB_ADXL355_OK && was_measuring) {
        r = ib_adxl355_measure(dev);
    }
    return r;
}

static int config_valid(const ib_part_desc_t *part, const ib_adxl355_config_t *cfg)
{
    return ib_adxl355_part_lsb_per_g(part, cfg->range) != 0 && cfg->odr_code <= IB_ADXL355_ODR_CODE_MAX &&
           cfg->hpf_code <= IB_ADXL355_HPF_CODE_MAX;
}

/* Write RANGE (keeping bits 7:2) and FILTER; the part must be in standby. */
static int write_config(ib_adxl355_t *dev, const ib_adxl355_config_t *cfg)
{
    uint8_t range_reg;
    int r = read_reg(dev, IB_ADXL355_REG_RANGE, &range_reg);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    range_reg = (uint8_t)((range_reg & (uint8_t)~IB_ADXL355_RANGE_MASK) | cfg->range);
    r = write_reg(dev, IB_ADXL355_REG_RANGE, range_reg);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    r = write_reg(dev, IB_ADXL355_REG_FILTER, (uint8_t)((cfg->hpf_code << 4) | cfg->odr_code));
    if (r != IB_ADXL355_OK) {
        return r;
    }
    dev->range = cfg->range;
    dev->odr_code = cfg->odr_code;
    dev->hpf_code = cfg->hpf_code;
    return IB_ADXL355_OK;
}

int ib_adxl355_configure(ib_adxl355_t *dev, const ib_adxl355_config_t *cfg)
{
    if (dev == NULL || dev->bus == NULL || cfg == NULL || !config_valid(dev->part, cfg)) {
        return IB_ADXL355_ERR_ARG;
    }
    uint8_t was;
    int r = enter_config(dev, &was);
    if (r == IB_ADXL355_OK) {
        r = write_config(dev, cfg);
    }
    return leave_config(dev, was, r);
}

int ib_adxl355_set_range(ib_adxl355_t *dev, uint8_t range)
{
    if (dev == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    ib_adxl355_config_t cfg = {range, dev->odr_code, dev->hpf_code};
    return ib_adxl355_configure(dev, &cfg);
}

int ib_adxl355_set_filter(ib_adxl355_t *dev, uint8_t odr_code, uint8_t hpf_code)
{
    if (dev == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    ib_adxl355_config_t cfg = {dev->range, odr_code, hpf_code};
    return ib_adxl355_configure(dev, &cfg);
}

int ib_adxl355_set_offset(ib_adxl355_t *dev, const int16_t offset[3])
{
    if (dev == NULL || dev->bus == NULL || offset == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    uint8_t buf[6];
    for (int i = 0; i < 3; i++) {
        uint16_t u = (uint16_t)offset[i];
        buf[2 * i] = (uint8_t)(u >> 8);
        buf[2 * i + 1] = (uint8_t)(u & 0xFFu);
    }
    uint8_t was;
    int r = enter_config(dev, &was);
    if (r == IB_ADXL355_OK) {
        r = ib_adxl355_write_regs(dev, IB_ADXL355_REG_OFFSET_X_H, buf, sizeof buf);
    }
    return leave_config(dev, was, r);
}

int ib_adxl355_get_offset(ib_adxl355_t *dev, int16_t offset[3])
{
    if (offset == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    uint8_t buf[6];
    int r = ib_adxl355_read_regs(dev, IB_ADXL355_REG_OFFSET_X_H, buf, sizeof buf);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    for (int i = 0; i < 3; i++) {
        uint16_t u = (uint16_t)(((uint16_t)buf[2 * i] << 8) | buf[2 * i + 1]);
        offset[i] = (int16_t)(u >= 0x8000u ? (int32_t)u - 0x10000 : (int32_t)u);
    }
    return IB_ADXL355_OK;
}

int ib_adxl355_init(ib_adxl355_t *dev, const ib_spi_bus_t *bus, uint8_t cs,
                    const ib_adxl355_config_t *cfg)
{
    static const ib_adxl355_config_t def = IB_ADXL355_CONFIG_DEFAULT;
    if (dev == NULL || bus == NULL || bus->transfer == NULL || bus->delay_us == NULL) {
        return IB_ADXL355_ERR_ARG;
    }
    if (cfg == NULL) {
        cfg = &def;
    }
    if (!config_valid(NULL, cfg)) { /* range codes 1..3 on every part of the family */
        return IB_ADXL355_ERR_ARG;
    }
    memset(dev, 0, sizeof *dev);
    dev->bus = bus;
    dev->cs = cs;
    set_reset_config(dev);

    int r = ib_adxl355_check_id(dev);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    r = ib_adxl355_soft_reset(dev);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    r = ib_adxl355_check_id(dev);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    r = ib_adxl355_configure(dev, cfg); /* in standby after the reset */
    if (r != IB_ADXL355_OK) {
        return r;
    }
    return ib_adxl355_measure(dev);
}

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
        delay_us(dev, poll_us);
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
    int r = xfer(dev, tx, rx, len);
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
        r = write_config(dev, &st_cfg);
    }
    if (r == IB_ADXL355_OK) {
        r = write_reg(dev, IB_ADXL355_REG_SELF_TEST, IB_ADXL355_SELF_TEST_ST1);
    }
    if (r == IB_ADXL355_OK) {
        r = ib_adxl355_measure(dev);
    }
    if (r == IB_ADXL355_OK) {
        r = st_phase(dev, base);
    }
    if (r == IB_ADXL355_OK) {
        r = write_reg(dev, IB_ADXL355_REG_SELF_TEST,
                      IB_ADXL355_SELF_TEST_ST1 | IB_ADXL355_SELF_TEST_ST2);
    }
    if (r == IB_ADXL355_OK) {
        r = st_phase(dev, forced);
    }

    /* Restore whatever happened above (a bus error may make this fail too; the first
     * error is the one reported). */
    int r2 = write_reg(dev, IB_ADXL355_REG_SELF_TEST, 0x00);
    if (r2 == IB_ADXL355_OK) {
        r2 = ib_adxl355_standby(dev);
    }
    if (r2 == IB_ADXL355_OK) {
        r2 = write_config(dev, &saved);
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
