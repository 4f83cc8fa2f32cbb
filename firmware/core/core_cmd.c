/* core_cmd.c - the commands: info, replies and retries, start_stream, self-test, execute. */
#include "core_priv.h"

/* ---------------------------------------------------------------- commands */

void ibc_info_fill(ib_core_t *c, ib_msg_info_t *m, uint16_t rid)
{
    memset(m, 0, sizeof *m);
    const ib_board_t *b = c->board;
    m->request_id = rid;
    m->protocol_version = IB_PROTOCOL_VERSION;
    m->board = b->board_id;
    ibc_fw_version(m->fw_version);
    m->clock_source = b->clock_source;
    if (b->build) {
        strncpy(m->fw_build, b->build, sizeof m->fw_build - 1u);
    }
    memcpy(m->mcu_uid, b->uid, sizeof m->mcu_uid);
    m->sensors_present = c->present;
    m->accel_range_g = c->accel_range_g;
    const ib_part_desc_t *pa = c->accel.ops->part(c->accel.ctx);
    m->parts[0] = pa && (c->present & 1u) ? pa->part : IB_PART_NONE;
    c->accel.ops->ids(c->accel.ctx, m->accel_ids);
    for (int k = 0; k < 3; k++) {
        const ib_part_desc_t *pg = c->gyro[k].ops->part(c->gyro[k].ctx);
        m->parts[1 + k] = pg && (c->present & (2u << k)) ? pg->part : IB_PART_NONE;
        c->gyro[k].ops->ids(c->gyro[k].ctx, &m->gyro_pid[k], &m->gyro_sn[k]);
    }
    m->stream_state = c->stream_state;
    m->param_source = c->param_source;
    m->stream_rate_hz = c->stream_state ? c->rate_hz : 0;
    m->max_rate_hz = 4000;
    m->param_block_version = IB_PARAM_BLOCK_VERSION;
    m->param_generation = c->param_generation;
    m->baud = b->baud;
    m->uptime_ms = c->uptime_ms;
}

/* Build the ibc_reply (optional data message + ack) into c->last_reply and mark it pending. */
void ibc_reply(ib_core_t *c, uint16_t rid, uint8_t command, uint8_t error, uint32_t value,
                  uint8_t data_type, size_t data_len)
{
    c->last_reply_n = 0;
    /* the stored ibc_reply now answers this frame: until ibc_on_frame records the command it ran,
     * nothing may be answered from it (a nacked frame after a command must not make a retry
     * of that command receive this nack) */
    c->last_rid_valid = 0;
    if (data_type) {
        c->last_reply_len[c->last_reply_n] = (uint16_t)ibc_encode_msg(c, data_type, data_len, c->last_reply[c->last_reply_n]);
        c->last_reply_n++;
    }
    ib_msg_ack_t a = {rid, command, error, value};
    size_t n = ib_msg_ack_pack(&a, c->msg_raw + IB_HEADER_SIZE);
    c->last_reply_len[c->last_reply_n] = (uint16_t)ibc_encode_msg(c, IB_MSG_ACK, n, c->last_reply[c->last_reply_n]);
    c->last_reply_n++;
    c->reply_pending = c->last_reply_n;
    if (error != IB_ERROR_OK) {
        c->stats.bad_commands++;
    }
}

/* Send pending ibc_reply frames as the link takes them; true when none is left. */
int ibc_flush_reply(ib_core_t *c)
{
    while (c->reply_pending) {
        uint8_t i = (uint8_t)(c->last_reply_n - c->reply_pending);
        size_t n = c->last_reply_len[i];
        if (c->board->link_tx_free(c->board->ctx) < n) {
            return 0;
        }
        ibc_link_put(c, c->last_reply[i], n);
        c->reply_pending--;
    }
    return 1;
}

static uint8_t do_start_stream(ib_core_t *c, const ib_msg_start_stream_t *m, uint32_t *value)
{
    static const uint16_t rates[IB_STREAM_RATES_COUNT] = IB_STREAM_RATES_HZ;
    int listed = 0;
    for (unsigned i = 0; i < IB_STREAM_RATES_COUNT; i++) {
        listed |= rates[i] == m->rate_hz;
    }
    uint32_t avg = 0;
    int odr = listed ? ibc_odr_for_rate(c, m->rate_hz, &avg) : -1;
    uint8_t maxb = m->mode == IB_STREAM_MODE_CALIBRATED ? IB_MSG_CAL_BATCH_MAX_RECORDS : IB_MSG_RAW_BATCH_MAX_RECORDS;
    if (odr < 0 || m->rate_hz > 4000u || m->mode > IB_STREAM_MODE_CALIBRATED || m->batch > maxb ||
        (m->accel_range_g != 0u && (c->present & 1u) && ibc_range_code(c, m->accel_range_g) == 0u)) {
        return IB_ERROR_BAD_ARGUMENT;
    }
    if (c->stream_state != IB_STREAM_STATE_STOPPED) {
        ibc_stream_stop(c);
    }
    if (m->accel_range_g) {
        c->accel_range_g = m->accel_range_g;
    }
    /* the accelerometer in range and ODR, its FIFO empty */
    if ((c->present & 1u) && c->accel.ops->start(c->accel.ctx, ibc_range_code(c, c->accel_range_g), (uint8_t)odr,
                                                 ACCEL_FIFO_MAX_SETS) != IB_SENSOR_OK) {
        c->stats.spi_errors++;
    }
    const int pipelined = c->board->spi->start != NULL; /* the DMA chain's reads */
    for (int k = 0; k < 3; k++) {
        if ((c->present & (1u << (1 + k))) && c->gyro[k].ops->start(c->gyro[k].ctx, pipelined) == IB_SENSOR_ERR_BUS) {
            c->stats.spi_errors++;
        }
    }
    c->rate_hz = m->rate_hz;
    uint32_t auto_b = m->rate_hz / 250u;
    c->batch_max = m->batch ? m->batch : (uint8_t)(auto_b < 1u ? 1u : auto_b > maxb ? maxb : auto_b);
    c->sample_index = 0;
    c->batch_n = 0;
    c->drop_pending = 0;
    memset(c->fault_state, 0, sizeof c->fault_state);
    c->job_list_temps = 0xFFu; /* list the chain's transfers again (the sensors present) */
    c->stream_state = m->mode == IB_STREAM_MODE_CALIBRATED ? IB_STREAM_STATE_CALIBRATED : IB_STREAM_STATE_RAW;
    c->board->set_tick_hz(c->board->ctx, m->rate_hz);
    *value = c->batch_max;
    return IB_ERROR_OK;
}

static uint8_t do_self_test(ib_core_t *c, ib_msg_self_test_result_t *r)
{
    memset(r, 0, sizeof *r);
    if (c->present & 1u) {
        r->tested |= 1u;
        if (c->accel.ops->self_test(c->accel.ctx, r->accel_delta_counts) == IB_SENSOR_OK) {
            r->passed |= 1u;
        }
    }
    for (int k = 0; k < 3; k++) {
        if (!(c->present & (1u << (1 + k)))) {
            continue;
        }
        r->tested |= (uint8_t)(1u << (1 + k));
        if (c->gyro[k].ops->self_test(c->gyro[k].ctx, &r->gyro_chk_faults[k]) == IB_SENSOR_OK) {
            r->passed |= (uint8_t)(1u << (1 + k));
        }
    }
    return r->passed == r->tested ? IB_ERROR_OK : IB_ERROR_SELF_TEST_FAILED;
}

/* What a command handler answers: the ack's error and value, and an optional data message
 * packed at c->msg_raw + IB_HEADER_SIZE. */
typedef struct {
    uint8_t err;
    uint8_t data_type;
    uint32_t value;
    size_t data_len;
} cmd_out_t;

static void cmd_set_params(ib_core_t *c, const ib_frame_t *f, cmd_out_t *o)
{
    ib_msg_set_params_t m;
    ib_msg_set_params_unpack(f->payload, &m);
    ib_triad_corr_t a, g;
    o->err = ib_core_check_params(&m.params, &a, &g);
    if (o->err == IB_ERROR_OK) {
        c->params = m.params;
        c->corr_accel = a;
        c->corr_gyro = g;
        c->cal_ready = 0; /* applied from the next sample */
        c->param_source = IB_PARAM_SOURCE_UNSAVED;
    }
}

static void cmd_get_params(ib_core_t *c, const ib_frame_t *f, cmd_out_t *o)
{
    ib_msg_get_params_t m;
    ib_msg_get_params_unpack(f->payload, &m);
    ib_msg_params_readback_t r;
    memset(&r, 0, sizeof r);
    r.request_id = f->seq;
    r.which = m.which;
    r.generation = c->param_generation;
    if (m.which == IB_PARAMS_WHICH_ACTIVE) {
        r.source = c->param_source;
        r.params = c->params;
    } else if (m.which == IB_PARAMS_WHICH_STORED) {
        ib_ps_info_t info;
        if (c->board->flash && ibc_read_stored(c->board->flash, &r.params, &info)) {
            r.source = IB_PARAM_SOURCE_FLASH;
        } else {
            ibc_identity_params(&r.params);
            r.source = IB_PARAM_SOURCE_FACTORY;
        }
    } else {
        o->err = IB_ERROR_BAD_ARGUMENT;
        return;
    }
    o->data_type = IB_MSG_PARAMS_READBACK;
    o->data_len = ib_msg_params_readback_pack(&r, c->msg_raw + IB_HEADER_SIZE);
}

static void cmd_save_params(ib_core_t *c, cmd_out_t *o)
{
    uint8_t blob[IB_PARAMS_SIZE];
    ib_params_pack(&c->params, blob);
    ib_ps_info_t info;
    ib_ps_status_t st = c->board->flash ? ib_ps_save(c->board->flash, IB_PARAM_BLOCK_VERSION, blob,
                                                    sizeof blob, &info)
                                        : IB_PS_ERR_BAD_ARG;
    if (st == IB_PS_OK) {
        c->param_generation = info.generation;
        c->param_slot = (int8_t)info.slot;
        c->param_source = IB_PARAM_SOURCE_FLASH;
        o->value = (info.generation & ~IB_SAVE_UNCHANGED_FLAG) | (info.unchanged ? IB_SAVE_UNCHANGED_FLAG : 0u);
    } else {
        o->err = IB_ERROR_FLASH_ERROR;
        o->value = (uint32_t)(int32_t)st;
    }
}

static void cmd_clear_params(ib_core_t *c, cmd_out_t *o)
{
    ib_ps_info_t info;
    ib_ps_status_t st = c->board->flash ? ib_ps_clear(c->board->flash, &info) : IB_PS_ERR_BAD_ARG;
    if (st == IB_PS_OK || st == IB_PS_CLEARED) {
        ibc_set_factory(c);
        c->param_generation = info.generation;
        c->param_slot = (int8_t)info.slot;
    } else {
        o->err = IB_ERROR_FLASH_ERROR;
        o->value = (uint32_t)(int32_t)st;
    }
}

static void cmd_self_test(ib_core_t *c, const ib_frame_t *f, cmd_out_t *o)
{
    ib_msg_self_test_result_t r;
    o->err = do_self_test(c, &r);
    r.request_id = f->seq;
    o->data_type = IB_MSG_SELF_TEST_RESULT;
    o->data_len = ib_msg_self_test_result_pack(&r, c->msg_raw + IB_HEADER_SIZE);
}

static void cmd_get_stats(ib_core_t *c, const ib_frame_t *f, cmd_out_t *o)
{
    ib_msg_get_stats_t m;
    ib_msg_get_stats_unpack(f->payload, &m);
    ibc_update_uptime(c);
    ib_msg_stats_t s = c->stats;
    s.request_id = f->seq;
    s.uptime_ms = c->uptime_ms;
    /* Every record written (save or clear) takes the next generation and goes into the
     * slot not holding the current one, erasing it first: after generation G the slot
     * holding it was erased (G + 1) / 2 times and the other G / 2 times. A lower bound:
     * erases of interrupted saves and of a chip erase are not counted (SPEC.md). */
    if (c->param_slot == 0 || c->param_slot == 1) {
        s.param_slot_erases[c->param_slot] = (c->param_generation + 1u) / 2u;
        s.param_slot_erases[1 - c->param_slot] = c->param_generation / 2u;
    }
    o->data_type = IB_MSG_STATS;
    o->data_len = ib_msg_stats_pack(&s, c->msg_raw + IB_HEADER_SIZE);
    if (m.reset) {
        memset(&c->stats, 0, sizeof c->stats);
    }
}

static void cmd_get_info(ib_core_t *c, const ib_frame_t *f, cmd_out_t *o)
{
    ib_msg_info_t m;
    ibc_update_uptime(c);
    ibc_info_fill(c, &m, f->seq);
    o->data_type = IB_MSG_INFO;
    o->data_len = ib_msg_info_pack(&m, c->msg_raw + IB_HEADER_SIZE);
}

/* One command: its handler, then the reply (ack and optional data message). Commands that
 * touch the sensors or the flash are refused while streaming (STREAMING). */
static void execute(ib_core_t *c, const ib_frame_t *f)
{
    cmd_out_t o = {IB_ERROR_OK, 0u, 0u, 0u};
    const int streaming = c->stream_state != IB_STREAM_STATE_STOPPED;
    const int quiet_only = f->type == IB_MSG_SAVE_PARAMS || f->type == IB_MSG_CLEAR_PARAMS ||
                           f->type == IB_MSG_SELF_TEST;
    if (streaming && quiet_only) {
        o.err = IB_ERROR_STREAMING;
    } else {
        switch (f->type) {
        case IB_MSG_PING: {
            ib_msg_ping_t m;
            ib_msg_ping_unpack(f->payload, &m);
            o.value = m.nonce;
            break;
        }
        case IB_MSG_GET_INFO:
            cmd_get_info(c, f, &o);
            break;
        case IB_MSG_START_STREAM: {
            ib_msg_start_stream_t m;
            ib_msg_start_stream_unpack(f->payload, &m);
            o.err = do_start_stream(c, &m, &o.value);
            break;
        }
        case IB_MSG_STOP_STREAM:
            if (streaming) {
                ibc_stream_stop(c);
            }
            break;
        case IB_MSG_SET_PARAMS:
            cmd_set_params(c, f, &o);
            break;
        case IB_MSG_GET_PARAMS:
            cmd_get_params(c, f, &o);
            break;
        case IB_MSG_SAVE_PARAMS:
            cmd_save_params(c, &o);
            break;
        case IB_MSG_CLEAR_PARAMS:
            cmd_clear_params(c, &o);
            break;
        case IB_MSG_REBOOT:
            c->reboot_pending = 1;
            break;
        case IB_MSG_SELF_TEST:
            cmd_self_test(c, f, &o);
            break;
        case IB_MSG_GET_STATS:
            cmd_get_stats(c, f, &o);
            break;
        default:
            o.err = IB_ERROR_UNKNOWN_COMMAND;
            break;
        }
    }
    ibc_reply(c, f->seq, f->type, o.err, o.value, o.data_type, o.data_len);
}

void ibc_on_frame(ib_core_t *c, int status, const ib_frame_t *f)
{
    switch (status) {
    case IB_FRAME_OK:
        break;
    case IB_FRAME_BAD_VERSION:
        ibc_reply(c, f->seq, f->type, IB_ERROR_BAD_VERSION, f->version, 0, 0);
        return;
    case IB_FRAME_UNKNOWN_TYPE:
        ibc_reply(c, f->seq, f->type, IB_ERROR_UNKNOWN_COMMAND, 0, 0, 0);
        return;
    case IB_FRAME_BAD_LENGTH:
        ibc_reply(c, f->seq, f->type, IB_ERROR_BAD_LENGTH, (uint32_t)f->payload_len, 0, 0);
        return;
    case IB_FRAME_BAD_ENUM:
    case IB_FRAME_OUT_OF_RANGE:
    case IB_FRAME_NOT_FINITE:
    case IB_FRAME_BAD_FLAGS:
        /* readable, but a field holds what the definition does not allow: the value says which
         * check (the ib_frame_status_t) */
        ibc_reply(c, f->seq, f->type, IB_ERROR_BAD_ARGUMENT, (uint32_t)status, 0, 0);
        return;
    default:
        c->stats.rx_frame_errors++; /* nothing in it can be trusted: no answer */
        return;
    }
    if (!ib_msg_is_command(f->type)) {
        ibc_reply(c, f->seq, f->type, IB_ERROR_UNKNOWN_COMMAND, 0, 0, 0);
        return;
    }
    /* a retry is the same command again: same request id, type and payload byte for byte
     * (not a checksum of them: two different payloads can share any checksum). Answer it
     * from the stored ibc_reply, do not run it again. */
    if (c->last_rid_valid && f->seq == c->last_rid && f->type == c->last_cmd_type &&
        f->payload_len == c->last_cmd_len && memcmp(f->payload, c->last_cmd_payload, f->payload_len) == 0) {
        c->reply_pending = c->last_reply_n;
        return;
    }
    execute(c, f);
    /* commands have fixed layouts no longer than IB_MAX_COMMAND_PAYLOAD (the length check ran
     * before); anything longer is not remembered, so it can never be taken for a retry */
    c->last_rid_valid = f->payload_len <= sizeof c->last_cmd_payload;
    if (c->last_rid_valid) {
        c->last_rid = f->seq;
        c->last_cmd_type = f->type;
        c->last_cmd_len = (uint16_t)f->payload_len;
        memcpy(c->last_cmd_payload, f->payload, f->payload_len);
    }
}
