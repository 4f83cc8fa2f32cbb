/*
 * adxl355.h - driver for the Analog Devices ADXL355 3-axis 20-bit accelerometer (SPI).
 *
 * Portable C11: the driver talks to the part only through an ib_spi_bus_t (spi_bus.h),
 * uses no floating point (the firmware also runs on a Cortex-M3 without FPU), no
 * dynamic memory, and every wait is bounded: a missing, wrong or broken part gives an
 * error code, never a hang.
 *
 * Register behaviour follows /work/shared/reference/sensors.md section 1:
 *   - SPI command byte (addr << 1) | R, address auto-increment on bursts, except at
 *     FIFO_DATA (0x11), where every 3 bytes pop one FIFO entry.
 *   - After a soft reset (0x52 to RESET 0x2F) the part reloads its NVM; while NVM_BUSY
 *     is set, reads return 0xFF and writes are ignored. The driver polls NVM_BUSY every
 *     1 ms, at most IB_ADXL355_NVM_POLL_MAX times (Zephyr), and compares the factory
 *     "shadow" bytes 0x50..0x54 before and after the reset (Linux, no-OS), retrying the
 *     reset up to IB_ADXL355_RESET_TRIES times.
 *   - Range, filter (ODR/LPF, HPF) and offsets are only changed in standby; every
 *     setter goes to standby, writes, and returns to measurement if the part was
 *     measuring before.
 *
 * Units: everything here is raw counts (docs/conventions.md). Acceleration counts are
 * the sign-extended 20-bit value; accel_mps2 = counts * G0 / lsb_per_g with
 * ib_adxl355_lsb_per_g(). Temperature counts are the unsigned 12-bit value;
 * temp_c = 25 + (counts - 1885) / -9.05.
 *
 * Typical use:
 *   ib_adxl355_t acc;
 *   ib_adxl355_config_t cfg = IB_ADXL355_CONFIG_DEFAULT;   (+-2 g, 4 kHz, HPF off)
 *   if (ib_adxl355_init(&acc, &bus, IB_CS_ACCEL, &cfg) != IB_ADXL355_OK) ... report
 *   ib_adxl355_sample_t s; ib_adxl355_read_sample(&acc, &s); if (s.new_data) ...
 */
#ifndef IB_ADXL355_H
#define IB_ADXL355_H

#include <stddef.h>
#include <stdint.h>

#include "parts_gen.h"
#include "protocol_gen.h"
#include "spi_bus.h"

/* ---- register map (sensors.md 1.2) ---- */
#define IB_ADXL355_REG_DEVID_AD 0x00
#define IB_ADXL355_REG_DEVID_MST 0x01
#define IB_ADXL355_REG_PARTID 0x02
#define IB_ADXL355_REG_REVID 0x03
#define IB_ADXL355_REG_STATUS 0x04
#define IB_ADXL355_REG_FIFO_ENTRIES 0x05
#define IB_ADXL355_REG_TEMP2 0x06
#define IB_ADXL355_REG_TEMP1 0x07
#define IB_ADXL355_REG_XDATA3 0x08
#define IB_ADXL355_REG_YDATA3 0x0B
#define IB_ADXL355_REG_ZDATA3 0x0E
#define IB_ADXL355_REG_FIFO_DATA 0x11
#define IB_ADXL355_REG_OFFSET_X_H 0x1E
#define IB_ADXL355_REG_OFFSET_X_L 0x1F
#define IB_ADXL355_REG_OFFSET_Y_H 0x20
#define IB_ADXL355_REG_OFFSET_Y_L 0x21
#define IB_ADXL355_REG_OFFSET_Z_H 0x22
#define IB_ADXL355_REG_OFFSET_Z_L 0x23
#define IB_ADXL355_REG_ACT_EN 0x24
#define IB_ADXL355_REG_ACT_THRESH_H 0x25
#define IB_ADXL355_REG_ACT_THRESH_L 0x26
#define IB_ADXL355_REG_ACT_COUNT 0x27
#define IB_ADXL355_REG_FILTER 0x28
#define IB_ADXL355_REG_FIFO_SAMPLES 0x29
#define IB_ADXL355_REG_INT_MAP 0x2A
#define IB_ADXL355_REG_SYNC 0x2B
#define IB_ADXL355_REG_RANGE 0x2C
#define IB_ADXL355_REG_POWER_CTL 0x2D
#define IB_ADXL355_REG_SELF_TEST 0x2E
#define IB_ADXL355_REG_RESET 0x2F
#define IB_ADXL355_REG_SHADOW 0x50 /* 0x50..0x54, factory bytes */
#define IB_ADXL355_SHADOW_LEN 5

/* ---- fixed values and bits (sensors.md 1.2, 1.3) ---- */
#define IB_ADXL355_DEVID_AD 0xAD
#define IB_ADXL355_DEVID_MST 0x1D
#define IB_ADXL355_PARTID 0xED
#define IB_ADXL355_RESET_CODE 0x52

#define IB_ADXL355_STATUS_DATA_RDY 0x01
#define IB_ADXL355_STATUS_FIFO_FULL 0x02
#define IB_ADXL355_STATUS_FIFO_OVR 0x04
#define IB_ADXL355_STATUS_ACTIVITY 0x08
#define IB_ADXL355_STATUS_NVM_BUSY 0x10
#define IB_ADXL355_STATUS_RESERVED 0xE0 /* bits 7:5, read 0 on a working part */

#define IB_ADXL355_POWER_STANDBY 0x01
#define IB_ADXL355_POWER_TEMP_OFF 0x02
#define IB_ADXL355_POWER_DRDY_OFF 0x04

#define IB_ADXL355_SELF_TEST_ST1 0x01
#define IB_ADXL355_SELF_TEST_ST2 0x02

#define IB_ADXL355_RANGE_MASK 0x03 /* RANGE bits 1:0; bits 7:6 (I2C_HS, INT_POL) kept */

#define IB_ADXL355_FIFO_SIZE 96         /* entries; one entry = one axis sample */
#define IB_ADXL355_FIFO_MARKER_X 0x01   /* third byte of a FIFO entry, bit0 */
#define IB_ADXL355_FIFO_MARKER_EMPTY 0x02 /* third byte of a FIFO entry, bit1 */

#define IB_ADXL355_ODR_CODE_MAX 10 /* ODR_LPF codes 0 (4 kHz) .. 10 (3.906 Hz) */
#define IB_ADXL355_HPF_CODE_MAX 6  /* HPF_CORNER 0 = off .. 6 */

/* ---- driver limits (all waits bounded) ---- */
#define IB_ADXL355_NVM_POLL_US 1000u   /* NVM_BUSY poll interval after a reset */
#define IB_ADXL355_NVM_POLL_MAX 100u   /* -> at most ~100 ms waiting for the NVM */
#define IB_ADXL355_RESET_TRIES 3u      /* soft resets tried until the shadow bytes match */
#define IB_ADXL355_FIFO_CHUNK 24u      /* FIFO entries popped per SPI transaction */
#define IB_ADXL355_ST_SETTLE 8u        /* samples discarded after each self-test switch */
#define IB_ADXL355_ST_AVERAGE 16u      /* samples averaged per self-test phase */
#define IB_ADXL355_ST_ODR_CODE 2u      /* self-test runs at 1 kHz, HPF off ... */
#define IB_ADXL355_ST_RANGE IB_ADXL355_RANGE_8G /* ... and +-8 g (room for 1 g + ST force) */

/* Error codes. Every function returns one of these (as int). */
typedef enum ib_adxl355_err {
    IB_ADXL355_OK = 0,
    IB_ADXL355_ERR_BUS = -1,         /* the SPI bus reported an error */
    IB_ADXL355_ERR_ID = -2,          /* DEVID_AD/DEVID_MST/PARTID wrong (no part: 0x00/0xFF) */
    IB_ADXL355_ERR_NVM_TIMEOUT = -3, /* NVM_BUSY did not clear after a soft reset */
    IB_ADXL355_ERR_SHADOW = -4,      /* shadow bytes 0x50..0x54 differ after every reset try */
    IB_ADXL355_ERR_ARG = -5,         /* bad argument (NULL, out-of-range code) */
    IB_ADXL355_ERR_SELFTEST = -6,    /* self-test deltas outside the limits */
    IB_ADXL355_ERR_NO_DATA = -7      /* no new sample (DATA_RDY) within the timeout */
} ib_adxl355_err_t;

/* Measurement range: the RANGE register code (bits 1:0). */
typedef enum ib_adxl355_range {
    IB_ADXL355_RANGE_2G = 1, /* 256000 LSB/g */
    IB_ADXL355_RANGE_4G = 2, /* 128000 LSB/g */
    IB_ADXL355_RANGE_8G = 3  /*  64000 LSB/g */
} ib_adxl355_range_t;

/* Configuration applied by ib_adxl355_init() / ib_adxl355_configure(). */
typedef struct ib_adxl355_config {
    uint8_t range;    /* ib_adxl355_range_t */
    uint8_t odr_code; /* FILTER ODR_LPF 0..10: ODR = 4000 Hz / 2^code, LPF = ODR/4 */
    uint8_t hpf_code; /* FILTER HPF_CORNER 0 (off) .. 6 */
} ib_adxl355_config_t;

#define IB_ADXL355_CONFIG_DEFAULT {IB_ADXL355_RANGE_2G, 0u, 0u}

/* Device state. Fill it with ib_adxl355_init(); read the fields, do not write them. */
typedef struct ib_adxl355 {
    const ib_spi_bus_t *bus;
    uint8_t cs;
    /* IDs as read from the part by the last ib_adxl355_check_id() (for reporting). */
    uint8_t devid_ad, devid_mst, partid, revid;
    /* The part those IDs name (protocol/parts.toml: ADXL355 or ADXL359); NULL when none. */
    const ib_part_desc_t *part;
    /* Shadow bytes 0x50..0x54 read before the last soft reset. */
    uint8_t shadow[IB_ADXL355_SHADOW_LEN];
    /* Cached configuration (what the driver last wrote). */
    uint8_t range;     /* ib_adxl355_range_t */
    uint8_t odr_code;
    uint8_t hpf_code;
    uint8_t measuring; /* 1: POWER_CTL.STANDBY = 0 */
    uint8_t last_status;  /* STATUS seen by the last sample or FIFO read */
    uint32_t fifo_discarded; /* FIFO entries dropped while resynchronising (running count) */
} ib_adxl355_t;

/* One sample from ib_adxl355_read_sample(). */
typedef struct ib_adxl355_sample {
    int32_t accel_counts[3]; /* X, Y, Z: sign-extended 20-bit counts */
    uint16_t temp_counts;    /* 12-bit unsigned temperature counts */
    uint8_t status;          /* STATUS register (the read clears DATA_RDY, FIFO_OVR, Activity) */
    uint8_t fifo_entries;    /* FIFO_ENTRIES (0..96) */
    uint8_t new_data;        /* 1 when DATA_RDY was set: the data was not read before
                                (0 when STATUS is implausible: reserved bits 7:5 or
                                NVM_BUSY set, e.g. 0xFF during an NVM reload) */
} ib_adxl355_sample_t;

/* Result of ib_adxl355_self_test(). */
typedef struct ib_adxl355_selftest {
    int32_t delta_counts[3]; /* mean(ST1+ST2) - mean(ST1), counts at lsb_per_g */
    int32_t lsb_per_g;       /* sensitivity of the range the test ran at (64000: +-8 g) */
    uint8_t axis_pass[3];    /* 1 when |delta| is inside the limit of that axis */
} ib_adxl355_selftest_t;

/* Self-test limits on |delta|: the part's self_test_min/max (protocol/parts.toml). */

/* ---- helpers without bus access ---- */

/* LSB per g of a range code on `part` (protocol/parts.toml; NULL: the ADXL355), 0 for a
 * code the part does not have. */
int32_t ib_adxl355_part_lsb_per_g(const ib_part_desc_t *part, uint8_t range);
/* The ADXL355's (256000/128000/64000). */
int32_t ib_adxl355_lsb_per_g(uint8_t range);

/* Sample period in microseconds of an ODR_LPF code: 250 << code (exact: ODR =
 * 4000 Hz / 2^code), 0 for a code above 10. */
uint32_t ib_adxl355_odr_period_us(uint8_t odr_code);

/* Assemble three data bytes (DATA3, DATA2, DATA1 or a FIFO entry) into the signed
 * 20-bit count: (b3<<12 | b2<<4 | b1>>4), sign-extended from bit 19. The low nibble of
 * b1 (FIFO flags) is ignored. */
int32_t ib_adxl355_counts_from_bytes(uint8_t b3, uint8_t b2, uint8_t b1);

/* ---- bus functions; all return ib_adxl355_err_t ---- */

/* The whole bring-up: attach to bus/cs, ib_adxl355_check_id(), ib_adxl355_soft_reset(),
 * ib_adxl355_check_id() again, ib_adxl355_configure(cfg) and ib_adxl355_measure().
 * cfg NULL means IB_ADXL355_CONFIG_DEFAULT (+-2 g, 4 kHz, HPF off). On success the part
 * is measuring. On a wrong or missing part returns IB_ADXL355_ERR_ID after at most
 * ~100 ms; the observed IDs stay in dev for reporting. */
int ib_adxl355_init(ib_adxl355_t *dev, const ib_spi_bus_t *bus, uint8_t cs,
                    const ib_adxl355_config_t *cfg);

/* Read DEVID_AD, DEVID_MST, PARTID, REVID in one 4-byte burst into dev and check the
 * first three (REVID is only reported). If all four bytes read 0xFF (the part may be
 * reloading its NVM), waits for NVM_BUSY to clear (bounded) and reads once more.
 * IB_ADXL355_ERR_ID on any mismatch, including a missing part (all 0x00). */
int ib_adxl355_check_id(ib_adxl355_t *dev);

/* Soft reset: read the shadow bytes 0x50..0x54, write 0x52 to RESET, poll STATUS
 * until NVM_BUSY clears (1 ms steps, at most IB_ADXL355_NVM_POLL_MAX), read the shadow
 * bytes again and compare; on a mismatch reset again (IB_ADXL355_RESET_TRIES in all).
 * Afterwards the part is in standby with reset register values; dev's cached
 * configuration is set to the reset values (+-2 g, ODR code 0, HPF off).
 * IB_ADXL355_ERR_NVM_TIMEOUT or IB_ADXL355_ERR_SHADOW on failure. */
int ib_adxl355_soft_reset(ib_adxl355_t *dev);

/* Wait (bounded) until STATUS.NVM_BUSY reads 0. IB_ADXL355_ERR_NVM_TIMEOUT otherwise. */
int ib_adxl355_wait_nvm(ib_adxl355_t *dev);

/* Enter standby (POWER_CTL = STANDBY). */
int ib_adxl355_standby(ib_adxl355_t *dev);

/* Leave standby: POWER_CTL = 0 (measurement, temperature on, DRDY on). */
int ib_adxl355_measure(ib_adxl355_t *dev);

/* Apply range, ODR and HPF codes (validated first: IB_ADXL355_ERR_ARG). Goes to standby,
 * writes RANGE (read-modify-write, keeping I2C_HS/INT_POL) and FILTER, and returns to
 * measurement if the part was measuring. */
int ib_adxl355_configure(ib_adxl355_t *dev, const ib_adxl355_config_t *cfg);

/* Change only the range (same standby rule). */
int ib_adxl355_set_range(ib_adxl355_t *dev, uint8_t range);

/* Change only the FILTER register: ODR_LPF code 0..10 and HPF code 0..6. */
int ib_adxl355_set_filter(ib_adxl355_t *dev, uint8_t odr_code, uint8_t hpf_code);

/* Write OFFSET_X/Y/Z (16-bit two's complement; 1 offset LSB = 16 data LSB, added by
 * the part after all other processing) in one 6-byte burst. Same standby rule. */
int ib_adxl355_set_offset(ib_adxl355_t *dev, const int16_t offset[3]);

/* Read OFFSET_X/Y/Z back. */
int ib_adxl355_get_offset(ib_adxl355_t *dev, int16_t offset[3]);

/* Read one sample: one 13-byte burst from STATUS (0x04) through ZDATA1 (0x10):
 * STATUS, FIFO_ENTRIES, TEMP2, TEMP1, X3..Z1. new_data tells whether DATA_RDY was set
 * (the STATUS read clears it, so the next read of the same sample gives new_data 0).
 * A STATUS of 0xFF (NVM reload, MISO floating high) never counts as new data. */
int ib_adxl355_read_sample(ib_adxl355_t *dev, ib_adxl355_sample_t *s);

/* Poll ib_adxl355_read_sample() until it gives new data, sleeping between polls
 * (a quarter of the sample period, at least 20 us) for at most timeout_us.
 * IB_ADXL355_ERR_NO_DATA when nothing new came. */
int ib_adxl355_wait_sample(ib_adxl355_t *dev, ib_adxl355_sample_t *s, uint32_t timeout_us);

/* Read complete X,Y,Z sets from the FIFO into xyz[0..max_sets-1]; *n_sets gets the
 * count. Reads STATUS and FIFO_ENTRIES in one 2-byte burst (this clears DATA_RDY,
 * FIFO_OVR and Activity; the STATUS value is kept in dev->last_status, so check it
 * there for FIFO_OVR), rounds the entry count down to a multiple of 3 (and to
 * max_sets * 3), and pops that many entries from FIFO_DATA in bursts of at most
 * IB_ADXL355_FIFO_CHUNK entries. Each entry's third byte is checked: the empty flag
 * (bit1) ends the read; a set must start at an entry with the X marker (bit0). Entries
 * before the first X marker, and a partial set cut short by a new X marker, are
 * discarded (counted in dev->fifo_discarded) and the read is extended by as many
 * entries, so a FIFO that starts mid-set still yields its complete sets. */
int ib_adxl355_read_fifo(ib_adxl355_t *dev, int32_t (*xyz)[3], size_t max_sets,
                         size_t *n_sets);

/* The FIFO read in pieces, for a board that runs the transfers itself (DMA):
 *   ib_adxl355_fifo_entries: from STATUS and FIFO_ENTRIES (a 2-byte read at 0x04) the number
 *     of entries to pop (whole sets, at most max_sets); keeps STATUS in dev->last_status.
 *   ib_adxl355_fifo_parse: the popped entries (3 bytes each, as read from FIFO_DATA) into
 *     complete sets, with the marker checks of ib_adxl355_read_fifo (sets beyond max_sets
 *     and entries out of step are discarded and counted); call _init before and _end after.
 * ib_adxl355_read_fifo is these three around its own transfers. */
typedef struct ib_adxl355_fifo_parse {
    unsigned axis;    /* next axis expected, 0 = waiting for an X marker */
    int empty;        /* an empty marker was seen */
    size_t sets;      /* complete sets written to xyz */
    size_t dropped;   /* entries discarded so far */
    int32_t cur[3];
} ib_adxl355_fifo_parse_t;

/* The command byte that starts a read burst at addr (0x09: STATUS, 0x23: FIFO_DATA). */
uint8_t ib_adxl355_read_cmd(uint8_t addr);
/* What to send to pop n entries (the first 1 + 3n bytes): the FIFO_DATA read command, then
 * zeros. In flash, so a DMA can send it. */
extern const uint8_t ib_adxl355_fifo_read_tx[1u + 3u * IB_ADXL355_FIFO_SIZE];
size_t ib_adxl355_fifo_entries(ib_adxl355_t *dev, const uint8_t hdr[2], size_t max_sets);
void ib_adxl355_fifo_parse_init(ib_adxl355_fifo_parse_t *p);
void ib_adxl355_fifo_parse(ib_adxl355_t *dev, ib_adxl355_fifo_parse_t *p, const uint8_t *buf, size_t n,
                           int32_t (*xyz)[3], size_t max_sets);
void ib_adxl355_fifo_parse_end(ib_adxl355_t *dev, ib_adxl355_fifo_parse_t *p);

/* Self-test. Saves the configuration, goes to +-8 g, 1 kHz, HPF off, measuring; sets
 * ST1, discards IB_ADXL355_ST_SETTLE samples and averages IB_ADXL355_ST_AVERAGE as the
 * baseline; sets ST1|ST2, settles and averages again; clears SELF_TEST and restores the
 * configuration and the measuring/standby state. res gets the deltas (forced minus
 * baseline, counts at +-8 g) and the per-axis verdict against the limits above (on
 * |delta|). Returns IB_ADXL355_OK when all three axes pass, IB_ADXL355_ERR_SELFTEST
 * when any fails, or a bus/no-data error (then res is not meaningful). */
int ib_adxl355_self_test(ib_adxl355_t *dev, ib_adxl355_selftest_t *res);

/* Raw register access for diagnostics: burst read/write of n (1..16) bytes from addr. */
int ib_adxl355_read_regs(ib_adxl355_t *dev, uint8_t addr, uint8_t *buf, size_t n);
int ib_adxl355_write_regs(ib_adxl355_t *dev, uint8_t addr, const uint8_t *buf, size_t n);

#endif
