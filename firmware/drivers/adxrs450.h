/*
 * adxrs450.h - driver for the Analog Devices ADXRS450 single-axis gyroscope
 * (+-300 deg/s, 32-bit pipelined SPI frames). One ib_adxrs450_t per chip: the board has
 * three of them on one bus, chip selects IB_CS_GYRO_X/Y/Z (spi_bus.h).
 *
 * Portable C11: the driver talks to the part only through an ib_spi_bus_t, uses no
 * floating point (Cortex-M3 without FPU), no dynamic memory, and has no loops that wait
 * on the part: every operation is a fixed, short list of frames and delays, so a
 * missing or broken part gives an error code, never a hang.
 *
 * Protocol (/work/shared/reference/sensors.md section 2, the authority):
 *   - One 32-bit command per chip-select frame, MSB first (tx[0] = bits 31:24).
 *   - Pipelined: the reply to command N comes out on MISO during frame N+1.
 *   - Commands carry odd parity in bit 0 (the whole word has an odd number of ones).
 *   - Every response is checked: P0 (bit 28) makes bits 31:16 odd, P1 (bit 0) makes
 *     all 32 bits odd. A word 0x00000000 or 0xFFFFFFFF (MISO stuck) counts as
 *     "missing part" rather than as a parity error.
 *   - Response type: ST (bits 27:26) = 11 for register replies, whose bits 31:29 are
 *     010 (read), 001 (write) or 000 (R/W error: bit 18 SPI, 17 RE, 16 DU);
 *     ST = 00/01/10 for sensor-data replies, whose bits 31:29 echo SQ (always 000 here).
 *
 * How each operation uses the pipeline:
 *   - Rate: two frames, both the sensor-data command 0x20000000 (as no-OS does). The
 *     reply to the previous command, received during the first frame, is discarded
 *     (its fault bits still go into faults_seen); the reply received during the second
 *     frame answers the first frame's command, so the rate was latched at the first
 *     frame of this call (fresh, not one read old). The second frame's own command
 *     latches a sample that the next operation discards.
 *   - Register read: the read command twice; the second frame returns the reply.
 *   - Register write: the write command, then a read of the same register as the fetch
 *     frame (so the write is never repeated); the second frame returns the write reply,
 *     whose data field must echo the value written.
 *
 * Start-up (ib_adxrs450_init, sensors.md 2.7), one chip, about 300 ms of delay_us:
 *     wait 100 ms (power-on time; the driver assumes it is called at power-on and
 *                  always waits, harmless if power came earlier)
 *   1 0x20000003 (CHK)  reply: the power-on word, expected 0x00000001. Anything else is
 *                       only a warning (recorded in powerup_word / powerup_word_ok):
 *                       the usual cause is a restart without a power cycle.
 *     wait 50 ms
 *   2 0x20000000        reply to the CHK command: discarded, as every driver does
 *     wait 50 ms
 *   3 0x20000000        reply must be good parity, ST = 10, all 7 fault bits set
 *     wait 50 ms
 *   4 0x20000000        the same check again
 *     wait 50 ms
 *   5 read FAULT twice  the first reply (to step 4) must be a clean sample (ST = 01, no
 *                       fault bits, as AVR checks); the FAULT register must read 0 in
 *                       bits 11:0 (as Linux checks)
 *   6 read PID          high byte must be 0x52 (the full value is kept)
 *   7 read SNH, SNL     32-bit serial number kept in the struct
 *
 * Units: everything is raw counts (docs/conventions.md): rate_rad_s = counts / 80 *
 * pi / 180 (the part's lsb_per_unit, protocol/parts.toml); temp_c = 45 + raw10 / 5.
 *
 * Typical use:
 *   ib_adxrs450_t gx;
 *   if (ib_adxrs450_init(&gx, &bus, IB_CS_GYRO_X) != IB_ADXRS450_OK) ... report
 *   ib_adxrs450_sample_t s;
 *   if (ib_adxrs450_read_rate(&gx, &s) == IB_ADXRS450_OK) ... use s.rate_counts
 */
#ifndef IB_ADXRS450_H
#define IB_ADXRS450_H

#include <stdint.h>

#include "parts_gen.h"
#include "protocol_gen.h"
#include "spi_bus.h"

/* ---- register map (sensors.md 2.8; 16-bit registers at even addresses) ---- */
#define IB_ADXRS450_REG_RATE 0x00
#define IB_ADXRS450_REG_TEM 0x02
#define IB_ADXRS450_REG_LOCST 0x04
#define IB_ADXRS450_REG_HICST 0x06
#define IB_ADXRS450_REG_QUAD 0x08
#define IB_ADXRS450_REG_FAULT 0x0A
#define IB_ADXRS450_REG_PID 0x0C
#define IB_ADXRS450_REG_SNH 0x0E
#define IB_ADXRS450_REG_SNL 0x10
#define IB_ADXRS450_REG_DNC 0x12
#define IB_ADXRS450_ADDR_MAX 0x1FF /* 9-bit address field A8:A0 */

/* ---- command words (sensors.md 2.3) ---- */
#define IB_ADXRS450_CMD_SENSOR_DATA 0x20000000u
#define IB_ADXRS450_CMD_CHK 0x00000002u   /* CHK bit of the sensor-data command */
#define IB_ADXRS450_CMD_READ 0x80000000u  /* 100 in bits 31:29, address in 25:17 */
#define IB_ADXRS450_CMD_WRITE 0x40000000u /* 010 in bits 31:29, address in 25:17, data 16:1 */

/* ---- response fields (sensors.md 2.4) ---- */
#define IB_ADXRS450_POWERUP_WORD 0x00000001u /* first response after power-on */
#define IB_ADXRS450_RESP_P0 0x10000000u      /* bit 28 */
#define IB_ADXRS450_RESP_P1 0x00000001u      /* bit 0 */
#define IB_ADXRS450_RESP_TYPE_SHIFT 29       /* bits 31:29 */
#define IB_ADXRS450_RESP_TYPE_ERROR 0u       /* R/W error (with ST = 11) */
#define IB_ADXRS450_RESP_TYPE_WRITE 1u
#define IB_ADXRS450_RESP_TYPE_READ 2u
#define IB_ADXRS450_RESP_ST_SHIFT 26 /* bits 27:26 */
#define IB_ADXRS450_RESP_ERR_SPI 0x00040000u /* R/W error: SPI/parity error (bit 18) */
#define IB_ADXRS450_RESP_ERR_RE 0x00020000u  /* R/W error: request error (bit 17) */
#define IB_ADXRS450_RESP_ERR_DU 0x00010000u  /* R/W error: data unavailable (bit 16) */

/* ST codes (sensors.md 2.6) */
#define IB_ADXRS450_ST_FAULT 0u    /* data invalid: PLL fault or FAULT.FAIL */
#define IB_ADXRS450_ST_VALID 1u    /* valid sensor data */
#define IB_ADXRS450_ST_SELFTEST 2u /* CHK-generated data (start-up) */
#define IB_ADXRS450_ST_REGISTER 3u /* register read/write reply */

/* Fault bits: the low byte is also bits 7:1 of every sensor-data response. */
#define IB_ADXRS450_FAULT_FAIL 0x0800u
#define IB_ADXRS450_FAULT_AMP 0x0400u
#define IB_ADXRS450_FAULT_OV 0x0200u
#define IB_ADXRS450_FAULT_UV 0x0100u
#define IB_ADXRS450_FAULT_PLL 0x0080u
#define IB_ADXRS450_FAULT_Q 0x0040u
#define IB_ADXRS450_FAULT_NVM 0x0020u
#define IB_ADXRS450_FAULT_POR 0x0010u
#define IB_ADXRS450_FAULT_PWR 0x0008u
#define IB_ADXRS450_FAULT_CST 0x0004u
#define IB_ADXRS450_FAULT_CHK 0x0002u
#define IB_ADXRS450_FAULT_LOW_MASK 0x00FEu /* PLL..CHK */
#define IB_ADXRS450_FAULT_ALL_MASK 0x0FFEu /* FAIL..CHK: FAULT bits 11:1 */

/* ---- identification and scaling ---- */
/* PID values and the rate scale: protocol/parts.toml (ADXRS450, ADXRS453), via dev->part */
#define IB_ADXRS450_TEMP_OFFSET_C 45 /* raw10 = 0 at 45 degC */
#define IB_ADXRS450_TEMP_LSB_PER_C 5

/* ---- start-up timing (sensors.md 2.7) ---- */
#define IB_ADXRS450_POWERON_DELAY_US 100000u
#define IB_ADXRS450_STARTUP_STEP_US 50000u

typedef enum ib_adxrs450_err {
    IB_ADXRS450_OK = 0,
    IB_ADXRS450_ERR_BUS = -1,          /* the SPI bus reported an error */
    IB_ADXRS450_ERR_PARITY = -2,       /* a response failed the P0 or P1 check */
    IB_ADXRS450_ERR_BAD_PID = -3,      /* PID names no gyro of protocol/parts.toml */
    IB_ADXRS450_ERR_MISSING = -4,      /* no part: MISO reads all 0x00 (or all 0xFF) */
    IB_ADXRS450_ERR_CHK_FAILED = -5,   /* start-up: CHK responses not ST=10 + all faults */
    IB_ADXRS450_ERR_FAULT = -6,        /* fault bits set, or ST not 01 in a sensor reply */
    IB_ADXRS450_ERR_BAD_RESPONSE = -7, /* wrong response type, R/W error reply, bad echo */
    IB_ADXRS450_ERR_ARG = -8           /* bad argument (NULL, address above 0x1FF) */
} ib_adxrs450_err_t;

/* One chip. Fill it with ib_adxrs450_init(); the fields are read-only to callers. */
typedef struct ib_adxrs450 {
    const ib_spi_bus_t *bus;
    uint8_t cs;
    uint8_t ready;            /* 1 after a fully successful ib_adxrs450_init() */
    uint8_t powerup_word_ok;  /* 1 when the first start-up reply was 0x00000001 */
    uint8_t last_rw_error;    /* SPI/RE/DU bits (>> 16) of the last R/W error reply */
    uint32_t powerup_word;    /* the first start-up reply, kept for the warning */
    uint16_t pid;             /* full PID register (0x52xx); 0 until read */
    const ib_part_desc_t *part; /* the part the PID names (ADXRS450, ADXRS453); NULL until then */
    uint16_t startup_fault;   /* FAULT register value read during start-up */
    uint32_t serial;          /* (SNH << 16) | SNL; 0 until read */
    uint32_t last_response;   /* the last response word the driver evaluated */
    uint32_t parity_errors;   /* responses that failed P0/P1 (all evaluated replies) */
    uint32_t bus_errors;      /* transfer() failures */
    uint8_t chk_faults;       /* fault bits 7:1 present in BOTH start-up CHK replies
                               * (0xFE when the continuous self-test raised all seven) */
    uint16_t faults_seen;     /* sticky OR of the fault bits of every reply with good
                               * parity, including discarded replies; clear it with
                               * ib_adxrs450_clear_faults_seen() */
} ib_adxrs450_t;

/* One rate reading. All fields are decoded from `raw` even when the call failed, as
 * long as the bus transfer itself worked. */
typedef struct ib_adxrs450_sample {
    int16_t rate_counts;  /* 80 LSB per deg/s, two's complement (bits 25:10) */
    uint8_t st;           /* status bits 27:26 (IB_ADXRS450_ST_*) */
    uint8_t faults;       /* bits 7:1 of the response: PLL Q NVM POR PWR CST CHK (bit 0 = 0) */
    uint8_t parity_error; /* 1 when P0 or P1 was wrong */
    uint8_t good;         /* 1 only if parity right, ST == 01, no fault bits */
    uint32_t raw;         /* the full response word */
} ib_adxrs450_sample_t;

/* ---- frame helpers (pure functions, no bus) ---- */

/* Set bit 0 of `word` so that the whole 32-bit word has odd parity (command rule). */
uint32_t ib_adxrs450_with_parity(uint32_t word);

/* The sensor-data command (SQ = 000); chk != 0 also sets the CHK bit.
 * 0x20000000 and 0x20000003. */
uint32_t ib_adxrs450_cmd_sensor_data(int chk);

/* The read command for a 9-bit register address: e.g. PID 0x0C -> 0x80180000. */
uint32_t ib_adxrs450_cmd_read(uint16_t addr);

/* The write command: address in 25:17, data in 16:1, e.g. DNC = 0 -> 0x40240000. */
uint32_t ib_adxrs450_cmd_write(uint16_t addr, uint16_t data);

/* 1 when a response word passes both checks: bits 31:16 odd (P0) and all 32 bits odd
 * (P1); 0 otherwise. The power-on word 0x00000001 fails P0 (sensors.md 2.5). */
int ib_adxrs450_response_parity_ok(uint32_t word);

/* Decode a sensor-data response into *s (rate, ST, faults, parity flag, good flag, raw).
 * Does no bus access. */
void ib_adxrs450_decode_sensor(uint32_t word, ib_adxrs450_sample_t *s);

/* ---- operations (each one a bounded sequence of frames) ---- */

/* Fill *dev for chip `cs` on `bus` and run the start-up sequence above (about 300 ms
 * of bus->delay_us). Returns IB_ADXRS450_OK, or the first error:
 *   ERR_ARG       dev or bus NULL, or bus without transfer/delay_us
 *   ERR_BUS       a transfer failed
 *   ERR_MISSING   both CHK-phase replies (steps 3, 4) read all 0x00 or all 0xFF: no
 *                 part answers (a later stuck reply also gives ERR_MISSING)
 *   ERR_PARITY    a CHK-phase reply or a register reply failed the parity checks
 *   ERR_CHK_FAILED the two CHK-phase replies were not ST = 10 with all 7 fault bits
 *   ERR_FAULT     the reply after the CHK phase was not a clean sample, or FAULT != 0
 *                 (the value is kept in startup_fault)
 *   ERR_BAD_PID   PID high byte not 0x52 (the value is kept in pid)
 *   ERR_BAD_RESPONSE a register read was answered with a wrong type or an R/W error
 * dev->ready is 1 only on success. A wrong power-on word is a warning, not an error. */
ib_adxrs450_err_t ib_adxrs450_init(ib_adxrs450_t *dev, const ib_spi_bus_t *bus, uint8_t cs);

/* Read one fresh rate sample (two frames, no delays). *s is always filled when the bus
 * worked. Returns OK only for a good sample; otherwise ERR_BUS, ERR_MISSING (reply all
 * 0x00/0xFF), ERR_PARITY, ERR_BAD_RESPONSE (not a sensor-data reply), or ERR_FAULT
 * (ST != 01 or fault bits set; s->faults and s->st say which). */
ib_adxrs450_err_t ib_adxrs450_read_rate(ib_adxrs450_t *dev, ib_adxrs450_sample_t *s);

/* ib_adxrs450_read_rate in pieces, for a board that runs the frames itself (DMA): send the
 * bytes of ib_adxrs450_rate_cmd_bytes in two chip-select frames, then pass both replies
 * (ib_adxrs450_word of the received bytes) to ib_adxrs450_rate_from_frames, which checks
 * and decodes them exactly as ib_adxrs450_read_rate does. A failed frame:
 * ib_adxrs450_note_bus_error. */
void ib_adxrs450_rate_cmd_bytes(uint8_t tx[4]);
uint32_t ib_adxrs450_word(const uint8_t rx[4]);
ib_adxrs450_err_t ib_adxrs450_rate_from_frames(ib_adxrs450_t *dev, uint32_t w0, uint32_t w,
                                               ib_adxrs450_sample_t *s);
void ib_adxrs450_note_bus_error(ib_adxrs450_t *dev);

/* The pipelined rate read (one frame per sample): every frame sends the sensor-data command
 * and its reply answers the previous frame's, so the rate reported was latched one frame
 * earlier (one sample period). ib_adxrs450_prime_rate sends one sensor-data frame (reply
 * discarded) so the next frame's reply is a rate; ib_adxrs450_rate_from_reply checks and
 * decodes a reply as ib_adxrs450_read_rate does. The temperature fits in the pipeline: a
 * frame with the bytes of ib_adxrs450_temp_cmd_bytes (its reply: the pending rate), then a
 * sensor-data frame whose reply, through ib_adxrs450_temp_from_reply (a register reply of
 * TEM, checked as ib_adxrs450_read_reg does), is the temperature. */
ib_adxrs450_err_t ib_adxrs450_prime_rate(ib_adxrs450_t *dev);
ib_adxrs450_err_t ib_adxrs450_rate_from_reply(ib_adxrs450_t *dev, uint32_t w, ib_adxrs450_sample_t *s);
void ib_adxrs450_temp_cmd_bytes(uint8_t tx[4]);
ib_adxrs450_err_t ib_adxrs450_temp_from_reply(ib_adxrs450_t *dev, uint32_t w, int16_t *raw10);

/* Read the 16-bit register at `addr` (two frames). The reply must have good parity,
 * ST = 11 and type 010; a R/W error reply gives ERR_BAD_RESPONSE with its SPI/RE/DU
 * bits in dev->last_rw_error. ERR_ARG for addr > 0x1FF or NULL value. */
ib_adxrs450_err_t ib_adxrs450_read_reg(ib_adxrs450_t *dev, uint16_t addr, uint16_t *value);

/* Write the 16-bit register at `addr` (write frame, then a read of the same address as
 * the fetch frame). The write reply must have good parity, ST = 11, type 001 and echo
 * `value` in its data field: a different echo (a read-only register, or bits the part
 * does not keep) gives ERR_BAD_RESPONSE. ERR_ARG for addr > 0x1FF. */
ib_adxrs450_err_t ib_adxrs450_write_reg(ib_adxrs450_t *dev, uint16_t addr, uint16_t value);

/* Read the TEM register and return the 10-bit signed temperature counts (bits 15:6):
 * temp_c = 45 + raw10 / 5. */
ib_adxrs450_err_t ib_adxrs450_read_temp(ib_adxrs450_t *dev, int16_t *raw10);

/* Temperature counts to hundredths of a degree C (integer): 4500 + raw10 * 20. */
int32_t ib_adxrs450_temp_centi_c(int16_t raw10);

/* Read the FAULT register (bits 11:1 as IB_ADXRS450_FAULT_*). Reading it reports and so
 * clears latched faults on the part; persistent causes re-assert (sensors.md 2.6). */
ib_adxrs450_err_t ib_adxrs450_read_fault(ib_adxrs450_t *dev, uint16_t *fault);

/* Forget the sticky dev->faults_seen bits. */
void ib_adxrs450_clear_faults_seen(ib_adxrs450_t *dev);

#endif
