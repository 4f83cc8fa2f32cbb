/* core.c - see core.h. Portable: no register access, hardware only through ib_board_t.
 * This file: the link helpers, boot and the poll loop; core_params.c, core_stream.c and
 * core_cmd.c hold the parameters, the sampling and the commands (core_priv.h). */
#include "core_priv.h"

/* The firmware version (setup.py and imubench.device.artifacts read these three lines). */
#define FW_VERSION_MAJOR 0u
#define FW_VERSION_MINOR 2u
#define FW_VERSION_PATCH 0u

void ibc_fw_version(uint8_t v[3])
{
    v[0] = FW_VERSION_MAJOR;
    v[1] = FW_VERSION_MINOR;
    v[2] = FW_VERSION_PATCH;
}

/* ------------------------------------------------------------------ helpers */

uint32_t ibc_now_us(const ib_core_t *c) { return c->board->time_us(c->board->ctx); }

void ibc_update_uptime(ib_core_t *c)
{
    uint32_t t = ibc_now_us(c);
    uint32_t dt = t - c->last_time_us; /* modulo 2^32: fine while polled every < 71 min */
    c->uptime_us_rem += dt;
    c->uptime_ms += c->uptime_us_rem / 1000u;
    c->uptime_us_rem %= 1000u;
    c->last_time_us = t;
}

/* Queue an encoded frame; the caller checked the space. */
void ibc_link_put(ib_core_t *c, const uint8_t *frame, size_t len)
{
    size_t n = c->board->link_write(c->board->ctx, frame, len);
    if (n == len) {
        c->stats.frames_sent++;
    } else {
        c->stats.frames_dropped++;
    }
}

/* Encode a device message whose payload is at c->msg_raw + IB_HEADER_SIZE. */
size_t ibc_encode_msg(ib_core_t *c, uint8_t type, size_t payload_len, uint8_t *out)
{
    size_t n = ib_frame_encode(c->msg_raw, type, c->tx_seq, ibc_now_us(c), payload_len, out);
    c->tx_seq++;
    return n;
}

/* Unsolicited message (stats, fault event, boot info): sent now if it fits, else dropped
 * and counted; it is never allowed to eat the ibc_reply reserve. */
void ibc_send_unsolicited(ib_core_t *c, uint8_t type, size_t payload_len)
{
    size_t n = ibc_encode_msg(c, type, payload_len, c->tx_frame);
    if (c->board->link_tx_free(c->board->ctx) >= n + REPLY_RESERVE / 2u) {
        ibc_link_put(c, c->tx_frame, n);
    } else {
        c->stats.frames_dropped++;
    }
}

/* -------------------------------------------------------------------- boot */

void ib_core_init(ib_core_t *c, const ib_board_t *b)
{
    memset(c, 0, sizeof *c);
    c->board = b;
    c->accel_range_g = 2;
    c->last_time_us = ibc_now_us(c);
    ib_frame_rx_init(&c->rx);
    c->job_list_temps = 0xFFu;
    b->set_tick_hz(b->ctx, 0);
    ibc_sensors_init(c);
    ibc_load_params(c);
    ibc_update_uptime(c);
    /* a 0x00 ends any partial frame the host holds, then the boot info (request id 0) */
    static const uint8_t zero = 0;
    if (b->link_tx_free(b->ctx) >= 1u) {
        (void)b->link_write(b->ctx, &zero, 1);
    }
    ib_msg_info_t m;
    ibc_info_fill(c, &m, 0);
    size_t n = ib_msg_info_pack(&m, c->msg_raw + IB_HEADER_SIZE);
    ibc_send_unsolicited(c, IB_MSG_INFO, n);
    for (uint8_t s = 0; s < 4; s++) {
        if (!(c->present & (1u << s))) {
            ibc_emit_fault(c, s, IB_FAULT_KIND_MISSING, 1, ibc_missing_detail(c, s));
            c->fault_state[s] = IB_FAULT_KIND_MISSING;
        }
    }
}

void ib_core_poll(ib_core_t *c)
{
    if (c->job_done) {
        ibc_sample_finish(c);
    }
    /* one command at a time: bytes after a command wait until its ibc_reply is out */
    (void)ibc_flush_reply(c);
    while (c->reply_pending == 0 && !c->reboot_pending) {
        if (c->rx_pos == c->rx_len) {
            c->rx_len = (uint8_t)c->board->link_read(c->board->ctx, c->rx_buf, sizeof c->rx_buf);
            c->rx_pos = 0;
            if (c->rx_len == 0) {
                break;
            }
        }
        ib_frame_t f;
        int st = ib_frame_rx_push(&c->rx, c->rx_buf[c->rx_pos++], &f);
        if (st >= 0) {
            ibc_on_frame(c, st, &f);
            (void)ibc_flush_reply(c);
        }
    }
    if (c->reboot_pending && c->reply_pending == 0) {
        c->reboot_pending = 0;
        c->board->reboot(c->board->ctx);
        return;
    }
}
