/*
 * test_cobs.c - ib_cobs_encode (firmware/core/frame.c, the block-copy encoder every sent
 * byte goes through) against a byte-at-a-time reference encoder of the same output (Cheshire
 * and Baker, "Consistent Overhead Byte Stuffing", 1999; a 254-byte block is followed by
 * another block even at the end of the input), and back through ib_cobs_decode: all-zero,
 * zero-free runs across the 254-byte limit, random bytes of every zero density.
 */
#include <stdint.h>
#include <string.h>

#include "ctest.h"
#include "frame.h"

static size_t cobs_ref(const uint8_t *in, size_t len, uint8_t *out)
{
    size_t code_at = 0, o = 1;
    uint8_t code = 1;
    for (size_t i = 0; i < len; i++) {
        if (in[i] != 0u) {
            out[o++] = in[i];
            if (++code != 0xFFu) {
                continue;
            }
        }
        out[code_at] = code;
        code_at = o++;
        code = 1;
    }
    out[code_at] = code;
    return o;
}

static uint8_t g_in[1200], g_out[1300], g_ref[1300], g_back[1300];

static void check_one(size_t len)
{
    size_t n = ib_cobs_encode(g_in, len, g_out);
    size_t r = cobs_ref(g_in, len, g_ref);
    CHECK_EQ_INT(n, r);
    CHECK(memcmp(g_out, g_ref, r) == 0);
    for (size_t i = 0; i < n; i++) {
        if (g_out[i] == 0u) {
            CHECK(!"a zero in the encoded bytes");
            break;
        }
    }
    size_t back = 0;
    CHECK_EQ_INT(ib_cobs_decode(g_out, n, g_back, sizeof g_back, &back), 0);
    CHECK_EQ_INT(back, len);
    CHECK(memcmp(g_back, g_in, len) == 0);
}

static void test_runs_around_the_block_limit(void)
{
    for (size_t len = 0; len <= 800u; len++) {
        memset(g_in, 0x5A, len); /* no zero: blocks of 254 */
        check_one(len);
        if (len) {
            g_in[len - 1] = 0; /* ending in a zero */
            check_one(len);
        }
        memset(g_in, 0, len);
        check_one(len);
    }
}

static void test_random_bytes(void)
{
    uint32_t x = 7u;
    for (unsigned density = 0; density <= 8u; density++) {
        for (unsigned rep = 0; rep < 40u; rep++) {
            size_t len = (size_t)(rep * 29u) % sizeof g_in;
            for (size_t i = 0; i < len; i++) {
                x = x * 1664525u + 1013904223u;
                uint8_t b = (uint8_t)(x >> 24);
                g_in[i] = ((x >> 8) & 7u) < density ? 0u : (uint8_t)(b | 1u);
            }
            check_one(len);
        }
    }
}

int main(void)
{
    RUN(test_runs_around_the_block_limit);
    RUN(test_random_bytes);
    return ctest_summary();
}
