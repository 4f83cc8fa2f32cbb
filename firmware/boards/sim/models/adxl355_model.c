/* adxl355_model.c - register-level ADXL355 model; see adxl355_model.h */
#include "adxl355_model.h"

#include <math.h>
#include <string.h>

#define PI_D 3.14159265358979323846

/* Register addresses (sensors.md 1.2) */
enum {
    R_DEVID_AD = 0x00,
    R_REVID = 0x03,
    R_STATUS = 0x04,
    R_FIFO_ENTRIES = 0x05,
    R_TEMP2 = 0x06,
    R_TEMP1 = 0x07,
    R_XDATA3 = 0x08,
    R_ZDATA1 = 0x10,
    R_FIFO_DATA = 0x11,
    R_OFFSET_X_H = 0x1E,
    R_OFFSET_Z_L = 0x23,
    R_ACT_EN = 0x24,
    R_ACT_THRESH_H = 0x25,
    R_ACT_THRESH_L = 0x26,
    R_ACT_COUNT = 0x27,
    R_FILTER = 0x28,
    R_FIFO_SAMPLES = 0x29,
    R_INT_MAP = 0x2A,
    R_SYNC = 0x2B,
    R_RANGE = 0x2C,
    R_POWER_CTL = 0x2D,
    R_SELF_TEST = 0x2E,
    R_RESET = 0x2F,
    R_SHADOW = 0x50,
    R_SHADOW_END = 0x54
};

#define ST_DATA_RDY 0x01u
#define ST_FIFO_FULL 0x02u
#define ST_FIFO_OVR 0x04u
#define ST_ACTIVITY 0x08u
#define PWR_STANDBY 0x01u
#define PWR_TEMP_OFF 0x02u
#define FIFO_X_FLAG (1u << 20)
#define DATA_MAX 524287
#define DATA_MIN (-524288)

/* HPF corner = k * ODR (sensors.md 1.6); code 7 reserved -> off */
static const double hpf_k[8] = {0.0, 24.7e-4, 6.2084e-4, 1.5545e-4, 0.3862e-4, 0.0954e-4,
                                0.0238e-4, 0.0};

static const uint8_t factory_shadow[5] = {0x3C, 0xA7, 0x15, 0xD2, 0x6B};

/* ---- truth ---- */

void adxl355_model_default_truth(adxl355_truth_t *truth)
{
    memset(truth, 0, sizeof *truth);
    for (int i = 0; i < 3; i++) {
        truth->m[i][i] = 1.0;
        truth->noise_n[i] = ADXL355_MODEL_NOISE_MPS2_RTHZ;
        truth->rw_k[i] = 1e-6 * SIM_G0_MPS2;
    }
}

static double uniform_pm(sim_rng_t *rng, double half)
{
    return (2.0 * sim_rng_uniform(rng) - 1.0) * half;
}

void adxl355_model_random_truth(adxl355_truth_t *truth, sim_rng_t *rng)
{
    const double g0 = SIM_G0_MPS2;
    memset(truth, 0, sizeof *truth);
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            truth->m[i][j] = (i == j) ? 1.0 + uniform_pm(rng, 0.01) : uniform_pm(rng, 0.01);
        }
        truth->bias_mps2[i] = uniform_pm(rng, 25e-3 * g0);
        truth->noise_n[i] = ADXL355_MODEL_NOISE_MPS2_RTHZ * (1.0 + uniform_pm(rng, 0.1));
        truth->rw_k[i] = (0.5e-6 + 1.5e-6 * sim_rng_uniform(rng)) * g0;
        truth->bias_tc[i] = uniform_pm(rng, 0.1e-3 * g0);
        truth->scale_tc[i] = uniform_pm(rng, 1e-4);
    }
    sim_rng_t tr = *rng; /* a copy: rng itself does not advance (older draws stay the same) */
    sim_rng_seed(&tr, sim_rng_u64(&tr) ^ 0x5448524D414Cull); /* "THRMAL" */
    for (int i = 0; i < 3; i++) {
        truth->bias_tc2[i] = uniform_pm(&tr, 2e-7 * g0);
        truth->bias_tc3[i] = uniform_pm(&tr, 2e-9 * g0);
        truth->hysteresis[i] = uniform_pm(&tr, 20e-6 * g0);
        truth->hysteresis_width_c[i] = 1.0 + 3.0 * sim_rng_uniform(&tr);
    }
}

double adxl355_truth_thermal_bias(const adxl355_truth_t *t, int i, double temp_c, double h)
{
    const double d = temp_c - 25.0;
    return t->bias_tc[i] * d + d * d * (t->bias_tc2[i] + t->bias_tc3[i] * d) + t->hysteresis[i] * h;
}

/* Play operator (backlash) of dead band w on the die temperature; see the header. */
static void hysteresis_update(adxl355_model_t *m, double temp_c)
{
    for (int i = 0; i < 3; i++) {
        double r = 0.5 * m->truth.hysteresis_width_c[i];
        if (!m->hyst_started) {
            m->hyst_y[i] = temp_c;
            m->hyst_h[i] = 0.0;
            continue;
        }
        if (r > 0.0) {
            double y = m->hyst_y[i];
            y = y < temp_c - r ? temp_c - r : (y > temp_c + r ? temp_c + r : y);
            m->hyst_y[i] = y;
            m->hyst_h[i] = (temp_c - y) / r;
        } else {
            if (temp_c != m->hyst_y[i]) {
                m->hyst_h[i] = temp_c > m->hyst_y[i] ? 1.0 : -1.0;
            }
            m->hyst_y[i] = temp_c;
        }
    }
    m->hyst_started = 1;
}

void adxl355_model_set_truth(adxl355_model_t *m, const adxl355_truth_t *truth)
{
    m->truth = *truth;
}

void adxl355_model_get_truth(const adxl355_model_t *m, adxl355_truth_t *truth)
{
    *truth = m->truth;
}

void adxl355_model_true_bias(const adxl355_model_t *m, double bias_mps2[3])
{
    for (int i = 0; i < 3; i++) {
        bias_mps2[i] = m->truth.bias_mps2[i] +
                       adxl355_truth_thermal_bias(&m->truth, i, m->temp_c, m->hyst_h[i]) +
                       m->rw_bias[i];
    }
}

/* ---- registers ---- */

static void reset_registers(adxl355_model_t *m)
{
    memset(m->reg, 0, sizeof m->reg);
    m->reg[R_ACT_COUNT] = 0x01;
    m->reg[R_FIFO_SAMPLES] = 0x60;
    m->reg[R_RANGE] = 0x81;
    m->reg[R_POWER_CTL] = 0x01;
    m->measuring = 0;
    m->fifo_head = 0;
    m->fifo_count = 0;
    m->act_run = 0;
    m->hpf_primed = 0;
    m->odr_active = 0;
}

void adxl355_model_init(adxl355_model_t *m, uint64_t seed)
{
    memset(m, 0, sizeof *m);
    adxl355_model_default_truth(&m->truth);
    m->st_force_g[0] = 0.3;
    m->st_force_g[1] = 0.3;
    m->st_force_g[2] = 1.5;
    m->id[0] = 0xAD;
    m->id[1] = 0x1D;
    m->id[2] = 0xED;
    m->id[3] = 0x01;
    memcpy(m->shadow, factory_shadow, sizeof m->shadow);
    m->reset_busy_us = ADXL355_MODEL_RESET_BUSY_US;
    m->temp_c = 25.0;
    sim_rng_seed(&m->rng, seed);
    reset_registers(m);
}

static unsigned odr_code(uint8_t filter)
{
    unsigned c = filter & 0x0Fu;
    return c > 10u ? 10u : c;
}

uint32_t adxl355_model_period_us(const adxl355_model_t *m)
{
    unsigned c = m->measuring ? m->odr_active : odr_code(m->reg[R_FILTER]);
    return 250u << c;
}

void adxl355_model_set_part(adxl355_model_t *m, const ib_part_desc_t *part)
{
    m->part = part;
    for (size_t i = 0; part != NULL && i < part->n_id_regs; i++) {
        if (part->id_regs[i].reg < 4u) {
            m->id[part->id_regs[i].reg] = (uint8_t)part->id_regs[i].value;
        }
    }
    if (part != NULL && part->part != IB_PART_ADXL355) { /* the ADXL355 keeps its representative noise */
        for (int i = 0; i < 3; i++) {
            m->truth.noise_n[i] = part->noise_per_rthz * SIM_G0_MPS2;
        }
    }
}

double adxl355_model_lsb_per_g(const adxl355_model_t *m)
{
    if (m->part != NULL) {
        unsigned code = m->reg[R_RANGE] & 0x03u;
        for (size_t i = 0; i < m->part->n_ranges; i++) {
            if (m->part->ranges[i].code == (code ? code : 1u)) {
                return m->part->ranges[i].lsb_per_unit;
            }
        }
    }
    switch (m->reg[R_RANGE] & 0x03u) {
    case 2:
        return 128000.0;
    case 3:
        return 64000.0;
    default: /* 1, and 00 (not used [U]) */
        return 256000.0;
    }
}

static int busy(const adxl355_model_t *m) { return m->t_us < m->busy_until_us; }

static void soft_reset(adxl355_model_t *m)
{
    reset_registers(m);
    m->busy_until_us = m->t_us + m->reset_busy_us;
    if (m->fault.shadow_corrupt) {
        m->shadow[2] = (uint8_t)(m->shadow[2] + 1u);
    }
}

static void start_measuring(adxl355_model_t *m)
{
    m->measuring = 1;
    m->odr_active = (uint8_t)odr_code(m->reg[R_FILTER]);
    m->next_sample_us = m->t_us + (250u << m->odr_active);
    m->hpf_primed = 0;
    m->act_run = 0;
}

/* Returns 1 when the write started a soft reset. */
static int write_reg(adxl355_model_t *m, uint8_t addr, uint8_t v)
{
    if (addr >= R_OFFSET_X_H && addr <= R_OFFSET_Z_L) {
        m->reg[addr] = v;
        return 0;
    }
    switch (addr) {
    case R_ACT_THRESH_H:
    case R_ACT_THRESH_L:
    case R_ACT_COUNT:
    case R_INT_MAP:
        m->reg[addr] = v;
        break;
    case R_ACT_EN:
    case R_SYNC:
        m->reg[addr] = (uint8_t)(v & 0x07u);
        break;
    case R_FILTER: /* the ODR/LPF in effect is latched when measurement starts */
    case R_FIFO_SAMPLES:
        m->reg[addr] = (uint8_t)(v & 0x7Fu);
        break;
    case R_RANGE:
        m->reg[addr] = (uint8_t)(v & 0xC3u);
        break;
    case R_POWER_CTL:
        m->reg[addr] = (uint8_t)(v & 0x07u);
        if ((v & PWR_STANDBY) == 0) {
            if (!m->measuring) {
                start_measuring(m);
            }
        } else {
            m->measuring = 0;
        }
        break;
    case R_SELF_TEST:
        m->reg[addr] = (uint8_t)(v & 0x03u);
        break;
    case R_RESET:
        if (v == 0x52u) {
            soft_reset(m);
            return 1;
        }
        break;
    default: /* read-only or unmapped: ignored */
        break;
    }
    return 0;
}

static unsigned fifo_watermark(const adxl355_model_t *m)
{
    unsigned w = m->reg[R_FIFO_SAMPLES];
    return (w == 0u || w > ADXL355_MODEL_FIFO_SIZE) ? ADXL355_MODEL_FIFO_SIZE : w;
}

static uint8_t read_reg(adxl355_model_t *m, uint8_t addr)
{
    if (addr <= R_REVID) {
        return m->id[addr];
    }
    if (addr == R_STATUS) {
        uint8_t s = m->reg[R_STATUS];
        if (m->fifo_count >= fifo_watermark(m)) {
            s |= ST_FIFO_FULL;
        }
        m->reg[R_STATUS] = (uint8_t)(m->reg[R_STATUS] & ~(ST_DATA_RDY | ST_FIFO_OVR | ST_ACTIVITY));
        return s;
    }
    if (addr == R_FIFO_ENTRIES) {
        return (uint8_t)m->fifo_count;
    }
    if ((addr >= R_TEMP2 && addr <= R_ZDATA1) || (addr >= R_OFFSET_X_H && addr <= R_SELF_TEST)) {
        return m->reg[addr];
    }
    if (addr >= R_SHADOW && addr <= R_SHADOW_END) {
        return m->shadow[addr - R_SHADOW];
    }
    return 0x00; /* FIFO_DATA handled by the caller; RESET and unmapped read 0 */
}

static void fifo_push(adxl355_model_t *m, uint32_t e)
{
    if (m->fifo_count >= ADXL355_MODEL_FIFO_SIZE) {
        m->reg[R_STATUS] |= ST_FIFO_OVR;
        return;
    }
    m->fifo[(m->fifo_head + m->fifo_count) % ADXL355_MODEL_FIFO_SIZE] = e;
    m->fifo_count++;
}

static void fifo_pop(adxl355_model_t *m, uint8_t out[3])
{
    if (m->fifo_count == 0) {
        out[0] = 0x00;
        out[1] = 0x00;
        out[2] = 0x02; /* empty indicator */
        return;
    }
    uint32_t e = m->fifo[m->fifo_head];
    m->fifo_head = (m->fifo_head + 1u) % ADXL355_MODEL_FIFO_SIZE;
    m->fifo_count--;
    uint32_t v = e & 0xFFFFFu;
    out[0] = (uint8_t)(v >> 12);
    out[1] = (uint8_t)((v >> 4) & 0xFFu);
    out[2] = (uint8_t)(((v & 0x0Fu) << 4) | ((e & FIFO_X_FLAG) ? 0x01u : 0x00u));
}

void adxl355_model_spi(adxl355_model_t *m, const uint8_t *tx, uint8_t *rx, size_t len)
{
    if (len == 0) {
        return;
    }
    if (m->fault.missing) {
        if (rx != NULL) {
            memset(rx, 0x00, len);
        }
        return;
    }
    if (busy(m)) {
        if (rx != NULL) {
            memset(rx, 0xFF, len);
        }
        return;
    }
    const uint8_t cmd = tx != NULL ? tx[0] : 0x00u;
    uint8_t addr = (uint8_t)(cmd >> 1);
    const int is_read = cmd & 0x01u;
    uint8_t latch[3] = {0, 0, 0};
    unsigned phase = 0; /* byte index inside the current FIFO entry */
    if (rx != NULL) {
        rx[0] = 0x00;
    }
    for (size_t i = 1; i < len; i++) {
        uint8_t out = 0x00;
        if (busy(m)) { /* a reset earlier in this transaction */
            out = 0xFF;
        } else if (is_read) {
            if (addr == R_FIFO_DATA) {
                if (phase == 0) {
                    fifo_pop(m, latch);
                }
                out = latch[phase];
                phase = (phase + 1u) % 3u;
            } else {
                out = read_reg(m, addr);
                addr = (uint8_t)((addr + 1u) & 0x7Fu);
            }
        } else {
            (void)write_reg(m, addr, tx != NULL ? tx[i] : 0x00u);
            if (addr != R_FIFO_DATA) {
                addr = (uint8_t)((addr + 1u) & 0x7Fu);
            }
        }
        if (rx != NULL) {
            rx[i] = out;
        }
    }
}

/* ---- sample generation ---- */

static int32_t sat20(int64_t v)
{
    if (v > DATA_MAX) {
        return DATA_MAX;
    }
    if (v < DATA_MIN) {
        return DATA_MIN;
    }
    return (int32_t)v;
}

static int32_t quantise(double counts)
{
    if (counts > 1e9) {
        counts = 1e9;
    } else if (counts < -1e9) {
        counts = -1e9;
    }
    return sat20((int64_t)llround(counts));
}

static void produce_sample(adxl355_model_t *m, const sim_world_t *w, uint64_t t_sample)
{
    const adxl355_truth_t *tr = &m->truth;
    const double g0 = SIM_G0_MPS2;
    const double dtemp = w->temperature_c - 25.0;
    const double fs = 1e6 / (double)(250u << m->odr_active);
    const double lsb = adxl355_model_lsb_per_g(m);
    const int st_on = (m->reg[R_SELF_TEST] & 0x03u) == 0x03u;
    const unsigned hpf = (m->reg[R_FILTER] >> 4) & 0x07u;

    /* bias random walk over the time since the previous update */
    if (m->rw_started) {
        double dt = (double)(t_sample - m->rw_last_us) * 1e-6;
        for (int i = 0; i < 3; i++) {
            if (tr->rw_k[i] != 0.0) {
                m->rw_bias[i] += tr->rw_k[i] * sqrt(dt) * sim_rng_gauss(&m->rng);
            }
        }
    }
    m->rw_last_us = t_sample;
    m->rw_started = 1;

    int32_t c[3];
    for (int i = 0; i < 3; i++) {
        double mf = 0.0;
        for (int j = 0; j < 3; j++) {
            mf += tr->m[i][j] * w->specific_force_mps2[j];
        }
        double u = (1.0 + tr->scale_tc[i] * dtemp) * mf + tr->bias_mps2[i] +
                   tr->bias_tc[i] * dtemp + m->rw_bias[i];
        /* curved part and hysteresis (0 for a part without them: u unchanged) */
        u += dtemp * dtemp * (tr->bias_tc2[i] + tr->bias_tc3[i] * dtemp) + tr->hysteresis[i] * m->hyst_h[i];
        if (tr->noise_n[i] != 0.0) {
            u += tr->noise_n[i] * sqrt(fs) * sim_rng_gauss(&m->rng);
        }
        if (st_on) {
            u += m->st_force_g[i] * g0;
        }
        if (hpf != 0u && hpf_k[hpf] > 0.0) {
            const double a = 1.0 / (1.0 + 2.0 * PI_D * hpf_k[hpf]);
            if (!m->hpf_primed) {
                m->hpf_x[i] = 0.0;
                m->hpf_y[i] = 0.0;
            }
            double y = a * (m->hpf_y[i] + u - m->hpf_x[i]);
            m->hpf_x[i] = u;
            m->hpf_y[i] = y;
            u = y;
        }
        int32_t raw = quantise(u / g0 * lsb);
        const uint8_t *o = &m->reg[R_OFFSET_X_H + 2 * i];
        int32_t off = (int32_t)(int16_t)(uint16_t)(((uint16_t)o[0] << 8) | o[1]);
        c[i] = sat20((int64_t)raw + 16 * (int64_t)off);
    }
    if (hpf != 0u) {
        m->hpf_primed = 1;
    }

    for (int i = 0; i < 3; i++) {
        uint32_t v = (uint32_t)c[i] & 0xFFFFFu;
        m->reg[R_XDATA3 + 3 * i] = (uint8_t)(v >> 12);
        m->reg[R_XDATA3 + 3 * i + 1] = (uint8_t)((v >> 4) & 0xFFu);
        m->reg[R_XDATA3 + 3 * i + 2] = (uint8_t)((v & 0x0Fu) << 4);
        fifo_push(m, v | (i == 0 ? FIFO_X_FLAG : 0u));
    }
    if ((m->reg[R_POWER_CTL] & PWR_TEMP_OFF) == 0) {
        const double t0 = m->part ? m->part->temp_offset_counts : 1885.0;
        const double slope = m->part ? m->part->temp_lsb_per_c : -9.05;
        long t = lround(t0 + slope * dtemp);
        if (t < 0) {
            t = 0;
        } else if (t > 4095) {
            t = 4095;
        }
        m->reg[R_TEMP2] = (uint8_t)((t >> 8) & 0x0F);
        m->reg[R_TEMP1] = (uint8_t)(t & 0xFF);
    }

    /* activity */
    const uint8_t act_en = m->reg[R_ACT_EN];
    if (act_en != 0u) {
        const int32_t thr =
            (int32_t)(((uint16_t)m->reg[R_ACT_THRESH_H] << 8) | m->reg[R_ACT_THRESH_L]);
        int above = 0;
        for (int i = 0; i < 3; i++) {
            int32_t mag = c[i] < 0 ? -c[i] : c[i];
            if ((act_en & (1u << i)) && (mag >> 3) > thr) {
                above = 1;
            }
        }
        m->act_run = above ? m->act_run + 1u : 0u;
        unsigned need = m->reg[R_ACT_COUNT] ? m->reg[R_ACT_COUNT] : 1u;
        if (m->act_run >= need) {
            m->reg[R_STATUS] |= ST_ACTIVITY;
        }
    } else {
        m->act_run = 0;
    }

    m->reg[R_STATUS] |= ST_DATA_RDY;
    m->samples++;
}

void adxl355_model_advance(adxl355_model_t *m, uint64_t t_us, const sim_world_t *world)
{
    static const sim_world_t rest = {{0.0, 0.0, 0.0}, {0.0, 0.0, 0.0}, 25.0};
    const sim_world_t *w = world != NULL ? world : &rest;
    if (t_us <= m->t_us) {
        return;
    }
    m->temp_c = w->temperature_c;
    hysteresis_update(m, m->temp_c); /* the die's history counts in standby too */
    if (m->measuring) {
        const uint64_t period = (uint64_t)250u << m->odr_active;
        while (m->next_sample_us <= t_us) {
            m->t_us = m->next_sample_us;
            if (!m->fault.stuck_data) {
                produce_sample(m, w, m->next_sample_us);
            }
            m->next_sample_us += period;
        }
    }
    m->t_us = t_us;
}

/* ---- fault setters ---- */

void adxl355_model_set_missing(adxl355_model_t *m, int on) { m->fault.missing = on; }

void adxl355_model_set_stuck_data(adxl355_model_t *m, int on) { m->fault.stuck_data = on; }

void adxl355_model_set_shadow_corrupt(adxl355_model_t *m, int on) { m->fault.shadow_corrupt = on; }

void adxl355_model_set_ids(adxl355_model_t *m, uint8_t devid_ad, uint8_t devid_mst,
                           uint8_t partid)
{
    m->id[0] = devid_ad;
    m->id[1] = devid_mst;
    m->id[2] = partid;
}
