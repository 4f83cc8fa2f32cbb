/* adxrs450_model.c - ADXRS450 SPI/physics model; see adxrs450_model.h for the choices. */
#include "adxrs450_model.h"

#include <math.h>
#include <string.h>

#define DEG2RAD (3.14159265358979323846 / 180.0)

/* registers */
#define REG_RATE 0x00u
#define REG_TEM 0x02u
#define REG_LOCST 0x04u
#define REG_HICST 0x06u
#define REG_QUAD 0x08u
#define REG_FAULT 0x0Au
#define REG_PID 0x0Cu
#define REG_SNH 0x0Eu
#define REG_SNL 0x10u
#define REG_DNC 0x12u

#define LOCST_VALUE 0xFE70u
#define HICST_VALUE 0x0190u
#define QUAD_NOMINAL 0x0010u
#define QUAD_Q_FAULT 0x1068u /* 4200 LSB, above the 4096 trip level */

#define RESP_TYPE_ERROR 0u
#define RESP_TYPE_WRITE 1u
#define RESP_TYPE_READ 2u
#define ST_FAULT 0u
#define ST_VALID 1u
#define ST_SELFTEST 2u
#define ST_REGISTER 3u
#define RESP_RW_FIXED 0x02000000u /* bits 25:21 = 1 0 SM2 SM1 SM0 with SM = 000 */
#define CHK_REPLIES 2u

/* ---- pure helpers ---- */

static int parity_odd(uint32_t w)
{
    w ^= w >> 16;
    w ^= w >> 8;
    w ^= w >> 4;
    return (int)((0x6996u >> (w & 0xFu)) & 1u);
}

uint32_t sim_adxrs450_response_parity(uint32_t word)
{
    word &= ~(0x10000000u | 1u);
    if (!parity_odd(word >> 16)) {
        word |= 0x10000000u;
    }
    if (!parity_odd(word)) {
        word |= 1u;
    }
    return word;
}

uint32_t sim_adxrs450_encode_sensor(uint8_t sq, uint8_t st, int16_t counts, uint8_t faults)
{
    uint32_t w = ((uint32_t)(sq & 7u) << 29) | ((uint32_t)(st & 3u) << 26) |
                 ((uint32_t)(uint16_t)counts << 10) | (uint32_t)(faults & 0xFEu);
    return sim_adxrs450_response_parity(w);
}

static uint32_t encode_register(uint8_t type, uint8_t sm, uint16_t data)
{
    uint32_t w = ((uint32_t)type << 29) | ((uint32_t)ST_REGISTER << 26) | RESP_RW_FIXED |
                 ((uint32_t)(sm & 7u) << 21) | ((uint32_t)data << 5);
    return sim_adxrs450_response_parity(w);
}

static uint32_t encode_error(uint8_t sm, uint32_t flags)
{
    /* type bits 31:29 = 000 (RESP_TYPE_ERROR) */
    uint32_t w = ((uint32_t)ST_REGISTER << 26) | RESP_RW_FIXED | ((uint32_t)(sm & 7u) << 21) |
                 (flags & (SIM_ADXRS450_ERR_SPI | SIM_ADXRS450_ERR_RE | SIM_ADXRS450_ERR_DU));
    return sim_adxrs450_response_parity(w);
}

uint16_t sim_adxrs450_tem_register(double temp_c)
{
    double r = floor((temp_c - 45.0) * 5.0 + 0.5);
    if (!(r >= -512.0)) { /* also catches NaN */
        r = -512.0;
    }
    if (r > 511.0) {
        r = 511.0;
    }
    int32_t raw10 = (int32_t)r;
    return (uint16_t)(((uint32_t)raw10 & 0x3FFu) << 6);
}

/* ---- truth ---- */

sim_adxrs450_truth_t sim_adxrs450_default_truth(int axis)
{
    sim_adxrs450_truth_t t;
    memset(&t, 0, sizeof t);
    if (axis >= 0 && axis < 3) {
        t.sens[axis] = 1.0;
    }
    t.noise_n = SIM_ADXRS450_NOISE_DPS_RTHZ * DEG2RAD;
    t.bias_instability_rad_s = SIM_ADXRS450_BIAS_INSTABILITY_DPH / 3600.0 * DEG2RAD;
    t.bias_rw_k = SIM_ADXRS450_RATE_RW_DPS_RTS * DEG2RAD;
    return t;
}

static double uniform_pm(sim_rng_t *rng, double half_width)
{
    return (2.0 * sim_rng_uniform(rng) - 1.0) * half_width;
}

void sim_adxrs450_random_truth(sim_adxrs450_truth_t *t, sim_rng_t *rng, int axis)
{
    *t = sim_adxrs450_default_truth(axis);
    for (int i = 0; i < 3; i++) {
        t->sens[i] = (i == axis) ? 1.0 + uniform_pm(rng, 0.03) : uniform_pm(rng, 0.01);
    }
    double b = 0.5 * sim_rng_gauss(rng);
    if (b > 3.0) {
        b = 3.0;
    }
    if (b < -3.0) {
        b = -3.0;
    }
    t->bias_rad_s = b * DEG2RAD;
    t->noise_n *= 1.0 + uniform_pm(rng, 0.2);
    t->bias_tempco_rad_s_per_c = uniform_pm(rng, 0.01) * DEG2RAD;
    t->scale_tempco_per_c = uniform_pm(rng, 1e-4);
    sim_rng_t gr = *rng; /* a copy: rng itself does not advance */
    sim_rng_seed(&gr, sim_rng_u64(&gr) ^ 0x6753454E53ull ^ (uint64_t)axis);
    for (int i = 0; i < 3; i++) {
        double v = 0.03 * sim_rng_gauss(&gr);
        v = v > 0.1 ? 0.1 : v < -0.1 ? -0.1 : v;
        t->gsens_rad_s_per_mps2[i] = v * DEG2RAD / 9.80665;
    }
    sim_rng_t hr = *rng; /* another copy for the thermal terms */
    sim_rng_seed(&hr, sim_rng_u64(&hr) ^ 0x5448524D414Cull ^ ((uint64_t)axis << 56));
    t->bias_tc2 = uniform_pm(&hr, 1e-4) * DEG2RAD;
    t->bias_tc3 = uniform_pm(&hr, 1e-6) * DEG2RAD;
    t->hysteresis = uniform_pm(&hr, 0.01) * DEG2RAD;
    t->hysteresis_width_c = 1.0 + 3.0 * sim_rng_uniform(&hr);
}

double sim_adxrs450_truth_thermal_bias(const sim_adxrs450_truth_t *t, double temp_c, double h)
{
    const double d = temp_c - SIM_ADXRS450_T_REF_C;
    return t->bias_tempco_rad_s_per_c * d + d * d * (t->bias_tc2 + t->bias_tc3 * d) + t->hysteresis * h;
}

/* Play operator of dead band hysteresis_width_c on the die temperature (adxl355_model.h). */
static void hysteresis_update(sim_adxrs450_t *m, double temp_c)
{
    double r = 0.5 * m->truth.hysteresis_width_c;
    if (!m->hyst_started) {
        m->hyst_y = temp_c;
        m->hyst_h = 0.0;
        m->hyst_started = 1;
    } else if (r > 0.0) {
        double y = m->hyst_y;
        y = y < temp_c - r ? temp_c - r : (y > temp_c + r ? temp_c + r : y);
        m->hyst_y = y;
        m->hyst_h = (temp_c - y) / r;
    } else {
        if (temp_c != m->hyst_y) {
            m->hyst_h = temp_c > m->hyst_y ? 1.0 : -1.0;
        }
        m->hyst_y = temp_c;
    }
}

void sim_adxrs450_set_truth(sim_adxrs450_t *m, const sim_adxrs450_truth_t *t) { m->truth = *t; }

const sim_adxrs450_truth_t *sim_adxrs450_get_truth(const sim_adxrs450_t *m)
{
    return &m->truth;
}

/* ---- physics ---- */

/* The bias-instability bank: first-order Gauss-Markov processes, one per decade of
 * correlation time, each of standard deviation FLICKER_WEIGHT * B (see the header). */
static const double flicker_tau_s[SIM_ADXRS450_FLICKER_N] = {2.0, 20.0, 200.0, 2000.0, 20000.0};

const double *sim_adxrs450_flicker_taus(void) { return flicker_tau_s; }

double sim_adxrs450_flicker_weight(void) { return SIM_ADXRS450_FLICKER_WEIGHT; }

int sim_adxrs450_flicker_n(void) { return SIM_ADXRS450_FLICKER_N; }

double sim_adxrs450_flicker_bias_rad_s(const sim_adxrs450_t *m)
{
    double z = 0.0;
    for (int i = 0; i < SIM_ADXRS450_FLICKER_N; i++) {
        z += m->flicker[i];
    }
    return m->truth.bias_instability_rad_s * SIM_ADXRS450_FLICKER_WEIGHT * z;
}

/* Move the slow bias terms (bank and rate random walk) over dt seconds: exact for any dt
 * (x <- a*x + sqrt(1 - a^2)*n for each unit-variance process, a = exp(-dt/T)). */
static void drift_step(sim_adxrs450_t *m, double dt)
{
    if (m->truth.bias_instability_rad_s > 0.0) {
        for (int i = 0; i < SIM_ADXRS450_FLICKER_N; i++) {
            double a = exp(-dt / flicker_tau_s[i]);
            m->flicker[i] = a * m->flicker[i] + sqrt(1.0 - a * a) * sim_rng_gauss(&m->drift_rng);
        }
    }
    if (m->truth.bias_rw_k > 0.0) {
        m->bias_rw_rad_s += m->truth.bias_rw_k * sqrt(dt) * sim_rng_gauss(&m->drift_rng);
    }
}

double sim_adxrs450_true_bias_rad_s(const sim_adxrs450_t *m)
{
    const sim_adxrs450_truth_t *t = &m->truth;
    double dt_c = m->world.temperature_c - SIM_ADXRS450_T_REF_C;
    double b = t->bias_rad_s + t->bias_tempco_rad_s_per_c * dt_c + m->bias_rw_rad_s +
               sim_adxrs450_flicker_bias_rad_s(m);
    /* curved part and hysteresis (0 for a part without them: b unchanged) */
    return b + (dt_c * dt_c * (t->bias_tc2 + t->bias_tc3 * dt_c) + t->hysteresis * m->hyst_h);
}

double sim_adxrs450_true_rate_rad_s(const sim_adxrs450_t *m)
{
    double dt_c = m->world.temperature_c - SIM_ADXRS450_T_REF_C;
    double w = 0.0;
    for (int i = 0; i < 3; i++) {
        w += m->truth.sens[i] * m->world.rate_rad_s[i];
    }
    double gf = 0.0;
    for (int i = 0; i < 3; i++) {
        gf += m->truth.gsens_rad_s_per_mps2[i] * m->world.specific_force_mps2[i];
    }
    return (1.0 + m->truth.scale_tempco_per_c * dt_c) * w + sim_adxrs450_true_bias_rad_s(m) + gf;
}

void sim_adxrs450_advance(sim_adxrs450_t *m, uint64_t t_us, const sim_world_t *world)
{
    if (world != NULL) {
        m->world = *world;
        hysteresis_update(m, world->temperature_c);
    }
    if (t_us <= m->t_us) {
        return;
    }
    double dt = (double)(t_us - m->t_us) * 1e-6;
    m->rate_integral_rad += sim_adxrs450_true_rate_rad_s(m) * dt;
    m->t_us = t_us;
    /* the slow terms move in steps of at least SIM_ADXRS450_DRIFT_STEP_US (the bias is
     * constant in between): cheap at kHz advance rates, exact at the step instants */
    if (t_us - m->drift_t_us >= SIM_ADXRS450_DRIFT_STEP_US) {
        drift_step(m, (double)(t_us - m->drift_t_us) * 1e-6);
        m->drift_t_us = t_us;
    }
}

static int16_t to_counts(double rate_rad_s)
{
    double c = floor(rate_rad_s / DEG2RAD * SIM_ADXRS450_LSB_PER_DPS + 0.5);
    if (!(c >= -32768.0)) { /* also catches NaN */
        c = -32768.0;
    }
    if (c > 32767.0) {
        c = 32767.0;
    }
    return (int16_t)c;
}

/* Latch a rate sample now (integrate and dump; see the header). */
static int16_t latch_rate(sim_adxrs450_t *m)
{
    uint64_t dt_us = m->t_us - m->last_latch_us;
    if (m->have_latch && dt_us < SIM_ADXRS450_MIN_LATCH_US) {
        return m->last_counts;
    }
    double mean, window_us;
    if (dt_us > SIM_ADXRS450_MAX_WINDOW_US || dt_us < SIM_ADXRS450_MIN_LATCH_US) {
        mean = sim_adxrs450_true_rate_rad_s(m);
        window_us = dt_us > SIM_ADXRS450_MAX_WINDOW_US ? (double)SIM_ADXRS450_MAX_WINDOW_US
                                                       : (double)SIM_ADXRS450_MIN_LATCH_US;
    } else {
        window_us = (double)dt_us;
        mean = m->rate_integral_rad / (window_us * 1e-6);
    }
    double noise = 0.0;
    if (m->truth.noise_n > 0.0) {
        noise = m->truth.noise_n / sqrt(window_us * 1e-6) * sim_rng_gauss(&m->rng);
    }
    m->last_counts = to_counts(mean + noise);
    m->rate_integral_rad = 0.0;
    m->last_latch_us = m->t_us;
    m->have_latch = 1;
    return m->last_counts;
}

/* ---- faults ---- */

static uint16_t fault_causes(uint16_t mask)
{
    mask &= SIM_ADXRS450_FAULT_ALL;
    if (mask & (SIM_ADXRS450_FAULT_UV | SIM_ADXRS450_FAULT_OV)) {
        mask |= SIM_ADXRS450_FAULT_PWR;
    }
    if (mask & SIM_ADXRS450_FAULT_AMP) {
        mask |= SIM_ADXRS450_FAULT_CST;
    }
    return mask;
}

static uint16_t faults_now(const sim_adxrs450_t *m)
{
    return (uint16_t)(m->fault_latched | m->fault_persistent);
}

/* The reply reported `bits`: they clear, persistent causes re-assert. */
static void faults_reported(sim_adxrs450_t *m, uint16_t bits)
{
    m->fault_latched = (uint16_t)((m->fault_latched & ~bits) | m->fault_persistent);
}

void sim_adxrs450_set_persistent_faults(sim_adxrs450_t *m, uint16_t mask)
{
    m->fault_persistent = fault_causes(mask);
    m->fault_latched |= m->fault_persistent;
}

void sim_adxrs450_inject_faults(sim_adxrs450_t *m, uint16_t mask)
{
    m->fault_latched |= fault_causes(mask);
}

void sim_adxrs450_corrupt_responses(sim_adxrs450_t *m, uint32_t count, uint32_t xor_mask)
{
    m->corrupt_remaining = count;
    m->corrupt_mask = xor_mask;
}

void sim_adxrs450_set_missing(sim_adxrs450_t *m, int missing) { m->missing = missing ? 1u : 0u; }

void sim_adxrs450_set_pid(sim_adxrs450_t *m, uint16_t pid) { m->pid = pid; }

void sim_adxrs450_set_part(sim_adxrs450_t *m, const ib_part_desc_t *part)
{
    if (part == NULL || part->part == IB_PART_ADXRS450) {
        return; /* the default chip */
    }
    m->pid = part->id_regs[0].value;
    m->truth.bias_instability_rad_s = part->bias_instability * DEG2RAD;
}

/* ---- registers ---- */

static int reg_valid(uint32_t addr)
{
    return addr <= REG_DNC && (addr & 1u) == 0u;
}

/* Register contents without side effects. */
static uint16_t reg_peek(const sim_adxrs450_t *m, uint32_t addr)
{
    switch (addr) {
    case REG_RATE:
        return (uint16_t)m->last_counts;
    case REG_TEM:
        return sim_adxrs450_tem_register(m->world.temperature_c);
    case REG_LOCST:
        return LOCST_VALUE;
    case REG_HICST:
        return HICST_VALUE;
    case REG_QUAD:
        return (m->fault_persistent & SIM_ADXRS450_FAULT_Q) ? QUAD_Q_FAULT : QUAD_NOMINAL;
    case REG_FAULT:
        return faults_now(m);
    case REG_PID:
        return m->pid;
    case REG_SNH:
        return (uint16_t)(m->serial >> 16);
    case REG_SNL:
        return (uint16_t)m->serial;
    case REG_DNC:
        return m->dnc;
    default:
        return 0;
    }
}

/* A register read command: side effects (RATE latches, FAULT reports) then contents. */
static uint16_t reg_read(sim_adxrs450_t *m, uint32_t addr)
{
    if (addr == REG_RATE) {
        return (uint16_t)latch_rate(m);
    }
    uint16_t v = reg_peek(m, addr);
    if (addr == REG_FAULT) {
        faults_reported(m, SIM_ADXRS450_FAULT_ALL);
    }
    return v;
}

/* ---- SPI ---- */

static int cmd_is_valid(uint32_t cmd)
{
    uint32_t top = cmd >> 29;
    return (cmd & 0x20000000u) != 0u || top == 4u || top == 2u;
}

static uint32_t sensor_reply(sim_adxrs450_t *m, uint32_t cmd)
{
    uint8_t sq = (uint8_t)((((cmd >> 28) & 1u) << 2) | (((cmd >> 31) & 1u) << 1) |
                           ((cmd >> 30) & 1u));
    int16_t counts = latch_rate(m);
    uint32_t reply;
    if (m->chk_remaining > 0) {
        m->chk_remaining--;
        reply = sim_adxrs450_encode_sensor(sq, ST_SELFTEST, 0, 0xFEu);
    } else {
        uint16_t f = faults_now(m);
        uint8_t low = (uint8_t)(f & 0xFEu);
        uint8_t st = (uint8_t)((f & (SIM_ADXRS450_FAULT_PLL | SIM_ADXRS450_FAULT_FAIL))
                                   ? ST_FAULT
                                   : ST_VALID);
        reply = sim_adxrs450_encode_sensor(sq, st, counts, low);
        faults_reported(m, low);
    }
    if (cmd & 0x2u) {
        m->chk_remaining = CHK_REPLIES;
    }
    return reply;
}

/* Execute one 32-bit command; return the reply for the next frame. */
static uint32_t execute(sim_adxrs450_t *m, uint32_t cmd)
{
    uint8_t sm = (uint8_t)((cmd >> 26) & 7u);
    if (!parity_odd(cmd)) {
        m->cmd_parity_errors++;
        if (!cmd_is_valid(cmd)) {
            m->invalid_cmds++;
            return encode_error(sm, SIM_ADXRS450_ERR_SPI | SIM_ADXRS450_ERR_RE);
        }
        return encode_error(sm, SIM_ADXRS450_ERR_SPI);
    }
    if (cmd & 0x20000000u) {
        return sensor_reply(m, cmd);
    }
    uint32_t top = cmd >> 29;
    uint32_t addr = (cmd >> 17) & 0x1FFu;
    if (top == 4u) {
        if (!reg_valid(addr)) {
            return encode_error(sm, SIM_ADXRS450_ERR_RE);
        }
        return encode_register(RESP_TYPE_READ, sm, reg_read(m, addr));
    }
    if (top == 2u) {
        if (!reg_valid(addr)) {
            return encode_error(sm, SIM_ADXRS450_ERR_RE);
        }
        if (addr == REG_DNC) {
            uint32_t d = (cmd >> 1) & 0x3FFu; /* 10-bit signed, sign-extended on read */
            m->dnc = (uint16_t)((d & 0x200u) ? (d | 0xFC00u) : d);
        }
        return encode_register(RESP_TYPE_WRITE, sm, reg_peek(m, addr));
    }
    m->invalid_cmds++;
    return encode_error(sm, SIM_ADXRS450_ERR_RE);
}

int sim_adxrs450_spi(sim_adxrs450_t *m, const uint8_t *tx, uint8_t *rx, size_t len)
{
    uint8_t out[4] = {0, 0, 0, 0};
    int ret = (len == 4) ? 0 : -1;
    if (!m->missing) {
        m->frames++;
        if (m->t_us - m->power_on_us < m->startup_us) {
            m->ignored_frames++;
        } else {
            uint32_t w = m->pending;
            if (m->corrupt_remaining > 0) {
                m->corrupt_remaining--;
                w ^= m->corrupt_mask;
            }
            out[0] = (uint8_t)(w >> 24);
            out[1] = (uint8_t)(w >> 16);
            out[2] = (uint8_t)(w >> 8);
            out[3] = (uint8_t)w;
            if (len == 4) {
                uint32_t cmd = 0;
                if (tx != NULL) {
                    cmd = ((uint32_t)tx[0] << 24) | ((uint32_t)tx[1] << 16) |
                          ((uint32_t)tx[2] << 8) | (uint32_t)tx[3];
                }
                m->last_cmd = cmd;
                m->pending = execute(m, cmd);
            } else {
                m->pending = encode_error(0, SIM_ADXRS450_ERR_SPI);
            }
        }
    }
    if (rx != NULL) {
        for (size_t i = 0; i < len; i++) {
            rx[i] = (i < 4) ? out[i] : 0u;
        }
    }
    return ret;
}

/* ---- life cycle ---- */

void sim_adxrs450_power_cycle(sim_adxrs450_t *m)
{
    m->power_on_us = m->t_us;
    m->pending = SIM_ADXRS450_POWERUP_WORD;
    m->dnc = 0;
    m->fault_latched = m->fault_persistent;
    m->chk_remaining = 0;
    m->rate_integral_rad = 0.0;
    m->last_latch_us = m->t_us;
    m->last_counts = 0;
    m->have_latch = 0;
}

void sim_adxrs450_init(sim_adxrs450_t *m, uint64_t seed, int axis)
{
    memset(m, 0, sizeof *m);
    m->axis = axis;
    m->truth = sim_adxrs450_default_truth(axis);
    sim_rng_seed(&m->rng, seed);
    m->serial = (uint32_t)(sim_rng_u64(&m->rng) >> 32);
    if (m->serial == 0u) {
        m->serial = 1u;
    }
    /* the slow bias terms draw from an rng of their own (the white noise's sequence does not
     * depend on them); the bank starts in its stationary state, as in a part already running */
    sim_rng_seed(&m->drift_rng, seed ^ 0x44524946544Bull);
    for (int i = 0; i < SIM_ADXRS450_FLICKER_N; i++) {
        m->flicker[i] = sim_rng_gauss(&m->drift_rng);
    }
    m->pid = SIM_ADXRS450_PID;
    m->startup_us = SIM_ADXRS450_STARTUP_US;
    m->world.temperature_c = SIM_ADXRS450_T_REF_C;
    sim_adxrs450_power_cycle(m);
}

/* ---- a chip alone, for noise tests and benches ---- */

int sim_adxrs450_record(uint64_t seed, int axis, int random_truth, double rate_hz, size_t n,
                        int16_t *counts)
{
    if (!(rate_hz > 0.0) || rate_hz > 1e4 || counts == NULL) {
        return -1;
    }
    static sim_adxrs450_t m; /* large-ish; one recording at a time */
    sim_adxrs450_init(&m, seed, axis);
    if (random_truth) {
        sim_rng_t r;
        sim_rng_seed(&r, seed ^ 0x5245434F5244ull);
        sim_adxrs450_truth_t t;
        sim_adxrs450_random_truth(&t, &r, axis);
        sim_adxrs450_set_truth(&m, &t);
    }
    m.startup_us = 0;
    sim_world_t w = m.world; /* at rest, 25 degC */
    const uint8_t cmd[4] = {0x20, 0x00, 0x00, 0x00}; /* sensor data, SQ 0, odd parity */
    uint8_t rx[4];
    for (size_t i = 0; i <= n; i++) {
        sim_adxrs450_advance(&m, (uint64_t)((double)(i + 1) * 1e6 / rate_hz + 0.5), &w);
        sim_adxrs450_spi(&m, cmd, rx, 4);
        if (i > 0) { /* the reply to the previous frame's command: the sample it latched */
            uint32_t word = ((uint32_t)rx[0] << 24) | ((uint32_t)rx[1] << 16) |
                            ((uint32_t)rx[2] << 8) | (uint32_t)rx[3];
            counts[i - 1] = (int16_t)(uint16_t)(word >> 10);
        }
    }
    return 0;
}
