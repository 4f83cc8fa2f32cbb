/* adxrs450.c - ADXRS450 gyro driver; see adxrs450.h for the protocol and the choices. */
#include "adxrs450.h"

#include <stddef.h>

/* ---- pure helpers ---- */

/* 1 when `w` has an odd number of one bits. */
static int parity_odd(uint32_t w)
{
    w ^= w >> 16;
    w ^= w >> 8;
    w ^= w >> 4;
    return (int)((0x6996u >> (w & 0xFu)) & 1u);
}

uint32_t ib_adxrs450_with_parity(uint32_t word)
{
    word &= ~1u;
    return parity_odd(word) ? word : (word | 1u);
}

uint32_t ib_adxrs450_cmd_sensor_data(int chk)
{
    uint32_t w = IB_ADXRS450_CMD_SENSOR_DATA;
    if (chk) {
        w |= IB_ADXRS450_CMD_CHK;
    }
    return ib_adxrs450_with_parity(w);
}

uint32_t ib_adxrs450_cmd_read(uint16_t addr)
{
    return ib_adxrs450_with_parity(IB_ADXRS450_CMD_READ |
                                   ((uint32_t)(addr & IB_ADXRS450_ADDR_MAX) << 17));
}

uint32_t ib_adxrs450_cmd_write(uint16_t addr, uint16_t data)
{
    return ib_adxrs450_with_parity(IB_ADXRS450_CMD_WRITE |
                                   ((uint32_t)(addr & IB_ADXRS450_ADDR_MAX) << 17) |
                                   ((uint32_t)data << 1));
}

int ib_adxrs450_response_parity_ok(uint32_t word)
{
    return parity_odd(word >> 16) && parity_odd(word);
}

static uint8_t resp_st(uint32_t w) { return (uint8_t)((w >> IB_ADXRS450_RESP_ST_SHIFT) & 3u); }

static uint8_t resp_type(uint32_t w) { return (uint8_t)(w >> IB_ADXRS450_RESP_TYPE_SHIFT); }

/* MISO stuck low (no part, or no pull-up) or stuck high. */
static int word_stuck(uint32_t w) { return w == 0x00000000u || w == 0xFFFFFFFFu; }

void ib_adxrs450_decode_sensor(uint32_t word, ib_adxrs450_sample_t *s)
{
    uint16_t rate = (uint16_t)((word >> 10) & 0xFFFFu);
    /* two's complement without relying on implementation-defined conversions */
    s->rate_counts = (rate & 0x8000u) ? (int16_t)(-(int32_t)(0x10000u - rate))
                                      : (int16_t)rate;
    s->st = resp_st(word);
    s->faults = (uint8_t)(word & IB_ADXRS450_FAULT_LOW_MASK);
    s->parity_error = (uint8_t)(ib_adxrs450_response_parity_ok(word) ? 0u : 1u);
    s->good = (s->parity_error == 0u && s->st == IB_ADXRS450_ST_VALID && s->faults == 0u)
                  ? 1u
                  : 0u;
    s->raw = word;
}

int32_t ib_adxrs450_temp_centi_c(int16_t raw10)
{
    return (int32_t)IB_ADXRS450_TEMP_OFFSET_C * 100 +
           (int32_t)raw10 * (100 / IB_ADXRS450_TEMP_LSB_PER_C);
}

/* ---- bus access ---- */

/* One chip-select frame: send `cmd`, return what came back on MISO in *resp. */
static ib_adxrs450_err_t frame(ib_adxrs450_t *dev, uint32_t cmd, uint32_t *resp)
{
    uint8_t tx[4];
    uint8_t rx[4] = {0, 0, 0, 0};
    tx[0] = (uint8_t)(cmd >> 24);
    tx[1] = (uint8_t)(cmd >> 16);
    tx[2] = (uint8_t)(cmd >> 8);
    tx[3] = (uint8_t)cmd;
    if (dev->bus->transfer(dev->bus->ctx, dev->cs, tx, rx, sizeof tx) != 0) {
        dev->bus_errors++;
        return IB_ADXRS450_ERR_BUS;
    }
    *resp = ((uint32_t)rx[0] << 24) | ((uint32_t)rx[1] << 16) | ((uint32_t)rx[2] << 8) |
            (uint32_t)rx[3];
    return IB_ADXRS450_OK;
}

/* A reply the driver does not use (it answers the previous operation's fetch frame):
 * only its fault bits are kept, so that a fault reported there is not lost entirely. */
static void note_discarded(ib_adxrs450_t *dev, uint32_t w)
{
    if (!word_stuck(w) && ib_adxrs450_response_parity_ok(w) &&
        resp_st(w) != IB_ADXRS450_ST_REGISTER) {
        dev->faults_seen |= (uint16_t)(w & IB_ADXRS450_FAULT_LOW_MASK);
    }
}

/* Integrity checks common to every evaluated reply. */
static ib_adxrs450_err_t check_word(ib_adxrs450_t *dev, uint32_t w)
{
    dev->last_response = w;
    if (word_stuck(w)) {
        return IB_ADXRS450_ERR_MISSING;
    }
    if (!ib_adxrs450_response_parity_ok(w)) {
        dev->parity_errors++;
        return IB_ADXRS450_ERR_PARITY;
    }
    return IB_ADXRS450_OK;
}

/* The second frame of a register operation: send `cmd`, and evaluate the reply it
 * brings back (the answer to the previous frame's command), which must be a register
 * reply of `type`; its data field goes to *data. */
/* A register reply of `type`: checks as reg_fetch does; its data field goes to *data. */
static ib_adxrs450_err_t check_reg_reply(ib_adxrs450_t *dev, uint32_t w, uint8_t type, uint16_t *data)
{
    ib_adxrs450_err_t e = check_word(dev, w);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    if (resp_st(w) != IB_ADXRS450_ST_REGISTER) {
        return IB_ADXRS450_ERR_BAD_RESPONSE;
    }
    if (resp_type(w) == IB_ADXRS450_RESP_TYPE_ERROR) {
        dev->last_rw_error = (uint8_t)((w >> 16) & 7u);
        return IB_ADXRS450_ERR_BAD_RESPONSE;
    }
    if (resp_type(w) != type) {
        return IB_ADXRS450_ERR_BAD_RESPONSE;
    }
    *data = (uint16_t)((w >> 5) & 0xFFFFu);
    return IB_ADXRS450_OK;
}

static ib_adxrs450_err_t reg_fetch(ib_adxrs450_t *dev, uint32_t cmd, uint8_t type,
                                   uint16_t *data)
{
    uint32_t w = 0;
    ib_adxrs450_err_t e = frame(dev, cmd, &w);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    return check_reg_reply(dev, w, type, data);
}

/* Two frames: cmd1 (its reply arrives in the second frame), then cmd2 as the fetch frame.
 * The reply received during the first frame belongs to the previous operation. */
static ib_adxrs450_err_t reg_transaction(ib_adxrs450_t *dev, uint32_t cmd1, uint32_t cmd2,
                                         uint8_t type, uint16_t *data)
{
    uint32_t w0 = 0;
    ib_adxrs450_err_t e = frame(dev, cmd1, &w0);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    note_discarded(dev, w0);
    return reg_fetch(dev, cmd2, type, data);
}

static int dev_ok(const ib_adxrs450_t *dev)
{
    return dev != NULL && dev->bus != NULL && dev->bus->transfer != NULL;
}

/* ---- operations ---- */

ib_adxrs450_err_t ib_adxrs450_read_reg(ib_adxrs450_t *dev, uint16_t addr, uint16_t *value)
{
    if (!dev_ok(dev) || value == NULL || addr > IB_ADXRS450_ADDR_MAX) {
        return IB_ADXRS450_ERR_ARG;
    }
    uint32_t cmd = ib_adxrs450_cmd_read(addr);
    return reg_transaction(dev, cmd, cmd, IB_ADXRS450_RESP_TYPE_READ, value);
}

ib_adxrs450_err_t ib_adxrs450_write_reg(ib_adxrs450_t *dev, uint16_t addr, uint16_t value)
{
    if (!dev_ok(dev) || addr > IB_ADXRS450_ADDR_MAX) {
        return IB_ADXRS450_ERR_ARG;
    }
    uint16_t echo = 0;
    ib_adxrs450_err_t e = reg_transaction(dev, ib_adxrs450_cmd_write(addr, value),
                                          ib_adxrs450_cmd_read(addr),
                                          IB_ADXRS450_RESP_TYPE_WRITE, &echo);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    return echo == value ? IB_ADXRS450_OK : IB_ADXRS450_ERR_BAD_RESPONSE;
}

ib_adxrs450_err_t ib_adxrs450_read_fault(ib_adxrs450_t *dev, uint16_t *fault)
{
    if (fault == NULL) {
        return IB_ADXRS450_ERR_ARG;
    }
    uint16_t v = 0;
    ib_adxrs450_err_t e = ib_adxrs450_read_reg(dev, IB_ADXRS450_REG_FAULT, &v);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    *fault = (uint16_t)(v & IB_ADXRS450_FAULT_ALL_MASK);
    dev->faults_seen |= *fault;
    return IB_ADXRS450_OK;
}

static int16_t tem_raw10(uint16_t v)
{
    int32_t t = (int32_t)((v >> 6) & 0x3FFu);
    if (t & 0x200) {
        t -= 0x400;
    }
    return (int16_t)t;
}

ib_adxrs450_err_t ib_adxrs450_read_temp(ib_adxrs450_t *dev, int16_t *raw10)
{
    if (raw10 == NULL) {
        return IB_ADXRS450_ERR_ARG;
    }
    uint16_t v = 0;
    ib_adxrs450_err_t e = ib_adxrs450_read_reg(dev, IB_ADXRS450_REG_TEM, &v);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    *raw10 = tem_raw10(v);
    return IB_ADXRS450_OK;
}

void ib_adxrs450_clear_faults_seen(ib_adxrs450_t *dev)
{
    if (dev != NULL) {
        dev->faults_seen = 0;
    }
}

ib_adxrs450_err_t ib_adxrs450_rate_from_reply(ib_adxrs450_t *dev, uint32_t w, ib_adxrs450_sample_t *s)
{
    ib_adxrs450_decode_sensor(w, s);
    /* check_word's checks, with the parity the decode just worked out (not a second time:
     * this runs for every gyro every sample) */
    dev->last_response = w;
    if (word_stuck(w)) {
        return IB_ADXRS450_ERR_MISSING;
    }
    if (s->parity_error) {
        dev->parity_errors++;
        return IB_ADXRS450_ERR_PARITY;
    }
    if (s->st == IB_ADXRS450_ST_REGISTER || resp_type(w) != 0u) {
        s->good = 0; /* a register/error reply, or an SQ echo we did not send */
        return IB_ADXRS450_ERR_BAD_RESPONSE;
    }
    dev->faults_seen |= s->faults;
    return s->good ? IB_ADXRS450_OK : IB_ADXRS450_ERR_FAULT;
}

static void cmd_bytes(uint32_t cmd, uint8_t tx[4])
{
    tx[0] = (uint8_t)(cmd >> 24);
    tx[1] = (uint8_t)(cmd >> 16);
    tx[2] = (uint8_t)(cmd >> 8);
    tx[3] = (uint8_t)cmd;
}

void ib_adxrs450_temp_cmd_bytes(uint8_t tx[4]) { cmd_bytes(ib_adxrs450_cmd_read(IB_ADXRS450_REG_TEM), tx); }

ib_adxrs450_err_t ib_adxrs450_temp_from_reply(ib_adxrs450_t *dev, uint32_t w, int16_t *raw10)
{
    uint16_t v = 0;
    ib_adxrs450_err_t e = check_reg_reply(dev, w, IB_ADXRS450_RESP_TYPE_READ, &v);
    if (e == IB_ADXRS450_OK) {
        *raw10 = tem_raw10(v);
    }
    return e;
}

ib_adxrs450_err_t ib_adxrs450_prime_rate(ib_adxrs450_t *dev)
{
    if (!dev_ok(dev)) {
        return IB_ADXRS450_ERR_ARG;
    }
    uint32_t w = 0;
    ib_adxrs450_err_t e = frame(dev, ib_adxrs450_cmd_sensor_data(0), &w);
    if (e == IB_ADXRS450_OK) {
        note_discarded(dev, w);
    }
    return e;
}

ib_adxrs450_err_t ib_adxrs450_rate_from_frames(ib_adxrs450_t *dev, uint32_t w0, uint32_t w,
                                               ib_adxrs450_sample_t *s)
{
    note_discarded(dev, w0);
    return ib_adxrs450_rate_from_reply(dev, w, s);
}

void ib_adxrs450_rate_cmd_bytes(uint8_t tx[4]) { cmd_bytes(ib_adxrs450_cmd_sensor_data(0), tx); }

uint32_t ib_adxrs450_word(const uint8_t rx[4])
{
    return ((uint32_t)rx[0] << 24) | ((uint32_t)rx[1] << 16) | ((uint32_t)rx[2] << 8) | (uint32_t)rx[3];
}

void ib_adxrs450_note_bus_error(ib_adxrs450_t *dev) { dev->bus_errors++; }

ib_adxrs450_err_t ib_adxrs450_read_rate(ib_adxrs450_t *dev, ib_adxrs450_sample_t *s)
{
    if (!dev_ok(dev) || s == NULL) {
        return IB_ADXRS450_ERR_ARG;
    }
    const uint32_t cmd = ib_adxrs450_cmd_sensor_data(0);
    uint32_t w0 = 0, w = 0;
    s->good = 0;
    ib_adxrs450_err_t e = frame(dev, cmd, &w0);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    e = frame(dev, cmd, &w);
    if (e != IB_ADXRS450_OK) {
        note_discarded(dev, w0);
        return e;
    }
    return ib_adxrs450_rate_from_frames(dev, w0, w, s);
}

/* The CHK-phase replies of start-up steps 3 and 4. */
static ib_adxrs450_err_t check_chk_reply(ib_adxrs450_t *dev, uint32_t w)
{
    ib_adxrs450_err_t e = check_word(dev, w);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    if (resp_st(w) != IB_ADXRS450_ST_SELFTEST ||
        (w & IB_ADXRS450_FAULT_LOW_MASK) != IB_ADXRS450_FAULT_LOW_MASK) {
        return IB_ADXRS450_ERR_CHK_FAILED;
    }
    return IB_ADXRS450_OK;
}

ib_adxrs450_err_t ib_adxrs450_init(ib_adxrs450_t *dev, const ib_spi_bus_t *bus, uint8_t cs)
{
    if (dev == NULL || bus == NULL || bus->transfer == NULL || bus->delay_us == NULL) {
        return IB_ADXRS450_ERR_ARG;
    }
    const ib_adxrs450_t zero = {0};
    *dev = zero;
    dev->bus = bus;
    dev->cs = cs;

    const uint32_t sd = ib_adxrs450_cmd_sensor_data(0);
    uint32_t w[5] = {0, 0, 0, 0, 0};
    ib_adxrs450_err_t e;

    /* steps 1..4 of sensors.md 2.7 */
    bus->delay_us(bus->ctx, IB_ADXRS450_POWERON_DELAY_US);
    e = frame(dev, ib_adxrs450_cmd_sensor_data(1), &w[0]);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    dev->powerup_word = w[0];
    dev->powerup_word_ok = (w[0] == IB_ADXRS450_POWERUP_WORD) ? 1u : 0u;
    for (int i = 1; i < 4; i++) {
        bus->delay_us(bus->ctx, IB_ADXRS450_STARTUP_STEP_US);
        e = frame(dev, sd, &w[i]);
        if (e != IB_ADXRS450_OK) {
            return e;
        }
    }
    if (word_stuck(w[2]) && word_stuck(w[3])) {
        dev->last_response = w[3];
        return IB_ADXRS450_ERR_MISSING;
    }
    dev->chk_faults = (uint8_t)(w[2] & w[3] & IB_ADXRS450_FAULT_LOW_MASK);
    e = check_chk_reply(dev, w[2]);
    if (e == IB_ADXRS450_OK) {
        e = check_chk_reply(dev, w[3]);
    }
    if (e != IB_ADXRS450_OK) {
        return e;
    }

    /* step 5: read FAULT; its first frame returns the reply to step 4 (a clean sample) */
    bus->delay_us(bus->ctx, IB_ADXRS450_STARTUP_STEP_US);
    const uint32_t rd_fault = ib_adxrs450_cmd_read(IB_ADXRS450_REG_FAULT);
    e = frame(dev, rd_fault, &w[4]);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    e = check_word(dev, w[4]);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    ib_adxrs450_sample_t s;
    ib_adxrs450_decode_sensor(w[4], &s);
    dev->faults_seen |= s.faults;
    uint16_t fault = 0;
    e = reg_fetch(dev, rd_fault, IB_ADXRS450_RESP_TYPE_READ, &fault);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    dev->startup_fault = fault;
    dev->faults_seen |= (uint16_t)(fault & IB_ADXRS450_FAULT_ALL_MASK);
    if (!s.good || resp_type(w[4]) != 0u || (fault & 0x0FFFu) != 0u) {
        return IB_ADXRS450_ERR_FAULT;
    }

    /* steps 6, 7: identification */
    e = ib_adxrs450_read_reg(dev, IB_ADXRS450_REG_PID, &dev->pid);
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    /* the part from its PID (protocol/parts.toml: ADXRS453 0x5202, else ADXRS450 0x52xx) */
    static const uint16_t pid_reg = IB_ADXRS450_REG_PID;
    dev->part = ib_part_identify(IB_PART_KIND_GYRO_AXIS, &pid_reg, &dev->pid, 1u);
    if (dev->part == NULL) {
        return IB_ADXRS450_ERR_BAD_PID;
    }
    uint16_t snh = 0, snl = 0;
    e = ib_adxrs450_read_reg(dev, IB_ADXRS450_REG_SNH, &snh);
    if (e == IB_ADXRS450_OK) {
        e = ib_adxrs450_read_reg(dev, IB_ADXRS450_REG_SNL, &snl);
    }
    if (e != IB_ADXRS450_OK) {
        return e;
    }
    dev->serial = ((uint32_t)snh << 16) | snl;
    dev->ready = 1;
    return IB_ADXRS450_OK;
}
