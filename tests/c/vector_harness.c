/*
 * vector_harness.c - drives the C codec from tests/wire/test_protocol_vectors.py.
 *
 * Reads commands on stdin, one per line, answers on stdout:
 *   decode HEX
 *       -> "err REASON" or "ok NAME SEQ TS", then "f PATH V..." per field and
 *          "r I PATH V..." per record field, then "end"
 *   encode NAME SEQ TS NREC   followed by "f PATH V..." / "r I PATH V..." lines, then "end"
 *       -> "hex HEX" (the whole frame with its 0x00) or "err REASON"
 *   step NOW PREV   (u32 device times) -> "step N": ib_time_step_us, the signed step
 * Values: integers in decimal, floats as %.9g (exact for float32), char arrays as hex.
 */
#define _POSIX_C_SOURCE 200809L
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "frame.h"
#include "protocol_desc_gen.h"
#include "wire.h"

#define MAX_LINE 4096

static const ib_desc_msg_t *find_msg(const char *name)
{
    for (const ib_desc_msg_t *m = ib_desc_messages; m->name; m++) {
        if (strcmp(m->name, name) == 0) {
            return m;
        }
    }
    return NULL;
}

static const ib_desc_field_t *find_field(const ib_desc_field_t *fs, const char *path)
{
    for (; fs && fs->name; fs++) {
        if (strcmp(fs->name, path) == 0) {
            return fs;
        }
    }
    return NULL;
}

static void print_field(const ib_desc_field_t *fd, const uint8_t *base)
{
    const uint8_t *p = base + fd->offset;
    if (fd->kind == 'c') {
        for (unsigned i = 0; i < fd->count; i++) {
            printf("%02x", p[i]);
        }
        return;
    }
    for (unsigned i = 0; i < fd->count; i++, p += fd->size) {
        if (i) {
            putchar(' ');
        }
        if (fd->kind == 'f') {
            float v;
            memcpy(&v, p, sizeof v);
            printf("%.9g", (double)v);
        } else if (fd->kind == 'i') {
            long long v = 0;
            if (fd->size == 1) { int8_t x; memcpy(&x, p, 1); v = x; }
            else if (fd->size == 2) { int16_t x; memcpy(&x, p, 2); v = x; }
            else { int32_t x; memcpy(&x, p, 4); v = x; }
            printf("%lld", v);
        } else {
            unsigned long long v = 0;
            if (fd->size == 1) { uint8_t x; memcpy(&x, p, 1); v = x; }
            else if (fd->size == 2) { uint16_t x; memcpy(&x, p, 2); v = x; }
            else if (fd->size == 4) { uint32_t x; memcpy(&x, p, 4); v = x; }
            else { uint64_t x; memcpy(&x, p, 8); v = x; }
            printf("%llu", v);
        }
    }
}

static int set_field(const ib_desc_field_t *fd, uint8_t *base, char *vals)
{
    uint8_t *p = base + fd->offset;
    if (fd->kind == 'c') {
        size_t n = strlen(vals);
        for (unsigned i = 0; i < fd->count; i++) {
            unsigned b = 0;
            if (2 * i + 1 < n) {
                sscanf(vals + 2 * i, "%2x", &b);
            }
            p[i] = (uint8_t)b;
        }
        return 0;
    }
    char *save = NULL;
    char *tok = strtok_r(vals, " ", &save);
    for (unsigned i = 0; i < fd->count; i++, p += fd->size) {
        if (!tok) {
            return -1;
        }
        if (fd->kind == 'f') {
            float v = strtof(tok, NULL);
            memcpy(p, &v, sizeof v);
        } else if (fd->kind == 'i') {
            long long v = strtoll(tok, NULL, 10);
            if (fd->size == 1) { int8_t x = (int8_t)v; memcpy(p, &x, 1); }
            else if (fd->size == 2) { int16_t x = (int16_t)v; memcpy(p, &x, 2); }
            else { int32_t x = (int32_t)v; memcpy(p, &x, 4); }
        } else {
            unsigned long long v = strtoull(tok, NULL, 10);
            if (fd->size == 1) { uint8_t x = (uint8_t)v; memcpy(p, &x, 1); }
            else if (fd->size == 2) { uint16_t x = (uint16_t)v; memcpy(p, &x, 2); }
            else if (fd->size == 4) { uint32_t x = (uint32_t)v; memcpy(p, &x, 4); }
            else { uint64_t x = (uint64_t)v; memcpy(p, &x, 8); }
        }
        tok = strtok_r(NULL, " ", &save);
    }
    return 0;
}

static uint8_t msg_buf[1024];
static uint8_t rec_buf[32][256];

static void do_decode(const char *hex)
{
    static uint8_t enc[2048];
    static uint8_t scratch[IB_MAX_FRAME];
    size_t n = strlen(hex) / 2;
    if (n > sizeof enc) {
        n = sizeof enc; /* still reported as oversize below */
    }
    for (size_t i = 0; i < n; i++) {
        unsigned b;
        sscanf(hex + 2 * i, "%2x", &b);
        enc[i] = (uint8_t)b;
    }
    if (n > 0 && enc[n - 1] == 0) {
        n--; /* the delimiter is not part of the frame */
    }
    ib_frame_t f;
    ib_frame_status_t st = ib_frame_parse(enc, n, scratch, &f);
    if (st != IB_FRAME_OK) {
        printf("err %s\n", ib_frame_status_name(st));
        return;
    }
    const ib_desc_msg_t *m = NULL;
    for (const ib_desc_msg_t *d = ib_desc_messages; d->name; d++) {
        if (d->id == f.type) {
            m = d;
        }
    }
    if (!m) {
        printf("err unknown_type\n");
        return;
    }
    memset(msg_buf, 0, sizeof msg_buf);
    m->unpack(f.payload, msg_buf);
    printf("ok %s %u %lu\n", m->name, (unsigned)f.seq, (unsigned long)f.timestamp_us);
    for (const ib_desc_field_t *fd = m->fields; fd->name; fd++) {
        printf("f %s ", fd->name);
        print_field(fd, msg_buf);
        putchar('\n');
    }
    if (m->record_fields) {
        size_t fixed = f.payload_len - (size_t)f.payload[m->count_offset] * m->record_wire_size;
        for (unsigned i = 0; i < f.payload[m->count_offset]; i++) {
            memset(rec_buf[0], 0, sizeof rec_buf[0]);
            m->record_unpack(f.payload + fixed + i * m->record_wire_size, rec_buf[0]);
            for (const ib_desc_field_t *fd = m->record_fields; fd->name; fd++) {
                printf("r %u %s ", i, fd->name);
                print_field(fd, rec_buf[0]);
                putchar('\n');
            }
        }
    }
    printf("end\n");
}

static void do_encode(char *args)
{
    char name[64];
    unsigned seq;
    unsigned long ts;
    unsigned nrec;
    if (sscanf(args, "%63s %u %lu %u", name, &seq, &ts, &nrec) != 4 || nrec > 32) {
        printf("err usage\n");
        return;
    }
    const ib_desc_msg_t *m = find_msg(name);
    memset(msg_buf, 0, sizeof msg_buf);
    memset(rec_buf, 0, sizeof rec_buf);
    char line[MAX_LINE];
    int bad = m == NULL;
    while (fgets(line, sizeof line, stdin)) {
        line[strcspn(line, "\r\n")] = 0;
        if (strcmp(line, "end") == 0) {
            break;
        }
        if (bad) {
            continue;
        }
        char path[128];
        int off = 0;
        if (line[0] == 'f' && sscanf(line, "f %127s %n", path, &off) == 1) {
            const ib_desc_field_t *fd = find_field(m->fields, path);
            if (!fd || set_field(fd, msg_buf, line + off) != 0) {
                bad = 1;
            }
        } else {
            unsigned i;
            if (sscanf(line, "r %u %127s %n", &i, path, &off) == 2 && i < nrec) {
                const ib_desc_field_t *fd = find_field(m->record_fields, path);
                if (!fd || set_field(fd, rec_buf[i], line + off) != 0) {
                    bad = 1;
                }
            } else {
                bad = 1;
            }
        }
    }
    if (bad) {
        printf("err bad_input\n");
        return;
    }
    static uint8_t raw[IB_MAX_FRAME + 64];
    static uint8_t out[IB_MAX_ENCODED + 1];
    size_t n = m->pack(msg_buf, raw + IB_HEADER_SIZE);
    for (unsigned i = 0; i < nrec; i++) {
        n += m->record_pack(rec_buf[i], raw + IB_HEADER_SIZE + n);
    }
    if (ib_msg_check_length(m->id, raw + IB_HEADER_SIZE, n) != 0) {
        printf("err bad_length\n");
        return;
    }
    size_t e = ib_frame_encode(raw, m->id, (uint16_t)seq, (uint32_t)ts, n, out);
    printf("hex ");
    for (size_t i = 0; i < e; i++) {
        printf("%02x", out[i]);
    }
    putchar('\n');
}

int main(void)
{
    static char line[1 << 16];
    while (fgets(line, sizeof line, stdin)) {
        line[strcspn(line, "\r\n")] = 0;
        if (strncmp(line, "decode ", 7) == 0) {
            do_decode(line + 7);
        } else if (strncmp(line, "encode ", 7) == 0) {
            do_encode(line + 7);
        } else if (strncmp(line, "step ", 5) == 0) {
            unsigned long now = 0, prev = 0;
            if (sscanf(line + 5, "%lu %lu", &now, &prev) == 2) {
                printf("step %ld\n", (long)ib_time_step_us((uint32_t)now, (uint32_t)prev));
            } else {
                printf("err usage\n");
            }
        } else if (line[0]) {
            printf("err usage\n");
        }
        fflush(stdout);
    }
    return 0;
}
