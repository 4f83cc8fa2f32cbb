/*
 * wire.h - little-endian field access for protocol payloads and flash blocks.
 * The protocol is little-endian throughout (protocol/SPEC.md); these helpers make that
 * true on any host, whatever its own byte order or alignment rules.
 */
#ifndef IB_WIRE_H
#define IB_WIRE_H

#include <stdint.h>
#include <string.h>

static inline void ib_put_u8(uint8_t *p, uint8_t v) { p[0] = v; }
static inline void ib_put_i8(uint8_t *p, int8_t v) { p[0] = (uint8_t)v; }
static inline void ib_put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}
static inline void ib_put_i16(uint8_t *p, int16_t v) { ib_put_u16(p, (uint16_t)v); }
static inline void ib_put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}
static inline void ib_put_i32(uint8_t *p, int32_t v) { ib_put_u32(p, (uint32_t)v); }
static inline void ib_put_u64(uint8_t *p, uint64_t v)
{
    ib_put_u32(p, (uint32_t)v);
    ib_put_u32(p + 4, (uint32_t)(v >> 32));
}
static inline void ib_put_f32(uint8_t *p, float v)
{
    uint32_t u;
    memcpy(&u, &v, sizeof u);
    ib_put_u32(p, u);
}

static inline uint8_t ib_get_u8(const uint8_t *p) { return p[0]; }
static inline int8_t ib_get_i8(const uint8_t *p) { return (int8_t)p[0]; }
static inline uint16_t ib_get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static inline int16_t ib_get_i16(const uint8_t *p) { return (int16_t)ib_get_u16(p); }
static inline uint32_t ib_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static inline int32_t ib_get_i32(const uint8_t *p) { return (int32_t)ib_get_u32(p); }
static inline uint64_t ib_get_u64(const uint8_t *p)
{
    return (uint64_t)ib_get_u32(p) | ((uint64_t)ib_get_u32(p + 4) << 32);
}
static inline float ib_get_f32(const uint8_t *p)
{
    uint32_t u = ib_get_u32(p);
    float v;
    memcpy(&v, &u, sizeof v);
    return v;
}

/* The step from device time `prev` to `now` (both u32 microseconds that wrap every 2^32 us):
 * (now - prev) mod 2^32 taken in [-2^31, 2^31), so a step of exactly 2^31 us is -2^31, a step
 * back, on both sides (protocol/SPEC.md, Header fields; the host's wire.decoder.time_step_us).
 * Written without converting an out-of-range unsigned value to int32_t (implementation-defined). */
static inline int32_t ib_time_step_us(uint32_t now, uint32_t prev)
{
    uint32_t d = now - prev;
    return d < 0x80000000u ? (int32_t)d : -(int32_t)(0xFFFFFFFFu - d) - 1;
}

/* Sign-extend the low `width` bits of `raw` (1..32). */
static inline int32_t ib_sign_extend(uint32_t raw, unsigned width)
{
    uint32_t m = 1u << (width - 1u);
    return (int32_t)((raw ^ m) - m);
}

#endif
