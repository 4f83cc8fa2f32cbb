/* sim_control_args.c - reading a control request's fields (one-line errors) and writing a reply. */
#define _GNU_SOURCE
#include "sim_control_priv.h"

int ctl_check_keys(req_t *q, int obj, const char *allowed)
{
    const sj_doc_t *d = q->d;
    for (int ch = d->nodes[obj].first; ch >= 0; ch = d->nodes[ch].next) {
        const char *k = d->nodes[ch].key;
        size_t kl = strlen(k);
        const char *p = allowed;
        int found = 0;
        while (*p) {
            const char *e = strchr(p, ',');
            size_t l = e ? (size_t)(e - p) : strlen(p);
            if (l == kl && strncmp(p, k, l) == 0) {
                found = 1;
                break;
            }
            p += l + (e ? 1 : 0);
        }
        if (!found) {
            return ctl_fail("unknown field '%s' (allowed: %s)", k, allowed);
        }
    }
    return 0;
}

int ctl_is_null(const sj_doc_t *d, int n) { return n < 0 || d->nodes[n].type == SJ_NULL; }

int ctl_node_num(const sj_doc_t *d, int n, const char *what, double *out)
{
    if (n < 0 || d->nodes[n].type != SJ_NUM || !isfinite(d->nodes[n].num)) {
        return ctl_fail("%s must be a finite number", what);
    }
    *out = d->nodes[n].num;
    return 0;
}

/* Optional number: 0 = absent (out untouched), 1 = read, -1 = error. */
int ctl_opt_num(req_t *q, int obj, const char *key, double *out)
{
    int n = sj_get(q->d, obj, key);
    if (ctl_is_null(q->d, n)) {
        return 0;
    }
    return ctl_node_num(q->d, n, key, out) == 0 ? 1 : -1;
}

int ctl_req_num(req_t *q, int obj, const char *key, double *out)
{
    int r = ctl_opt_num(q, obj, key, out);
    if (r == 0) {
        return ctl_fail("missing '%s'", key);
    }
    return r < 0 ? -1 : 0;
}

int ctl_node_vec(const sj_doc_t *d, int n, const char *what, double *out, int len,
                    int scalar_ok)
{
    if (n >= 0 && scalar_ok && d->nodes[n].type == SJ_NUM) {
        double v = 0.0;
        if (ctl_node_num(d, n, what, &v) != 0) {
            return -1;
        }
        for (int i = 0; i < len; i++) {
            out[i] = v;
        }
        return 0;
    }
    if (n < 0 || d->nodes[n].type != SJ_ARR || d->nodes[n].count != len) {
        return ctl_fail("%s must be an array of %d numbers%s", what, len, scalar_ok ? " (or one number)" : "");
    }
    for (int i = 0; i < len; i++) {
        if (ctl_node_num(d, sj_at(d, n, i), what, &out[i]) != 0) {
            return -1;
        }
    }
    return 0;
}

int ctl_node_mat3(const sj_doc_t *d, int n, const char *what, double m[3][3])
{
    if (n >= 0 && d->nodes[n].type == SJ_ARR && d->nodes[n].count == 9) {
        double f[9];
        if (ctl_node_vec(d, n, what, f, 9, 0) != 0) {
            return -1;
        }
        memcpy(m, f, sizeof f);
        return 0;
    }
    if (n < 0 || d->nodes[n].type != SJ_ARR || d->nodes[n].count != 3) {
        return ctl_fail("%s must be a 3x3 array (or 9 numbers, row-major)", what);
    }
    for (int i = 0; i < 3; i++) {
        if (ctl_node_vec(d, sj_at(d, n, i), what, m[i], 3, 0) != 0) {
            return -1;
        }
    }
    return 0;
}

int ctl_sensor_cs(req_t *q, int obj, int allow_accel)
{
    int n = sj_get(q->d, obj, "sensor");
    if (n < 0 || q->d->nodes[n].type != SJ_STR) {
        return ctl_fail("missing 'sensor' (\"accel\", \"gyro_x\", \"gyro_y\" or \"gyro_z\")");
    }
    const char *s = q->d->nodes[n].str;
    if (!strcmp(s, "accel") && allow_accel) {
        return IB_CS_ACCEL;
    }
    if (!strcmp(s, "gyro_x")) {
        return IB_CS_GYRO_X;
    }
    if (!strcmp(s, "gyro_y")) {
        return IB_CS_GYRO_Y;
    }
    if (!strcmp(s, "gyro_z")) {
        return IB_CS_GYRO_Z;
    }
    return ctl_fail("bad sensor '%s' (%s\"gyro_x\", \"gyro_y\" or \"gyro_z\")", s,
                allow_accel ? "\"accel\", " : "");
}

int ctl_opt_bool(req_t *q, int obj, const char *key, int dflt, int *out)
{
    int n = sj_get(q->d, obj, key);
    if (ctl_is_null(q->d, n)) {
        *out = dflt;
        return 0;
    }
    if (q->d->nodes[n].type != SJ_BOOL && q->d->nodes[n].type != SJ_NUM) {
        return ctl_fail("%s must be true or false", key);
    }
    *out = q->d->nodes[n].num != 0.0;
    return 0;
}

void ctl_put_vec(sj_buf_t *r, const char *key, const double *v, int n)
{
    sj_key(r, key);
    sj_vec(r, v, n);
}

void ctl_put_num(sj_buf_t *r, const char *key, double v)
{
    sj_key(r, key);
    sj_num(r, v);
}

void ctl_put_u64(sj_buf_t *r, const char *key, uint64_t v)
{
    sj_key(r, key);
    sj_printf(r, "%llu", (unsigned long long)v);
}

void ctl_put_bool(sj_buf_t *r, const char *key, int v)
{
    sj_key(r, key);
    sj_raw(r, v ? "true" : "false");
}
