/* core_stream.c - the sensors, sampling (synchronous and DMA chain) and batching. */
#include "core_priv.h"

/* ----------------------------------------------------------------- sensors */

/* The register code of full scale g on the accelerometer's part (protocol/parts.toml); 0: none. */
uint8_t ibc_range_code(const ib_core_t *c, uint8_t g)
{
    const ib_part_range_t *r = ib_part_range(c->accel.part, g);
    return r ? r->code : 0u;
}

void ibc_sensors_init(ib_core_t *c)
{
    const ib_spi_bus_t *bus = c->board->spi;
    c->present = 0;
    ib_adxl355_config_t cfg = {1u, 2u, 0u}; /* code 1: every part's lowest range */
    if (ib_adxl355_init(&c->accel, bus, IB_CS_ACCEL, &cfg) == IB_ADXL355_OK) {
        c->present |= 1u << IB_SENSOR_ACCEL;
        c->accel_range_g = (uint8_t)c->accel.part->default_full_scale;
    }
    for (int k = 0; k < 3; k++) {
        if (ib_adxrs450_init(&c->gyro[k], bus, (uint8_t)(IB_CS_GYRO_X + k)) == IB_ADXRS450_OK) {
            c->present |= (uint8_t)(1u << (IB_SENSOR_GYRO_X + k));
        }
    }
}

/* The ODR code for a stream rate: the lowest ODR (4000 Hz / 2^k) of which the stream period
 * is a whole multiple of at most ACCEL_FIFO_MAX_SETS samples (averaged per tick). -1: none. */
int ibc_odr_for_rate(uint32_t rate_hz, uint32_t *avg)
{
    if (rate_hz == 0u || 1000000u % rate_hz != 0u) {
        return -1;
    }
    uint32_t period = 1000000u / rate_hz;
    for (int k = IB_ADXL355_ODR_CODE_MAX; k >= 0; k--) {
        uint32_t odr_period = ib_adxl355_odr_period_us((uint8_t)k);
        if (odr_period <= period && period % odr_period == 0u && period / odr_period <= ACCEL_FIFO_MAX_SETS) {
            *avg = period / odr_period;
            return k;
        }
    }
    return -1;
}

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
    } else if (c->batch_hdr.accel_status & 0x04u) {
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
        uint8_t t[2];
        if (ib_adxl355_read_regs(&c->accel, 0x06, t, 2) == IB_ADXL355_OK) {
            c->accel_temp_counts = (uint16_t)(((t[0] & 0x0Fu) << 8) | t[1]);
        } else {
            c->batch_spi_error |= 1u;
            c->stats.spi_errors++;
        }
    }
    for (int k = 0; k < 3 && read_temps; k++) {
        if (c->present & (1u << (1 + k))) {
            int16_t raw10;
            ib_adxrs450_err_t e = ib_adxrs450_read_temp(&c->gyro[k], &raw10);
            if (e == IB_ADXRS450_OK) {
                c->gyro_temp_raw10[k] = raw10;
            } else if (e == IB_ADXRS450_ERR_BUS) {
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
    int accel_err;             /* IB_ADXL355_OK or the error */
    size_t total;              /* FIFO sets read */
    int32_t sum[3];            /* their sum */
    uint8_t st_or;             /* STATUS bits seen */
    ib_adxrs450_err_t gyro_err[3];
    ib_adxrs450_sample_t g[3];
} sample_in_t;

/* Read one sample of every sensor with the blocking bus calls (boards without bus->start). */
static void read_sync(ib_core_t *c, sample_in_t *in)
{
    memset(in, 0, sizeof *in);
    if (c->present & 1u) {
        /* every set the FIFO collected since the last tick, in chunks of 8 (small stack) */
        int32_t sets[8][3];
        size_t n = 0;
        int err = IB_ADXL355_OK;
        do {
            err = ib_adxl355_read_fifo(&c->accel, sets, 8u, &n);
            in->st_or |= c->accel.last_status;
            for (size_t i = 0; err == IB_ADXL355_OK && i < n; i++) {
                in->sum[0] += sets[i][0];
                in->sum[1] += sets[i][1];
                in->sum[2] += sets[i][2];
            }
            in->total += n;
        } while (err == IB_ADXL355_OK && n == 8u && in->total < ACCEL_FIFO_MAX_SETS + 8u);
        in->accel_err = err;
    }
    for (int k = 0; k < 3; k++) {
        if (c->present & (1u << (1 + k))) {
            in->gyro_err[k] = ib_adxrs450_read_rate(&c->gyro[k], &in->g[k]);
        }
    }
}

/* The calibrated stream's terms that change only with the temperatures (once a batch), the
 * range or the parameters. */
static void cal_prepare(ib_core_t *c)
{
    float ta[3], tg[3];
    const ib_part_desc_t *pa = c->accel.part ? c->accel.part : ib_part_by_id(IB_PART_ADXL355);
    /* the range on pa itself: with no accelerometer found (its part NULL) the stream still
     * carries finite numbers, on the ADXL355's scale, flagged missing */
    const ib_part_range_t *rg = ib_part_range(pa, c->accel_range_g);
    float lsb = (float)ib_adxl355_part_lsb_per_g(pa, rg ? rg->code : pa->ranges[0].code);
    float t_acc = pa->temp_ref_c + ((float)c->accel_temp_counts - pa->temp_offset_counts) / pa->temp_lsb_per_c;
    for (int k = 0; k < 3; k++) {
        const ib_part_desc_t *pg = c->gyro[k].part ? c->gyro[k].part : ib_part_by_id(IB_PART_ADXRS450);
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
        if (in->accel_err != IB_ADXL355_OK) {
            c->batch_spi_error |= 1u;
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else if (in->total == 0) {
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_ACCEL_STALE;
            status |= IB_SAMPLE_STATUS_ACCEL_BAD;
        } else {
            const int32_t n_sets = (int32_t)in->total, h = n_sets / 2; /* 32-bit: no libgcc divide */
            for (int k = 0; k < 3; k++) {
                /* rounded mean, symmetric about zero */
                int32_t sum = in->sum[k];
                acc[k] = n_sets == 1 ? sum : sum >= 0 ? (sum + h) / n_sets : -((-sum + h) / n_sets);
                c->accel_last[k] = acc[k];
            }
        }
        c->batch_hdr.accel_status |= in->st_or;
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
        const ib_adxrs450_sample_t *s = &in->g[k];
        if (in->gyro_err[k] == IB_ADXRS450_ERR_BUS) {
            c->batch_spi_error |= (uint8_t)(1u << (1 + k));
            c->batch_hdr.sensor_flags |= IB_BATCH_FLAGS_SPI_ERROR;
            c->stats.spi_errors++;
            status |= bad;
            continue;
        }
        rate[k] = s->rate_counts;
        c->batch_hdr.gyro_faults[k] |= (uint8_t)(s->faults | (s->parity_error ? 1u : 0u));
        if (s->st != 1u) {
            c->batch_gyro_st_bad[k] = (uint8_t)(s->st | 0x80u);
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
 * Steps: 0 ADXL355 STATUS, FIFO_ENTRIES, TEMP2, TEMP1 in one burst; 1 pop the FIFO (the
 * whole sets the header counted, at most JOB_FIFO_SETS); 2 + 2k: gyro k's frame, whose ibc_reply
 * is the rate latched by the previous sample's frame (the pipelined read of adxrs450.h: one
 * frame per gyro instead of two, the rate one sample period old); at the start of a batch
 * that frame sends "read TEM" instead and step 3 + 2k the sensor-data command, whose ibc_reply is
 * the temperature. The steps that apply (sensors present) are listed at each batch start
 * (job_plan), so a step's work in the interrupt is to take the next entry. Each step is
 * started from the previous one's completion interrupt (job_next); the main loop is free
 * meanwhile and finishes the sample (ibc_sample_finish) when job_done is set. */
#define JOB_FIFO_SETS (IB_ADXL355_FIFO_SIZE / 3u) /* the whole FIFO: 160 Hz takes 25 sets a tick */
#define JOB_WAIT_US 5000u
enum { JOB_PLAIN = 0, JOB_HDR = 1, JOB_FIFO = 2 };

static void job_next(void *arg, int rc);

static void job_add(ib_job_step_t **s, const uint8_t *tx, uint8_t *rx, uint8_t len, uint8_t cs, uint8_t sensor,
                    uint8_t kind)
{
    ib_job_step_t *e = (*s)++;
    e->tx = tx;
    e->rx = rx;
    e->len = len;
    e->cs = cs;
    e->sensor = sensor;
    e->kind = kind;
}

/* List the transfers of a chain for the sensors present (temps: a batch start's). */
static void job_plan(ib_core_t *c, uint8_t temps)
{
    ib_job_step_t *s = c->job_list;
    if (c->present & 1u) {
        job_add(&s, c->job_hdr_tx, c->job_hdr_rx, temps ? (uint8_t)sizeof c->job_hdr_tx : 3u, IB_CS_ACCEL, 0u,
                JOB_HDR);
        job_add(&s, ib_adxl355_fifo_read_tx, c->job_fifo_rx, 0u, IB_CS_ACCEL, 0u, JOB_FIFO);
    }
    for (uint8_t k = 0; k < 3u; k++) {
        if (!(c->present & (1u << (1u + k)))) {
            continue;
        }
        uint8_t cs = (uint8_t)(IB_CS_GYRO_X + k);
        job_add(&s, temps ? c->job_tem_tx : c->job_gyro_tx, c->job_gyro_rx[k][0], 4u, cs, (uint8_t)(1u + k),
                JOB_PLAIN);
        if (temps) {
            job_add(&s, c->job_gyro_tx, c->job_gyro_rx[k][1], 4u, cs, (uint8_t)(1u + k), JOB_PLAIN);
        }
    }
    c->job_end = s;
    c->job_list_temps = temps;
}

/* Start the first transfer at or after s that applies (its sensor has not failed; the FIFO
 * pop only when the header counted entries); the chain is over when none is left. */
static void job_run(ib_core_t *c, const ib_job_step_t *s)
{
    const ib_spi_bus_t *b = c->board->spi;
    for (; s < c->job_end; s++) {
        if (c->job_rc[s->sensor]) {
            continue;
        }
        size_t len = s->len;
        if (s->kind == JOB_FIFO) {
            if (c->job_fifo_n == 0u) {
                continue;
            }
            len = 1u + 3u * (size_t)c->job_fifo_n;
        }
        c->job_cur = s;
        if (b->start(b->ctx, s->cs, s->tx, s->rx, len, job_next, c) == 0) {
            return;
        }
        c->job_rc[s->sensor] = -1;
    }
    c->job_busy = 0;
    c->job_done = 1;
}

/* A transfer of the chain ended (bus interrupt): note it, start the next. */
static void job_next(void *arg, int rc)
{
    ib_core_t *c = (ib_core_t *)arg;
    const ib_job_step_t *s = c->job_cur;
    if (rc < 0) {
        c->job_rc[s->sensor] = -1;
    } else if (s->kind == JOB_HDR) {
        c->job_fifo_n = (uint8_t)ib_adxl355_fifo_entries(&c->accel, &c->job_hdr_rx[1], JOB_FIFO_SETS);
    }
    job_run(c, s + 1);
}

static void job_begin(ib_core_t *c, uint8_t temps)
{
    memset(c->job_rc, 0, sizeof c->job_rc);
    c->job_temps = temps;
    c->job_fifo_n = 0;
    c->job_done = 0;
    c->job_busy = 1;
    if (c->job_list_temps != temps) {
        job_plan(c, temps);
    }
    job_run(c, c->job_list);
}

/* Turn what the chain brought back into the sample. */
void ibc_sample_finish(ib_core_t *c)
{
    sample_in_t in; /* every field sample_commit reads is set below (no memset: once a sample) */
    in.accel_err = IB_ADXL355_OK;
    in.total = 0;
    in.sum[0] = in.sum[1] = in.sum[2] = 0;
    in.st_or = 0;
    c->job_done = 0;
    if (c->present & 1u) {
        if (c->job_rc[0] != 0) {
            in.accel_err = IB_ADXL355_ERR_BUS;
        } else {
            in.st_or = c->accel.last_status;
            if (c->job_temps) {
                c->accel_temp_counts = (uint16_t)(((c->job_hdr_rx[3] & 0x0Fu) << 8) | c->job_hdr_rx[4]);
                c->batch_hdr.accel_temp_counts = c->accel_temp_counts;
            }
            if (c->job_fifo_n) {
                int32_t sets[8][3]; /* in chunks of 8 sets (small stack) */
                ib_adxl355_fifo_parse_t p;
                ib_adxl355_fifo_parse_init(&p);
                size_t total = 0;
                for (size_t e0 = 0; e0 < c->job_fifo_n && !p.empty; e0 += 24u) {
                    size_t n = c->job_fifo_n - e0 < 24u ? c->job_fifo_n - e0 : 24u;
                    p.sets = 0;
                    ib_adxl355_fifo_parse(&c->accel, &p, &c->job_fifo_rx[1u + 3u * e0], n, sets, 8u);
                    for (size_t i = 0; i < p.sets; i++) {
                        in.sum[0] += sets[i][0];
                        in.sum[1] += sets[i][1];
                        in.sum[2] += sets[i][2];
                    }
                    total += p.sets;
                }
                ib_adxl355_fifo_parse_end(&c->accel, &p);
                p.sets = total;
                in.total = p.sets;
            }
        }
    }
    for (int k = 0; k < 3; k++) {
        if (!(c->present & (1u << (1 + k)))) {
            continue;
        }
        if (c->job_rc[1 + k] != 0) {
            ib_adxrs450_note_bus_error(&c->gyro[k]);
            in.gyro_err[k] = IB_ADXRS450_ERR_BUS;
            continue;
        }
        in.gyro_err[k] = ib_adxrs450_rate_from_reply(&c->gyro[k], ib_adxrs450_word(c->job_gyro_rx[k][0]), &in.g[k]);
        int16_t raw10;
        if (c->job_temps &&
            ib_adxrs450_temp_from_reply(&c->gyro[k], ib_adxrs450_word(c->job_gyro_rx[k][1]), &raw10) == IB_ADXRS450_OK) {
            c->gyro_temp_raw10[k] = raw10;
            c->batch_hdr.gyro_temp_counts[k] = raw10;
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
