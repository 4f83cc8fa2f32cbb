/*
 * frame.h - framing of the imubench protocol (protocol/SPEC.md), portable C.
 *
 * Wire frame = COBS(header[8] + payload + CRC-32C[4]) followed by 0x00.
 * Header: version u8, type u8, seq u16, timestamp_us u32, little-endian.
 *
 * Sending: write the payload at buf + IB_HEADER_SIZE of a raw buffer, then
 * ib_frame_encode() adds header and CRC and COBS-encodes into the output.
 * Receiving: feed bytes to ib_frame_rx_push(); each complete frame is checked in the
 * order of ib_frame_status (same order as the host decoder) and handed back.
 */
#ifndef IB_FRAME_H
#define IB_FRAME_H

#include <stddef.h>
#include <stdint.h>

#include "protocol_gen.h"

/* Why a received frame was rejected; the order is the order of the checks. */
typedef enum {
    IB_FRAME_OK = 0,
    IB_FRAME_OVERSIZE,     /* encoded longer than IB_MAX_ENCODED or decoded than IB_MAX_FRAME */
    IB_FRAME_COBS,         /* not valid COBS */
    IB_FRAME_TOO_SHORT,    /* shorter than header + CRC */
    IB_FRAME_CRC,          /* CRC-32C mismatch */
    IB_FRAME_BAD_VERSION,  /* version byte is not IB_PROTOCOL_VERSION */
    IB_FRAME_UNKNOWN_TYPE, /* message type not in the definition */
    IB_FRAME_BAD_LENGTH,   /* payload length or record count wrong for the type */
    /* the frame is well formed but a field holds what the definition does not allow
     * (ib_msg_check_values, generated from protocol/imubench.toml) */
    IB_FRAME_BAD_ENUM,     /* not one of its enum's values (or of the field's listed values) */
    IB_FRAME_OUT_OF_RANGE, /* below its min or above its max (e.g. a sample period of 0) */
    IB_FRAME_NOT_FINITE,   /* a float that must be finite is NaN or infinite */
    IB_FRAME_BAD_FLAGS     /* a bit outside the field's bit set */
} ib_frame_status_t;

const char *ib_frame_status_name(ib_frame_status_t s);

typedef struct {
    uint8_t version;
    uint8_t type;
    uint16_t seq;
    uint32_t timestamp_us;
    const uint8_t *payload; /* points into the decoder's buffer */
    size_t payload_len;
} ib_frame_t;

/* COBS. encode: returns the encoded length (at most len + len/254 + 1), no delimiter.
 * decode: returns 0 and the decoded length, -1 on malformed input, -2 when the output
 * would exceed `cap`. */
size_t ib_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);
int ib_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap, size_t *out_len);

/*
 * Build a frame. `raw` holds the payload at raw + IB_HEADER_SIZE (payload_len bytes) and
 * must have room for IB_HEADER_SIZE + payload_len + IB_CRC_SIZE bytes; the header and CRC
 * are written into it. The COBS-encoded frame plus its 0x00 delimiter go to `out`
 * (room: IB_MAX_ENCODED + 1). Returns the number of bytes in `out`, or 0 if payload_len
 * exceeds IB_MAX_PAYLOAD.
 */
size_t ib_frame_encode(uint8_t *raw, uint8_t type, uint16_t seq, uint32_t timestamp_us,
                       size_t payload_len, uint8_t *out);

/* Check one encoded frame (without the 0x00). `scratch` (IB_MAX_FRAME bytes) receives the
 * decoded bytes and may be `enc` itself (in-place decoding); on IB_FRAME_OK `f` describes
 * the frame (f->payload points into scratch). Header fields are filled in as far as the
 * checks got. */
ib_frame_status_t ib_frame_parse(const uint8_t *enc, size_t len, uint8_t *scratch, ib_frame_t *f);

/* Streaming receiver: accumulates bytes up to each 0x00 delimiter, then decodes the frame
 * in place (COBS output is never longer than its input). */
typedef struct {
    uint8_t buf[IB_MAX_ENCODED];
    size_t n;
    uint8_t overflow; /* dropping bytes of an over-long frame until the next 0x00 */
} ib_frame_rx_t;

void ib_frame_rx_init(ib_frame_rx_t *rx);

/* Push one byte. Returns -1 while no frame is complete (also for idle 0x00 bytes),
 * otherwise the ib_frame_status_t of the frame that this delimiter completed; on
 * IB_FRAME_OK `f` is valid until the next push. */
int ib_frame_rx_push(ib_frame_rx_t *rx, uint8_t byte, ib_frame_t *f);

#endif
