/* core_params.c - the parameters: checks, the correction, factory values, loading from flash. */
#include "core_priv.h"

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
void ibc_correct_terms(const ib_params_t *p, int gyro, const ib_triad_corr_t *t, const float temp_c[3],
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

void ibc_correct_apply(const float w[3][3], const float u[3], const float bias[3], float out[3])
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
    ibc_correct_terms(p, gyro, t, temp_c, 1.0f, 1.0f, bias, w);
    ibc_correct_apply(w, u, bias, out);
}

void ibc_identity_params(ib_params_t *p)
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

void ibc_set_factory(ib_core_t *c)
{
    ibc_identity_params(&c->params);
    (void)ib_core_check_params(&c->params, &c->corr_accel, &c->corr_gyro);
    c->cal_ready = 0;
    c->param_source = IB_PARAM_SOURCE_FACTORY;
}

/* Layouts 2 and 1 of the parameter block: layout 3 without the bias polynomial's c2, c3
 * (4 x 3 float32) and the spans (4 int8); layout 1 also without gyro_g (9 float32). */
#define IB_PARAMS_SIZE_V2 (IB_PARAMS_SIZE - 52u)
#define IB_PARAMS_SIZE_V1 (IB_PARAMS_SIZE_V2 - 36u)
_Static_assert(IB_PARAM_BLOCK_VERSION == 3u, "ibc_read_stored migrates layouts 1 and 2 to layout 3: update it");

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
int ibc_read_stored(const ib_flash_if_t *fl, ib_params_t *p, ib_ps_info_t *info)
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

void ibc_load_params(ib_core_t *c)
{
    ibc_set_factory(c);
    c->param_generation = 0;
    c->param_slot = -1;
    if (!c->board->flash) {
        return;
    }
    ib_ps_info_t info;
    ib_params_t p;
    int ok = ibc_read_stored(c->board->flash, &p, &info);
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
