/*
 * core.h - the firmware core: boot, sample pipeline, command handling, parameters.
 *
 * Portable C11, no register access: it talks to the hardware only through the ib_board_t
 * it is given (board.h), to the sensors only through their ops tables (sensor.h: the core
 * names no part), to flash only through the parameter store. The same code runs on the STM32 boards and in the simulator.
 */
#ifndef IB_CORE_H
#define IB_CORE_H

#include <stdint.h>

#include "board.h"
#include "frame.h"
#include "protocol_gen.h"
#include "sensor.h"

/* What the correction needs beyond the active parameter block: M^-1, computed once when a
 * block is accepted. The bias, its temperature polynomial, the scale term, t_ref and the span
 * are read from the block itself (ib_core_t.params), not copied (RAM: issue 23). */
typedef struct {
    float m_inv[3][3];
} ib_triad_corr_t;

typedef struct ib_core {
    const ib_board_t *board;

    /* sensors: generic, each its driver's ops and context (sensor.h), chosen at boot */
    ib_accel_t accel;
    ib_gyro_t gyro[IB_GYRO_SLOTS];
    uint8_t present;              /* bit per sensor (enum ib_sensor) */
    uint8_t accel_range_g;
    int32_t accel_last[3];        /* last good accelerometer value (repeated when stale) */
    uint16_t accel_temp_counts;   /* read once per batch */
    int16_t gyro_temp_raw10[3];

    /* parameters */
    ib_params_t params;           /* active block */
    ib_triad_corr_t corr_accel, corr_gyro;
    uint8_t param_source;         /* enum ib_param_source */
    uint32_t param_generation;    /* of the stored block, 0 = none */
    int8_t param_slot;            /* flash slot holding it, -1 = none */

    /* stream */
    uint8_t stream_state;         /* enum ib_stream_state */
    uint16_t rate_hz;
    uint8_t batch_max;
    uint32_t sample_index;        /* of the next sample */
    uint8_t batch_n;              /* samples in the batch being built */
    uint8_t drop_pending;         /* samples were dropped since the last batch sent */
    uint8_t batch_spi_error;      /* bit per sensor: a transfer failed in this batch */
    uint8_t batch_gyro_st_bad[3]; /* 0x80 | ST of a gyro reply with ST != 01 in this batch */
    ib_batch_header_t batch_hdr;
    uint32_t batch_t0_us;
    /* the calibrated stream's per-batch terms (core_stream.c, cal_prepare): per triad ([0] the
     * accelerometer, in counts, [1] the gyros, in rad/s) the bias at the batch's temperatures
     * (b + c1 dt + c2 dt^2 + c3 dt^3, dt the clamped temperature minus t_ref) and
     * W = M^-1 diag(unit / (1 + scale_tc dt)); cal_ready 0 after a parameter or range change */
    float cal_bias[2][3], cal_w[2][3][3];
    float gyro_rad_per_count[3]; /* each gyro part's scale (protocol/parts.toml), rad/s per count */
    uint8_t cal_ready;
    uint8_t batch_buf[IB_MAX_FRAME];  /* raw frame being built: header, payload, CRC */
    uint8_t fault_state[4];       /* fault kind last reported per sensor, 0 = none */

    /* link */
    uint16_t tx_seq;
    ib_frame_rx_t rx;
    uint8_t rx_buf[32];           /* received bytes not yet pushed into rx (a staging copy of the
                                   * board ring: commands only, so 32 do; RAM, issue 23) */
    uint8_t rx_len, rx_pos;
    uint8_t msg_raw[IB_MAX_FRAME];    /* scratch for building one message */
    uint8_t tx_frame[IB_MAX_ENCODED + 1];
    /* the last command's reply (data message + ack), kept to answer a retry */
    uint8_t last_reply[2][IB_MAX_ENCODED + 1];
    uint16_t last_reply_len[2];
    uint8_t last_reply_n;
    uint8_t reply_pending;        /* reply frames not yet handed to the link */
    /* the last executed command, whole, to recognise a retry by content (SPEC.md, Retries):
     * a checksum would let two different commands with one id pass as the same */
    uint8_t last_rid_valid;
    uint16_t last_rid;            /* request id of the last executed command */
    uint8_t last_cmd_type;        /* its type */
    uint16_t last_cmd_len;        /* its payload length */
    uint8_t last_cmd_payload[IB_MAX_COMMAND_PAYLOAD]; /* and its payload, byte for byte */
    uint8_t reboot_pending;

    /* asynchronous sample read (boards whose bus has start(): SPI by DMA). ib_core_tick
     * starts the chain, the bus interrupt runs it (job_next), ib_core_poll finishes the
     * sample once it is done. */
    volatile uint8_t job_busy;    /* a chain is running */
    volatile uint8_t job_done;    /* a finished chain waits for sample_finish */
    int8_t job_rc[4];             /* per sensor: 0, or <0 when a transfer failed */
    uint8_t job_temps;            /* this chain also reads the temperatures (batch start) */
    /* the chain's transfers for the sensors present (each driver's ops plan its own, into its
     * own buffers), listed when the kind of chain changes (a batch start's reads the
     * temperatures too: twice a batch); job_cur is the running one */
    ib_xfer_t job_list[4u * IB_XFER_MAX];
    const ib_xfer_t *job_cur, *job_end;
    uint8_t job_list_temps;       /* the kind listed: 0, 1, or 0xFF none yet */

    ib_msg_stats_t stats;
    uint32_t uptime_ms;
    uint32_t uptime_us_rem;
    uint32_t last_time_us;
    uint32_t last_stats_ms;
} ib_core_t;

/* Boot: sensors start-up, parameters from flash, then a 0x00 and an unsolicited info. */
void ib_core_init(ib_core_t *c, const ib_board_t *b);

/* One sample period elapsed (`missed` periods were skipped before it: counted as dropped).
 * due_us: the device time at which this tick fell due on the board's period grid (start +
 * k x period); a batch is stamped with its first sample's due time, so the stamps stay on the
 * grid however late the main loop reaches a tick (docs/protocol.md, batch time). */
void ib_core_tick(ib_core_t *c, uint32_t missed, uint32_t due_us);

/* Main-loop work: received bytes, commands, finishing a sample read by the DMA chain. Call as
 * often as possible. (The periodic stats are sent from ib_core_tick.) */
void ib_core_poll(ib_core_t *c);

/* Validate a parameter block as set_params does; returns IB_ERROR_OK or the error code.
 * On success fills the two corrections (may be NULL). */
uint8_t ib_core_check_params(const ib_params_t *p, ib_triad_corr_t *accel, ib_triad_corr_t *gyro);

/* Apply block p's correction of one triad (gyro 0: the accelerometer, 1: the gyros; t its
 * M^-1 from ib_core_check_params) to a nominally scaled measurement u (SI, the gyro's with
 * G·a already taken off); temp_c is the temperature of each axis' sensor (the accelerometer's
 * for all three accelerometer axes; each gyro's own). docs/conventions.md, Temperature model. */
void ib_core_correct(const ib_params_t *p, int gyro, const ib_triad_corr_t *t, const float u[3],
                     const float temp_c[3], float out[3]);

#endif
