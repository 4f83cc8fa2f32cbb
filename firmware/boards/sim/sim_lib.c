/*
 * sim_lib.c - the virtual device's world as a shared library (build/host/libimumodels.so,
 * `make sim`), for the ARM emulator (host/imubench/device/arm/): it runs the exact STM32
 * images under Unicorn and needs the SAME sensor models, physics, control channel and
 * serial endpoint as imubench-sim, not a second copy in Python.
 *
 * What is in the library: models/ (ADXL355, ADXRS450, rng), sim_physics.c, sim_board.c
 * (model advance with the world, SPI faults: sim_spi_exchange), sim_control.c (the JSON
 * control channel, unchanged), sim_link.c (the TCP/pty serial endpoint with its link faults
 * and statistics), sim_flash.c (linked, unused: the emulator's flash is the chip's own flash
 * interface), sim_json.c and this file. NOT in it: the firmware core and sim_main.c; the
 * firmware is the ARM image.
 *
 * This file supplies what sim_main.c supplies to the others (g_sim, logging, reset requests,
 * speed) and the entry points the emulator calls through ctypes (simlib_*). Device time
 * (g_sim.t_us) is set by the emulator from its cycle counter before every call that looks
 * at it.
 *
 * It also holds the emulator's instruction counter: simlib_block_hook is registered with
 * Unicorn as a UC_HOOK_BLOCK callback (a C function pointer, so no Python runs per block).
 * It adds the number of Thumb instructions of each translation block about to execute to
 * a counter (and to the counter of the address range the block starts in), and stops the
 * emulation once the counter reaches the limit the emulator set (its next event).
 */
#define _GNU_SOURCE
#include "sim.h"

#include <errno.h>
#include <poll.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <time.h>

sim_t g_sim;

static int g_reset_req;
static int g_log_enabled = 1;

uint64_t sim_wall_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

void sim_log(const char *fmt, ...)
{
    if (!g_log_enabled) {
        return;
    }
    char buf[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    fprintf(stderr, "[imubench-arm %.6f] %s\n", (double)g_sim.t_us * 1e-6, buf);
}

/* The control channel's power_cut (and a flash power cut) ask for a reset: the emulator
 * takes it after the current call (simlib_take_reset). */
void sim_request_reset(int kind)
{
    if (kind > g_reset_req) {
        g_reset_req = kind;
    }
}

void sim_set_speed(double speed) { g_sim.speed = speed; }

int sim_streaming(void) { return g_sim.core.stream_state != IB_STREAM_STATE_STOPPED; }

/* ------------------------------------------------------------------ set-up */

/* The ARM emulator's --pty (the ROM bootloader's port for stm32flash, and the image's USART1
 * after it): set before simlib_open. */
static int g_want_pty;
void simlib_set_pty(int on) { g_want_pty = on; }
const char *simlib_pty_name(void) { return g_sim.link.pty_master >= 0 ? g_sim.link.pty_name : ""; }

/* The target whose board the seed names (its UID and gyro serials, sim_identity_seed):
 * set before simlib_open; "" or "host" gives the host build's board. */
static char g_identity_target[16];
void simlib_set_identity_target(const char *name)
{
    snprintf(g_identity_target, sizeof g_identity_target, "%s", name != NULL ? name : "");
}

/* --parts (sim_set_parts): set before simlib_open; 0, or -1 with the reason in err. */
int simlib_set_parts(const char *spec, char *err, int errlen)
{
    return sim_set_parts(spec, err, errlen > 0 ? (size_t)errlen : 0u);
}

int simlib_open(uint64_t seed, int truth_random, const uint8_t *uid, int tcp_port, int control_port,
                double speed)
{
    sim_t *s = &g_sim;
    memset(s, 0, sizeof *s);
    s->control_listen = -1;
    s->seed = seed;
    s->speed = speed;
    s->truth_random = truth_random;
    s->baud = SIM_DEFAULT_BAUD;
    if (sim_link_open(&s->link, g_want_pty, tcp_port, s->baud) != 0) {
        return -1;
    }
    /* The emulated USART is the UART: bytes reach this ring when they have been shifted
     * out, so the ring's own drain is immediate. */
    s->link.bytes_per_us = 1e12;
    if (sim_control_open(control_port) != 0) {
        return -1;
    }
    sim_seed_models(seed, truth_random, g_identity_target);
    if (uid != NULL) {
        memcpy(s->uid, uid, sizeof s->uid);
    }
    sim_phys_init(&s->phys);
    return 0;
}

void simlib_close(void)
{
    sim_control_close();
    sim_link_close(&g_sim.link);
}

void simlib_set_log(int on) { g_log_enabled = on; }
/* --clock lockstep: device time moves only inside a granted run (sim_control.c "run"); the
 * emulator's serve loop asks sim_control_run_target how far. */
void simlib_set_lockstep(int on) { g_sim.lockstep = on; }

int simlib_tcp_port(void) { return g_sim.link.tcp_port; }
int simlib_control_port(void) { return g_sim.control_port; }
void simlib_uid(uint8_t out[12]) { memcpy(out, g_sim.uid, 12); }
double simlib_speed(void) { return g_sim.speed; }
int simlib_quit(void) { return g_sim.quit; }

void simlib_set_time(uint64_t t_us)
{
    if (t_us > g_sim.t_us) {
        g_sim.t_us = t_us;
        sim_link_uart_update(&g_sim.link, t_us);
    }
}

uint64_t simlib_time(void) { return g_sim.t_us; }

/* What status reports about the firmware side, as the emulator sees it. */
void simlib_set_state(int stream_state, uint32_t tick_hz, uint64_t ticks, uint64_t ticks_missed,
                      uint32_t boots, uint32_t power_cuts, uint32_t reboots)
{
    sim_t *s = &g_sim;
    s->core.stream_state = (uint8_t)stream_state;
    s->tick_hz = tick_hz;
    s->ticks = ticks;
    s->ticks_missed = ticks_missed;
    s->boots = boots;
    s->power_cuts = power_cuts;
    s->reboots = reboots;
}

void simlib_set_target(const char *name, uint64_t instructions, uint64_t faults, uint64_t unmodelled,
                       uint64_t spi_mismatch, double idle_s, double sysclk_hz)
{
    sim_t *s = &g_sim;
    snprintf(s->target, sizeof s->target, "%s", name);
    s->arm_instructions = instructions;
    s->arm_faults = faults;
    s->arm_unmodelled = unmodelled;
    s->arm_spi_mismatch = spi_mismatch;
    s->arm_idle_s = idle_s;
    s->arm_sysclk_hz = sysclk_hz;
}

void simlib_set_arm_detail(const uint64_t regions[5], uint64_t idle_instructions, double busy_s, double stall_s,
                           double spi_bus_s, uint64_t spi_bytes, uint64_t spi_transactions, double cpi)
{
    sim_t *s = &g_sim;
    memcpy(s->arm_regions, regions, sizeof s->arm_regions);
    s->arm_idle_instructions = idle_instructions;
    s->arm_busy_s = busy_s;
    s->arm_stall_s = stall_s;
    s->arm_spi_bus_s = spi_bus_s;
    s->arm_spi_bytes = spi_bytes;
    s->arm_spi_transactions = spi_transactions;
    s->arm_cpi = cpi;
}

/* Next device time (us) the world or a control-channel wait needs the device to reach. */
uint64_t simlib_next_event(void)
{
    uint64_t a = sim_control_next_deadline(), b = sim_phys_next_event(&g_sim.phys, g_sim.t_us);
    return a < b ? a : b;
}

int simlib_take_reset(void)
{
    int k = g_reset_req;
    g_reset_req = SIM_RESET_NONE;
    return k;
}

/* ------------------------------------------------------------------ sensors */

/* A transaction is handed to the models once, at chip-select release, with the bytes the
 * firmware really sent (sim_spi_exchange: world, faults, model). While it is in progress
 * the emulated SPI needs each reply byte as soon as its byte has been clocked: peek runs
 * the transaction so far on a copy of the state the exchange touches and restores it. */
typedef struct {
    adxl355_model_t accel;
    sim_adxrs450_t gyro;
    sim_spi_faults_t faults;
    sim_rng_t fault_rng;
    double omega_int_at[3];
    double die_c;          /* the addressed sensor's die (sim_thermal_t) */
    uint64_t die_t_us;
    uint64_t transfers;
} spi_snap_t;

static spi_snap_t g_snap;

static void snap_save(int cs)
{
    sim_t *s = &g_sim;
    if (cs == IB_CS_ACCEL) {
        g_snap.accel = s->accel;
    } else {
        g_snap.gyro = s->gyro[cs - 1];
    }
    g_snap.faults = s->spi_faults;
    g_snap.fault_rng = s->spi_fault_rng;
    memcpy(g_snap.omega_int_at, s->omega_int_at[cs], sizeof g_snap.omega_int_at);
    g_snap.die_c = s->thermal.die_c[cs];
    g_snap.die_t_us = s->thermal.die_t_us[cs];
    g_snap.transfers = s->spi_transfers;
}

static void snap_restore(int cs)
{
    sim_t *s = &g_sim;
    if (cs == IB_CS_ACCEL) {
        s->accel = g_snap.accel;
    } else {
        s->gyro[cs - 1] = g_snap.gyro;
    }
    s->spi_faults = g_snap.faults;
    s->spi_fault_rng = g_snap.fault_rng;
    memcpy(s->omega_int_at[cs], g_snap.omega_int_at, sizeof g_snap.omega_int_at);
    s->thermal.die_c[cs] = g_snap.die_c;
    s->thermal.die_t_us[cs] = g_snap.die_t_us;
    s->spi_transfers = g_snap.transfers;
}

int simlib_spi_peek(int cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    if (cs < 0 || cs >= IB_CS_COUNT) {
        return -1;
    }
    snap_save(cs);
    int rc = sim_spi_exchange((uint8_t)cs, tx, rx, len);
    snap_restore(cs);
    return rc;
}

int simlib_spi_commit(int cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    if (cs < 0 || cs >= IB_CS_COUNT) {
        return -1;
    }
    return sim_spi_exchange((uint8_t)cs, tx, rx, len);
}

void simlib_power_cycle_models(void) { sim_power_cycle_models(); }

/* ------------------------------------------------------------------ flash */

/* One flash operation of the chip's flash interface (an unlock..lock span: one erase or
 * one program() call of the image's driver). 1 when the armed power cut falls into it
 * (the control channel's power_cut {after_flash_ops}), as sim_flash.c counts them. */
int simlib_flash_op(void)
{
    sim_flash_t *f = &g_sim.flash;
    f->ops_since_boot++;
    f->ops_total++;
    if (f->cut_after > 0 && --f->cut_after == 0) {
        f->cuts++;
        return 1;
    }
    return 0;
}

void simlib_flash_boot(void) { g_sim.flash.ops_since_boot = 0; }

/* ------------------------------------------------------------------ link */

void simlib_link_fds(int *listen_fd, int *client_fd)
{
    *listen_fd = g_sim.link.tcp_listen;
    /* the connected peer: a TCP client, else the pty (whose bytes go to the same rings) */
    *client_fd = g_sim.link.tcp_client >= 0 ? g_sim.link.tcp_client : g_sim.link.pty_master;
}

int simlib_link_accept(void) { return sim_link_accept(&g_sim.link); }
void simlib_link_receive(void) { sim_link_receive(&g_sim.link); }
void simlib_link_flush(void) { sim_link_flush(&g_sim.link); }
size_t simlib_link_staged(void) { return sim_link_staged(&g_sim.link); }
int simlib_link_blocked(void) { return g_sim.link.os_blocked; }

/* Lockstep: hand staged bytes to the OS, waiting while the host's socket is full, until at
 * most `keep` are staged (the emulated USART then never finds the ring full because the host
 * is slow; nothing the device does depends on when the host reads). */
static void flush_blocking(size_t keep)
{
    sim_link_t *l = &g_sim.link;
    while (sim_link_staged(l) > keep) {
        sim_link_flush(l);
        if (!l->os_blocked) {
            continue;
        }
        int fd = l->tcp_client >= 0 ? l->tcp_client : l->pty_master;
        struct pollfd p = {fd, POLLOUT, 0};
        if (poll(&p, 1, 100) < 0 && errno != EINTR) {
            return;
        }
    }
}

/* Bytes the emulated USART has shifted out; what the ring cannot take is refused. */
size_t simlib_link_push(const uint8_t *data, size_t len)
{
    sim_link_uart_update(&g_sim.link, g_sim.t_us);
    size_t n = sim_link_write(&g_sim.link, data, len);
    sim_link_uart_update(&g_sim.link, g_sim.t_us + 1u);
    if (g_sim.lockstep && sim_link_staged(&g_sim.link) > (SIM_TX_STORE - SIM_TX_RING) / 4) {
        flush_blocking(0);
    }
    return n;
}

/* Received bytes waiting for the emulated USART's receiver. */
size_t simlib_link_rx_pending(void) { return (size_t)(g_sim.link.rx_head - g_sim.link.rx_tail) & (SIM_RX_RING - 1u); }
size_t simlib_link_pull(uint8_t *buf, size_t cap) { return sim_link_read(&g_sim.link, buf, cap); }

/* Power cut: what the endpoint had not sent yet is lost, as with the host build. */
void simlib_link_reset(void) { sim_link_reset(&g_sim.link, g_sim.t_us); }

/* ------------------------------------------------------------ instruction counter */

typedef void (*uc_stop_fn)(void *uc);

static uint64_t g_icount;
static uint64_t g_ilimit = UINT64_MAX;
static uc_stop_fn g_stop;
static const uint16_t *g_code;  /* the flash image, half-words */
static uint32_t g_code_base, g_code_hw;
static const uint8_t *g_region; /* address range of each half-word (0..7) */
static uint64_t g_region_count[8];

void simlib_counter_setup(void *stop_fn, const uint16_t *code, uint32_t base, uint32_t n_halfwords,
                          const uint8_t *region)
{
    g_stop = (uc_stop_fn)stop_fn;
    g_code = code;
    g_code_base = base;
    g_code_hw = n_halfwords;
    g_region = region;
}

uint64_t simlib_icount(void) { return g_icount; }
void simlib_set_limit(uint64_t limit) { g_ilimit = limit; }
void simlib_region_counts(uint64_t out[8]) { memcpy(out, g_region_count, sizeof g_region_count); }

void simlib_block_hook(void *uc, uint64_t address, uint32_t size, void *user)
{
    (void)user;
    uint64_t n = 0;
    uint32_t i = (uint32_t)((address - g_code_base) >> 1), end = i + (size >> 1);
    if (address >= g_code_base && end <= g_code_hw) {
        uint8_t reg = g_region ? g_region[i] : 0u;
        while (i < end) {
            /* Thumb-2: a half-word starting with 0b11101, 0b11110 or 0b11111 begins a
             * 32-bit instruction (ARMv7-M ARM A5.1) */
            i += (g_code[i] >> 11) >= 0x1Du ? 2u : 1u;
            n++;
        }
        g_region_count[reg & 7u] += n;
    } else {
        n = size / 2u ? size / 2u : 1u;
    }
    g_icount += n;
    if (g_icount >= g_ilimit && g_stop) {
        g_stop(uc);
    }
}
