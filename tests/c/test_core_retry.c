/*
 * test_core_retry.c - the firmware core's retry cache, on a minimal board (no sensors, no
 * flash, a byte-buffer link): a command is answered from the stored reply only when it is
 * the same command again (request id, type and payload byte for byte), never when only a
 * checksum of its payload matches (SPEC.md, Commands: Retries).
 */
#include <stdlib.h>
#include <string.h>

#include "core.h"
#include "crc32c.h"
#include "ctest.h"
#include "frame.h"
#include "protocol_gen.h"

/* ------------------------------------------------------------------ the board */
typedef struct {
    uint8_t in[4096];
    size_t in_len, in_pos;
    uint8_t out[8192];
    size_t out_len;
    uint32_t t_us;
} tb_t;

static tb_t g_tb;

static uint32_t tb_time(void *ctx) { return ((tb_t *)ctx)->t_us += 10u; }
static void tb_tick(void *ctx, uint32_t hz) { (void)ctx; (void)hz; }
static size_t tb_free(void *ctx) { return sizeof ((tb_t *)ctx)->out - ((tb_t *)ctx)->out_len; }
static size_t tb_write(void *ctx, const uint8_t *d, size_t n)
{
    tb_t *t = ctx;
    if (n > tb_free(t)) {
        return 0;
    }
    memcpy(t->out + t->out_len, d, n);
    t->out_len += n;
    return n;
}
static size_t tb_read(void *ctx, uint8_t *buf, size_t cap)
{
    tb_t *t = ctx;
    size_t n = t->in_len - t->in_pos < cap ? t->in_len - t->in_pos : cap;
    memcpy(buf, t->in + t->in_pos, n);
    t->in_pos += n;
    return n;
}
static int tb_spi(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)ctx; (void)cs; (void)tx;
    if (rx) {
        memset(rx, 0, len); /* nothing answers: every sensor missing */
    }
    return 0;
}
static void tb_delay(void *ctx, uint32_t us) { ((tb_t *)ctx)->t_us += us; }
static void tb_reboot(void *ctx) { (void)ctx; }

static const ib_spi_bus_t g_bus = {tb_spi, tb_delay, &g_tb, NULL}; /* no start(): synchronous reads */
static const ib_board_t g_board = {
    IB_BOARD_SIM, IB_CLOCK_SOURCE_NONE, 0, {0}, "test", tb_time, tb_tick, tb_free, tb_write, tb_read,
    &g_bus, NULL, tb_reboot, &g_tb};

static ib_core_t g_core;

/* Send one command (payload already packed) with request id `rid`; return the ack. */
static ib_msg_ack_t command(uint8_t type, uint16_t rid, const uint8_t *payload, size_t len)
{
    uint8_t raw[IB_MAX_FRAME];
    uint8_t enc[IB_MAX_ENCODED + 1];
    memcpy(raw + IB_HEADER_SIZE, payload, len);
    size_t n = ib_frame_encode(raw, type, rid, 0, len, enc);
    enc[n++] = 0;
    g_tb.in_len = g_tb.in_pos = 0;
    memcpy(g_tb.in, enc, n);
    g_tb.in_len = n;
    g_tb.out_len = 0;
    for (int i = 0; i < 8; i++) {
        ib_core_poll(&g_core);
    }
    /* the last frame of the output is the ack */
    ib_msg_ack_t a;
    memset(&a, 0xEE, sizeof a);
    ib_frame_rx_t rx;
    ib_frame_rx_init(&rx);
    for (size_t i = 0; i < g_tb.out_len; i++) {
        ib_frame_t f;
        if (ib_frame_rx_push(&rx, g_tb.out[i], &f) == IB_FRAME_OK && f.type == IB_MSG_ACK) {
            ib_msg_ack_unpack(f.payload, &a);
        }
    }
    return a;
}

static void boot(void)
{
    memset(&g_tb, 0, sizeof g_tb);
    ib_core_init(&g_core, &g_board);
}

static void example(ib_params_t *p, float bias)
{
    memset(p, 0, sizeof *p);
    for (int k = 0; k < 3; k++) {
        p->accel_m[k * 4] = 1.0f;
        p->gyro_m[k * 4] = 1.0f;
    }
    p->accel_b_mps2[0] = bias;
    p->accel_b_mps2[1] = -0.25f;
    p->accel_b_mps2[2] = 0.125f;
    p->accel_t_ref_c = 25.0f;
    p->gyro_t_ref_c = 25.0f;
    p->accel_t_min_c = p->gyro_t_min_c = -40; /* the default span (layout 3) */
    p->accel_t_max_c = p->gyro_t_max_c = 85;
    p->cal_id = 77;
}

/* Make `b` (same length as `a`, a copy of it) a different payload with the same CRC-32C by
 * flipping a combination of the `nfree` candidate bits (bit k of byte k/8). The CRC is linear
 * over GF(2) for equal lengths, so with more than 32 candidates a non-empty combination whose
 * CRC effect is zero exists: Gaussian elimination finds it. Returns 0 on success. */
static int crc_twin(const uint8_t *a, uint8_t *b, size_t len, const unsigned *bits, unsigned nfree)
{
    uint32_t base = ib_crc32c(0, a, len);
    uint32_t col[64];
    uint64_t comb[64];
    uint8_t tmp[IB_MAX_PAYLOAD];
    if (nfree > 64u || len > sizeof tmp) {
        return -1;
    }
    for (unsigned i = 0; i < nfree; i++) {
        memcpy(tmp, a, len);
        tmp[bits[i] / 8u] ^= (uint8_t)(1u << (bits[i] % 8u));
        col[i] = ib_crc32c(0, tmp, len) ^ base;
        comb[i] = 1ull << i;
    }
    /* eliminate: for each CRC bit, pick a pivot column and clear that bit from the others */
    unsigned used = 0;
    for (unsigned bit = 0; bit < 32u; bit++) {
        unsigned p = nfree;
        for (unsigned i = used; i < nfree; i++) {
            if (col[i] >> bit & 1u) {
                p = i;
                break;
            }
        }
        if (p == nfree) {
            continue;
        }
        uint32_t tc = col[p]; col[p] = col[used]; col[used] = tc;
        uint64_t tm = comb[p]; comb[p] = comb[used]; comb[used] = tm;
        for (unsigned i = 0; i < nfree; i++) {
            if (i != used && (col[i] >> bit & 1u)) {
                col[i] ^= col[used];
                comb[i] ^= comb[used];
            }
        }
        used++;
    }
    for (unsigned i = used; i < nfree; i++) {
        if (col[i] == 0u && comb[i] != 0u) {
            memcpy(b, a, len);
            for (unsigned k = 0; k < nfree; k++) {
                if (comb[i] >> k & 1u) {
                    b[bits[k] / 8u] ^= (uint8_t)(1u << (bits[k] % 8u));
                }
            }
            return 0;
        }
    }
    return -1;
}

static void get_active(ib_params_t *out)
{
    uint8_t req[IB_MSG_GET_PARAMS_SIZE] = {IB_PARAMS_WHICH_ACTIVE, 0, 0, 0};
    uint8_t raw[IB_MAX_FRAME];
    uint8_t enc[IB_MAX_ENCODED + 1];
    memcpy(raw + IB_HEADER_SIZE, req, sizeof req);
    size_t n = ib_frame_encode(raw, IB_MSG_GET_PARAMS, 60000u, 0, sizeof req, enc);
    enc[n++] = 0;
    memcpy(g_tb.in, enc, n);
    g_tb.in_len = n;
    g_tb.in_pos = 0;
    g_tb.out_len = 0;
    for (int i = 0; i < 8; i++) {
        ib_core_poll(&g_core);
    }
    ib_frame_rx_t rx;
    ib_frame_rx_init(&rx);
    memset(out, 0, sizeof *out);
    for (size_t i = 0; i < g_tb.out_len; i++) {
        ib_frame_t f;
        if (ib_frame_rx_push(&rx, g_tb.out[i], &f) == IB_FRAME_OK && f.type == IB_MSG_PARAMS_READBACK) {
            ib_msg_params_readback_t r;
            ib_msg_params_readback_unpack(f.payload, &r);
            *out = r.params;
        }
    }
}

/* Two different set_params blocks with one CRC-32C and one request id: the second is applied
 * (or refused), never acked and ignored. */
static void test_equal_crc_is_not_a_retry(void)
{
    boot();
    ib_params_t pa;
    example(&pa, 0.5f);
    uint8_t a[IB_MSG_SET_PARAMS_SIZE], b[IB_MSG_SET_PARAMS_SIZE];
    ib_msg_set_params_t m = {pa};
    ib_msg_set_params_pack(&m, a);
    /* candidates: the 8 low mantissa bits of each accel bias (offset 36..47, little-endian) and
     * the 32 bits of cal_id (offset 156): any combination keeps the block valid */
    unsigned bits[56];
    unsigned n = 0;
    for (unsigned k = 0; k < 3; k++) {
        for (unsigned j = 0; j < 8; j++) {
            bits[n++] = (36u + 4u * k) * 8u + j;
        }
    }
    for (unsigned j = 0; j < 32; j++) {
        bits[n++] = 156u * 8u + j;
    }
    CHECK_EQ_INT(crc_twin(a, b, sizeof a, bits, n), 0);
    CHECK(memcmp(a, b, sizeof a) != 0);
    CHECK_EQ_INT(ib_crc32c(0, a, sizeof a), ib_crc32c(0, b, sizeof b));
    ib_msg_set_params_t mb;
    ib_msg_set_params_unpack(b, &mb);
    CHECK_EQ_INT(ib_core_check_params(&mb.params, NULL, NULL), IB_ERROR_OK);

    ib_msg_ack_t r1 = command(IB_MSG_SET_PARAMS, 4242, a, sizeof a);
    CHECK_EQ_INT(r1.error, IB_ERROR_OK);
    CHECK_EQ_INT(r1.request_id, 4242);
    ib_msg_ack_t r2 = command(IB_MSG_SET_PARAMS, 4242, b, sizeof b);
    CHECK_EQ_INT(r2.request_id, 4242);
    ib_params_t now;
    get_active(&now);
    uint8_t packed[IB_PARAMS_SIZE];
    ib_params_pack(&now, packed);
    if (r2.error == IB_ERROR_OK) {
        CHECK(memcmp(packed, b, sizeof packed) == 0); /* acked: applied */
    } else {
        CHECK(memcmp(packed, a, sizeof packed) == 0); /* refused: the first stays */
    }
    /* a true retry (the same bytes again) is still answered without running it */
    uint32_t bad_before = g_core.stats.bad_commands;
    ib_msg_ack_t r3 = command(IB_MSG_SET_PARAMS, 4242, b, sizeof b);
    CHECK_EQ_INT(r3.error, r2.error);
    CHECK_EQ_INT(g_core.stats.bad_commands, bad_before);
}

/* A frame nacked before it runs (bad length) replaces the stored reply: a retry of the command
 * before it must not be answered with that nack (nor with anything of another request id). */
static void test_nack_in_between_does_not_answer_a_retry(void)
{
    boot();
    uint8_t ping[4] = {0x78, 0x56, 0x34, 0x12};
    ib_msg_ack_t r1 = command(IB_MSG_PING, 100, ping, sizeof ping);
    CHECK_EQ_INT(r1.error, IB_ERROR_OK);
    CHECK_EQ_INT(r1.value, 0x12345678u);
    ib_msg_ack_t bad = command(IB_MSG_PING, 101, ping, 2);
    CHECK_EQ_INT(bad.error, IB_ERROR_BAD_LENGTH);
    ib_msg_ack_t r2 = command(IB_MSG_PING, 100, ping, sizeof ping);
    CHECK_EQ_INT(r2.request_id, 100);
    CHECK_EQ_INT(r2.command, IB_MSG_PING);
    CHECK_EQ_INT(r2.error, IB_ERROR_OK);
    CHECK_EQ_INT(r2.value, 0x12345678u);
}

int main(void)
{
    RUN(test_equal_crc_is_not_a_retry);
    RUN(test_nack_in_between_does_not_answer_a_retry);
    return ctest_summary();
}
