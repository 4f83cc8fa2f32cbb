/*
 * sim_world.h - the physical world the simulated sensors read (board frame).
 *
 * Board frame (docs/conventions.md): X forward, Y left, Z up, right-handed.
 * Specific force f = a - g_vec: a board lying still and level (Z up) reads
 * f = (0, 0, +g0). Positive angular rate follows the right-hand rule about the axis.
 */
#ifndef SIM_WORLD_H
#define SIM_WORLD_H

#include <stdint.h>

#define SIM_G0_MPS2 9.80665 /* standard gravity; the product's one value of g */

typedef struct sim_world {
    double specific_force_mps2[3]; /* in the board frame, m/s^2 */
    double rate_rad_s[3];          /* angular rate of the board, board frame, rad/s */
    double temperature_c;          /* die temperature of the sensor this world is handed to,
                                      degC (sim_thermal_t: each die its own) */
} sim_world_t;

#endif
