/* sim_thermal.c - the board's thermal model: each die lags the ambient (sim_physics.c) through
 * its own first-order time constant; the doc of the model is below. */
#define _GNU_SOURCE
#include "sim.h"
#include <math.h>
#include <string.h>

/* ------------------------------------------------------------------ thermal model
 *
 * Each sensor die i (0 = ADXL355, 1..3 = ADXRS450 X, Y, Z) has a temperature that follows
 * the ambient A(t) (the chamber above) with a first-order lag plus self-heating:
 *     dT_i/dt = (A(t) + S_i - T_i) / tau_i.
 * A(t) is piecewise linear (a ramp, then constant), so over a piece with slope k the exact
 * solution from T_i(t0) is
 *     T_i(t0 + s) = T_i(t0) + (A(t0) + S_i - k tau_i - T_i(t0)) (1 - e^(-s/tau_i)) + k s.
 * The state (T_i, its time) is stepped with that whenever a model is advanced, split at the
 * ramp's end, so the result does not depend on how often it is evaluated. 1 - e^(-x) is a
 * four-term series for the tiny x of a sample period (x = 250 us / 240 s = 1e-6; error
 * below x^5/120), exp() only for long steps.
 *
 * Figures (docs/simulator.md "Thermal behaviour"):
 *   tau_i  a small board in still air settles in minutes: 3 to 10 min per sensor (engineering
 *          estimate; a package on a PCB follows the board, whose time constant is set by its
 *          heat capacity and the convection from its surface).
 *   S_i    self-heating of the powered board at the sensor: the ADXL355 itself draws about
 *          200 uA (under 1 mW, no measurable rise of its own), so its rise is the board's,
 *          warmed by the MCU, the regulators and the gyros; an ADXRS450 dissipates a few tens
 *          of mW itself (several mA at 5 V, from memory of the data sheet [U]). Engineering
 *          estimate: 0.5 .. 2.5 degC at the ADXL355, 2 .. 5 degC at a gyro.
 */

void sim_thermal_init(sim_thermal_t *th)
{
    static const double tau[SIM_DIES] = SIM_THERMAL_NOMINAL_TAU_S;
    static const double heat[SIM_DIES] = SIM_THERMAL_NOMINAL_SELF_HEAT_C;
    memset(th, 0, sizeof *th);
    memcpy(th->tau_s, tau, sizeof tau);
    memcpy(th->self_heat_c, heat, sizeof heat);
}

void sim_thermal_random(sim_thermal_t *th, sim_rng_t *rng)
{
    for (int i = 0; i < SIM_DIES; i++) {
        th->tau_s[i] = 180.0 + 420.0 * sim_rng_uniform(rng);
        th->self_heat_c[i] = i == 0 ? 0.5 + 2.0 * sim_rng_uniform(rng) : 2.0 + 3.0 * sim_rng_uniform(rng);
    }
}

/* Slope of the ambient on the piece that starts at t (degC/s). */
static double ambient_slope(const sim_physics_t *p, uint64_t t_us)
{
    if (!(p->ramp_c_per_s > 0.0) || t_us < p->temp_t0_us || t_us >= p->temp_end_us ||
        sim_phys_temperature(p, t_us) == p->temp_target_c) {
        return 0.0;
    }
    return p->temp_target_c >= p->temp0_c ? p->ramp_c_per_s : -p->ramp_c_per_s;
}

/* 1 - e^(-x) for x >= 0 */
static double one_minus_exp(double x)
{
    if (x < 1e-3) {
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))));
    }
    return -expm1(-x);
}

/* Exact step of one die from (t0, T0) to t1 on one linear piece of the ambient. */
static double die_step(const sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t0,
                       double temp0, uint64_t t1)
{
    double s = (double)(t1 - t0) * 1e-6;
    double k = ambient_slope(p, t0);
    double tau = th->tau_s[i];
    double u0 = sim_phys_temperature(p, t0) + th->self_heat_c[i];
    return temp0 + (u0 - k * tau - temp0) * one_minus_exp(s / tau) + k * s;
}

static double die_at(const sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t_us)
{
    uint64_t t0 = th->die_t_us[i];
    double temp = th->die_c[i];
    if (t_us <= t0) {
        return temp;
    }
    if (p->ramp_c_per_s > 0.0 && p->temp_end_us > t0 && p->temp_end_us < t_us) {
        temp = die_step(th, p, i, t0, temp, p->temp_end_us); /* split at the ramp's end */
        t0 = p->temp_end_us;
    }
    return die_step(th, p, i, t0, temp, t_us);
}

double sim_thermal_die_peek(const sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t_us)
{
    if (!th->enabled || i < 0 || i >= SIM_DIES) {
        return sim_phys_temperature(p, t_us);
    }
    return die_at(th, p, i, t_us);
}

double sim_thermal_die(sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t_us)
{
    if (!th->enabled || i < 0 || i >= SIM_DIES) {
        return sim_phys_temperature(p, t_us);
    }
    if (t_us > th->die_t_us[i]) {
        th->die_c[i] = die_at(th, p, i, t_us);
        th->die_t_us[i] = t_us;
    }
    return th->die_c[i];
}

void sim_thermal_sync(sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us)
{
    for (int i = 0; i < SIM_DIES; i++) {
        (void)sim_thermal_die(th, p, i, t_us);
    }
}

int sim_thermal_set(sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us, int enabled,
                    const double tau_s[SIM_DIES], const double self_heat_c[SIM_DIES])
{
    for (int i = 0; i < SIM_DIES; i++) {
        if ((tau_s && !(tau_s[i] >= 1.0 && tau_s[i] <= 1e6)) ||
            (self_heat_c && !(self_heat_c[i] >= -50.0 && self_heat_c[i] <= 100.0))) {
            return -1;
        }
    }
    sim_thermal_sync(th, p, t_us); /* the old figures hold up to now */
    if (enabled && !th->enabled) {
        for (int i = 0; i < SIM_DIES; i++) {
            th->die_c[i] = sim_phys_temperature(p, t_us);
            th->die_t_us[i] = t_us;
        }
    }
    th->enabled = enabled;
    if (tau_s) {
        memcpy(th->tau_s, tau_s, sizeof th->tau_s);
    }
    if (self_heat_c) {
        memcpy(th->self_heat_c, self_heat_c, sizeof th->self_heat_c);
    }
    return 0;
}

void sim_thermal_soak(sim_thermal_t *th, sim_physics_t *p, uint64_t t_us, double c)
{
    sim_thermal_sync(th, p, t_us);
    sim_phys_set_temperature(p, t_us, c, 0.0);
    for (int i = 0; i < SIM_DIES; i++) {
        th->die_c[i] = c;
        th->die_t_us[i] = t_us;
    }
}

uint64_t sim_thermal_settle_time(const sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us,
                                 double tol_c)
{
    if (!th->enabled) {
        return t_us;
    }
    if (p->ramp_c_per_s > 0.0 && p->temp_end_us > t_us) {
        return p->temp_end_us;
    }
    double amb = sim_phys_temperature(p, t_us), wait_s = 0.0;
    for (int i = 0; i < SIM_DIES; i++) {
        double off = fabs(die_at(th, p, i, t_us) - (amb + th->self_heat_c[i]));
        if (off > tol_c && tol_c > 0.0) {
            double w = th->tau_s[i] * log(off / tol_c);
            wait_s = w > wait_s ? w : wait_s;
        }
    }
    if (wait_s <= 0.0) {
        return t_us;
    }
    return t_us + (uint64_t)ceil(wait_s * 1e6) + 1u;
}
