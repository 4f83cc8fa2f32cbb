/* core.c - see core.h. Portable: no register access, hardware only through ib_board_t. */
#include "core.h"

#include <math.h>
#include <string.h>

#include "param_store.h"
#include "wire.h"

#define FW_VERSION_MAJOR 0u
#define FW_VERSION_MINOR 2u
#define FW_VERSION_PATCH 0u

#define G0_MPS2 9.80665f
#define RAD_PER_DEG (3.14159265358979f / 180.0f)
#define ACCEL_FIFO_MAX_SETS 32u
/* TX room always kept free for replies when a sample batch is queued. */
#define REPLY_RESERVE (2u * (IB_MAX_ENCODED + 1u))
#define STATS_PERIOD_MS 1000u
/* The calibrated span of factory defaults and of a migrated layout-1 or -2 block, degC. */
#define SPAN_DEFAULT_MIN_C ((int8_t)-40)
#define SPAN_DEFAULT_MAX_C ((int8_t)85)

/* ------------------------------------------------------------------ helpers */

static uint32_t now_us(const ib_core_t *c) { return c->board->time_us(c->board->ctx); }

static void update_uptime(ib_core_t *c)
{
    uint32_t t = now_us(c);
    uint32_t dt = t - c->last_time_us; /* modulo 2^32: fine while polled every < 71 min */
    c->uptime_us_rem += dt;
    c->uptime_ms += c->uptime_us_rem / 1000u;
    c->uptime_us_rem %= 1000u;
    c->last_time_us = t;
}

/* Queue an encoded frame; the caller checked the space. */
static void link_put(ib_core_t *c, const uint8_t *frame, size_t len)
{
    size_t n = c->board->link_write(c->board->ctx, frame, len);
    if (n == len) {
        c->stats.frames_sent++;
    } else {
        c->stats.frames_dropped++;
    }
}

/* Encode a device message whose payload is at c->msg_raw + IB_HEADER_SIZE. */
static size_t encode_msg(ib_core_t *c, uint8_t type, size_t payload_len, uint8_t *out)
{
    size_t n = ib_frame_encode(c->msg_raw, type, c->tx_seq, now_us(c), payload_len, out);
    c->tx_seq++;
    return n;
}

/* Unsolicited message (stats, fault event, boot info): sent now if it fits, else dropped
 * and counted; it is never allowed to eat the reply reserve. */
static void send_unsolicited(ib_core_t *c, uint8_t type, size_t payload_len)
{
    size_t n = encode_msg(c, type, payload_len, c->tx_frame);
    if (c->board->link_tx_free(c->board->ctx) >= n + REPLY_RESERVE / 2u) {
        link_put(c, c->tx_frame, n);
    } else {
        c->stats.frames_dropped++;
    }
}

/* ------------------------------------------------------------- parameters */

static int finite_f(float x) { return isfinite(x) != 0; }


/* Inverse of a row-major 3x3 matrix in single precision (the limits keep M close to the
 * identity, so float is ample; the Cortex-M4F has a single-precision FPU only). */
static int invert3(const float m[9], float inv[3][3])
{
    float a = m[0], b = m[1], cc = m[2], d = m[3], e = m[4], f = m[5], g = m[6], h = m[7], i = m[8];
    float A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
    float det = a * A + b * B + cc * C;
    if (!(fabsf(det) > IB_LIMIT_M_DET_MIN) || !isfinite(det)) {
        return -1;
    }
    float r = 1.0f / det;
    inv[0][0] = A * r;
    inv[0][1] = -(b * i - cc * h) * r;
    inv[0][2] = (b * f - cc * e) * r;
    inv[1][0] = B * r;
    inv[1][1] = (a * i - cc * g) * r;
    inv[1][2] = -(a * f - cc * d) * r;
    inv[2][0] = C * r;
    inv[2][1] = -(a * h - b * g) * r;
    inv[2][2] = (a * e - b * d) * r;
    return 0;
}

/* One triad's fields of a parameter block, and its limits: a view, so the checks and the
 * correction read the block where it is (nothing copied into RAM). */
typedef struct {
    const float *m, *b, *c1, *s, *c2, *c3; /* M (9), bias, bias_tc (c1), scale_tc, c2, c3 (3 each) */
    float t_ref;
    int8_t t_min, t_max;
    float bias_max, c1_max, c2_max, c3_max, span_max;
} triad_view_t;

static void triad_view(const ib_params_t *p, int gyro, triad_view_t *v)
{
    if (gyro) {
        *v = (triad_view_t){p->gyro_m, p->gyro_b_rad_s, p->gyro_bias_tc_rad_s_per_c, p->gyro_scale_tc_per_c,
                            p->gyro_bias_tc2_rad_s_per_c2, p->gyro_bias_tc3_rad_s_per_c3, p->gyro_t_ref_c,
                            p->gyro_t_min_c, p->gyro_t_max_c, IB_LIMIT_GYRO_BIAS_MAX_RAD_S,
                            IB_LIMIT_GYRO_BIAS_TC_MAX_RAD_S_PER_C, IB_LIMIT_GYRO_BIAS_TC2_MAX_RAD_S_PER_C2,
                            IB_LIMIT_GYRO_BIAS_TC3_MAX_RAD_S_PER_C3, IB_LIMIT_GYRO_T_SPAN_MAX_C};
    } else {
        *v = (triad_view_t){p->accel_m, p->accel_b_mps2, p->accel_bias_tc_mps2_per_c, p->accel_scale_tc_per_c,
                            p->accel_bias_tc2_mps2_per_c2, p->accel_bias_tc3_mps2_per_c3, p->accel_t_ref_c,
                            p->accel_t_min_c, p->accel_t_max_c, IB_LIMIT_ACCEL_BIAS_MAX_MPS2,
                            IB_LIMIT_ACCEL_BIAS_TC_MAX_MPS2_PER_C, IB_LIMIT_ACCEL_BIAS_TC2_MAX_MPS2_PER_C2,
                            IB_LIMIT_ACCEL_BIAS_TC3_MAX_MPS2_PER_C3, IB_LIMIT_ACCEL_T_SPAN_MAX_C};
    }
}

/* Layout 3's checks of one triad, after t_ref (SPEC.md, Parameters on the device): the span in
 * the part's rated range and not empty, t_ref inside it; per axis c2, c3, and a bound of the
 * bias polynomial's excursion over the span, D (|c1| + D (|c2| + D |c3|)) with D the larger
 * distance from t_ref to an end, within the bias limit. All in float32, in this order (the
 * host's wire/params.py _check_poly repeats it). */
static uint8_t check_poly(const triad_view_t *v)
{
    float lo = (float)v->t_min, hi = (float)v->t_max;
    if (lo < IB_LIMIT_T_SPAN_MIN_C || hi > v->span_max || !(lo < hi) || v->t_ref < lo || v->t_ref > hi) {
        return IB_ERROR_PARAM_OUT_OF_RANGE;
    }
    float d = v->t_ref - lo, d_hi = hi - v->t_ref;
    if (d_hi > d) {
        d = d_hi;
    }
    for (int k = 0; k < 3; k++) {
        float a2 = fabsf(v->c2[k]), a3 = fabsf(v->c3[k]);
        if (a2 > v->c2_max || a3 > v->c3_max) {
            return IB_ERROR_PARAM_OUT_OF_RANGE;
        }
        float e = d * (fabsf(v->c1[k]) + d * (a2 + d * a3));
        if (!(e <= v->bias_max)) {
            return IB_ERROR_PARAM_OUT_OF_RANGE;
        }
    }
    return IB_ERROR_OK;
}

static uint8_t check_triad(const triad_view_t *v, ib_triad_corr_t *out)
{
    ib_triad_corr_t t;
    memset(&t, 0, sizeof t);
    const float *m = v->m;
    if (invert3(m, t.m_inv) != 0) {
        return IB_ERROR_PARAM_ILL_CONDITIONED;
    }
    float fm = 0.0f, fi = 0.0f;
    for (int k = 0; k < 9; k++) {
        fm += m[k] * m[k];
        fi += t.m_inv[k / 3][k % 3] * t.m_inv[k / 3][k % 3];
    }
    /* ||M||_F * ||M^-1||_F > limit, compared squared (no sqrt needed) */
    if (fm * fi > IB_LIMIT_M_COND_MAX * IB_LIMIT_M_COND_MAX) {
        return IB_ERROR_PARAM_ILL_CONDITIONED;
    }
    for (int r = 0; r < 3; r++) {
        for (int k = 0; k < 3; k++) {
            float x = m[r * 3 + k];
            if (r == k ? (x < IB_LIMIT_M_DIAG_MIN || x > IB_LIMIT_M_DIAG_MAX) : fabsf(x) > IB_LIMIT_M_OFFDIAG_MAX) {
                return IB_ERROR_PARAM_OUT_OF_RANGE;
            }
        }
    }
    for (int k = 0; k < 3; k++) {
        if (fabsf(v->b[k]) > v->bias_max || fabsf(v->c1[k]) > v->c1_max || fabsf(v->s[k]) > IB_LIMIT_SCALE_TC_MAX_PER_C) {
            return IB_ERROR_PARAM_OUT_OF_RANGE;
        }
    }
    if (v->t_ref < IB_LIMIT_T_REF_MIN_C || v->t_ref > IB_LIMIT_T_REF_MAX_C) {
        return IB_ERROR_PARAM_OUT_OF_RANGE;
    }
    uint8_t e = check_poly(v);
    if (e == IB_ERROR_OK && out) {
        *out = t;
    }
    return e;
}

static int all_finite(const float *x, unsigned n)
{
    for (unsigned k = 0; k < n; k++) {
        if (!finite_f(x[k])) {
            return 0;
        }
    }
    return 1;
}

uint8_t ib_core_check_params(const ib_params_t *p, ib_triad_corr_t *accel, ib_triad_corr_t *gyro)
{
    /* every float finite: walk the struct's float members */
    const float *groups[] = {p->accel_m, p->accel_b_mps2, p->gyro_m, p->gyro_b_rad_s,
                             p->accel_bias_tc_mps2_per_c, p->accel_scale_tc_per_c,
                             p->gyro_bias_tc_rad_s_per_c, p->gyro_scale_tc_per_c,
                             &p->accel_t_ref_c, &p->gyro_t_ref_c, p->gyro_g_rad_s_per_mps2,
                             p->accel_bias_tc2_mps2_per_c2, p->accel_bias_tc3_mps2_per_c3,
                             p->gyro_bias_tc2_rad_s_per_c2, p->gyro_bias_tc3_rad_s_per_c3};
    static const uint8_t sizes[] = {9, 3, 9, 3, 3, 3, 3, 3, 1, 1, 9, 3, 3, 3, 3};
    for (unsigned g = 0; g < sizeof sizes; g++) {
        if (!all_finite(groups[g], sizes[g])) {
            return IB_ERROR_PARAM_NOT_FINITE;
        }
    }
    triad_view_t v;
    triad_view(p, 0, &v);
    uint8_t e = check_triad(&v, accel);
    if (e != IB_ERROR_OK) {
        return e;
    }
    triad_view(p, 1, &v);
    e = check_triad(&v, gyro);
    if (e != IB_ERROR_OK) {
        return e;
    }
    for (unsigned k = 0; k < 9; k++) { /* g-sensitivity last (SPEC.md, Parameters on the device) */
        if (fabsf(p->gyro_g_rad_s_per_mps2[k]) > IB_LIMIT_GYRO_G_MAX_RAD_S_PER_MPS2) {
            return IB_ERROR_PARAM_OUT_OF_RANGE;
        }
    }
    return IB_ERROR_OK;
}

/* ib_core_correct in two parts: what depends on the temperatures only (the stream reads them
 * once a batch, so this runs once a batch) and what depends on the sample. Once a batch: the
 * bias at the clamped temperature, b + c1 dt + c2 dt^2 + c3 dt^3 (Horner), in input units
 * (u = input x unit), and W = M^-1 diag(unit / (1 + s dt)); per sample then only
 * out = W (u - bias): no divide, and for the accelerometer no counts-to-SI multiply either. */
static void correct_terms(const ib_params_t *p, int gyro, const ib_triad_corr_t *t, const float temp_c[3],
                          float unit, float per_unit, float bias[3], float w[3][3])
{
    triad_view_t v;
    triad_view(p, gyro, &v);
    float lo = (float)v.t_min, hi = (float)v.t_max;
    for (int k = 0; k < 3; k++) {
        float tc = temp_c[k] < lo ? lo : temp_c[k] > hi ? hi : temp_c[k]; /* clamp to the span */
        float dt = tc - v.t_ref;
        bias[k] = (v.b[k] + dt * (v.c1[k] + dt * (v.c2[k] + dt * v.c3[k]))) * per_unit;
        float g = unit / (1.0f + v.s[k] * dt); /* 1 + s dt >= 0.835: |s| <= 1e-3, |dt| <= 165 */
        for (int r = 0; r < 3; r++) {
            w[r][k] = t->m_inv[r][k] * g;
        }
    }
}

static void correct_apply(const float w[3][3], const float u[3], const float bias[3], float out[3])
{
    float v0 = u[0] - bias[0], v1 = u[1] - bias[1], v2 = u[2] - bias[2];
    for (int r = 0; r < 3; r++) {
        out[r] = w[r][0] * v0 + w[r][1] * v1 + w[r][2] * v2;
    }
}

void ib_core_correct(const ib_params_t *p, int gyro, const ib_triad_corr_t *t, const float u[3],
                     const float temp_c[3], float out[3])
{
    float bias[3], w[3][3];
    correct_terms(p, gyro, t, temp_c, 1.0f, 1.0f, bias, w);
    correct_apply(w, u, bias, out);
}

static void identity_params(ib_params_t *p)
{
    memset(p, 0, sizeof *p);
    for (int k = 0; k < 3; k++) {
        p->accel_m[k * 4] = 1.0f;
        p->gyro_m[k * 4] = 1.0f;
    }
    p->accel_t_ref_c = 25.0f;
    p->gyro_t_ref_c = 25.0f;
    p->accel_t_min_c = p->gyro_t_min_c = SPAN_DEFAULT_MIN_C;
    p->accel_t_max_c = p->gyro_t_max_c = SPAN_DEFAULT_MAX_C;
}

static void set_factory(ib_core_t *c)
{
    identity_params(&c->params);
    (void)ib_core_check_params(&c->params, &c->corr_accel, &c->corr_gyro);
    c->cal_ready = 0;
    c->param_source = IB_PARAM_SOURCE_FACTORY;
}

/* Layouts 2 and 1 of the parameter block: layout 3 without the bias polynomial's c2, c3
 * (4 x 3 float32) and the spans (4 int8); layout 1 also without gyro_g (9 float32). */
#define IB_PARAMS_SIZE_V2 (IB_PARAMS_SIZE - 52u)
#define IB_PARAMS_SIZE_V1 (IB_PARAMS_SIZE_V2 - 36u)
_Static_assert(IB_PARAM_BLOCK_VERSION == 3u, "read_stored migrates layouts 1 and 2 to layout 3: update it");

/* The span a migrated block gets (wire/params.py migrated_span): -40..85 degC, its upper end
 * raised to hold t_ref when t_ref lies above 85 degC, so that a block valid before stays valid. */
static int8_t migrated_t_max(float t_ref)
{
    int8_t hi = SPAN_DEFAULT_MAX_C; /* rounded up by counting: no float-to-int helper on the F103 */
    while (hi < 127 && (float)hi < t_ref) {
        hi++;
    }
    return hi;
}

/* The stored parameter block, read into p: today's layout, or layout 2 or 1 (its prefixes)
 * migrated with c2 = c3 = 0, the default span and (layout 1) G = 0. Returns 1 when a block was
 * read. */
static int read_stored(const ib_flash_if_t *fl, ib_params_t *p, ib_ps_info_t *info)
{
    uint8_t blob[IB_PARAMS_SIZE];
    ib_ps_status_t st = ib_ps_load(fl, IB_PARAM_BLOCK_VERSION, blob, sizeof blob, info);
    if (st == IB_PS_OK && info->payload_len == IB_PARAMS_SIZE) {
        ib_params_unpack(blob, p);
        return 1;
    }
    if (st == IB_PS_ERR_PAYLOAD_VERSION &&
        ((info->payload_version == 1u && info->payload_len == IB_PARAMS_SIZE_V1) ||
         (info->payload_version == 2u && info->payload_len == IB_PARAMS_SIZE_V2))) {
        /* what the old layout lacks is zero (G, c2, c3: +0.0f is all zero bits), then the span */
        memset(blob + info->payload_len, 0, IB_PARAMS_SIZE - info->payload_len);
        ib_params_unpack(blob, p);
        p->accel_t_min_c = p->gyro_t_min_c = SPAN_DEFAULT_MIN_C;
        p->accel_t_max_c = migrated_t_max(p->accel_t_ref_c);
        p->gyro_t_max_c = migrated_t_max(p->gyro_t_ref_c);
        return 1;
    }
    return 0;
}

static void load_params(ib_core_t *c)
{
    set_factory(c);
    c->param_generation = 0;
    c->param_slot = -1;
    if (!c->board->flash) {
        return;
    }
    ib_ps_info_t info;
    ib_params_t p;
    int ok = read_stored(c->board->flash, &p, &info);
    c->param_generation = info.generation;
    c->param_slot = (int8_t)info.slot;
    if (!ok) {
        return; /* none, cleared, unknown version: factory defaults, flagged in info */
    }
    ib_triad_corr_t a, g;
    if (ib_core_check_params(&p, &a, &g) != IB_ERROR_OK) {
        return; /* a stored block that fails today's checks is not applied */
    }
    c->params = p;
    c->corr_accel = a;
    c->corr_gyro = g;
    c->cal_ready = 0;
    c->param_source = IB_PARAM_SOURCE_FLASH;
}

/* ----------------------------------------------------------------- sensors */

/* The register code of full scale g on the accelerometer's part (protocol/parts.toml); 0: none. */
static uint8_t range_code(const ib_core_t *c, uint8_t g)
{
    const ib_part_range_t *r = ib_part_range(c->accel.part, g);
    return r ? r->code : 0u;
}

static void sensors_init(ib_core_t *c)
{
    const ib_spi_bus_t *bus = c->board->spi;
    c->present = 0;
    ib_adxl355_config_t cfg = {1u, 2u, 0u}; /* code 1: every part's lowest range */
    if (ib_adxl355_init(&c->accel, bus, IB_CS_ACCEL, &cfg) == IB_ADXL355_OK) {
        c->present |= 1u << IB_SENSOR_ACCEL;
        c->accel_range_g = (uint8_t)c->accel.part->default_full_scale;
    }
    for (int k = 0; k < 3; k++) {
        if (ib_adxrs450_init(&c->gyro[k], bus, (uint8_t)(IB_CS_GYRO_X + k)) == IB_ADXRS450_OK) {
            c->present |= (uint8_t)(1u << (IB_SENSOR_GYRO_X + k));
        }
    }
}

/* The ODR code for a stream rate: the lowest ODR (4000 Hz / 2^k) of which the stream period
 * is a whole multiple of at most ACCEL_FIFO_MAX_SETS samples (averaged per tick). -1: none. */
static int odr_for_rate(uint32_t rate_hz, uint32_t *avg)
{
    if (rate_hz == 0u || 1000000u % rate_hz != 0u) {
        return -1;
    }
    uint32_t period = 1000000u / rate_hz;
    for (int k = IB_ADXL355_ODR_CODE_MAX; k >= 0; k--) {
        uint32_t odr_period = ib_adxl355_odr_period_us((uint8_t)k);
        if (odr_period <= period && period % odr_period == 0u && period / odr_period <= ACCEL_FIFO_MAX_SETS) {
            *avg = period / odr_period;
            return k;
        }
    }
    return -1;
}

/* ------------------------------------------------------------------ stream */

static void emit_fault(ib_core_t *c, uint8_t sensor, uint8_t kind, uint8_t active, uint32_t detail)
{
    ib_msg_fault_event_t e = {sensor, kind, active, 0, detail};
    size_t n = ib_msg_fault_event_pack(&e, c->msg_raw + IB_HEADER_SIZE);
    send_unsolicited(c, IB_MSG_FAULT_EVENT, n);
}

/* Compare what this batch saw per sensor with what was last reported; report changes. */
static void report_faults(ib_core_t *c)
{
    uint8_t kind[4] = {0, 0, 0, 0};
    uint32_t detail[4] = {0, 0, 0, 0};
    if (!(c->present & 1u)) {
        kind[0] = IB_FAULT_KIND_MISSING;
    } else if (c->batch_spi_error & 1u) {
        kind[0] = IB_FAULT_KIND_SPI_ERROR;
    } else if (c->batch_hdr.accel_status & 0x04u) {
        kind[0] = IB_FAULT_KIND_ACCEL_FIFO_OVERRUN;
    } else if (c->batch_hdr.sensor_flags & IB_BATCH_FLAGS_ACCEL_STALE) {
        kind[0] = IB_FAULT_KIND_ACCEL_STALE;
    }
    for (int k = 0; k < 3; k++) {
        uint8_t s = (uint8_t)(1 + k);
        if (!(c->present & (1u << s))) {
            kind[s] = IB_FAULT_KIND_MISSING;
        } else if (c->batch_spi_error & (1u << s)) {
            kind[s] = IB_FAULT_KIND_SPI_ERROR;
        } else if (c->batch_hdr.gyro_faults[k] & 1u) {
            kind[s] = IB_FAULT_KIND_PARITY;
        } else if (c->batch_hdr.gyro_faults[k] & 0xFEu) {
            kind[s] = IB_FAULT_KIND_GYRO_FAULT_BITS;
            detail[s] = c->batch_hdr.gyro_faults[k];
        } else if (c->batch_gyro_st_bad[k]) {
            kind[s] = IB_FAULT_KIND_GYRO_STATUS;
            detail[s] = c->batch_gyro_st_bad[k];
        }
    }
    for (uint8_t s = 0; s < 4; s++) {
        if (kind[s] != c->fault_state[s]) {
            if (c->fault_state[s]) {
                emit_fault(c, s, c->fault_state[s], 0, 0);
            }
            if (kind[s]) {
                emit_fault(c, s, kind[s], 1, detail[s]);
            }
            c->fault_state[s] = kind[s];
        }
    }
}

/* read_temps 0: the sample chain reads them (job_temps) */
static void batch_begin(ib_core_t *c, uint32_t t_us, int read_temps)
{
    memset(&c->batch_hdr, 0, sizeof c->batch_hdr);
    c->batch_hdr.sample_index = c->sample_index;
    c->batch_hdr.period_us = (uint16_t)(1000000u / c->rate_hz);
    c->batch_hdr.accel_range_g = c->accel_range_g;
    c->batch_hdr.sensor_flags = (uint8_t)(~c->present & 0x0Fu);
    if (c->drop_pending) {
        c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SAMPLES_DROPPED;
    }
    c->batch_t0_us = t_us;
    c->batch_n = 0;
    c->batch_spi_error = 0;
    memset(c->batch_gyro_st_bad, 0, sizeof c->batch_gyro_st_bad);
    /* temperatures once per batch */
    if (read_temps && (c->present & 1u)) {
        uint8_t t[2];
        if (ib_adxl355_read_regs(&c->accel, 0x06, t, 2) == IB_ADXL355_OK) {
            c->accel_temp_counts = (uint16_t)(((t[0] & 0x0Fu) << 8) | t[1]);
        } else {
            c->batch_spi_error |= 1u;
            c->stats.spi_errors++;
        }
    }
    for (int k = 0; k < 3 && read_temps; k++) {
        if (c->present & (1u << (1 + k))) {
            int16_t raw10;
            ib_adxrs450_err_t e = ib_adxrs450_read_temp(&c->gyro[k], &raw10);
            if (e == IB_ADXRS450_OK) {
                c->gyro_temp_raw10[k] = raw10;
            } else if (e == IB_ADXRS450_ERR_BUS) {
                c->batch_spi_error |= (uint8_t)(1u << (1 + k));
                c->stats.spi_errors++;
            }
        }
    }
    c->batch_hdr.accel_temp_counts = c->accel_temp_counts;
    for (int k = 0; k < 3; k++) {
        c->batch_hdr.gyro_temp_counts[k] = c->gyro_temp_raw10[k];
    }
}

static void batch_send(ib_core_t *c)
{
    if (c->batch_n == 0) {
        return;
    }
    int cal = c->stream_state == IB_STREAM_STATE_CALIBRATED;
    size_t rsize = cal ? IB_CAL_SAMPLE_SIZE : IB_RAW_SAMPLE_SIZE;
    c->batch_hdr.count = c->batch_n;
    if (c->batch_spi_error) {
        c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
    }
    ib_batch_header_pack(&c->batch_hdr, c->batch_buf + IB_HEADER_SIZE);
    size_t payload = IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * rsize;
    report_faults(c);
    /* the frame is encoded only when it can be sent whole, replies first */
    size_t worst = IB_HEADER_SIZE + payload + IB_CRC_SIZE + 3u;
    if (c->reply_pending == 0 && c->board->link_tx_free(c->board->ctx) >= worst + REPLY_RESERVE) {
        size_t n = ib_frame_encode(c->batch_buf, cal ? IB_MSG_CAL_BATCH : IB_MSG_RAW_BATCH, c->tx_seq,
                                   c->batch_t0_us, payload, c->tx_frame);
        c->tx_seq++;
        link_put(c, c->tx_frame, n);
        c->drop_pending = 0;
    } else {
        c->stats.frames_dropped++;
        c->stats.samples_dropped += c->batch_n;
        c->drop_pending = 1;
    }
    c->batch_n = 0;
}

/* What one sample read brought back, from the synchronous reads or the DMA chain. */
typedef struct {
    int accel_err;             /* IB_ADXL355_OK or the error */
    size_t total;              /* FIFO sets read */
    int32_t sum[3];            /* their sum */
    uint8_t st_or;             /* STATUS bits seen */
    ib_adxrs450_err_t gyro_err[3];
    ib_adxrs450_sample_t g[3];
} sample_in_t;

/* Read one sample of every sensor with the blocking bus calls (boards without bus->start). */
static void read_sync(ib_core_t *c, sample_in_t *in)
{
    memset(in, 0, sizeof *in);
    if (c->present & 1u) {
        /* every set the FIFO collected since the last tick, in chunks of 8 (small stack) */
        int32_t sets[8][3];
        size_t n = 0;
        int err = IB_ADXL355_OK;
        do {
            err = ib_adxl355_read_fifo(&c->accel, sets, 8u, &n);
            in->st_or |= c->accel.last_status;
            for (size_t i = 0; err == IB_ADXL355_OK && i < n; i++) {
                in->sum[0] += sets[i][0];
                in->sum[1] += sets[i][1];
                in->sum[2] += sets[i][2];
            }
            in->total += n;
        } while (err == IB_ADXL355_OK && n == 8u && in->total < ACCEL_FIFO_MAX_SETS + 8u);
        in->accel_err = err;
    }
    for (int k = 0; k < 3; k++) {
        if (c->present & (1u << (1 + k))) {
            in->gyro_err[k] = ib_adxrs450_read_rate(&c->gyro[k], &in->g[k]);
        }
    }
}

/* The calibrated stream's terms that change only with the temperatures (once a batch), the
 * range or the parameters. */
static void cal_prepare(ib_core_t *c)
{
    float ta[3], tg[3];
    const ib_part_desc_t *pa = c->accel.part ? c->accel.part : ib_part_by_id(IB_PART_ADXL355);
    float lsb = (float)ib_adxl355_part_lsb_per_g(pa, range_code(c, c->accel_range_g));
    float t_acc = pa->temp_ref_c + ((float)c->accel_temp_counts - pa->temp_offset_counts) / pa->temp_lsb_per_c;
    for (int k = 0; k < 3; k++) {
        const ib_part_desc_t *pg = c->gyro[k].part ? c->gyro[k].part : ib_part_by_id(IB_PART_ADXRS450);
        ta[k] = t_acc;
        c->gyro_rad_per_count[k] = RAD_PER_DEG / pg->ranges[0].lsb_per_unit;
        tg[k] = pg->temp_ref_c + ((float)c->gyro_temp_raw10[k] - pg->temp_offset_counts) / pg->temp_lsb_per_c;
    }
    /* the accelerometer's terms in counts: the sample's counts go in as they are */
    correct_terms(&c->params, 0, &c->corr_accel, ta, G0_MPS2 / lsb, lsb / G0_MPS2, c->cal_bias[0], c->cal_w[0]);
    correct_terms(&c->params, 1, &c->corr_gyro, tg, 1.0f, 1.0f, c->cal_bias[1], c->cal_w[1]);
    c->cal_ready = 1;
}

/* Append the sample to the batch (and send the batch when full). */
static void sample_commit(ib_core_t *c, const sample_in_t *in)
{
    uint8_t status = 0;
    int32_t acc[3] = {c->accel_last[0], c->accel_last[1], c->accel_last[2]};
    if (c->present & 1u) {
        if (in->accel_err != IB_ADXL355_OK) {
            c->batch_spi_error |= 1u;
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else if (in->total == 0) {
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_ACCEL_STALE;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else {
            const int32_t n_sets = (int32_t)in->total, h = n_sets / 2; /* 32-bit: no libgcc divide */
            for (int k = 0; k < 3; k++) {
                /* rounded mean, symmetric about zero */
                int32_t sum = in->sum[k];
                acc[k] = n_sets == 1 ? sum : sum >= 0 ? (sum + h) / n_sets : -((-sum + h) / n_sets);
                c->accel_last[k] = acc[k];
            }
        }
        c->batch_hdr.accel_status |= in->st_or;
    } else {
        status |= IB_SAMPLE_STATUS_ACCEL_BAD;
    }
    int16_t rate[3] = {0, 0, 0};
    for (int k = 0; k < 3; k++) {
        uint8_t bad = (uint8_t)(IB_SAMPLE_STATUS_GYRO_X_BAD << k);
        if (!(c->present & (1u << (1 + k)))) {
            status |= bad;
            continue;
        }
        const ib_adxrs450_sample_t *s = &in->g[k];
        if (in->gyro_err[k] == IB_ADXRS450_ERR_BUS) {
            c->batch_spi_error |= (uint8_t)(1u << (1 + k));
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= bad;
            continue;
        }
        rate[k] = s->rate_counts;
        c->batch_hdr.gyro_faults[k] |= (uint8_t)(s->faults | (s->parity_error ? 1u : 0u));
        if (s->st != 1u) {
            c->batch_gyro_st_bad[k] = (uint8_t)(s->st | 0x80u);
        }
        if (!s->good) {
            status |= bad;
        }
    }
    if (status) {
        c->stats.sensor_faults++;
    }
    uint8_t *rec;
    if (c->stream_state == IB_STREAM_STATE_CALIBRATED) {
        ib_cal_sample_t cs;
        float u[3], w[3];
        if (c->batch_n == 0 || !c->cal_ready) {
            cal_prepare(c); /* the temperatures are new at a batch's first sample */
        }
        for (int k = 0; k < 3; k++) {
            u[k] = (float)acc[k]; /* counts: cal_prepare put the scale into cal_w[0] */
            w[k] = (float)rate[k] * c->gyro_rad_per_count[k]; /* the part's scale, cal_prepare */
        }
        correct_apply(c->cal_w[0], u, c->cal_bias[0], cs.accel_mps2);
        const float *gs = c->params.gyro_g_rad_s_per_mps2; /* g-sensitivity: w − G·a first */
        for (int k = 0; k < 3; k++) {
            /* cs.accel_mps2 is written whole by correct_apply above; cppcheck does not follow it */
            // cppcheck-suppress uninitvar
            w[k] -= gs[k * 3] * cs.accel_mps2[0] + gs[k * 3 + 1] * cs.accel_mps2[1] + gs[k * 3 + 2] * cs.accel_mps2[2];
        }
        correct_apply(c->cal_w[1], w, c->cal_bias[1], cs.rate_rad_s);
        cs.status = status;
        rec = c->batch_buf + IB_HEADER_SIZE + IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * IB_CAL_SAMPLE_SIZE;
        ib_cal_sample_pack(&cs, rec);
    } else {
        ib_raw_sample_t rs = {acc[0], acc[1], acc[2], status, {rate[0], rate[1], rate[2]}};
        rec = c->batch_buf + IB_HEADER_SIZE + IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * IB_RAW_SAMPLE_SIZE;
        ib_raw_sample_pack(&rs, rec);
    }
    c->batch_n++;
    c->sample_index++;
    c->stats.samples_produced++;
    if (c->batch_n >= c->batch_max) {
        batch_send(c);
    }
}

/* ---- the sample read as a chain of DMA transfers (bus->start) ----
 * Steps: 0 ADXL355 STATUS, FIFO_ENTRIES, TEMP2, TEMP1 in one burst; 1 pop the FIFO (the
 * whole sets the header counted, at most JOB_FIFO_SETS); 2 + 2k: gyro k's frame, whose reply
 * is the rate latched by the previous sample's frame (the pipelined read of adxrs450.h: one
 * frame per gyro instead of two, the rate one sample period old); at the start of a batch
 * that frame sends "read TEM" instead and step 3 + 2k the sensor-data command, whose reply is
 * the temperature. The steps that apply (sensors present) are listed at each batch start
 * (job_plan), so a step's work in the interrupt is to take the next entry. Each step is
 * started from the previous one's completion interrupt (job_next); the main loop is free
 * meanwhile and finishes the sample (sample_finish) when job_done is set. */
#define JOB_FIFO_SETS (IB_ADXL355_FIFO_SIZE / 3u) /* the whole FIFO: 160 Hz takes 25 sets a tick */
#define JOB_WAIT_US 5000u
enum { JOB_PLAIN = 0, JOB_HDR = 1, JOB_FIFO = 2 };

static void job_next(void *arg, int rc);

static void job_add(ib_job_step_t **s, const uint8_t *tx, uint8_t *rx, uint8_t len, uint8_t cs, uint8_t sensor,
                    uint8_t kind)
{
    ib_job_step_t *e = (*s)++;
    e->tx = tx;
    e->rx = rx;
    e->len = len;
    e->cs = cs;
    e->sensor = sensor;
    e->kind = kind;
}

/* List the transfers of a chain for the sensors present (temps: a batch start's). */
static void job_plan(ib_core_t *c, uint8_t temps)
{
    ib_job_step_t *s = c->job_list;
    if (c->present & 1u) {
        job_add(&s, c->job_hdr_tx, c->job_hdr_rx, temps ? (uint8_t)sizeof c->job_hdr_tx : 3u, IB_CS_ACCEL, 0u,
                JOB_HDR);
        job_add(&s, ib_adxl355_fifo_read_tx, c->job_fifo_rx, 0u, IB_CS_ACCEL, 0u, JOB_FIFO);
    }
    for (uint8_t k = 0; k < 3u; k++) {
        if (!(c->present & (1u << (1u + k)))) {
            continue;
        }
        uint8_t cs = (uint8_t)(IB_CS_GYRO_X + k);
        job_add(&s, temps ? c->job_tem_tx : c->job_gyro_tx, c->job_gyro_rx[k][0], 4u, cs, (uint8_t)(1u + k),
                JOB_PLAIN);
        if (temps) {
            job_add(&s, c->job_gyro_tx, c->job_gyro_rx[k][1], 4u, cs, (uint8_t)(1u + k), JOB_PLAIN);
        }
    }
    c->job_end = s;
    c->job_list_temps = temps;
}

/* Start the first transfer at or after s that applies (its sensor has not failed; the FIFO
 * pop only when the header counted entries); the chain is over when none is left. */
static void job_run(ib_core_t *c, const ib_job_step_t *s)
{
    const ib_spi_bus_t *b = c->board->spi;
    for (; s < c->job_end; s++) {
        if (c->job_rc[s->sensor]) {
            continue;
        }
        size_t len = s->len;
        if (s->kind == JOB_FIFO) {
            if (c->job_fifo_n == 0u) {
                continue;
            }
            len = 1u + 3u * (size_t)c->job_fifo_n;
        }
        c->job_cur = s;
        if (b->start(b->ctx, s->cs, s->tx, s->rx, len, job_next, c) == 0) {
            return;
        }
        c->job_rc[s->sensor] = -1;
    }
    c->job_busy = 0;
    c->job_done = 1;
}

/* A transfer of the chain ended (bus interrupt): note it, start the next. */
static void job_next(void *arg, int rc)
{
    ib_core_t *c = (ib_core_t *)arg;
    const ib_job_step_t *s = c->job_cur;
    if (rc < 0) {
        c->job_rc[s->sensor] = -1;
    } else if (s->kind == JOB_HDR) {
        c->job_fifo_n = (uint8_t)ib_adxl355_fifo_entries(&c->accel, &c->job_hdr_rx[1], JOB_FIFO_SETS);
    }
    job_run(c, s + 1);
}

static void job_begin(ib_core_t *c, uint8_t temps)
{
    memset(c->job_rc, 0, sizeof c->job_rc);
    c->job_temps = temps;
    c->job_fifo_n = 0;
    c->job_done = 0;
    c->job_busy = 1;
    if (c->job_list_temps != temps) {
        job_plan(c, temps);
    }
    job_run(c, c->job_list);
}

/* Turn what the chain brought back into the sample. */
static void sample_finish(ib_core_t *c)
{
    sample_in_t in; /* every field sample_commit reads is set below (no memset: once a sample) */
    in.accel_err = IB_ADXL355_OK;
    in.total = 0;
    in.sum[0] = in.sum[1] = in.sum[2] = 0;
    in.st_or = 0;
    c->job_done = 0;
    if (c->present & 1u) {
        if (c->job_rc[0] != 0) {
            in.accel_err = IB_ADXL355_ERR_BUS;
        } else {
            in.st_or = c->accel.last_status;
            if (c->job_temps) {
                c->accel_temp_counts = (uint16_t)(((c->job_hdr_rx[3] & 0x0Fu) << 8) | c->job_hdr_rx[4]);
                c->batch_hdr.accel_temp_counts = c->accel_temp_counts;
            }
            if (c->job_fifo_n) {
                int32_t sets[8][3]; /* in chunks of 8 sets (small stack) */
                ib_adxl355_fifo_parse_t p;
                ib_adxl355_fifo_parse_init(&p);
                size_t total = 0;
                for (size_t e0 = 0; e0 < c->job_fifo_n && !p.empty; e0 += 24u) {
                    size_t n = c->job_fifo_n - e0 < 24u ? c->job_fifo_n - e0 : 24u;
                    p.sets = 0;
                    ib_adxl355_fifo_parse(&c->accel, &p, &c->job_fifo_rx[1u + 3u * e0], n, sets, 8u);
                    for (size_t i = 0; i < p.sets; i++) {
                        in.sum[0] += sets[i][0];
                        in.sum[1] += sets[i][1];
                        in.sum[2] += sets[i][2];
                    }
                    total += p.sets;
                }
                ib_adxl355_fifo_parse_end(&c->accel, &p);
                p.sets = total;
                in.total = p.sets;
            }
        }
    }
    for (int k = 0; k < 3; k++) {
        if (!(c->present & (1u << (1 + k)))) {
            continue;
        }
        if (c->job_rc[1 + k] != 0) {
            ib_adxrs450_note_bus_error(&c->gyro[k]);
            in.gyro_err[k] = IB_ADXRS450_ERR_BUS;
            continue;
        }
        in.gyro_err[k] = ib_adxrs450_rate_from_reply(&c->gyro[k], ib_adxrs450_word(c->job_gyro_rx[k][0]), &in.g[k]);
        int16_t raw10;
        if (c->job_temps &&
            ib_adxrs450_temp_from_reply(&c->gyro[k], ib_adxrs450_word(c->job_gyro_rx[k][1]), &raw10) == IB_ADXRS450_OK) {
            c->gyro_temp_raw10[k] = raw10;
            c->batch_hdr.gyro_temp_counts[k] = raw10;
        }
    }
    sample_commit(c, &in);
}

/* Let a running chain end (bounded) and finish its sample: before anything else uses the
 * bus or the batch. */
static void job_wait(ib_core_t *c)
{
    if (c->job_busy) {
        uint32_t t0 = now_us(c);
        while (c->job_busy && now_us(c) - t0 < JOB_WAIT_US) {
        }
        if (c->job_busy) { /* the bus never completed: report every sensor's read as failed */
            c->job_busy = 0;
            memset(c->job_rc, 0xFF, sizeof c->job_rc);
            c->job_done = 1;
        }
    }
    if (c->job_done) {
        sample_finish(c);
    }
}

void ib_core_tick(ib_core_t *c, uint32_t missed, uint32_t due_us)
{
    if (c->stream_state == IB_STREAM_STATE_STOPPED) {
        return;
    }
    job_wait(c);
    /* the periodic stats: checked once a sample (not on every main-loop pass, each a time read) */
    update_uptime(c);
    if (c->uptime_ms - c->last_stats_ms >= STATS_PERIOD_MS) {
        c->last_stats_ms = c->uptime_ms;
        ib_msg_stats_t s = c->stats;
        s.request_id = 0;
        s.uptime_ms = c->uptime_ms;
        size_t len = ib_msg_stats_pack(&s, c->msg_raw + IB_HEADER_SIZE);
        send_unsolicited(c, IB_MSG_STATS, len);
    }
    if (missed) {
        /* samples inside a batch are consecutive: close the batch, then skip */
        batch_send(c);
        c->sample_index += missed;
        c->stats.samples_dropped += missed;
        c->drop_pending = 1;
    }
    const int async = c->board->spi->start != NULL;
    const uint8_t first = c->batch_n == 0;
    if (first) {
        batch_begin(c, due_us, !async);
    }
    if (async) {
        job_begin(c, first);
        return;
    }
    sample_in_t in;
    read_sync(c, &in);
    sample_commit(c, &in);
}

static void stream_stop(ib_core_t *c)
{
    job_wait(c);
    batch_send(c);
    c->stream_state = IB_STREAM_STATE_STOPPED;
    c->board->set_tick_hz(c->board->ctx, 0);
}

/* ---------------------------------------------------------------- commands */

static void info_fill(ib_core_t *c, ib_msg_info_t *m, uint16_t rid)
{
    memset(m, 0, sizeof *m);
    const ib_board_t *b = c->board;
    m->request_id = rid;
    m->protocol_version = IB_PROTOCOL_VERSION;
    m->board = b->board_id;
    m->fw_version[0] = FW_VERSION_MAJOR;
    m->fw_version[1] = FW_VERSION_MINOR;
    m->fw_version[2] = FW_VERSION_PATCH;
    m->clock_source = b->clock_source;
    if (b->build) {
        strncpy(m->fw_build, b->build, sizeof m->fw_build - 1u);
    }
    memcpy(m->mcu_uid, b->uid, sizeof m->mcu_uid);
    m->sensors_present = c->present;
    m->accel_range_g = c->accel_range_g;
    m->parts[0] = c->accel.part && (c->present & 1u) ? c->accel.part->part : IB_PART_NONE;
    for (int k = 0; k < 3; k++) {
        m->parts[1 + k] = c->gyro[k].part && (c->present & (2u << k)) ? c->gyro[k].part->part : IB_PART_NONE;
    }
    m->accel_ids[0] = c->accel.devid_ad;
    m->accel_ids[1] = c->accel.devid_mst;
    m->accel_ids[2] = c->accel.partid;
    m->accel_ids[3] = c->accel.revid;
    for (int k = 0; k < 3; k++) {
        m->gyro_pid[k] = c->gyro[k].pid;
        m->gyro_sn[k] = c->gyro[k].serial;
    }
    m->stream_state = c->stream_state;
    m->param_source = c->param_source;
    m->stream_rate_hz = c->stream_state ? c->rate_hz : 0;
    m->max_rate_hz = 4000;
    m->param_block_version = IB_PARAM_BLOCK_VERSION;
    m->param_generation = c->param_generation;
    m->baud = b->baud;
    m->uptime_ms = c->uptime_ms;
}

/* Build the reply (optional data message + ack) into c->last_reply and mark it pending. */
static void reply(ib_core_t *c, uint16_t rid, uint8_t command, uint8_t error, uint32_t value,
                  uint8_t data_type, size_t data_len)
{
    c->last_reply_n = 0;
    /* the stored reply now answers this frame: until on_frame records the command it ran,
     * nothing may be answered from it (a nacked frame after a command must not make a retry
     * of that command receive this nack) */
    c->last_rid_valid = 0;
    if (data_type) {
        c->last_reply_len[c->last_reply_n] = (uint16_t)encode_msg(c, data_type, data_len, c->last_reply[c->last_reply_n]);
        c->last_reply_n++;
    }
    ib_msg_ack_t a = {rid, command, error, value};
    size_t n = ib_msg_ack_pack(&a, c->msg_raw + IB_HEADER_SIZE);
    c->last_reply_len[c->last_reply_n] = (uint16_t)encode_msg(c, IB_MSG_ACK, n, c->last_reply[c->last_reply_n]);
    c->last_reply_n++;
    c->reply_pending = c->last_reply_n;
    if (error != IB_ERROR_OK) {
        c->stats.bad_commands++;
    }
}

/* Send pending reply frames as the link takes them; true when none is left. */
static int flush_reply(ib_core_t *c)
{
    while (c->reply_pending) {
        uint8_t i = (uint8_t)(c->last_reply_n - c->reply_pending);
        size_t n = c->last_reply_len[i];
        if (c->board->link_tx_free(c->board->ctx) < n) {
            return 0;
        }
        link_put(c, c->last_reply[i], n);
        c->reply_pending--;
    }
    return 1;
}

static uint8_t do_start_stream(ib_core_t *c, const ib_msg_start_stream_t *m, uint32_t *value)
{
    static const uint16_t rates[IB_STREAM_RATES_COUNT] = IB_STREAM_RATES_HZ;
    int listed = 0;
    for (unsigned i = 0; i < IB_STREAM_RATES_COUNT; i++) {
        listed |= rates[i] == m->rate_hz;
    }
    uint32_t avg = 0;
    int odr = listed ? odr_for_rate(m->rate_hz, &avg) : -1;
    uint8_t maxb = m->mode == IB_STREAM_MODE_CALIBRATED ? IB_MSG_CAL_BATCH_MAX_RECORDS : IB_MSG_RAW_BATCH_MAX_RECORDS;
    if (odr < 0 || m->rate_hz > 4000u || m->mode > IB_STREAM_MODE_CALIBRATED || m->batch > maxb ||
        (m->accel_range_g != 0u && (c->present & 1u) && range_code(c, m->accel_range_g) == 0u)) {
        return IB_ERROR_BAD_ARGUMENT;
    }
    if (c->stream_state != IB_STREAM_STATE_STOPPED) {
        stream_stop(c);
    }
    if (m->accel_range_g) {
        c->accel_range_g = m->accel_range_g;
    }
    if (c->present & 1u) {
        ib_adxl355_config_t cfg = {range_code(c, c->accel_range_g), (uint8_t)odr, 0u};
        if (ib_adxl355_configure(&c->accel, &cfg) != IB_ADXL355_OK) {
            c->stats.spi_errors++;
        }
        int32_t sink[8][3];
        size_t n = 0, left = ACCEL_FIFO_MAX_SETS;
        do { /* start with an empty FIFO */
            if (ib_adxl355_read_fifo(&c->accel, sink, 8u, &n) != IB_ADXL355_OK) {
                break;
            }
            left = left > n ? left - n : 0;
        } while (n == 8u && left);
    }
    if (c->board->spi->start) { /* pipelined rate reads: the first frame's reply must be a rate */
        for (int k = 0; k < 3; k++) {
            if ((c->present & (1u << (1 + k))) && ib_adxrs450_prime_rate(&c->gyro[k]) == IB_ADXRS450_ERR_BUS) {
                c->stats.spi_errors++;
            }
        }
    }
    c->rate_hz = m->rate_hz;
    uint32_t auto_b = m->rate_hz / 250u;
    c->batch_max = m->batch ? m->batch : (uint8_t)(auto_b < 1u ? 1u : auto_b > maxb ? maxb : auto_b);
    c->sample_index = 0;
    c->batch_n = 0;
    c->drop_pending = 0;
    memset(c->fault_state, 0, sizeof c->fault_state);
    c->job_list_temps = 0xFFu; /* list the chain's transfers again (the sensors present) */
    c->stream_state = m->mode == IB_STREAM_MODE_CALIBRATED ? IB_STREAM_STATE_CALIBRATED : IB_STREAM_STATE_RAW;
    c->board->set_tick_hz(c->board->ctx, m->rate_hz);
    *value = c->batch_max;
    return IB_ERROR_OK;
}

static uint8_t do_self_test(ib_core_t *c, ib_msg_self_test_result_t *r)
{
    memset(r, 0, sizeof *r);
    if (c->present & 1u) {
        r->tested |= 1u;
        ib_adxl355_selftest_t st;
        int e = ib_adxl355_self_test(&c->accel, &st);
        for (int k = 0; k < 3; k++) {
            r->accel_delta_counts[k] = st.delta_counts[k];
        }
        if (e == IB_ADXL355_OK) {
            r->passed |= 1u;
        }
    }
    for (int k = 0; k < 3; k++) {
        if (!(c->present & (1u << (1 + k)))) {
            continue;
        }
        r->tested |= (uint8_t)(1u << (1 + k));
        /* the CHK sequence is part of the start-up: run it again */
        ib_adxrs450_err_t e = ib_adxrs450_init(&c->gyro[k], c->board->spi, (uint8_t)(IB_CS_GYRO_X + k));
        r->gyro_chk_faults[k] = c->gyro[k].chk_faults;
        if (e == IB_ADXRS450_OK) {
            r->passed |= (uint8_t)(1u << (1 + k));
        }
    }
    return r->passed == r->tested ? IB_ERROR_OK : IB_ERROR_SELF_TEST_FAILED;
}

static void execute(ib_core_t *c, const ib_frame_t *f)
{
    uint16_t rid = f->seq;
    uint8_t t = f->type;
    uint8_t err = IB_ERROR_OK;
    uint32_t value = 0;
    uint8_t data_type = 0;
    size_t data_len = 0;
    uint8_t *out = c->msg_raw + IB_HEADER_SIZE;
    int streaming = c->stream_state != IB_STREAM_STATE_STOPPED;
    switch (t) {
    case IB_MSG_PING: {
        ib_msg_ping_t m;
        ib_msg_ping_unpack(f->payload, &m);
        value = m.nonce;
        break;
    }
    case IB_MSG_GET_INFO: {
        ib_msg_info_t m;
        update_uptime(c);
        info_fill(c, &m, rid);
        data_type = IB_MSG_INFO;
        data_len = ib_msg_info_pack(&m, out);
        break;
    }
    case IB_MSG_START_STREAM: {
        ib_msg_start_stream_t m;
        ib_msg_start_stream_unpack(f->payload, &m);
        err = do_start_stream(c, &m, &value);
        break;
    }
    case IB_MSG_STOP_STREAM:
        if (streaming) {
            stream_stop(c);
        }
        break;
    case IB_MSG_SET_PARAMS: {
        ib_msg_set_params_t m;
        ib_msg_set_params_unpack(f->payload, &m);
        ib_triad_corr_t a, g;
        err = ib_core_check_params(&m.params, &a, &g);
        if (err == IB_ERROR_OK) {
            c->params = m.params;
            c->corr_accel = a;
            c->corr_gyro = g;
            c->cal_ready = 0; /* applied from the next sample */
            c->param_source = IB_PARAM_SOURCE_UNSAVED;
        }
        break;
    }
    case IB_MSG_GET_PARAMS: {
        ib_msg_get_params_t m;
        ib_msg_get_params_unpack(f->payload, &m);
        ib_msg_params_readback_t r;
        memset(&r, 0, sizeof r);
        r.request_id = rid;
        r.which = m.which;
        r.generation = c->param_generation;
        if (m.which == IB_PARAMS_WHICH_ACTIVE) {
            r.source = c->param_source;
            r.params = c->params;
        } else if (m.which == IB_PARAMS_WHICH_STORED) {
            ib_ps_info_t info;
            if (c->board->flash && read_stored(c->board->flash, &r.params, &info)) {
                r.source = IB_PARAM_SOURCE_FLASH;
            } else {
                identity_params(&r.params);
                r.source = IB_PARAM_SOURCE_FACTORY;
            }
        } else {
            err = IB_ERROR_BAD_ARGUMENT;
            break;
        }
        data_type = IB_MSG_PARAMS_READBACK;
        data_len = ib_msg_params_readback_pack(&r, out);
        break;
    }
    case IB_MSG_SAVE_PARAMS: {
        if (streaming) {
            err = IB_ERROR_STREAMING;
            break;
        }
        uint8_t blob[IB_PARAMS_SIZE];
        ib_params_pack(&c->params, blob);
        ib_ps_info_t info;
        ib_ps_status_t st = c->board->flash ? ib_ps_save(c->board->flash, IB_PARAM_BLOCK_VERSION, blob,
                                                        sizeof blob, &info)
                                            : IB_PS_ERR_BAD_ARG;
        if (st == IB_PS_OK) {
            c->param_generation = info.generation;
            c->param_slot = (int8_t)info.slot;
            c->param_source = IB_PARAM_SOURCE_FLASH;
            value = (info.generation & ~IB_SAVE_UNCHANGED_FLAG) | (info.unchanged ? IB_SAVE_UNCHANGED_FLAG : 0u);
        } else {
            err = IB_ERROR_FLASH_ERROR;
            value = (uint32_t)(int32_t)st;
        }
        break;
    }
    case IB_MSG_CLEAR_PARAMS: {
        if (streaming) {
            err = IB_ERROR_STREAMING;
            break;
        }
        ib_ps_info_t info;
        ib_ps_status_t st = c->board->flash ? ib_ps_clear(c->board->flash, &info) : IB_PS_ERR_BAD_ARG;
        if (st == IB_PS_OK || st == IB_PS_CLEARED) {
            set_factory(c);
            c->param_generation = info.generation;
            c->param_slot = (int8_t)info.slot;
        } else {
            err = IB_ERROR_FLASH_ERROR;
            value = (uint32_t)(int32_t)st;
        }
        break;
    }
    case IB_MSG_REBOOT:
        c->reboot_pending = 1;
        break;
    case IB_MSG_SELF_TEST: {
        if (streaming) {
            err = IB_ERROR_STREAMING;
            break;
        }
        ib_msg_self_test_result_t r;
        err = do_self_test(c, &r);
        r.request_id = rid;
        data_type = IB_MSG_SELF_TEST_RESULT;
        data_len = ib_msg_self_test_result_pack(&r, out);
        break;
    }
    case IB_MSG_GET_STATS: {
        ib_msg_get_stats_t m;
        ib_msg_get_stats_unpack(f->payload, &m);
        update_uptime(c);
        ib_msg_stats_t s = c->stats;
        s.request_id = rid;
        s.uptime_ms = c->uptime_ms;
        /* Every record written (save or clear) takes the next generation and goes into the
         * slot not holding the current one, erasing it first: after generation G the slot
         * holding it was erased (G + 1) / 2 times and the other G / 2 times. A lower bound:
         * erases of interrupted saves and of a chip erase are not counted (SPEC.md). */
        if (c->param_slot == 0 || c->param_slot == 1) {
            s.param_slot_erases[c->param_slot] = (c->param_generation + 1u) / 2u;
            s.param_slot_erases[1 - c->param_slot] = c->param_generation / 2u;
        }
        data_type = IB_MSG_STATS;
        data_len = ib_msg_stats_pack(&s, out);
        if (m.reset) {
            memset(&c->stats, 0, sizeof c->stats);
        }
        break;
    }
    default:
        err = IB_ERROR_UNKNOWN_COMMAND;
        break;
    }
    reply(c, rid, t, err, value, data_type, data_len);
}

static void on_frame(ib_core_t *c, int status, const ib_frame_t *f)
{
    switch (status) {
    case IB_FRAME_OK:
        break;
    case IB_FRAME_BAD_VERSION:
        reply(c, f->seq, f->type, IB_ERROR_BAD_VERSION, f->version, 0, 0);
        return;
    case IB_FRAME_UNKNOWN_TYPE:
        reply(c, f->seq, f->type, IB_ERROR_UNKNOWN_COMMAND, 0, 0, 0);
        return;
    case IB_FRAME_BAD_LENGTH:
        reply(c, f->seq, f->type, IB_ERROR_BAD_LENGTH, (uint32_t)f->payload_len, 0, 0);
        return;
    case IB_FRAME_BAD_ENUM:
    case IB_FRAME_OUT_OF_RANGE:
    case IB_FRAME_NOT_FINITE:
    case IB_FRAME_BAD_FLAGS:
        /* readable, but a field holds what the definition does not allow: the value says which
         * check (the ib_frame_status_t) */
        reply(c, f->seq, f->type, IB_ERROR_BAD_ARGUMENT, (uint32_t)status, 0, 0);
        return;
    default:
        c->stats.rx_frame_errors++; /* nothing in it can be trusted: no answer */
        return;
    }
    if (!ib_msg_is_command(f->type)) {
        reply(c, f->seq, f->type, IB_ERROR_UNKNOWN_COMMAND, 0, 0, 0);
        return;
    }
    /* a retry is the same command again: same request id, type and payload byte for byte
     * (not a checksum of them: two different payloads can share any checksum). Answer it
     * from the stored reply, do not run it again. */
    if (c->last_rid_valid && f->seq == c->last_rid && f->type == c->last_cmd_type &&
        f->payload_len == c->last_cmd_len && memcmp(f->payload, c->last_cmd_payload, f->payload_len) == 0) {
        c->reply_pending = c->last_reply_n;
        return;
    }
    execute(c, f);
    /* commands have fixed layouts no longer than IB_MAX_COMMAND_PAYLOAD (the length check ran
     * before); anything longer is not remembered, so it can never be taken for a retry */
    c->last_rid_valid = f->payload_len <= sizeof c->last_cmd_payload;
    if (c->last_rid_valid) {
        c->last_rid = f->seq;
        c->last_cmd_type = f->type;
        c->last_cmd_len = (uint16_t)f->payload_len;
        memcpy(c->last_cmd_payload, f->payload, f->payload_len);
    }
}

/* -------------------------------------------------------------------- boot */

void ib_core_init(ib_core_t *c, const ib_board_t *b)
{
    memset(c, 0, sizeof *c);
    c->board = b;
    c->accel_range_g = 2;
    c->last_time_us = now_us(c);
    ib_frame_rx_init(&c->rx);
    c->job_list_temps = 0xFFu;
    c->job_hdr_tx[0] = ib_adxl355_read_cmd(IB_ADXL355_REG_STATUS);
    ib_adxrs450_rate_cmd_bytes(c->job_gyro_tx);
    ib_adxrs450_temp_cmd_bytes(c->job_tem_tx);
    b->set_tick_hz(b->ctx, 0);
    sensors_init(c);
    load_params(c);
    update_uptime(c);
    /* a 0x00 ends any partial frame the host holds, then the boot info (request id 0) */
    static const uint8_t zero = 0;
    if (b->link_tx_free(b->ctx) >= 1u) {
        (void)b->link_write(b->ctx, &zero, 1);
    }
    ib_msg_info_t m;
    info_fill(c, &m, 0);
    size_t n = ib_msg_info_pack(&m, c->msg_raw + IB_HEADER_SIZE);
    send_unsolicited(c, IB_MSG_INFO, n);
    for (uint8_t s = 0; s < 4; s++) {
        if (!(c->present & (1u << s))) {
            uint32_t detail = s == 0 ? ((uint32_t)c->accel.devid_ad << 16 | (uint32_t)c->accel.devid_mst << 8 |
                                        c->accel.partid)
                                     : c->gyro[s - 1].pid;
            emit_fault(c, s, IB_FAULT_KIND_MISSING, 1, detail);
            c->fault_state[s] = IB_FAULT_KIND_MISSING;
        }
    }
}

void ib_core_poll(ib_core_t *c)
{
    if (c->job_done) {
        sample_finish(c);
    }
    /* one command at a time: bytes after a command wait until its reply is out */
    (void)flush_reply(c);
    while (c->reply_pending == 0 && !c->reboot_pending) {
        if (c->rx_pos == c->rx_len) {
            c->rx_len = (uint8_t)c->board->link_read(c->board->ctx, c->rx_buf, sizeof c->rx_buf);
            c->rx_pos = 0;
            if (c->rx_len == 0) {
                break;
            }
        }
        ib_frame_t f;
        int st = ib_frame_rx_push(&c->rx, c->rx_buf[c->rx_pos++], &f);
        if (st >= 0) {
            on_frame(c, st, &f);
            (void)flush_reply(c);
        }
    }
    if (c->reboot_pending && c->reply_pending == 0) {
        c->reboot_pending = 0;
        c->board->reboot(c->board->ctx);
        return;
    }
}
