/* core_stream.c - sampling (synchronous and DMA chain) and batching, through the generic
 * sensors of sensor.h. */
#include "core_priv.h"

/* ------------------------------------------------------------------ stream */

void ibc_emit_fault(ib_core_t *c, uint8_t sensor, uint8_t kind, uint8_t active, uint32_t detail)
{
    ib_msg_fault_event_t e = {sensor, kind, active, 0, detail};
    size_t n = ib_msg_fault_event_pack(&e, c->msg_raw + IB_HEADER_SIZE);
    ibc_send_unsolicited(c, IB_MSG_FAULT_EVENT, n);
}

/* Compare what this batch saw per sensor with what was last reported; report changes. */
static void report_faults(ib_core_t *c)
{
    uint8_t kind[4] = {0, 0, 0, 0};
    uint32_t detail[4] = {0, 0, 0, 0};
    if (!(c->present & 1u)) {
        kind[0] = IB_FAULT_KIND_MISSING;
    } else if (c->batch_spi_error & 1u) {
        kind[0] = IB_FAULT_KIND_SPI_ERROR;
    } else if (c->batch_hdr.accel_status & c->accel.ops->status_fifo_overrun) {
        kind[0] = IB_FAULT_KIND_ACCEL_FIFO_OVERRUN;
    } else if (c->batch_hdr.sensor_flags & IB_BATCH_FLAGS_ACCEL_STALE) {
        kind[0] = IB_FAULT_KIND_ACCEL_STALE;
    }
    for (int k = 0; k < 3; k++) {
        uint8_t s = (uint8_t)(1 + k);
        if (!(c->present & (1u << s))) {
            kind[s] = IB_FAULT_KIND_MISSING;
        } else if (c->batch_spi_error & (1u << s)) {
            kind[s] = IB_FAULT_KIND_SPI_ERROR;
        } else if (c->batch_hdr.gyro_faults[k] & 1u) {
            kind[s] = IB_FAULT_KIND_PARITY;
        } else if (c->batch_hdr.gyro_faults[k] & 0xFEu) {
            kind[s] = IB_FAULT_KIND_GYRO_FAULT_BITS;
            detail[s] = c->batch_hdr.gyro_faults[k];
        } else if (c->batch_gyro_st_bad[k]) {
            kind[s] = IB_FAULT_KIND_GYRO_STATUS;
            detail[s] = c->batch_gyro_st_bad[k];
        }
    }
    for (uint8_t s = 0; s < 4; s++) {
        if (kind[s] != c->fault_state[s]) {
            if (c->fault_state[s]) {
                ibc_emit_fault(c, s, c->fault_state[s], 0, 0);
            }
            if (kind[s]) {
                ibc_emit_fault(c, s, kind[s], 1, detail[s]);
            }
            c->fault_state[s] = kind[s];
        }
    }
}

/* read_temps 0: the sample chain reads them (job_temps) */
static void batch_begin(ib_core_t *c, uint32_t t_us, int read_temps)
{
    memset(&c->batch_hdr, 0, sizeof c->batch_hdr);
    c->batch_hdr.sample_index = c->sample_index;
    c->batch_hdr.period_us = (uint16_t)(1000000u / c->rate_hz);
    c->batch_hdr.accel_range_g = c->accel_range_g;
    c->batch_hdr.sensor_flags = (uint8_t)(~c->present & 0x0Fu);
    if (c->drop_pending) {
        c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SAMPLES_DROPPED;
    }
    c->batch_t0_us = t_us;
    c->batch_n = 0;
    c->batch_spi_error = 0;
    memset(c->batch_gyro_st_bad, 0, sizeof c->batch_gyro_st_bad);
    /* temperatures once per batch */
    if (read_temps && (c->present & 1u)) {
        uint16_t t;
        int e = c->accel.ops->read_temp(c->accel.ctx, &t);
        if (e == IB_SENSOR_OK) {
            c->accel_temp_counts = t;
        } else if (e == IB_SENSOR_ERR_BUS) {
            c->batch_spi_error |= 1u;
            c->stats.spi_errors++;
        }
    }
    for (int k = 0; k < 3 && read_temps; k++) {
        if (c->present & (1u << (1 + k))) {
            int16_t raw10;
            int e = c->gyro[k].ops->read_temp(c->gyro[k].ctx, &raw10);
            if (e == IB_SENSOR_OK) {
                c->gyro_temp_raw10[k] = raw10;
            } else if (e == IB_SENSOR_ERR_BUS) {
                c->batch_spi_error |= (uint8_t)(1u << (1 + k));
                c->stats.spi_errors++;
            }
        }
    }
    c->batch_hdr.accel_temp_counts = c->accel_temp_counts;
    for (int k = 0; k < 3; k++) {
        c->batch_hdr.gyro_temp_counts[k] = c->gyro_temp_raw10[k];
    }
}

static void batch_send(ib_core_t *c)
{
    if (c->batch_n == 0) {
        return;
    }
    int cal = c->stream_state == IB_STREAM_STATE_CALIBRATED;
    size_t rsize = cal ? IB_CAL_SAMPLE_SIZE : IB_RAW_SAMPLE_SIZE;
    c->batch_hdr.count = c->batch_n;
    if (c->batch_spi_error) {
        c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
    }
    ib_batch_header_pack(&c->batch_hdr, c->batch_buf + IB_HEADER_SIZE);
    size_t payload = IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * rsize;
    report_faults(c);
    /* the frame is encoded only when it can be sent whole, replies first */
    size_t worst = IB_HEADER_SIZE + payload + IB_CRC_SIZE + 3u;
    if (c->reply_pending == 0 && c->board->link_tx_free(c->board->ctx) >= worst + REPLY_RESERVE) {
        size_t n = ib_frame_encode(c->batch_buf, cal ? IB_MSG_CAL_BATCH : IB_MSG_RAW_BATCH, c->tx_seq,
                                   c->batch_t0_us, payload, c->tx_frame);
        c->tx_seq++;
        ibc_link_put(c, c->tx_frame, n);
        c->drop_pending = 0;
    } else {
        c->stats.frames_dropped++;
        c->stats.samples_dropped += c->batch_n;
        c->drop_pending = 1;
    }
    c->batch_n = 0;
}

/* What one sample read brought back, from the synchronous reads or the DMA chain. */
typedef struct {
    ib_accel_read_t a;
    ib_gyro_read_t g[IB_GYRO_SLOTS];
} sample_in_t;

/* Read one sample of every sensor with the blocking bus calls (boards without bus->start). */
static void read_sync(ib_core_t *c, sample_in_t *in)
{
    memset(in, 0, sizeof *in);
    if (c->present & 1u) {
        c->accel.ops->read(c->accel.ctx, ACCEL_FIFO_MAX_SETS, &in->a);
    }
    for (int k = 0; k < 3; k++) {
        if (c->present & (1u << (1 + k))) {
            c->gyro[k].ops->read(c->gyro[k].ctx, &in->g[k]);
        }
    }
}

/* The calibrated stream's terms that change only with the temperatures (once a batch), the
 * range or the parameters. */
static void cal_prepare(ib_core_t *c)
{
    float ta[3], tg[3];
    /* with no part found, the slot driver's base part: the stream still carries finite
     * numbers, on that part's scale, flagged missing */
    const ib_part_desc_t *pa = ibc_accel_part(c);
    const ib_part_range_t *rg = ib_part_range(pa, c->accel_range_g);
    float lsb = rg ? rg->lsb_per_unit : pa->ranges[0].lsb_per_unit;
    float t_acc = pa->temp_ref_c + ((float)c->accel_temp_counts - pa->temp_offset_counts) / pa->temp_lsb_per_c;
    for (int k = 0; k < 3; k++) {
        const ib_part_desc_t *pg = ibc_gyro_part(c, k);
        ta[k] = t_acc;
        c->gyro_rad_per_count[k] = RAD_PER_DEG / pg->ranges[0].lsb_per_unit;
        tg[k] = pg->temp_ref_c + ((float)c->gyro_temp_raw10[k] - pg->temp_offset_counts) / pg->temp_lsb_per_c;
    }
    /* the accelerometer's terms in counts: the sample's counts go in as they are */
    ibc_correct_terms(&c->params, 0, &c->corr_accel, ta, G0_MPS2 / lsb, lsb / G0_MPS2, c->cal_bias[0], c->cal_w[0]);
    ibc_correct_terms(&c->params, 1, &c->corr_gyro, tg, 1.0f, 1.0f, c->cal_bias[1], c->cal_w[1]);
    c->cal_ready = 1;
}

/* Append the sample to the batch (and send the batch when full). */
static void sample_commit(ib_core_t *c, const sample_in_t *in)
{
    uint8_t status = 0;
    int32_t acc[3] = {c->accel_last[0], c->accel_last[1], c->accel_last[2]};
    if (c->present & 1u) {
        if (in->a.err != IB_SENSOR_OK) {
            c->batch_spi_error |= 1u;
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else if (in->a.sets == 0) {
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_ACCEL_STALE;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else {
            const int32_t n_sets = (int32_t)in->a.sets, h = n_sets / 2; /* 32-bit: no libgcc divide */
            for (int k = 0; k < 3; k++) {
                /* rounded mean, symmetric about zero */
                int32_t sum = in->a.sum[k];
                acc[k] = n_sets == 1 ? sum : sum >= 0 ? (sum + h) / n_sets : -((-sum + h) / n_sets);
                c->accel_last[k] = acc[k];
            }
        }
        c->batch_hdr.accel_status |= in->a.status;
    } else {
        status |= IB_SAMPLE_STATUS_ACCEL_BAD;
    }
    int16_t rate[3] = {0, 0, 0};
    for (int k = 0; k < 3; k++) {
        uint8_t bad = (uint8_t)(IB_SAMPLE_STATUS_GYRO_X_BAD << k);
        if (!(c->present & (1u << (1 + k)))) {
            status |= bad;
            continue;
        }
        const ib_gyro_read_t *s = &in->g[k];
        if (s->err == IB_SENSOR_ERR_BUS) {
            c->batch_spi_error |= (uint8_t)(1u << (1 + k));
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= bad;
            continue;
        }
        rate[k] = s->rate_counts;
        c->batch_hdr.gyro_faults[k] |= s->faults;
        if (s->status_bad) {
            c->batch_gyro_st_bad[k] = s->status_bad;
        }
        if (!s->good) {
            status |= bad;
        }
    }
    if (status) {
        c->stats.sensor_faults++;
    }
    uint8_t *rec;
    if (c->stream_state == IB_STREAM_STATE_CALIBRATED) {
        ib_cal_sample_t cs;
        float u[3], w[3];
        if (c->batch_n == 0 || !c->cal_ready) {
            cal_prepare(c); /* the temperatures are new at a batch's first sample */
        }
        for (int k = 0; k < 3; k++) {
            u[k] = (float)acc[k]; /* counts: cal_prepare put the scale into cal_w[0] */
            w[k] = (float)rate[k] * c->gyro_rad_per_count[k]; /* the part's scale, cal_prepare */
        }
        ibc_correct_apply(c->cal_w[0], u, c->cal_bias[0], cs.accel_mps2);
        const float *gs = c->params.gyro_g_rad_s_per_mps2; /* g-sensitivity: w − G·a first */
        for (int k = 0; k < 3; k++) {
            /* cs.accel_mps2 is written whole by ibc_correct_apply above; cppcheck does not follow it */
            // cppcheck-suppress uninitvar
            w[k] -= gs[k * 3] * cs.accel_mps2[0] + gs[k * 3 + 1] * cs.accel_mps2[1] + gs[k * 3 + 2] * cs.accel_mps2[2];
        }
        ibc_correct_apply(c->cal_w[1], w, c->cal_bias[1], cs.rate_rad_s);
        cs.status = status;
        rec = c->batch_buf + IB_HEADER_SIZE + IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * IB_CAL_SAMPLE_SIZE;
        ib_cal_sample_pack(&cs, rec);
    } else {
        ib_raw_sample_t rs = {acc[0], acc[1], acc[2], status, {rate[0], rate[1], rate[2]}};
        rec = c->batch_buf + IB_HEADER_SIZE + IB_BATCH_HEADER_SIZE + (size_t)c->batch_n * IB_RAW_SAMPLE_SIZE;
        ib_raw_sample_pack(&rs, rec);
    }
    c->batch_n++;
    c->sample_index++;
    c->stats.samples_produced++;
    if (c->batch_n >= c->batch_max) {
        batch_send(c);
    }
}

/* ---- the sample read as a chain of DMA transfers (bus->start) ----
 * Each sensor present adds its transfers (its ops' chain.plan, into its driver's buffers: an
 * accelerometer's status burst and FIFO pop, a gyro's pipelined frame, more at a batch's
 * start, which reads the temperatures too; firmware/drivers, the ops files). They are listed
 * when the kind of chain changes (job_plan), so a step's work in the interrupt is to take the
 * next entry. Each step is started from the previous one's completion interrupt (job_next);
 * a step with len 0 asks its driver for the length just before (chain.len: the FIFO pop's
 * comes from the header before it), a step tagged IB_XFER_NOTIFY tells its driver it ended
 * (chain.done). The main loop is free meanwhile and finishes the sample (ibc_sample_finish:
 * each driver's finish) when job_done is set. */
#define JOB_WAIT_US 5000u

static void job_next(void *arg, int rc);

/* The chain ops and context of sensor s (enum ib_sensor). */
static const ib_chain_ops_t *job_ops(const ib_core_t *c, uint8_t s, void **ctx)
{
    if (s == IB_SENSOR_ACCEL) {
        *ctx = c->accel.ctx;
        return &c->accel.ops->chain;
    }
    *ctx = c->gyro[s - 1u].ctx;
    return &c->gyro[s - 1u].ops->chain;
}

/* List the transfers of a chain for the sensors present (temps: a batch start's). */
static void job_plan(ib_core_t *c, uint8_t temps)
{
    static const uint8_t cs[4] = {IB_CS_ACCEL, IB_CS_GYRO_X, IB_CS_GYRO_Y, IB_CS_GYRO_Z};
    ib_xfer_t *x = c->job_list;
    for (uint8_t s = 0; s < 4u; s++) {
        if (!(c->present & (1u << s))) {
            continue;
        }
        void *ctx;
        uint8_t n = job_ops(c, s, &ctx)->plan(ctx, temps, x);
        for (uint8_t i = 0; i < n; i++, x++) {
            x->cs = cs[s];
            x->sensor = s;
        }
    }
    c->job_end = x;
    c->job_list_temps = temps;
}

/* Start the first transfer at or after x that applies (its sensor has not failed, its length
 * not 0); the chain is over when none is left. */
static void job_run(ib_core_t *c, const ib_xfer_t *x)
{
    const ib_spi_bus_t *b = c->board->spi;
    for (; x < c->job_end; x++) {
        if (c->job_rc[x->sensor]) {
            continue;
        }
        size_t len = x->len;
        if (len == 0u) {
            void *ctx;
            len = job_ops(c, x->sensor, &ctx)->len(ctx, x);
            if (len == 0u) {
                continue;
            }
        }
        c->job_cur = x;
        if (b->start(b->ctx, x->cs, x->tx, x->rx, len, job_next, c) == 0) {
            return;
        }
        c->job_rc[x->sensor] = -1;
    }
    c->job_busy = 0;
    c->job_done = 1;
}

/* A transfer of the chain ended (bus interrupt): note it, start the next. */
static void job_next(void *arg, int rc)
{
    ib_core_t *c = (ib_core_t *)arg;
    const ib_xfer_t *x = c->job_cur;
    if (rc < 0) {
        c->job_rc[x->sensor] = -1;
    } else if (x->tag & IB_XFER_NOTIFY) {
        void *ctx;
        job_ops(c, x->sensor, &ctx)->done(ctx, x);
    }
    job_run(c, x + 1);
}

static void job_begin(ib_core_t *c, uint8_t temps)
{
    memset(c->job_rc, 0, sizeof c->job_rc);
    c->job_temps = temps;
    c->job_done = 0;
    c->job_busy = 1;
    if (c->job_list_temps != temps) {
        job_plan(c, temps);
    }
    job_run(c, c->job_list);
}

/* Turn what the chain brought back into the sample: each sensor's driver reads its buffers. */
void ibc_sample_finish(ib_core_t *c)
{
    sample_in_t in; /* each driver's finish writes its reading whole (no memset: once a sample) */
    c->job_done = 0;
    in.a.err = IB_SENSOR_OK; /* (sample_commit reads a reading only of a sensor present) */
    in.a.sets = 0;
    in.a.status = 0;
    if (c->present & 1u) {
        c->accel.ops->finish(c->accel.ctx, c->job_rc[0], c->job_temps, &in.a);
        if (in.a.temp_ok) {
            c->accel_temp_counts = in.a.temp_counts;
            c->batch_hdr.accel_temp_counts = c->accel_temp_counts;
        }
    }
    for (int k = 0; k < 3; k++) {
        if (!(c->present & (1u << (1 + k)))) {
            continue;
        }
        c->gyro[k].ops->finish(c->gyro[k].ctx, c->job_rc[1 + k], c->job_temps, &in.g[k]);
        if (in.g[k].temp_ok) {
            c->gyro_temp_raw10[k] = in.g[k].temp_counts;
            c->batch_hdr.gyro_temp_counts[k] = in.g[k].temp_counts;
        }
    }
    sample_commit(c, &in);
}

/* Let a running chain end (bounded) and finish its sample: before anything else uses the
 * bus or the batch. */
static void job_wait(ib_core_t *c)
{
    if (c->job_busy) {
        uint32_t t0 = ibc_now_us(c);
        while (c->job_busy && ibc_now_us(c) - t0 < JOB_WAIT_US) {
        }
        if (c->job_busy) { /* the bus never completed: report every sensor's read as failed */
            c->job_busy = 0;
            memset(c->job_rc, 0xFF, sizeof c->job_rc);
            c->job_done = 1;
        }
    }
    if (c->job_done) {
        ibc_sample_finish(c);
    }
}

void ib_core_tick(ib_core_t *c, uint32_t missed, uint32_t due_us)
{
    if (c->stream_state == IB_STREAM_STATE_STOPPED) {
        return;
    }
    job_wait(c);
    /* the periodic stats: checked once a sample (not on every main-loop pass, each a time read) */
    ibc_update_uptime(c);
    if (c->uptime_ms - c->last_stats_ms >= STATS_PERIOD_MS) {
        c->last_stats_ms = c->uptime_ms;
        ib_msg_stats_t s = c->stats;
        s.request_id = 0;
        s.uptime_ms = c->uptime_ms;
        size_t len = ib_msg_stats_pack(&s, c->msg_raw + IB_HEADER_SIZE);
        ibc_send_unsolicited(c, IB_MSG_STATS, len);
    }
    if (missed) {
        /* samples inside a batch are consecutive: close the batch, then skip */
        batch_send(c);
        c->sample_index += missed;
        c->stats.samples_dropped += missed;
        c->drop_pending = 1;
    }
    const int async = c->board->spi->start != NULL;
    const uint8_t first = c->batch_n == 0;
    if (first) {
        batch_begin(c, due_us, !async);
    }
    if (async) {
        job_begin(c, first);
        return;
    }
    sample_in_t in;
    read_sync(c, &in);
    sample_commit(c, &in);
}

void ibc_stream_stop(ib_core_t *c)
{
    job_wait(c);
    batch_send(c);
    c->stream_state = IB_STREAM_STATE_STOPPED;
    c->board->set_tick_hz(c->board->ctx, 0);
}
