/*
 * adxl355_model.h - register-level model of the ADXL355 accelerometer for the simulator.
 *
 * The simulator puts this model behind its SPI layer (chip select IB_CS_ACCEL): every
 * chip-select-low transaction goes to adxl355_model_spi(), and the simulator calls
 * adxl355_model_advance() to move device time forward with the current physical world.
 * Register behaviour follows /work/shared/reference/sensors.md section 1.
 *
 * Signal model (SI, board frame = sensor frame; docs/conventions.md), per output sample:
 *     dT = T - 25 degC          (T = the die temperature the world carries)
 *     u  = (1 + scale_tc*dT) * (M f) + b + bias_tc*dT + bias_tc2*dT^2 + bias_tc3*dT^3
 *          + hysteresis*h + b_rw + n + f_st
 *   f     specific force from sim_world_t
 *   M, b  scale/misalignment and bias (u = M x + b of the calibration model)
 *   scale_tc multiplies a whole row of M (per axis)
 *   h     thermal hysteresis branch in [-1, 1], per axis: a play operator (backlash) of dead
 *         band hysteresis_width_c on T: y = clamp(y, T - w/2, T + w/2), h = (T - y)/(w/2).
 *         h = +1 while the die has warmed for more than w since it last cooled (the warming
 *         branch), -1 on the cooling branch, in between inside the dead band; it starts at 0
 *         (a part that has sat at one temperature). w = 0: h = the sign of the last change.
 *         So the warming and cooling branches are 2*hysteresis apart.
 *   b_rw  bias random walk: at each sample b_rw += K * sqrt(dt) * N(0,1), dt = time
 *         since the previous random-walk update (standby gaps therefore count)
 *   n     white noise, sigma = N * sqrt(ODR) per sample (conventions.md)
 *   f_st  self-test force st_force_g * g0, applied while SELF_TEST has ST1 and ST2 set
 * then optionally high-pass filtered (FILTER.HPF_CORNER), quantised to counts
 * (round to nearest) at the RANGE sensitivity (256000/128000/64000 LSB/g,
 * g0 = SIM_G0_MPS2), saturated to the 20-bit range, OFFSET*16 added, saturated again.
 *
 * Choices where the reference is silent or marked [U] (keep tests consistent with these):
 *   - Timing: samples fall due every 250 << ODR code microseconds of device time,
 *     the first one a full period after leaving standby. Nothing is produced in
 *     standby. The world passed to advance() is taken as constant over the advanced
 *     interval; each sample is stamped at its due time.
 *   - FILTER writes are stored at once, but the ODR/LPF code in effect is latched when
 *     measurement starts (no-OS: "LPF cannot change in measurement mode"); RANGE, HPF,
 *     OFFSET and SELF_TEST take effect with the next sample.
 *   - The LPF (ODR/4) is not modelled: each sample is the instantaneous input plus white
 *     noise of sigma N*sqrt(ODR). The noise density does not depend on the range.
 *   - HPF: first-order high-pass y[k] = a*(y[k-1] + x[k] - x[k-1]), a = 1/(1 + 2*pi*k_c)
 *     with k_c the sensors.md multiplier (corner = k_c*ODR); code 7 behaves as off. The
 *     filter state restarts on leaving standby.
 *   - RANGE code 00 behaves as +-2 g. ODR codes 11..15 behave as code 10 (3.906 Hz).
 *   - Register write masks: FILTER bits 6:0, FIFO_SAMPLES bits 6:0, ACT_EN bits 2:0,
 *     SYNC bits 2:0, RANGE bits 7,6,1,0, POWER_CTL bits 2:0, SELF_TEST bits 1:0; other
 *     bits read as 0. Writes to read-only and unmapped addresses are ignored; unmapped
 *     addresses (0x12..0x1D, 0x30..0x4F, 0x55..0x7F) read 0x00; RESET reads 0x00.
 *   - FIFO_SAMPLES outside 1..96 acts as 96 for FIFO_FULL.
 *   - FIFO: each entry is pushed on its own (X, then Y, then Z); an entry that does not
 *     fit is dropped and sets FIFO_OVR (so a FIFO that was read down by a non-multiple
 *     of 3 can end up misaligned, as the driver must cope with). The FIFO keeps its
 *     contents across standby; a soft reset empties it. The FIFO holds the same values
 *     as the data registers (offset included).
 *   - FIFO_DATA reads: an entry is popped when the first of its three bytes is clocked;
 *     if chip select rises before the third byte, the rest of that entry is lost.
 *     Reading an empty FIFO returns 00 00 02 (empty flag). The address does not advance
 *     while it is at FIFO_DATA, however the burst got there.
 *   - The command byte clocks out 0x00 on MISO (0xFF while the NVM is busy).
 *   - STATUS: DATA_RDY, FIFO_OVR and Activity are cleared when the STATUS byte is
 *     clocked out (the byte shows them still set); FIFO_FULL and NVM_BUSY are live.
 *   - Activity: a sample counts when any enabled axis has |data| >> 3 > ACT_THRESH;
 *     Activity sets after ACT_COUNT consecutive such samples (ACT_COUNT 0 acts as 1).
 *   - Temperature: TEMP = round(1885 - 9.05 * (T - 25)) clamped to 0..4095, updated with
 *     every sample unless POWER_CTL.TEMP_OFF; no noise. Data and temperature registers
 *     read 0 after power-on and soft reset until the first sample.
 *   - Soft reset (0x52 to RESET; other values ignored): for reset_busy_us of device time
 *     (default ADXL355_MODEL_RESET_BUSY_US = 500 us) every MISO byte reads 0xFF (so
 *     STATUS shows NVM_BUSY) and writes are ignored; the registers take their reset
 *     values at once (invisible until the window ends). The shadow bytes, the truth and
 *     the random-walk bias are not changed by a reset (unless the shadow fault is set).
 *   - Self-test force only with both ST1 and ST2 set.
 *   - DRDY_OFF, INT_MAP, SYNC, INT_POL, I2C_HS are stored but have no effect.
 */
#ifndef ADXL355_MODEL_H
#define ADXL355_MODEL_H

#include <stddef.h>
#include <stdint.h>

#include "parts_gen.h"
#include "sim_rng.h"
#include "sim_world.h"

#define ADXL355_MODEL_FIFO_SIZE 96
#define ADXL355_MODEL_RESET_BUSY_US 500u

/* Representative noise density of the part at +-2 g: 22.5 ug/sqrt(Hz). */
#define ADXL355_MODEL_NOISE_MPS2_RTHZ (22.5e-6 * SIM_G0_MPS2)

/* The physical truth of one part (what calibration has to find). */
typedef struct adxl355_truth {
    double m[3][3];        /* scale factor / misalignment, u = M f + b (row = sensor axis) */
    double bias_mps2[3];   /* bias b at 25 degC, m/s^2 */
    double noise_n[3];     /* white noise Allan coefficient N, m/s^2/sqrt(Hz) */
    double rw_k[3];        /* bias random walk K, m/s^2*sqrt(Hz) (= m/s^2/sqrt(s)) */
    double bias_tc[3];     /* bias temperature coefficient, m/s^2 per degC from 25 degC */
    double scale_tc[3];    /* scale temperature coefficient, 1/degC, multiplies row i of M */
    double bias_tc2[3];    /* curved part: m/s^2 per degC^2 about 25 degC */
    double bias_tc3[3];    /* m/s^2 per degC^3 about 25 degC */
    double hysteresis[3];  /* half the gap between the warming and cooling branches, m/s^2 */
    double hysteresis_width_c[3]; /* play-operator dead band, degC (>= 0) */
} adxl355_truth_t;

/* Fault injection; all zero is a healthy part. Change them at any time. */
typedef struct adxl355_model_faults {
    int missing;        /* no part: MISO reads 0x00 for every byte, writes do nothing */
    int stuck_data;     /* the part stops producing samples: DATA_RDY never sets, data
                           registers, TEMP and FIFO stay as they are */
    int shadow_corrupt; /* every soft reset reloads shadow byte 0x52 wrongly (one more
                           than before), so a driver's before/after comparison fails */
} adxl355_model_faults_t;

typedef struct adxl355_model {
    /* ---- may be set by the owner (simulator, tests) ---- */
    adxl355_truth_t truth;
    double st_force_g[3];     /* self-test force, g (default +0.3, +0.3, +1.5) */
    uint8_t id[4];            /* DEVID_AD, DEVID_MST, PARTID, REVID as read (wrong-ID fault) */
    const ib_part_desc_t *part; /* the part modelled (protocol/parts.toml): PARTID, sensitivity
                                   per RANGE code, temperature intercept; NULL = ADXL355 */
    uint8_t shadow[5];        /* factory bytes at 0x50..0x54 */
    uint32_t reset_busy_us;   /* NVM reload time after a soft reset */
    adxl355_model_faults_t fault;

    /* ---- state (read only for the owner) ---- */
    uint64_t t_us;            /* device time reached by the last advance */
    uint64_t next_sample_us;  /* when the next sample falls due (while measuring) */
    uint64_t busy_until_us;   /* NVM busy while t_us < busy_until_us */
    uint64_t rw_last_us;      /* time of the last random-walk update */
    uint64_t samples;         /* samples produced since init */
    uint8_t reg[128];         /* register file (IDs, shadow and FIFO_DATA are not in here) */
    uint8_t measuring;        /* POWER_CTL.STANDBY == 0 */
    uint8_t odr_active;       /* ODR code in effect (latched when measurement starts) */
    uint8_t rw_started;       /* rw_last_us valid */
    uint32_t fifo[ADXL355_MODEL_FIFO_SIZE]; /* bits 19:0 data, bit 20 = X marker */
    unsigned fifo_head, fifo_count;
    double rw_bias[3];        /* current random-walk part of the bias, m/s^2 */
    double hpf_x[3], hpf_y[3];/* HPF state (input, output of the previous sample) */
    int hpf_primed;
    unsigned act_run;         /* consecutive samples above the activity threshold */
    double temp_c;            /* temperature of the last advance, degC */
    double hyst_y[3];         /* play-operator state per axis, degC */
    double hyst_h[3];         /* hysteresis branch per axis, -1 .. 1 */
    uint8_t hyst_started;     /* hyst_y valid */
    sim_rng_t rng;
} adxl355_model_t;

/* Default truth: identity M, zero bias, zero temperature coefficients, white noise
 * N = 22.5 ug/sqrt(Hz) on every axis and bias random walk K = 1 ug*sqrt(Hz)
 * (about 9.8e-6 m/s^2*sqrt(Hz)). */
void adxl355_model_default_truth(adxl355_truth_t *truth);

/* A random but representative part (uniform draws, per axis):
 *   bias            +-25 mg
 *   scale (M diag)  1 +- 1 %
 *   cross-axis      off-diagonal M +- 1 %
 *   N               22.5 ug/sqrt(Hz) * (0.9 .. 1.1)
 *   K               0.5 .. 2 ug*sqrt(Hz)
 *   bias tempco     +-0.1 mg/degC   (datasheet max 0.15 mg/degC)
 *   scale tempco    +-1e-4 /degC    (+-0.01 %/degC)
 *   bias_tc2        +-2e-4 mg/degC^2, bias_tc3 +-2e-6 mg/degC^3: with the linear term the
 *                   slope stays within the data sheet's 0.15 mg/degC maximum of the 0 g
 *                   offset tempco over -40 .. +85 degC (sensors.md; the split between the
 *                   linear and the curved part is an engineering estimate)
 *   hysteresis      0 .. 20 ug, either sign; dead band 1 .. 4 degC (engineering estimate:
 *                   the data sheet gives none; heating and cooling branches that differ are
 *                   reported by Niu et al. 2013 and Kim & Jung 2025, see docs/simulator.md)
 * Values in SI. Draws from rng; the curved and hysteresis terms from an rng of their own
 * seeded from rng's state, so rng advances as it did without them (same other draws). */
void adxl355_model_random_truth(adxl355_truth_t *truth, sim_rng_t *rng);

/* Power-on state: registers at reset values (standby), default truth, IDs AD 1D ED 01,
 * factory shadow bytes, self-test force (0.3, 0.3, 1.5) g, no faults, time 0, noise
 * generator seeded with `seed`. */
void adxl355_model_init(adxl355_model_t *m, uint64_t seed);

void adxl355_model_set_truth(adxl355_model_t *m, const adxl355_truth_t *truth);
void adxl355_model_get_truth(const adxl355_model_t *m, adxl355_truth_t *truth);

/* Current true bias of each axis in m/s^2 at the last advanced temperature:
 * b + bias_tc*dT + bias_tc2*dT^2 + bias_tc3*dT^3 + hysteresis*h + b_rw (no white noise, no
 * self-test, no OFFSET registers). */
void adxl355_model_true_bias(const adxl355_model_t *m, double bias_mps2[3]);

/* The temperature-dependent part of the bias of axis i at die temperature temp_c on
 * hysteresis branch h (-1 .. 1): bias_tc*dT + bias_tc2*dT^2 + bias_tc3*dT^3 + hysteresis*h. */
double adxl355_truth_thermal_bias(const adxl355_truth_t *t, int i, double temp_c, double h);

/* Advance device time to t_us (ignored if not later than the current time), producing
 * every sample that falls due in (t_now, t_us] from `world`. */
void adxl355_model_advance(adxl355_model_t *m, uint64_t t_us, const sim_world_t *world);

/* One chip-select-low transaction of len bytes (tx NULL clocks 0x00, rx NULL discards). */
void adxl355_model_spi(adxl355_model_t *m, const uint8_t *tx, uint8_t *rx, size_t len);

/* Fault setters (same as writing the fields). */
void adxl355_model_set_missing(adxl355_model_t *m, int on);
void adxl355_model_set_stuck_data(adxl355_model_t *m, int on);
void adxl355_model_set_shadow_corrupt(adxl355_model_t *m, int on);
void adxl355_model_set_ids(adxl355_model_t *m, uint8_t devid_ad, uint8_t devid_mst,
                           uint8_t partid);

/* Model part `part` of the ADXL355 family (protocol/parts.toml; the ADXL359: PARTID 0xE9,
 * +-10/20/40 g at 51200/25600/12800 LSB/g, temperature intercept 1852 LSB, noise density
 * 80 ug/sqrt(Hz)); the register map is the ADXL355's (one regmap in Linux's adxl355_core.c). */
void adxl355_model_set_part(adxl355_model_t *m, const ib_part_desc_t *part);

/* Sensitivity of the current RANGE setting, LSB/g. */
double adxl355_model_lsb_per_g(const adxl355_model_t *m);

/* Current sample period in us (250 << ODR code). */
uint32_t adxl355_model_period_us(const adxl355_model_t *m);

#endif
