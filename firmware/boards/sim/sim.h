/*
 * sim.h - the simulator board (virtual device): the firmware core built for Linux with the
 * register-level sensor models (models/) behind a simulated SPI bus, a simulated UART
 * exposed as a pseudo-terminal and/or a TCP socket, a parameter flash kept in a file, a
 * turntable/climate-chamber "world", and a JSON-lines control channel.
 *
 * One process, one thread, one poll() loop (sim_main.c). Files:
 *   sim_main.c     options, start-up line, boot / power cycle, the paced event loop
 *   sim_board.c    the ib_board_t / ib_spi_bus_t callbacks the core calls
 *   sim_link.c     UART TX ring drained in device time, pty and TCP endpoints
 *   sim_flash.c    ib_flash_if_t on a file (NOR semantics, power-cut injection)
 *   sim_physics.c  orientation, motion (turntable / rate table), ambient temperature
 *   sim_thermal.c  the dies' thermal lag behind the ambient
 *   sim_main.c     options, resets, pacing, main; sim_loop.c the main loop (host build only)
 *   sim_control.c  control channel (JSON lines over TCP); its commands in sim_control_world.c
 *                  and sim_control_truth.c, request helpers in sim_control_args.c
 *   sim_json.c     tiny JSON reader / writer for the control channel
 *
 * Device time: a 64-bit microsecond counter (sim.t_us) owned by the board. It advances
 * only tick by tick, by delay_us, by SPI transfer time and, when idle, with the paced wall
 * clock (speed factor). time_us() returns its low 32 bits.
 */
#ifndef SIM_H
#define SIM_H

#include <poll.h>
#include <setjmp.h>
#include <stddef.h>
#include <stdint.h>

#include "adxl355_model.h"
#include "adxrs450_model.h"
#include "board.h"
#include "core.h"
#include "sim_flash.h"
#include "sim_rng.h"
#include "sim_world.h"

#define SIM_BUILD_ID "sim-0.1.0" /* at most 15 characters go into info.fw_build */

/* ---- link (sim_link.c) ---- */
#define SIM_TX_RING 8192u       /* the UART driver's TX buffer: what link_tx_free sees */
#define SIM_TX_STORE 65536u     /* storage: the ring + bytes already "on the wire" that the OS
                                   has not taken yet (host not reading); power of two */
#define SIM_RX_RING 8192u       /* received bytes not yet read by the core; power of two */
#define SIM_DEFAULT_BAUD 2000000u

typedef struct sim_link {
    uint8_t tx[SIM_TX_STORE];
    uint64_t tx_head;   /* bytes queued by the core (running count) */
    uint64_t tx_uart;   /* bytes the UART has shifted out by device time */
    uint64_t tx_fault;  /* bytes link faults (flip) were applied to */
    uint64_t tx_os;     /* bytes handed to the OS endpoint, discarded or dropped */
    double uart_credit; /* bytes the UART may still send (fraction carried) */
    uint64_t uart_t_us; /* device time of the last UART update */
    double bytes_per_us;

    uint8_t rx[SIM_RX_RING];
    uint32_t rx_head, rx_tail;

    int pty_master, pty_slave; /* -1 when no pty */
    char pty_name[128];
    int tcp_listen, tcp_client; /* -1 when none */
    int tcp_port;
    int os_blocked;             /* the last write to the endpoint would have blocked */

    uint32_t drop_remaining;    /* link_drop fault: bytes still to drop */
    uint32_t flip_remaining;    /* link_flip fault: bytes still to corrupt */
    sim_rng_t fault_rng;

    /* statistics */
    uint64_t bytes_written_os, bytes_discarded, bytes_dropped, bytes_flipped, bytes_received;
    uint64_t tx_refused;        /* bytes link_write could not take (should stay 0) */
    uint64_t conn_rx, conn_tx;  /* bytes received from / written to the current connection
                                   (since the TCP client was accepted; the pty: since start) */
    uint32_t clients_accepted;
} sim_link_t;

/* ---- flash: sim_flash.h ---- */

/* ---- physics (sim_physics.c) ---- */
#define SIM_PATH_MAX_LEGS 32

/* One leg of a path (sim_phys_path): rest to rest in dur_us, translating by dp_m (level
 * frame) and turning by angle_rad about axis (board frame), both on the minimum-jerk
 * profile h(s) = 10 s^3 - 15 s^4 + 6 s^5, s = (t - t0) / dur. The start state (r0, p0,
 * omega integral) is filled in when the path is set. */
typedef struct sim_leg {
    uint64_t t0_us, dur_us;
    double dp_m[3];
    double axis[3];
    double angle_rad;
    double r0[3][3];
    double p0_m[3];
    double wi0[3];
} sim_leg_t;

typedef struct sim_physics {
    /* orientation: R maps board-frame vectors to the level (earth) frame, Z up. Under a
     * motion, R(t) = R0 * Rot(axis, rate * (min(t, t_end) - t0)). */
    double r0[3][3];
    uint64_t t0_us;
    double axis[3];          /* unit vector, board frame */
    double rate_rad_s;       /* signed rate about axis */
    uint64_t t_end_us;       /* end of the move; UINT64_MAX for set_rate; == t0 when none */
    double angle_total_rad;  /* rate * duration for a finite move (exact end angle) */
    int kind;                /* SIM_MOTION_NONE / _ROTATE / _RATE */
    double omega_int0[3];    /* integral of omega (board frame) from 0 to t0, rad */
    /* position of the board's origin in the level frame, m (moves only on a path) */
    double pos0_m[3];
    sim_leg_t legs[SIM_PATH_MAX_LEGS]; /* SIM_MOTION_PATH: legs back to back from t0 */
    int n_legs;
    /* temperature: linear ramp from temp0 at temp_t0 towards temp_target */
    double temp0_c, temp_target_c, ramp_c_per_s;
    uint64_t temp_t0_us, temp_end_us;
} sim_physics_t;

enum { SIM_MOTION_NONE = 0, SIM_MOTION_ROTATE = 1, SIM_MOTION_RATE = 2, SIM_MOTION_PATH = 3 };

/* ---- thermal model of the sensor dies (sim_thermal.c) ----
 * One die per sensor, indexed like the chip selects: 0 = ADXL355, 1..3 = ADXRS450 X, Y, Z.
 * Enabled, each die follows the ambient (the chamber, sim_physics_t) with a first-order lag
 * plus the steady self-heating of the powered board:
 *     dT_i/dt = (T_ambient(t) + self_heat_c[i] - T_i) / tau_s[i]
 * stepped exactly (the ambient is piecewise linear in time) whenever a model is advanced.
 * Disabled (the default), every die is at the ambient and there is no self-heating. */
#define SIM_DIES 4
typedef struct sim_thermal {
    int enabled;
    double tau_s[SIM_DIES];       /* thermal time constant of each die, s */
    double self_heat_c[SIM_DIES]; /* steady rise of each die over the ambient when powered, degC */
    double die_c[SIM_DIES];       /* die temperature at die_t_us (enabled only) */
    uint64_t die_t_us[SIM_DIES];
} sim_thermal_t;

/* Nominal thermal figures of the default (ideal) part; random truth draws its own
 * (sim_thermal_random, sources in sim_thermal.c). */
#define SIM_THERMAL_NOMINAL_TAU_S {240.0, 300.0, 360.0, 420.0}
#define SIM_THERMAL_NOMINAL_SELF_HEAT_C {1.5, 3.0, 3.5, 2.5}

/* ---- faults on the SPI bus ---- */
typedef struct sim_spi_faults {
    uint32_t error_count[IB_CS_COUNT];   /* the next N transfers fail */
    double error_prob[IB_CS_COUNT];      /* each transfer fails with this probability */
    uint64_t errors_injected[IB_CS_COUNT];
} sim_spi_faults_t;

/* ---- the whole simulator ---- */
typedef struct sim {
    /* device time and pacing */
    uint64_t t_us;
    double speed;            /* device time per wall time; 0 = as fast as possible */
    uint64_t anchor_wall_ns; /* pacing anchor: device time anchor_dev_us at wall anchor */
    uint64_t anchor_dev_us;
    uint64_t slips;          /* times the pacing re-anchored because the CPU fell behind */
    int lockstep;            /* --clock lockstep: device time moves only inside a granted run
                                (sim_control_world.c "run"); speed is then a ceiling */

    /* sample tick */
    uint32_t tick_hz;
    uint64_t tick_base_us;
    uint64_t tick_n;         /* index of the next tick after tick_base */
    uint64_t next_tick_us;
    uint64_t ticks;          /* ib_core_tick calls since start */
    uint64_t ticks_missed;

    /* core and boot */
    ib_core_t core;
    ib_board_t board;
    ib_spi_bus_t spi;
    ib_flash_if_t flash_if;
    jmp_buf reset_jmp;
    int in_core;             /* a core function is on the stack (longjmp allowed) */
    int reset_pending;       /* SIM_RESET_* requested outside the core */
    int reset_kind;          /* kind of the reset being taken */
    uint32_t boots, power_cuts, reboots;
    uint32_t spin;           /* board calls without progress inside one core call */

    /* sensors and world */
    adxl355_model_t accel;
    sim_adxrs450_t gyro[3];
    double omega_int_at[IB_CS_COUNT][3]; /* integral of omega at each model's last advance */
    sim_physics_t phys;
    sim_thermal_t thermal;   /* die temperatures (kept across power cuts and sim_phys_init) */
    sim_spi_faults_t spi_faults;
    sim_rng_t spi_fault_rng;
    uint64_t spi_transfers;

    sim_link_t link;
    sim_flash_t flash;

    /* identity */
    uint64_t seed;
    uint32_t baud;
    uint8_t uid[12];
    int truth_random;

    /* the target the firmware runs on: "" = this host build; set by the ARM emulator
     * (sim_lib.c) with its own figures, reported by status */
    char target[16];
    uint64_t arm_instructions, arm_faults, arm_unmodelled, arm_spi_mismatch;
    double arm_idle_s, arm_sysclk_hz;
    uint64_t arm_regions[5];      /* instructions by code range: other, core, drivers, board, lib */
    uint64_t arm_idle_instructions, arm_spi_bytes, arm_spi_transactions;
    double arm_busy_s, arm_stall_s, arm_spi_bus_s, arm_cpi;

    /* control */
    int control_listen;
    int control_port;
    int quit;
} sim_t;

enum { SIM_RESET_NONE = 0, SIM_RESET_REBOOT = 1, SIM_RESET_POWER_CUT = 2 };

extern sim_t g_sim;

/* ---- sim_main.c ---- */
void sim_log(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
uint64_t sim_wall_ns(void);
/* Request a reset of the device. Inside a core call this does not return (longjmp to the
 * main loop, like a real reset); outside it is taken by the main loop. */
void sim_request_reset(int kind);
void sim_power_cycle_models(void);
void sim_set_speed(double speed);
int sim_streaming(void);

/* ---- sim_board.c ---- */
void sim_board_setup(void);
void sim_advance_to(uint64_t t_us);   /* move device time forward (never back) */
void sim_models_sync(void);           /* advance every model to the current device time */
void sim_model_advance(int cs);       /* advance one model (chip select) to now */
void sim_model_world(int cs, sim_world_t *w); /* world for advancing model cs to now */
/* Seed the models; target names the board's identity (sim_identity_seed in sim_board.c):
 * "host" (or NULL) for the host build, "f103" / "f4" for the ARM images. */
void sim_seed_models(uint64_t seed, int random_truth, const char *target);
uint64_t sim_identity_seed(uint64_t seed, const char *target);
void sim_board_flash_hooks(void); /* give g_sim.flash its clock, power and log (before opening it) */
/* The board's parts (protocol/parts.toml): "accel=adxl359,gyro_z=adxrs453" (slots accel, gyro,
 * gyro_x, gyro_y, gyro_z; names any case; unnamed slots keep ADXL355 / ADXRS450). Set before
 * the models are seeded; 0, or -1 with a one-line reason in err. */
int sim_set_parts(const char *spec, char *err, size_t errlen);
const uint8_t *sim_parts(void);   /* enum ib_part per slot, sensor order */
void sim_apply_parts(void);       /* give the models their parts (sim_seed_models does) */
void sim_randomize_truth(uint64_t seed);
void sim_spin_reset(void);
int sim_spi_exchange(uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);

/* ---- sim_link.c ---- */
int sim_listen_tcp(int port, int *bound_port); /* 127.0.0.1, non-blocking; -1 on error */
int sim_link_open(sim_link_t *l, int want_pty, int tcp_port, uint32_t baud);
void sim_link_close(sim_link_t *l);
void sim_link_reset(sim_link_t *l, uint64_t t_us);  /* power cut: buffers cleared */
void sim_link_uart_update(sim_link_t *l, uint64_t t_us);
size_t sim_link_tx_free(sim_link_t *l);
size_t sim_link_write(sim_link_t *l, const uint8_t *data, size_t len);
size_t sim_link_read(sim_link_t *l, uint8_t *buf, size_t cap);
void sim_link_flush(sim_link_t *l);                 /* hand shifted-out bytes to the OS */
void sim_link_receive(sim_link_t *l);               /* read from the OS into the RX ring */
int sim_link_accept(sim_link_t *l);
size_t sim_link_staged(const sim_link_t *l);        /* shifted out, not yet taken by the OS */
size_t sim_link_queued(const sim_link_t *l);        /* in the UART ring */
/* Device time (us from now) until the UART has shifted out something more, 0 if nothing
 * is queued. */
uint64_t sim_link_next_drain_us(const sim_link_t *l);


/* ---- sim_physics.c ---- */
void sim_phys_init(sim_physics_t *p);
void sim_phys_settle(sim_physics_t *p, uint64_t t_us);       /* fold the motion up to t */
void sim_phys_orientation(const sim_physics_t *p, uint64_t t_us, double r[3][3]);
void sim_phys_gravity_dir(const sim_physics_t *p, uint64_t t_us, double g[3]);
void sim_phys_omega(const sim_physics_t *p, uint64_t t_us, double w[3]);
void sim_phys_omega_integral(const sim_physics_t *p, uint64_t t_us, double out[3]);
/* Specific force in the board frame, m/s^2: g0 * gravity_dir + R^T a_level. */
void sim_phys_specific_force(const sim_physics_t *p, uint64_t t_us, double f[3]);
/* Position (m), velocity (m/s) and acceleration (m/s^2) in the level frame. */
void sim_phys_kinematics(const sim_physics_t *p, uint64_t t_us, double pos[3], double vel[3],
                         double acc[3]);
double sim_phys_temperature(const sim_physics_t *p, uint64_t t_us);
int sim_phys_moving(const sim_physics_t *p, uint64_t t_us);  /* a finite move in progress */
/* Commands; all take effect at t_us. Return 0 or -1 (bad argument). */
int sim_phys_set_gravity(sim_physics_t *p, uint64_t t_us, const double g[3]);
void sim_phys_set_rpy(sim_physics_t *p, uint64_t t_us, double roll, double pitch, double yaw);
int sim_phys_rotate(sim_physics_t *p, uint64_t t_us, const double axis[3], double rate_rad_s,
                    double duration_s);
void sim_phys_set_rate(sim_physics_t *p, uint64_t t_us, const double w[3]);
/* Drive a path: n legs (dur_us, dp_m, axis, angle_rad used; the rest is filled in),
 * back to back from t_us. -1 when n is out of 1..SIM_PATH_MAX_LEGS or a leg is bad. */
int sim_phys_path(sim_physics_t *p, uint64_t t_us, const sim_leg_t *legs, int n);
/* Index of the path leg in progress at t, -1 when no path is being driven. */
int sim_phys_path_leg(const sim_physics_t *p, uint64_t t_us);
void sim_phys_set_temperature(sim_physics_t *p, uint64_t t_us, double c, double ramp_c_per_s);
void sim_phys_rpy(const double r[3][3], double *roll, double *pitch, double *yaw);
/* Next device time something changes by itself (move end, ramp end), UINT64_MAX if none. */
uint64_t sim_phys_next_event(const sim_physics_t *p, uint64_t t_us);

/* Thermal model (sim_thermal_t above). */
void sim_thermal_init(sim_thermal_t *th);                 /* disabled, nominal figures */
void sim_thermal_random(sim_thermal_t *th, sim_rng_t *rng); /* draw tau_s and self_heat_c */
/* Temperature of die i at t_us: advances the die's state to t_us when later (exact step);
 * an earlier t_us gives the state's own (latest) value. Disabled: the ambient at t_us. */
double sim_thermal_die(sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t_us);
/* The same without changing the state (status, truth). */
double sim_thermal_die_peek(const sim_thermal_t *th, const sim_physics_t *p, int i, uint64_t t_us);
void sim_thermal_sync(sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us);
/* Switch on/off and/or change the figures at t_us (NULL = keep). Switching on starts every
 * die at the ambient (self-heating then builds up with the lag, as after a power-up). -1 on
 * a bad figure (tau_s not in 1 .. 1e6 s, self_heat_c not in -50 .. 100 degC). */
int sim_thermal_set(sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us, int enabled,
                    const double tau_s[SIM_DIES], const double self_heat_c[SIM_DIES]);
/* Chamber at c at once with every die at c (a soak: hours in a fridge); self-heating builds
 * up again from there. */
void sim_thermal_soak(sim_thermal_t *th, sim_physics_t *p, uint64_t t_us, double c);
/* Device time when every die will be within tol_c of its steady value (ambient + self-heat)
 * if the chamber holds still; t_us when already there; the ramp's end while the chamber
 * ramps (ask again then). */
uint64_t sim_thermal_settle_time(const sim_thermal_t *th, const sim_physics_t *p, uint64_t t_us,
                                 double tol_c);

/* ---- sim_control.c ---- */
int sim_control_open(int port);
void sim_control_close(void);
int sim_control_pollfds(struct pollfd *pfd, int max);   /* fds to watch */
void sim_control_handle(struct pollfd *pfd, int n);     /* after poll() */
void sim_control_check_waits(void);                     /* deferred replies now due */
uint64_t sim_control_next_deadline(void);               /* device time of the earliest wait */
/* Lockstep: 0 = no run granted (the device is frozen); 2 = a run is asked for but the host's
 * link bytes have not all arrived yet (receive them first); 1 = granted: *target (when not
 * NULL) is the device time to run to. */
int sim_control_run_target(uint64_t *target);

#endif
