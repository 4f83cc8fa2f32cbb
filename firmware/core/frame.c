/* frame.c - see frame.h */
#include "frame.h"

#include <string.h>

#include "crc32c.h"
#include "wire.h"

const char *ib_frame_status_name(ib_frame_status_t s)
{
    switch (s) {
    case IB_FRAME_OK: return "ok";
    case IB_FRAME_OVERSIZE: return "oversize";
    case IB_FRAME_COBS: return "cobs";
    case IB_FRAME_TOO_SHORT: return "too_short";
    case IB_FRAME_CRC: return "crc";
    case IB_FRAME_BAD_VERSION: return "bad_version";
    case IB_FRAME_UNKNOWN_TYPE: return "unknown_type";
    case IB_FRAME_BAD_LENGTH: return "bad_length";
    case IB_FRAME_BAD_ENUM: return "bad_enum";
    case IB_FRAME_OUT_OF_RANGE: return "out_of_range";
    case IB_FRAME_NOT_FINITE: return "not_finite";
    case IB_FRAME_BAD_FLAGS: return "bad_flags";
    default: return "?";
    }
}

size_t ib_cobs_encode(const uint8_t *in, size_t len, uint8_t *out)
{
    /* Block by block: copy the run of non-zero bytes (at most 254), a word at a time while a
     * word holds no zero (the "has a zero byte" test of Mycroft, 1987), then write the block's
     * code in front of it. This runs over every byte sent: about 3 Cortex-M instructions a
     * byte in a run, where a byte-at-a-time state machine took 11. Output byte for byte as before: a block of 254
     * data bytes (code 0xFF) consumes no zero, and is followed by another block even at the
     * end of the input. */
    const uint8_t *end = in + len;
    uint8_t *o = out;
    for (;;) {
        uint8_t *code_at = o++;
        const uint8_t *lim = (size_t)(end - in) > 254u ? in + 254 : end;
        while ((size_t)(lim - in) >= 4u) { /* four bytes at a time while none is zero */
            uint32_t w;
            memcpy(&w, in, 4);
            if ((w - 0x01010101u) & ~w & 0x80808080u) {
                break;
            }
            memcpy(o, &w, 4);
            o += 4;
            in += 4;
        }
        while (in < lim) {
            uint8_t b = *in;
            if (b == 0u) {
                break;
            }
            *o++ = b;
            in++;
        }
        size_t code = (size_t)(o - code_at);
        *code_at = (uint8_t)code;
        if (code != 0xFFu) {
            if (in == end) {
                break;
            }
            in++; /* the zero this block stands for */
        }
    }
    return (size_t)(o - out);
}

/* Safe in place (out == in): every output byte is written after the input byte it comes
 * from has been read, and the output never runs ahead of the input. */
int ib_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap, size_t *out_len)
{
    size_t i = 0;
    size_t o = 0;
    while (i < len) {
        uint8_t code = in[i++];
        if (code == 0) {
            return -1;
        }
        for (uint8_t k = 1; k < code; k++) {
            if (i >= len || in[i] == 0) {
                return -1;
            }
            if (o >= cap) {
                return -2;
            }
            out[o++] = in[i++];
        }
        if (code != 0xFF && i < len) {
            if (o >= cap) {
                return -2;
            }
            out[o++] = 0;
        }
    }
    *out_len = o;
    return 0;
}

size_t ib_frame_encode(uint8_t *raw, uint8_t type, uint16_t seq, uint32_t timestamp_us,
                       size_t payload_len, uint8_t *out)
{
    if (payload_len > IB_MAX_PAYLOAD) {
        return 0;
    }
    raw[0] = IB_PROTOCOL_VERSION;
    raw[1] = type;
    ib_put_u16(raw + 2, seq);
    ib_put_u32(raw + 4, timestamp_us);
    size_t n = IB_HEADER_SIZE + payload_len;
    ib_put_u32(raw + n, ib_crc32c(0, raw, n));
    n += IB_CRC_SIZE;
    size_t e = ib_cobs_encode(raw, n, out);
    out[e++] = 0;
    return e;
}

ib_frame_status_t ib_frame_parse(const uint8_t *enc, size_t len, uint8_t *scratch, ib_frame_t *f)
{
    size_t n = 0;
    f->version = 0;
    f->type = 0;
    f->seq = 0;
    f->timestamp_us = 0;
    f->payload = scratch;
    f->payload_len = 0;
    if (len > IB_MAX_ENCODED) {
        return IB_FRAME_OVERSIZE;
    }
    int dr = ib_cobs_decode(enc, len, scratch, IB_MAX_FRAME, &n);
    if (dr == -2) {
        return IB_FRAME_OVERSIZE; /* decodes to more than IB_MAX_FRAME */
    }
    if (dr != 0) {
        return IB_FRAME_COBS;
    }
    if (n < IB_HEADER_SIZE + IB_CRC_SIZE) {
        return IB_FRAME_TOO_SHORT;
    }
    if (ib_crc32c(0, scratch, n - IB_CRC_SIZE) != ib_get_u32(scratch + n - IB_CRC_SIZE)) {
        return IB_FRAME_CRC;
    }
    f->version = scratch[0];
    f->type = scratch[1];
    f->seq = ib_get_u16(scratch + 2);
    f->timestamp_us = ib_get_u32(scratch + 4);
    f->payload = scratch + IB_HEADER_SIZE;
    f->payload_len = n - IB_HEADER_SIZE - IB_CRC_SIZE;
    if (f->version != IB_PROTOCOL_VERSION) {
        return IB_FRAME_BAD_VERSION;
    }
    int lc = ib_msg_check_length(f->type, f->payload, f->payload_len);
    if (lc == -1) {
        return IB_FRAME_UNKNOWN_TYPE;
    }
    if (lc != 0) {
        return IB_FRAME_BAD_LENGTH;
    }
    switch (ib_msg_check_values(f->type, f->payload, f->payload_len)) {
    case IB_VALUE_OK: return IB_FRAME_OK;
    case IB_VALUE_BAD_ENUM: return IB_FRAME_BAD_ENUM;
    case IB_VALUE_OUT_OF_RANGE: return IB_FRAME_OUT_OF_RANGE;
    case IB_VALUE_NOT_FINITE: return IB_FRAME_NOT_FINITE;
    default: return IB_FRAME_BAD_FLAGS;
    }
}

void ib_frame_rx_init(ib_frame_rx_t *rx)
{
    rx->n = 0;
    rx->overflow = 0;
}

int ib_frame_rx_push(ib_frame_rx_t *rx, uint8_t byte, ib_frame_t *f)
{
    if (byte != 0) {
        if (rx->n < sizeof rx->buf) {
            rx->buf[rx->n++] = byte;
        } else {
            rx->overflow = 1;
        }
        return -1;
    }
    if (rx->overflow) {
        rx->overflow = 0;
        rx->n = 0;
        return IB_FRAME_OVERSIZE;
    }
    if (rx->n == 0) {
        return -1;
    }
    size_t len = rx->n;
    rx->n = 0;
    return (int)ib_frame_parse(rx->buf, len, rx->buf, f);
}
