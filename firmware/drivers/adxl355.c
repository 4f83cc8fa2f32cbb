/* adxl355.c - ADXL355-family driver (ADXL355, ADXL359: protocol/parts.toml), its register half:
 * access, identification, reset, configuration; samples, FIFO and self-test in adxl355_data.c.
 * See adxl355.h. Integer math only. */
#include "adxl355_priv.h"

#include <string.h>


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

int adxl355_xfer(ib_adxl355_t *dev, const uint8_t *tx, uint8_t *rx, size_t len)
{
    int r = dev->bus->transfer(dev->bus->ctx, dev->cs, tx, rx, len);
    return r < 0 ? IB_ADXL355_ERR_BUS : IB_ADXL355_OK;
}

void adxl355_delay_us(const ib_adxl355_t *dev, uint32_t us)
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
    int r = adxl355_xfer(dev, tx, rx, n + 1u);
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
    return adxl355_xfer(dev, tx, NULL, n + 1u);
}

static int read_reg(ib_adxl355_t *dev, uint8_t addr, uint8_t *val)
{
    return ib_adxl355_read_regs(dev, addr, val, 1);
}

int adxl355_write_reg(ib_adxl355_t *dev, uint8_t addr, uint8_t val)
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
            adxl355_delay_us(dev, IB_ADXL355_NVM_POLL_US);
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
        r = adxl355_write_reg(dev, IB_ADXL355_REG_RESET, IB_ADXL355_RESET_CODE);
        if (r != IB_ADXL355_OK) {
            return r;
        }
        set_reset_config(dev);
        adxl355_delay_us(dev, IB_ADXL355_NVM_POLL_US);
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
    int r = adxl355_write_reg(dev, IB_ADXL355_REG_POWER_CTL, IB_ADXL355_POWER_STANDBY);
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
    int r = adxl355_write_reg(dev, IB_ADXL355_REG_POWER_CTL, 0x00);
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
int adxl355_write_config(ib_adxl355_t *dev, const ib_adxl355_config_t *cfg)
{
    uint8_t range_reg;
    int r = read_reg(dev, IB_ADXL355_REG_RANGE, &range_reg);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    range_reg = (uint8_t)((range_reg & (uint8_t)~IB_ADXL355_RANGE_MASK) | cfg->range);
    r = adxl355_write_reg(dev, IB_ADXL355_REG_RANGE, range_reg);
    if (r != IB_ADXL355_OK) {
        return r;
    }
    r = adxl355_write_reg(dev, IB_ADXL355_REG_FILTER, (uint8_t)((cfg->hpf_code << 4) | cfg->odr_code));
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
        r = adxl355_write_config(dev, cfg);
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
