/* sim_json.c - see sim_json.h */
#define _GNU_SOURCE
#include "sim_json.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    sj_doc_t *d;
    char *p;
    int depth;
} parser_t;

static void skip_ws(parser_t *ps)
{
    while (*ps->p == ' ' || *ps->p == '\t' || *ps->p == '\n' || *ps->p == '\r') {
        ps->p++;
    }
}

static int new_node(parser_t *ps, sj_type_t t)
{
    if (ps->d->n >= SJ_MAX_NODES) {
        ps->d->error = "too many values";
        return -1;
    }
    int i = ps->d->n++;
    sj_node_t *n = &ps->d->nodes[i];
    memset(n, 0, sizeof *n);
    n->type = t;
    n->first = n->next = -1;
    return i;
}

static int hexval(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

static char *put_utf8(char *o, unsigned cp)
{
    if (cp < 0x80) {
        *o++ = (char)cp;
    } else if (cp < 0x800) {
        *o++ = (char)(0xC0 | (cp >> 6));
        *o++ = (char)(0x80 | (cp & 0x3F));
    } else if (cp < 0x10000) {
        *o++ = (char)(0xE0 | (cp >> 12));
        *o++ = (char)(0x80 | ((cp >> 6) & 0x3F));
        *o++ = (char)(0x80 | (cp & 0x3F));
    } else {
        *o++ = (char)(0xF0 | (cp >> 18));
        *o++ = (char)(0x80 | ((cp >> 12) & 0x3F));
        *o++ = (char)(0x80 | ((cp >> 6) & 0x3F));
        *o++ = (char)(0x80 | (cp & 0x3F));
    }
    return o;
}

/* At the opening quote; unescapes in place; returns the string start or NULL. */
static const char *parse_string(parser_t *ps)
{
    char *in = ps->p + 1, *out = in, *start = in;
    for (;;) {
        unsigned char c = (unsigned char)*in;
        if (c < 0x20) { /* includes the terminating NUL */
            ps->d->error = "bad string";
            return NULL;
        }
        if (c == '"') {
            ps->p = in + 1;
            *out = '\0';
            return start;
        }
        if (c != '\\') {
            *out++ = *in++;
            continue;
        }
        in++;
        switch (*in) {
        case '"': *out++ = '"'; break;
        case '\\': *out++ = '\\'; break;
        case '/': *out++ = '/'; break;
        case 'b': *out++ = '\b'; break;
        case 'f': *out++ = '\f'; break;
        case 'n': *out++ = '\n'; break;
        case 'r': *out++ = '\r'; break;
        case 't': *out++ = '\t'; break;
        case 'u': {
            unsigned cp = 0;
            for (int i = 1; i <= 4; i++) {
                int h = hexval(in[i]);
                if (h < 0) {
                    ps->d->error = "bad \\u escape";
                    return NULL;
                }
                cp = cp * 16 + (unsigned)h;
            }
            in += 4;
            if (cp >= 0xD800 && cp < 0xDC00 && in[1] == '\\' && in[2] == 'u') {
                unsigned lo = 0;
                int ok = 1;
                for (int i = 3; i <= 6; i++) {
                    int h = hexval(in[i]);
                    if (h < 0) {
                        ok = 0;
                        break;
                    }
                    lo = lo * 16 + (unsigned)h;
                }
                if (ok && lo >= 0xDC00 && lo < 0xE000) {
                    cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
                    in += 6;
                }
            }
            out = put_utf8(out, cp); /* never longer than the 6+ escape bytes it replaces */
            break;
        }
        default:
            ps->d->error = "bad escape";
            return NULL;
        }
        in++;
    }
}

static int parse_value(parser_t *ps);

static int parse_container(parser_t *ps, int is_obj)
{
    int node = new_node(ps, is_obj ? SJ_OBJ : SJ_ARR);
    if (node < 0) {
        return -1;
    }
    if (++ps->depth > 32) {
        ps->d->error = "nested too deeply";
        return -1;
    }
    ps->p++;
    skip_ws(ps);
    int last = -1;
    if (*ps->p == (is_obj ? '}' : ']')) {
        ps->p++;
        ps->depth--;
        return node;
    }
    for (;;) {
        const char *key = NULL;
        skip_ws(ps);
        if (is_obj) {
            if (*ps->p != '"') {
                ps->d->error = "expected a member name";
                return -1;
            }
            key = parse_string(ps);
            if (key == NULL) {
                return -1;
            }
            skip_ws(ps);
            if (*ps->p != ':') {
                ps->d->error = "expected ':'";
                return -1;
            }
            ps->p++;
        }
        int child = parse_value(ps);
        if (child < 0) {
            return -1;
        }
        ps->d->nodes[child].key = key;
        if (last < 0) {
            ps->d->nodes[node].first = child;
        } else {
            ps->d->nodes[last].next = child;
        }
        last = child;
        ps->d->nodes[node].count++;
        skip_ws(ps);
        if (*ps->p == ',') {
            ps->p++;
            continue;
        }
        if (*ps->p == (is_obj ? '}' : ']')) {
            ps->p++;
            ps->depth--;
            return node;
        }
        ps->d->error = is_obj ? "expected ',' or '}'" : "expected ',' or ']'";
        return -1;
    }
}

static int parse_value(parser_t *ps)
{
    skip_ws(ps);
    char c = *ps->p;
    if (c == '{' || c == '[') {
        return parse_container(ps, c == '{');
    }
    if (c == '"') {
        int n = new_node(ps, SJ_STR);
        if (n < 0) {
            return -1;
        }
        const char *s = parse_string(ps);
        if (s == NULL) {
            return -1;
        }
        ps->d->nodes[n].str = s;
        return n;
    }
    if (strncmp(ps->p, "true", 4) == 0 || strncmp(ps->p, "false", 5) == 0) {
        int n = new_node(ps, SJ_BOOL);
        if (n < 0) {
            return -1;
        }
        ps->d->nodes[n].num = c == 't' ? 1.0 : 0.0;
        ps->p += c == 't' ? 4 : 5;
        return n;
    }
    if (strncmp(ps->p, "null", 4) == 0) {
        ps->p += 4;
        return new_node(ps, SJ_NULL);
    }
    if (c == '-' || (c >= '0' && c <= '9')) {
        char *end;
        double v = strtod(ps->p, &end);
        if (end == ps->p) {
            ps->d->error = "bad number";
            return -1;
        }
        int n = new_node(ps, SJ_NUM);
        if (n < 0) {
            return -1;
        }
        ps->d->nodes[n].num = v;
        ps->p = end;
        return n;
    }
    ps->d->error = c == '\0' ? "unexpected end" : "unexpected character";
    return -1;
}

int sj_parse(sj_doc_t *d, char *text)
{
    parser_t ps = {d, text, 0};
    d->n = 0;
    d->error = NULL;
    int root = parse_value(&ps);
    if (root < 0) {
        return -1;
    }
    skip_ws(&ps);
    if (*ps.p != '\0') {
        d->error = "trailing characters";
        return -1;
    }
    return root;
}

int sj_get(const sj_doc_t *d, int obj, const char *key)
{
    if (obj < 0 || d->nodes[obj].type != SJ_OBJ) {
        return -1;
    }
    for (int c = d->nodes[obj].first; c >= 0; c = d->nodes[c].next) {
        if (strcmp(d->nodes[c].key, key) == 0) {
            return c;
        }
    }
    return -1;
}

int sj_at(const sj_doc_t *d, int arr, int i)
{
    if (arr < 0 || d->nodes[arr].type != SJ_ARR) {
        return -1;
    }
    int c = d->nodes[arr].first;
    while (c >= 0 && i-- > 0) {
        c = d->nodes[c].next;
    }
    return c;
}

/* ---- writer ---- */

static void reserve(sj_buf_t *b, size_t more)
{
    if (b->oom || b->len + more + 1 <= b->cap) {
        return;
    }
    size_t cap = b->cap ? b->cap : 256;
    while (cap < b->len + more + 1) {
        cap *= 2;
    }
    char *p = realloc(b->p, cap);
    if (p == NULL) {
        b->oom = 1;
        return;
    }
    b->p = p;
    b->cap = cap;
}

void sj_buf_free(sj_buf_t *b)
{
    free(b->p);
    memset(b, 0, sizeof *b);
}

static void append(sj_buf_t *b, const char *s, size_t n)
{
    reserve(b, n);
    if (b->oom) {
        return;
    }
    memcpy(b->p + b->len, s, n);
    b->len += n;
    b->p[b->len] = '\0';
}

void sj_raw(sj_buf_t *b, const char *s) { append(b, s, strlen(s)); }

void sj_printf(sj_buf_t *b, const char *fmt, ...)
{
    char tmp[512];
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(tmp, sizeof tmp, fmt, ap);
    va_end(ap);
    if (n < 0) {
        return;
    }
    if ((size_t)n < sizeof tmp) {
        append(b, tmp, (size_t)n);
        return;
    }
    reserve(b, (size_t)n);
    if (b->oom) {
        return;
    }
    va_start(ap, fmt);
    vsnprintf(b->p + b->len, (size_t)n + 1, fmt, ap);
    va_end(ap);
    b->len += (size_t)n;
}

void sj_str(sj_buf_t *b, const char *s)
{
    append(b, "\"", 1);
    for (; *s; s++) {
        unsigned char c = (unsigned char)*s;
        if (c == '"' || c == '\\') {
            char e[2] = {'\\', (char)c};
            append(b, e, 2);
        } else if (c < 0x20) {
            char e[8];
            snprintf(e, sizeof e, "\\u%04x", c);
            append(b, e, 6);
        } else {
            append(b, (const char *)&c, 1);
        }
    }
    append(b, "\"", 1);
}

void sj_num(sj_buf_t *b, double v)
{
    if (!isfinite(v)) {
        sj_raw(b, "null");
    } else if (v == floor(v) && fabs(v) < 9e15) {
        sj_printf(b, "%.0f", v);
    } else {
        sj_printf(b, "%.17g", v);
    }
}

void sj_vec(sj_buf_t *b, const double *v, int n)
{
    append(b, "[", 1);
    for (int i = 0; i < n; i++) {
        if (i) {
            append(b, ", ", 2);
        }
        sj_num(b, v[i]);
    }
    append(b, "]", 1);
}

void sj_key(sj_buf_t *b, const char *key)
{
    if (b->len > 0 && b->p[b->len - 1] != '{' && b->p[b->len - 1] != '[') {
        append(b, ", ", 2);
    }
    sj_str(b, key);
    append(b, ": ", 2);
}
