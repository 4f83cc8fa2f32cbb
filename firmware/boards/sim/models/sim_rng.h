/*
 * sim_rng.h - deterministic random numbers for the sensor models
 * (xoshiro256** seeded through splitmix64; Gaussian by the polar method).
 * Each model owns one sim_rng_t, so one seed reproduces a whole run.
 */
#ifndef SIM_RNG_H
#define SIM_RNG_H

#include <stdint.h>

typedef struct sim_rng {
    uint64_t s[4];
    double spare;
    int has_spare;
} sim_rng_t;

void sim_rng_seed(sim_rng_t *r, uint64_t seed);
uint64_t sim_rng_u64(sim_rng_t *r);
double sim_rng_uniform(sim_rng_t *r);  /* in [0, 1) */
double sim_rng_gauss(sim_rng_t *r);    /* standard normal, mean 0, sigma 1 */

#endif
