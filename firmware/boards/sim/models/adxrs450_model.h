/*
 * adxrs450_model.h - register/SPI-level model of one ADXRS450 single-axis gyro for the
 * simulator. One sim_adxrs450_t per chip (the board has three: IB_CS_GYRO_X/Y/Z measure
 * rotation about board X/Y/Z, axis 0/1/2).
 *
 * Protocol as /work/shared/reference/sensors.md section 2 (the authority); where it is
 * marked [U] or silent, the choice made here is listed under "Choices" below.
 *
 * Use:
 *   sim_adxrs450_init(&g, seed, 0);                   power on at t = 0, default truth
 *   sim_adxrs450_set_truth(&g, &t);                    optional
 *   loop: sim_adxrs450_advance(&g, t_us, &world);      world holds over (t_prev, t_us]
 *         sim_adxrs450_spi(&g, tx, rx, 4);             one chip-select frame at g's time
 *
 * ---- Physics (all in rad/s; T = world temperature in degC = this chip's die temperature;
 *      reference T_REF = 25 degC, dT = T - 25) --
 *   chip rate r(t) = (1 + scale_tempco*dT) * (sens . omega_board)
 *                    + bias_rad_s + bias_tempco*dT + b_rw(t) + b_bi(t) + gsens . f_board
 *                    + bias_tc2*dT^2 + bias_tc3*dT^3 + hysteresis*h
 *   h: thermal hysteresis branch in [-1, 1], a play operator of dead band hysteresis_width_c
 *      on T (as the ADXL355 model: +1 on the warming branch, -1 on the cooling branch, 0 at
 *      the start), updated whenever the world changes; the branches are 2*hysteresis apart.
 *   b_rw: rate random walk, b_rw += K*sqrt(dt)*n over each drift step of length dt
 *         (so ADEV = K*sqrt(tau/3) whatever the step size; docs/conventions.md).
 *   b_bi: bias instability (flicker), B * FLICKER_WEIGHT * sum of SIM_ADXRS450_FLICKER_N
 *         unit-variance first-order Gauss-Markov processes with correlation times 2, 20,
 *         200, 2000, 20000 s (one per decade, the usual sum-of-Gauss-Markov stand-in for
 *         1/f noise). FLICKER_WEIGHT = 0.8603 puts the bank's own Allan deviation at
 *         0.664*B (IEEE Std 952-1997: the flicker floor of a bias instability B) within
 *         +-2 % over tau = 20 .. 5000 s and +-4 % over 10 .. 10^4 s; below 10 s it falls
 *         under the white noise, above 2*10^4 s it falls as 1/sqrt(tau) and the rate random
 *         walk takes over. The bank starts in its stationary state.
 *   b_rw and b_bi draw from an rng of their own and move in steps of at least
 *   SIM_ADXRS450_DRIFT_STEP_US (10 ms; each step exact for its length), constant between.
 *   Sampling (integrate and dump): a sample latched at time t is the mean of r over the
 *   interval since the previous latch, plus white noise of sigma N/sqrt(dt), so a stream
 *   read at rate fs has per-sample sigma N*sqrt(fs) and ADEV = N/sqrt(tau) whatever fs.
 *   It is quantised to 80 LSB per deg/s (round to nearest) and saturated to int16.
 *   - A latch less than SIM_ADXRS450_MIN_LATCH_US after the previous one returns the
 *     previous sample again and does not start a new interval. This keeps two-frame
 *     readers exact (their fetch frame latches a throw-away sample microseconds after
 *     the real one); a one-frame-per-read driver sees repeated samples above 10 kHz,
 *     far above the part's ~77.5 Hz bandwidth.
 *   - An interval longer than SIM_ADXRS450_MAX_WINDOW_US (the first sample after power-on,
 *     or after a pause) uses the current noise-free rate and sigma N/sqrt(100 ms).
 *   Latches happen on the sensor-data command and on a read of the RATE register.
 *
 * ---- Protocol ----
 *   - spi(): one chip-select frame of 4 bytes, MSB first; the model's time is the time of
 *     its last advance(). The reply to command N is shifted out during frame N+1; the
 *     whole reply word (rate, ST, faults) is computed when command N arrives.
 *   - Power-on (init, power_cycle): the first reply shifted out is 0x00000001. Frames in
 *     the first startup_us (default SIM_ADXRS450_STARTUP_US = 100 ms) after power-on are
 *     ignored: MISO reads 0x00 and the command is lost.
 *   - Command parity: odd over 32 bits. A bad-parity command is not executed; its reply
 *     is the R/W error response with SPI set (and RE too when the command is not a valid
 *     sensor-data/read/write pattern, as for the Linux fetch frame 0x00000000).
 *   - Decoding: bit 29 set = sensor data (SQ in bits 31,30,28; CHK bit 1); bits 31:29 =
 *     100 read, 010 write; anything else (e.g. 0x00000001) is invalid: R/W error with RE.
 *   - Sensor-data reply: SQ2:SQ0 echo in 31:29, P0, ST, rate 25:10, bits 9:8 = 0, fault
 *     bits 7:1 (PLL Q NVM POR PWR CST CHK), P1. ST = 00 when PLL or FAIL is set, else 01.
 *   - CHK: the reply to the CHK command itself is a normal sample; the next two
 *     sensor-data replies have ST = 10, all 7 fault bits and rate 0 (0x080000FF with
 *     SQ = 0), then replies are normal again (count-based, not time-based). A new CHK
 *     restarts the count. CHK faults never enter the FAULT register.
 *   - Read / write replies: type 010 / 001 in 31:29, P0, ST = 11, bits 25:21 = 1 0 SM2
 *     SM1 SM0 (the reference's "probably 10 + SM"), data in 20:5, bits 4:1 = 0, P1.
 *     The write reply echoes the register contents after the write.
 *   - R/W error reply: 000, P0, ST = 11, bits 25:21 as above, bit 18 SPI, 17 RE, 16 DU,
 *     every other bit 0 (no fault bits), P1. DU is never produced.
 *   - Register map: 0x00 RATE (a read latches a sample as above), 0x02 TEM, 0x04 LOCST,
 *     0x06 HICST, 0x08 QUAD, 0x0A FAULT, 0x0C PID, 0x0E SNH, 0x10 SNL, 0x12 DNC. Any other
 *     address (odd ones included) gets the R/W error reply with RE.
 *   - Only DNC is writable: it keeps the low 10 bits as a signed value and reads back
 *     sign-extended to 16 bits (write 0x03FF or 0xFFFF -> reads 0xFFFF). DNC does not
 *     change the rate output (its LSB weight is [U]). A write to another valid register
 *     changes nothing and its reply echoes the unchanged contents.
 *   - TEM = raw10 << 6, raw10 = round((T - 45) * 5) clamped to -512..511.
 *   - PID = 0x5201 (the low byte is [U] in the reference). Serial number: 32 bits
 *     derived from the seed (never 0). LOCST = 0xFE70, HICST = 0x0190 (arbitrary values;
 *     the reference gives names only). QUAD = 0x0010, or 0x1068 (4200 > 4096) while a Q
 *     fault is persistent.
 * ---- Faults (sensors.md 2.6) ----
 *   - FAULT register bits 11:1 (FAIL AMP OV UV PLL Q NVM POR PWR CST CHK). Injected UV or
 *     OV also set PWR; AMP also sets CST.
 *   - A latched bit stays until a reply reports it: a sensor-data reply reports (and
 *     clears) bits 7:1, a FAULT register read reports (and clears) bits 11:1. Persistent
 *     causes re-assert immediately after each report, so they appear in every reply and
 *     still once more after the cause is removed.
 *   - FAIL and PLL force ST = 00 (the rate field still carries the sample).
 * ---- Fault injection ----
 *   persistent faults, one-shot faults, XOR corruption of the next N reply words (mask
 *   0x00000001 breaks P1 only; 0x10000000 breaks P0 and P1), missing chip (MISO 0x00,
 *   no state change), power cycle, PID override.
 */
#ifndef SIM_ADXRS450_MODEL_H
#define SIM_ADXRS450_MODEL_H

#include <stddef.h>
#include <stdint.h>

#include "parts_gen.h"
#include "sim_rng.h"
#include "sim_world.h"

#define SIM_ADXRS450_PID 0x5201u
#define SIM_ADXRS450_POWERUP_WORD 0x00000001u
#define SIM_ADXRS450_STARTUP_US 100000u     /* commands ignored before this after power-on */
#define SIM_ADXRS450_MIN_LATCH_US 100u      /* latches closer than this repeat the sample */
#define SIM_ADXRS450_MAX_WINDOW_US 100000u  /* longest averaging interval of one sample */
#define SIM_ADXRS450_T_REF_C 25.0           /* reference temperature of the tempcos */
#define SIM_ADXRS450_LSB_PER_DPS 80.0

/* The default chip's noise (docs/simulator.md, "Gyro noise"): white rate noise density
 * 0.015 deg/s/sqrt(Hz) and in-run bias stability 25 deg/h (Analog Devices, ADXRS450 data
 * sheet, Rev. C: specifications and front page), read as IEEE Std 952-1997's bias
 * instability B (Allan floor 0.664*B = 16.6 deg/h, the read-off of docs/noise.md); a rate
 * random walk the data sheet does not give, 8e-5 deg/s*sqrt(Hz) (engineering estimate:
 * it meets the floor at tau = 10^4 s, so the curve rises with slope +1/2 after that). */
#define SIM_ADXRS450_NOISE_DPS_RTHZ 0.015
#define SIM_ADXRS450_BIAS_INSTABILITY_DPH 25.0
#define SIM_ADXRS450_RATE_RW_DPS_RTS 8.0e-5
#define SIM_ADXRS450_FLICKER_N 5
#define SIM_ADXRS450_FLICKER_WEIGHT 0.8603 /* each process's sigma / B */
#define SIM_ADXRS450_DRIFT_STEP_US 10000u

/* FAULT register bits (same values as the driver's IB_ADXRS450_FAULT_*) */
#define SIM_ADXRS450_FAULT_FAIL 0x0800u
#define SIM_ADXRS450_FAULT_AMP 0x0400u
#define SIM_ADXRS450_FAULT_OV 0x0200u
#define SIM_ADXRS450_FAULT_UV 0x0100u
#define SIM_ADXRS450_FAULT_PLL 0x0080u
#define SIM_ADXRS450_FAULT_Q 0x0040u
#define SIM_ADXRS450_FAULT_NVM 0x0020u
#define SIM_ADXRS450_FAULT_POR 0x0010u
#define SIM_ADXRS450_FAULT_PWR 0x0008u
#define SIM_ADXRS450_FAULT_CST 0x0004u
#define SIM_ADXRS450_FAULT_CHK 0x0002u
#define SIM_ADXRS450_FAULT_ALL 0x0FFEu

/* R/W error reply flags */
#define SIM_ADXRS450_ERR_SPI 0x00040000u
#define SIM_ADXRS450_ERR_RE 0x00020000u
#define SIM_ADXRS450_ERR_DU 0x00010000u

/* The true error model of one chip (what calibration should find). */
typedef struct sim_adxrs450_truth {
    double sens[3];           /* chip rate = sens . omega_board (+ bias); ideal: unit row */
    double bias_rad_s;        /* null offset at 25 degC */
    double noise_n;           /* white noise, Allan coefficient N, rad/s/sqrt(Hz) */
    double bias_rw_k;         /* rate random walk K, rad/s*sqrt(Hz) (ADEV = K*sqrt(tau/3)) */
    double bias_instability_rad_s; /* bias instability B, rad/s (flicker floor 0.664*B) */
    double bias_tempco_rad_s_per_c; /* bias change per degC away from 25 degC */
    double scale_tempco_per_c;      /* relative scale change per degC away from 25 degC */
    double gsens_rad_s_per_mps2[3]; /* g-sensitivity: the chip reads gsens . f more (f the board's
                                       specific force, m/s^2); data sheet 0.03 deg/s/g typical */
    double bias_tc2;          /* curved part of the bias: rad/s per degC^2 about 25 degC */
    double bias_tc3;          /* rad/s per degC^3 about 25 degC */
    double hysteresis;        /* half the gap between warming and cooling branches, rad/s */
    double hysteresis_width_c;/* play-operator dead band, degC (>= 0) */
} sim_adxrs450_truth_t;

typedef struct sim_adxrs450 {
    /* physics */
    int axis;                     /* 0, 1, 2 = board X, Y, Z */
    sim_adxrs450_truth_t truth;
    sim_rng_t rng;
    uint64_t t_us;                /* time of the last advance() */
    sim_world_t world;            /* world of the last advance() */
    double hyst_y;                /* play-operator state, degC */
    double hyst_h;                /* hysteresis branch, -1 .. 1 */
    uint8_t hyst_started;
    double bias_rw_rad_s;         /* accumulated random-walk part of the bias */
    double flicker[SIM_ADXRS450_FLICKER_N]; /* bias-instability bank, unit variance each */
    uint64_t drift_t_us;          /* time the slow terms were last moved to */
    sim_rng_t drift_rng;          /* their rng (seeded from the chip's seed) */
    double rate_integral_rad;     /* integral of the noise-free chip rate since last latch */
    uint64_t last_latch_us;
    int16_t last_counts;          /* last latched sample */
    uint8_t have_latch;           /* a sample was latched since power-on */

    /* protocol state */
    uint64_t power_on_us;
    uint32_t startup_us;          /* settable; 0 disables the start-up dead time */
    uint32_t pending;             /* reply to shift out in the next frame */
    uint16_t pid;
    uint32_t serial;
    uint16_t dnc;                 /* as read back (sign-extended 10-bit) */
    uint16_t fault_latched;
    uint16_t fault_persistent;
    uint8_t chk_remaining;        /* CHK-flagged sensor replies still to come */
    uint8_t missing;
    uint32_t corrupt_remaining;
    uint32_t corrupt_mask;

    /* statistics for tests */
    uint32_t frames;              /* frames seen (while present) */
    uint32_t ignored_frames;      /* frames during the start-up dead time */
    uint32_t cmd_parity_errors;
    uint32_t invalid_cmds;
    uint32_t last_cmd;
} sim_adxrs450_t;

/* The ideal chip for `axis` (0/1/2): unit sensitivity row, zero bias, zero tempcos, and
 * the data sheet's noise (above): N = 0.015 deg/s/sqrt(Hz) = 2.618e-4 rad/s/sqrt(Hz),
 * B = 25 deg/h = 1.212e-4 rad/s, K = 8e-5 deg/s*sqrt(Hz) = 1.396e-6 rad/s*sqrt(Hz).
 * Allan deviation (all three terms): 55 deg/h at 1 s, 23.4 at 10 s, 17.4 at 100 s, 17.4 at
 * 1000 s, 23 at 10^4 s; minimum 17.2 deg/h near 175 s, so the read-off min/0.664 gives
 * 25.9 deg/h (white noise and random walk add 3 % to B's floor there).
 * An axis outside 0..2 gives a zero row. */
sim_adxrs450_truth_t sim_adxrs450_default_truth(int axis);

/* Draw a representative imperfect chip for `axis` from `rng` (documented ranges; the
 * [U] datasheet figures are null +-3 deg/s, sensitivity +-3 %):
 *   bias      Gaussian, sigma 0.5 deg/s, clipped to +-3 deg/s
 *   scale     1 + uniform +-3 %            cross-axis terms uniform +-1 % each
 *   N         default * uniform 0.8..1.2   K, B default
 *   bias tempco  uniform +-0.01 deg/s/degC scale tempco uniform +-1e-4 /degC
 *   g-sensitivity  Gaussian, sigma 0.03 deg/s/g per component, clipped to +-0.1 (drawn from
 *                  an rng of its own seeded from rng's state, so the other draws and the other
 *                  parts' truths are those of a model without it)
 *   bias_tc2     uniform +-1e-4 deg/s/degC^2, bias_tc3 uniform +-1e-6 deg/s/degC^3: with the
 *                linear term the null moves by at most 2 deg/s over -40 .. +105 degC, inside
 *                the [U] +-3 deg/s null accuracy (sensors.md); the split is an engineering
 *                estimate
 *   hysteresis   uniform +-0.01 deg/s, dead band 1 .. 4 degC (engineering estimate; see the
 *                ADXL355 model and docs/simulator.md)
 *                (these four from a further rng of their own, as the g-sensitivity) */
void sim_adxrs450_random_truth(sim_adxrs450_truth_t *t, sim_rng_t *rng, int axis);

/* Power the chip on at t = 0 with the default truth for `axis`, an rng seeded by `seed`
 * (use a different seed per chip), a serial number derived from `seed`, PID 0x5201,
 * DNC 0, no faults, startup_us = SIM_ADXRS450_STARTUP_US, the world at rest at 25 degC. */
void sim_adxrs450_init(sim_adxrs450_t *m, uint64_t seed, int axis);

/* Replace / read the truth. set_truth keeps the accumulated random-walk bias (K = 0 freezes
 * it) and the bank's state (B = 0 takes the bias-instability part out: b_bi = 0). */
void sim_adxrs450_set_truth(sim_adxrs450_t *m, const sim_adxrs450_truth_t *t);
const sim_adxrs450_truth_t *sim_adxrs450_get_truth(const sim_adxrs450_t *m);

/* Move time to t_us (microseconds, the simulator's clock) with `world` holding over
 * (previous time, t_us]: accumulates the rate integral and moves the slow bias terms.
 * t_us not after the current time only replaces the world. world == NULL keeps it. */
void sim_adxrs450_advance(sim_adxrs450_t *m, uint64_t t_us, const sim_world_t *world);

/* One chip-select frame: tx (NULL sends 0x00) in, rx (NULL discards) out, at the model's
 * current time. Returns 0 for a 4-byte frame. Any other length is not a command: rx gets
 * the first bytes of the queued reply (0x00 past 4 bytes), the queued reply becomes the
 * R/W error reply with SPI set, and the function returns -1. */
int sim_adxrs450_spi(sim_adxrs450_t *m, const uint8_t *tx, uint8_t *rx, size_t len);

/* Current true bias (constant + temperature terms at the current temperature and hysteresis
 * branch + random walk + bias instability), rad/s. */
double sim_adxrs450_true_bias_rad_s(const sim_adxrs450_t *m);

/* Temperature-dependent part of the bias at temp_c on hysteresis branch h (-1 .. 1), rad/s:
 * bias_tempco*dT + bias_tc2*dT^2 + bias_tc3*dT^3 + hysteresis*h. */
double sim_adxrs450_truth_thermal_bias(const sim_adxrs450_truth_t *t, double temp_c, double h);

/* The bias-instability part b_bi of the true bias, rad/s. */
double sim_adxrs450_flicker_bias_rad_s(const sim_adxrs450_t *m);

/* The bank's correlation times, s (SIM_ADXRS450_FLICKER_N of them), and each process's
 * sigma / B (for the curve the model should give: imubench.device.sim_gyro). */
const double *sim_adxrs450_flicker_taus(void);
double sim_adxrs450_flicker_weight(void);
int sim_adxrs450_flicker_n(void);

/* Current noise-free chip output (the r(t) above), rad/s. */
double sim_adxrs450_true_rate_rad_s(const sim_adxrs450_t *m);

/* Fault causes that stay present (FAULT register bits; UV/OV add PWR, AMP adds CST).
 * 0 removes them; bits already latched still show once (sensors.md 2.6). */
void sim_adxrs450_set_persistent_faults(sim_adxrs450_t *m, uint16_t mask);

/* Latch faults once (a transient event): reported by the next reply that carries them. */
void sim_adxrs450_inject_faults(sim_adxrs450_t *m, uint16_t mask);

/* XOR `xor_mask` into each of the next `count` reply words shifted out. */
void sim_adxrs450_corrupt_responses(sim_adxrs450_t *m, uint32_t count, uint32_t xor_mask);

/* missing != 0: the chip is absent, MISO reads 0x00 and frames change nothing. */
void sim_adxrs450_set_missing(sim_adxrs450_t *m, int missing);

/* Power cycle at the current time: power-on reply word again, latched faults, CHK
 * state, DNC, the pending reply and the sample integrator reset, the start-up dead time
 * restarts. Truth, bias random walk, fault causes (persistent faults), pending parity
 * corruption and the missing flag are kept. */
void sim_adxrs450_power_cycle(sim_adxrs450_t *m);

/* Model gyro part `part` (protocol/parts.toml): its PID (the ADXRS450 keeps 0x5201, the
 * ADXRS453 answers 0x5202) and its bias instability (ADXRS453: 16 deg/h); the protocol and
 * register map are shared (Linux drivers/iio/gyro/adxrs450.c drives both). */
void sim_adxrs450_set_part(sim_adxrs450_t *m, const ib_part_desc_t *part);

/* Override the PID register (to test a wrong part). */
void sim_adxrs450_set_pid(sim_adxrs450_t *m, uint16_t pid);

/* One chip alone at rest at 25 degC, read the way the firmware reads it (a sensor-data
 * command per sample at rate_hz, the reply in the next frame): n rate samples in counts
 * (80 LSB per deg/s), the default truth for `axis`, or with random_truth the truth
 * sim_adxrs450_random_truth draws from an rng seeded from `seed`. For noise tests without a
 * virtual session (libimumodels.so; imubench.device.sim_gyro). 0, or -1 for a bad rate. */
int sim_adxrs450_record(uint64_t seed, int axis, int random_truth, double rate_hz, size_t n,
                        int16_t *counts);

/* ---- pure encoders (exposed for tests) ---- */

/* Set P0 (bits 31:16 odd) and P1 (all 32 bits odd) of a response word. */
uint32_t sim_adxrs450_response_parity(uint32_t word);

/* A sensor-data reply: SQ2:SQ0 echo `sq`, status `st`, rate `counts`, fault bits 7:1. */
uint32_t sim_adxrs450_encode_sensor(uint8_t sq, uint8_t st, int16_t counts, uint8_t faults);

/* TEM register contents for a die temperature. */
uint16_t sim_adxrs450_tem_register(double temp_c);

#endif
