/*
 * sensor.h - the part interface: what the core asks of a sensor, whatever its part.
 *
 * One ops table per kind of sensor (an accelerometer triad, a single-axis gyro), in the style
 * of Zephyr's sensor driver API (a `struct sensor_driver_api` of function pointers and a
 * `dev->data` per instance) and PX4's driver classes: the core (core*.c) holds per slot a
 * generic sensor (ib_accel_t, ib_gyro_t: the ops, the driver's context for that instance and
 * nothing else) and never names a part. A driver (firmware/drivers/<family>_ops.c) fills one
 * table for every part it reads and keeps the context of each slot it serves.
 *
 * Which table a slot gets is decided at boot from the part table: ib_sensor_drivers
 * (drivers_gen.c, generated from protocol/parts.toml's `driver` of each part) lists every part
 * with its driver's ops. The core tries each distinct driver of the slot's kind in that order;
 * the driver reads the part's ID registers over its own bus protocol and identifies them with
 * ib_part_identify (parts_gen.h); the slot is taken when the part found is one the table gives
 * to that driver.
 *
 * Units: counts throughout (docs/conventions.md); a part's scale and temperature law are in
 * its ib_part_desc_t. Return codes: IB_SENSOR_OK, IB_SENSOR_ERR_BUS for a failed transfer (the
 * core counts it as an SPI error), any other negative code for the rest (the driver's own).
 */
#ifndef IB_SENSOR_H
#define IB_SENSOR_H

#include <stddef.h>
#include <stdint.h>

#include "parts_gen.h"
#include "spi_bus.h"

#define IB_SENSOR_OK 0
#define IB_SENSOR_ERR_BUS (-1)

#define IB_ACCEL_SLOTS 1u /* the board's accelerometer triad */
#define IB_GYRO_SLOTS 3u  /* one single-axis gyro per board axis */
#define IB_XFER_MAX 2u    /* transfers one sensor adds to a sample's chain, at most */

/* One transfer of the non-blocking sample read (a chain of them runs from the bus interrupt:
 * core_stream.c). The driver fills tx, rx, len and tag; the core sets cs and sensor. */
typedef struct ib_xfer {
    const uint8_t *tx;
    uint8_t *rx;
    uint8_t len;    /* bytes; 0: ask chain.len just before it runs (0 again: skip it) */
    uint8_t cs;     /* IB_CS_* */
    uint8_t sensor; /* enum ib_sensor: a failed transfer skips the sensor's other ones */
    uint8_t tag;    /* the driver's own step number; IB_XFER_NOTIFY: call chain.done after it */
} ib_xfer_t;
#define IB_XFER_NOTIFY 0x80u

/* What every kind has for the non-blocking read. plan: the sensor's transfers of one sample
 * (temps: a batch's first, which reads the temperature too) into out[0..IB_XFER_MAX-1], their
 * number returned; the buffers are the driver's (its context). len and done run in the bus
 * interrupt: keep them short. */
typedef struct ib_chain_ops {
    uint8_t (*plan)(void *ctx, uint8_t temps, ib_xfer_t *out);
    size_t (*len)(void *ctx, const ib_xfer_t *x);
    void (*done)(void *ctx, const ib_xfer_t *x);
} ib_chain_ops_t;

/* ---- accelerometer triad ---- */

/* One sample period's reading: every X,Y,Z set the part collected since the last one. */
typedef struct ib_accel_read {
    int err;              /* IB_SENSOR_OK, IB_SENSOR_ERR_BUS, or the driver's error */
    uint32_t sets;        /* X,Y,Z sets read */
    int32_t sum[3];       /* their sum per axis, counts */
    uint8_t status;       /* the part's status bits seen (batch header accel_status) */
    uint8_t temp_ok;      /* temp_counts was read (chain with temps) */
    uint16_t temp_counts; /* raw temperature counts (the part's temp_* law) */
} ib_accel_read_t;

typedef struct ib_accel_ops {
    ib_chain_ops_t chain;
    /* The driver's context for slot (0..IB_ACCEL_SLOTS-1): one per instance, owned by it. */
    void *(*instance)(uint8_t slot);
    /* Bring the part on chip select cs of bus up in its lowest range, measuring; IB_SENSOR_OK
     * when a part this driver reads answered (the IDs read stay for ids() either way). */
    int (*init)(void *ctx, const ib_spi_bus_t *bus, uint8_t cs);
    const ib_part_desc_t *(*part)(void *ctx); /* the part identified, NULL none */
    void (*ids)(void *ctx, uint8_t ids[4]);   /* the ID registers read (info.accel_ids) */
    /* Output data rates: code 0..odr_code_max, each a sample period in us. */
    uint8_t odr_code_max;
    uint32_t (*odr_period_us)(uint8_t odr_code);
    /* Configure range (the part table's code) and ODR, then empty the FIFO (at most
     * max_sets sets read); the configuration's result. */
    int (*start)(void *ctx, uint8_t range_code, uint8_t odr_code, uint32_t max_sets);
    int (*read_temp)(void *ctx, uint16_t *counts);
    /* The blocking read of one sample period (boards without bus->start): at least max_sets. */
    void (*read)(void *ctx, uint32_t max_sets, ib_accel_read_t *out);
    /* The sample from what the chain brought back (rc != 0: one of its transfers failed);
     * writes every field of out (the core does not clear it first). */
    void (*finish)(void *ctx, int rc, uint8_t temps, ib_accel_read_t *out);
    /* The part's self-test: the response per axis, counts (self_test_result.accel_delta_counts). */
    int (*self_test)(void *ctx, int32_t delta_counts[3]);
    uint8_t status_fifo_overrun; /* the status bit of a FIFO overrun (fault ACCEL_FIFO_OVERRUN) */
    uint8_t base_part;           /* enum ib_part whose scale a slot reports with no part found */
} ib_accel_ops_t;

/* ---- single-axis gyro ---- */

typedef struct ib_gyro_read {
    int err;              /* IB_SENSOR_OK, IB_SENSOR_ERR_BUS, or the driver's error */
    int16_t rate_counts;  /* the part's lsb_per_unit per deg/s */
    uint8_t faults;       /* batch gyro_faults: bit 0 a parity error, 7:1 the part's fault bits */
    uint8_t status_bad;   /* 0, or 0x80 | the part's status code when the data is not valid */
    uint8_t good;         /* 1: the rate is valid */
    uint8_t temp_ok;      /* temp_counts was read (chain with temps) */
    int16_t temp_counts;  /* raw temperature counts (the part's temp_* law) */
} ib_gyro_read_t;

typedef struct ib_gyro_ops {
    ib_chain_ops_t chain;
    void *(*instance)(uint8_t slot); /* 0..IB_GYRO_SLOTS-1 */
    /* Start-up (with the part's start-up self-test); IB_SENSOR_OK when a part this driver
     * reads answered. The ID read stays for ids() either way. */
    int (*init)(void *ctx, const ib_spi_bus_t *bus, uint8_t cs);
    const ib_part_desc_t *(*part)(void *ctx);
    void (*ids)(void *ctx, uint16_t *id, uint32_t *serial); /* info.gyro_pid, info.gyro_sn */
    /* Before a stream; pipelined: the chain's read (each transfer's reply answers the one before) */
    int (*start)(void *ctx, int pipelined);
    int (*read_temp)(void *ctx, int16_t *counts);
    void (*read)(void *ctx, ib_gyro_read_t *out);
    void (*finish)(void *ctx, int rc, uint8_t temps, ib_gyro_read_t *out); /* writes all of out */
    /* The part's self-test; detail: the fault bits it raised (self_test_result.gyro_chk_faults) */
    int (*self_test)(void *ctx, uint8_t *detail);
    uint8_t base_part;
} ib_gyro_ops_t;

/* ---- the generic sensors the core holds ---- */

typedef struct ib_accel {
    const ib_accel_ops_t *ops; /* the slot's driver (the last one tried when none found a part) */
    void *ctx;
} ib_accel_t;

typedef struct ib_gyro {
    const ib_gyro_ops_t *ops;
    void *ctx;
} ib_gyro_t;

/* ---- the part table's drivers (drivers_gen.c, generated from protocol/parts.toml) ---- */

typedef struct ib_sensor_driver {
    uint8_t part;                /* enum ib_part */
    const ib_accel_ops_t *accel; /* the driver's table of the part's kind, the other NULL */
    const ib_gyro_ops_t *gyro;
} ib_sensor_driver_t;

extern const ib_sensor_driver_t ib_sensor_drivers[];
extern const size_t ib_sensor_driver_count;

#endif
