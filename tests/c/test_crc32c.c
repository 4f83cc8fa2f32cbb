/*
 * test_crc32c.c - the two builds of ib_crc32c (firmware/core/crc32c.c): the slicing-by-4
 * one (the host build, the F4 images) and the one-table one (-DIB_CRC32C_BYTEWISE=1, the F103
 * images), both against a bit-at-a-time reference of the definition in crc32c.h, over every
 * length and start alignment a word-at-a-time loop can get wrong, and chained.
 */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "ctest.h"

/* the library's build (libfw.a: slicing-by-4 unless built bytewise) */
uint32_t ib_crc32c(uint32_t crc, const void *data, size_t len);

/* the one-table build, compiled here under another name */
#define ib_crc32c ib_crc32c_bytewise
#define IB_CRC32C_BYTEWISE 1
#include "crc32c.c"
#undef ib_crc32c

static uint32_t crc_ref(uint32_t crc, const uint8_t *p, size_t len)
{
    crc = ~crc;
    for (size_t i = 0; i < len; i++) {
        crc ^= p[i];
        for (int b = 0; b < 8; b++) {
            crc = (crc & 1u) ? (crc >> 1) ^ 0x82F63B78u : crc >> 1;
        }
    }
    return ~crc;
}

static void test_check_value(void)
{
    const char *s = "123456789";
    CHECK_EQ_INT(ib_crc32c(0, s, 9), 0xE3069283u);
    CHECK_EQ_INT(ib_crc32c_bytewise(0, s, 9), 0xE3069283u);
    CHECK_EQ_INT(ib_crc32c(0, s, 0), 0u);
}

static void test_every_length_and_alignment(void)
{
    uint8_t buf[80];
    uint32_t x = 12345u;
    for (size_t i = 0; i < sizeof buf; i++) {
        x = x * 1103515245u + 12345u;
        buf[i] = (uint8_t)(x >> 16);
    }
    buf[7] = 0; /* zeros and 0xFF among the bytes */
    buf[20] = 0xFF;
    for (size_t off = 0; off < 4u; off++) {
        for (size_t len = 0; off + len <= 72u; len++) {
            uint32_t want = crc_ref(0, buf + off, len);
            CHECK_EQ_INT(ib_crc32c(0, buf + off, len), want);
            CHECK_EQ_INT(ib_crc32c_bytewise(0, buf + off, len), want);
        }
    }
}

static void test_chained(void)
{
    uint8_t buf[64];
    for (size_t i = 0; i < sizeof buf; i++) {
        buf[i] = (uint8_t)(i * 37u + 11u);
    }
    uint32_t whole = crc_ref(0, buf, sizeof buf);
    for (size_t cut = 0; cut <= sizeof buf; cut++) {
        CHECK_EQ_INT(ib_crc32c(ib_crc32c(0, buf, cut), buf + cut, sizeof buf - cut), whole);
        CHECK_EQ_INT(ib_crc32c_bytewise(ib_crc32c_bytewise(0, buf, cut), buf + cut, sizeof buf - cut), whole);
    }
}

int main(void)
{
    RUN(test_check_value);
    RUN(test_every_length_and_alignment);
    RUN(test_chained);
    return ctest_summary();
}
