/*
 * sim_main.c - the virtual device process: options, start-up line, boot / power cycle,
 * and the paced event loop.
 *
 *   imubench-sim [--pty] [--tcp PORT] [--control PORT] [--flash FILE] [--speed X]
 *                [--seed N] [--truth default|random] [--baud B] [--uid HEX24]
 *                [--clock realtime|lockstep]
 *
 * Without --pty and --tcp the link listens on TCP (a free port). Once the ports are open
 * it prints ONE JSON line on stdout, e.g.
 *   {"pty": null, "port_url": "socket://127.0.0.1:40123", "tcp_port": 40123,
 *    "control": "127.0.0.1:40125", "control_port": 40125, "pid": 4242,
 *    "flash": "/tmp/imubench-sim-XXXX/flash.bin", "seed": 1, ...}
 * and logs only to stderr afterwards. It exits on SIGTERM/SIGINT/SIGHUP, on the control
 * command "quit", and when its parent process dies (getppid() checked every 100 ms).
 *
 * Pacing. Device time runs `speed` times the wall clock: target(wall) = anchor_dev +
 * (wall - anchor_wall) * speed. Each loop iteration runs the device up to the target:
 * every sample tick that falls due in device time (ib_core_tick at its exact due time,
 * then ib_core_poll), then moves device time to the target and polls once more; then it
 * hands the link bytes to the OS in one batch and blocks in poll() until the next due
 * tick / event (at least 1 ms, at most 20 ms while idle) or I/O. So there is no syscall
 * per tick, and an idle device sleeps. When the core consumed device time on its own
 * (delay_us, e.g. the ~1 s of sensor start-up at boot), device time is ahead of the
 * target: the device is busy, the loop only serves the control channel and waits. When
 * the CPU cannot keep up (target more than 200 ms x speed ahead of the device), the
 * anchor slips: device time stays continuous and no tick is skipped, the run is just
 * slower than asked (logged). speed 0 = as fast as possible: ticks run back to back
 * (pausing up to 50 ms when the host does not read the link), idle device time follows
 * the wall clock but jumps straight to the next pending event (wait deadline, end of a
 * move or temperature ramp).
 *
 * Lockstep (--clock lockstep). The device is frozen except while the host grants it time
 * with the control command "run" (sim_control.c): the run first receives the link bytes the
 * host wrote, then runs the ticks up to its end (speed > 0: no faster than speed x the wall
 * clock, a ceiling), moves device time to the end and polls once, hands every link byte
 * shifted out by then to the OS, waiting for the host to read when its socket is full
 * (flow control: nothing is dropped because the host is slow), and replies. Intermediate
 * stops (the wall budget, the ceiling) fall only between ticks, so what the device does
 * depends on device time alone: the same seed and the same host gives the same bytes on
 * any machine, idle or busy. The real-time clock (the default of this program) is the
 * pacing above: device time runs against the wall clock and a host that does not read
 * loses bytes, as with a real board.
 *
 * Resets. A power cut (flash op, control command) and board.reboot() longjmp out of the
 * core back to core_call() when they happen inside a core call, exactly like a reset
 * cuts the firmware off wherever it is; the loop then re-initialises a zeroed core.
 */
#define _GNU_SOURCE
#include "sim.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "sim_json.h"
#include "sim_main_priv.h"

sim_t g_sim;

volatile sig_atomic_t g_sim_signal;
pid_t g_sim_parent; /* 0: do not watch */
int g_sim_parent_gone;
static const char *g_orphan_dir; /* --orphan-cleanup DIR: the host's folder, removed if it dies */


uint64_t sim_wall_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

void sim_log(const char *fmt, ...)
{
    char buf[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    fprintf(stderr, "[imubench-sim %.6f] %s\n", (double)g_sim.t_us * 1e-6, buf);
}

int sim_streaming(void) { return g_sim.core.stream_state != IB_STREAM_STATE_STOPPED; }

/* ---- resets ---- */

void sim_request_reset(int kind)
{
    sim_t *s = &g_sim;
    if (s->in_core) {
        s->in_core = 0;
        s->reset_kind = kind;
        longjmp(s->reset_jmp, 1);
    }
    if (kind > s->reset_pending) {
        s->reset_pending = kind;
    }
}

enum { CORE_INIT, CORE_TICK, CORE_POLL };

/* Run one core entry point; -1 when it was cut off by a reset (g_sim.reset_kind says
 * which). Nothing here is modified between setjmp and longjmp. */
static int core_call(int what, uint32_t arg, uint32_t arg2)
{
    sim_t *s = &g_sim;
    if (setjmp(s->reset_jmp) != 0) {
        return -1;
    }
    s->in_core = 1;
    s->spin = 0;
    switch (what) {
    case CORE_INIT:
        ib_core_init(&s->core, &s->board);
        break;
    case CORE_TICK:
        ib_core_tick(&s->core, arg, arg2);
        break;
    default:
        ib_core_poll(&s->core);
        break;
    }
    s->in_core = 0;
    return 0;
}

static void boot(int kind)
{
    sim_t *s = &g_sim;
    for (;;) {
        s->reset_pending = SIM_RESET_NONE;
        if (kind == SIM_RESET_POWER_CUT) {
            s->power_cuts++;
            sim_power_cycle_models();
            sim_log("power cut: power-cycling the sensors and restarting the firmware");
        } else if (kind == SIM_RESET_REBOOT) {
            s->reboots++;
            sim_log("reboot: restarting the firmware");
        }
        if (kind == SIM_RESET_REBOOT) {
            /* board.h: reboot() comes after the ack was queued and the link drained; what
             * is still queued is sent (a core that did not wait loses nothing) */
            s->link.rx_head = s->link.rx_tail = 0;
        } else {
            sim_link_reset(&s->link, s->t_us); /* power: UART buffers lost */
        }
        s->tick_hz = 0;
        s->flash.ops_since_boot = 0;
        s->boots++;
        memset(&s->core, 0, sizeof s->core);
        uint64_t t0 = s->t_us;
        if (core_call(CORE_INIT, 0, 0) == 0) {
            sim_log("boot %u done (%.3f s of device time)", s->boots, (double)(s->t_us - t0) * 1e-6);
            return;
        }
        kind = s->reset_kind;
    }
}

/* ---- pacing ---- */

uint64_t sim_pace_target(uint64_t now_ns)
{
    sim_t *s = &g_sim;
    if (now_ns <= s->anchor_wall_ns) {
        return s->anchor_dev_us;
    }
    double speed = s->speed > 0.0 ? s->speed : 1.0;
    return s->anchor_dev_us + (uint64_t)((double)(now_ns - s->anchor_wall_ns) * 1e-3 * speed);
}

void sim_set_speed(double speed)
{
    sim_t *s = &g_sim;
    uint64_t now = sim_wall_ns();
    uint64_t target = sim_pace_target(now);
    /* paced -> paced: keep the device's lead or lag; from "as fast as possible": now */
    s->anchor_dev_us = s->speed > 0.0 ? target : s->t_us;
    s->anchor_wall_ns = now;
    s->speed = speed;
}

static uint64_t tick_time(uint64_t n)
{
    sim_t *s = &g_sim;
    return s->tick_base_us + n * 1000000ull / s->tick_hz;
}

/* Lockstep: hand the link bytes to the OS, waiting (poll) while the host's socket is full,
 * until at most `keep` bytes are staged. The host reads in a thread of its own; a host that
 * is gone (client dropped) discards them. */
void sim_flush_blocking(size_t keep)
{
    sim_t *s = &g_sim;
    sim_link_t *l = &s->link;
    while (sim_link_staged(l) > keep && !g_sim_signal) {
        sim_link_flush(l);
        if (!l->os_blocked) {
            continue;
        }
        int fd = l->tcp_client >= 0 ? l->tcp_client : l->pty_master;
        struct pollfd p = {fd, POLLOUT, 0};
        if (poll(&p, 1, 100) == 0 && g_sim_parent != 0 && getppid() != g_sim_parent) {
            g_sim_parent_gone = 1;
            s->quit = 1;
            return;
        }
    }
}

/* Run the device up to device time `target`. Returns 1 when it stopped early (wall
 * budget used up) with ticks still due. `final` 0 (lockstep, below the run's end): run the
 * ticks due by `target` only, no idle advance and poll at `target` (stops that depend on the
 * wall clock must not change what the device does). */
int sim_run_device_to(uint64_t target, uint64_t budget_end_ns, int final)
{
    sim_t *s = &g_sim;
    if (s->reset_pending) {
        boot(s->reset_pending);
    }
    if (s->t_us > target) {
        return 0; /* the core is still "busy" (delay_us ran ahead): wait for the clock */
    }
    unsigned n = 0;
    while (s->tick_hz != 0 && s->next_tick_us <= target) {
        sim_advance_to(s->next_tick_us);
        uint32_t missed = 0;
        /* periods that passed entirely while the core was busy */
        while (tick_time(s->tick_n + 1) <= s->t_us) {
            s->tick_n++;
            missed++;
        }
        uint32_t due_us = (uint32_t)tick_time(s->tick_n);
        s->tick_n++;
        s->next_tick_us = tick_time(s->tick_n);
        s->ticks++;
        s->ticks_missed += missed;
        if (core_call(CORE_TICK, missed, due_us) != 0) {
            boot(s->reset_kind);
            return 0;
        }
        if (core_call(CORE_POLL, 0, 0) != 0) {
            boot(s->reset_kind);
            return 0;
        }
        if (s->reset_pending) {
            boot(s->reset_pending);
            return 0;
        }
        if (s->lockstep && sim_link_staged(&s->link) > (SIM_TX_STORE - SIM_TX_RING) / 4) {
            sim_flush_blocking(0); /* the UART never stalls on a slow host */
        }
        if (s->t_us > target) {
            return 0;
        }
        if ((++n & 31u) == 0 && sim_wall_ns() > budget_end_ns) {
            return 1;
        }
    }
    if (!final) {
        return 0;
    }
    sim_advance_to(target);
    if (core_call(CORE_POLL, 0, 0) != 0) {
        boot(s->reset_kind);
    }
    return 0;
}

int sim_run_device(uint64_t target, uint64_t budget_end_ns)
{
    return sim_run_device_to(target, budget_end_ns, 1);
}

/* ---- options ---- */

static void usage(FILE *f)
{
    fprintf(f,
            "usage: imubench-sim [--pty] [--tcp PORT] [--control PORT] [--flash FILE]\n"
            "                    [--speed X] [--seed N] [--truth default|random] [--baud B]\n"
            "                    [--uid HEX24] [--orphan-cleanup DIR] [--clock realtime|lockstep]\n"
            "                    [--parts SLOT=PART,...]\n"
            "  --pty          expose the device's serial port on a new pseudo-terminal\n"
            "  --tcp PORT     ... and/or on TCP 127.0.0.1:PORT (0 = free port; the default\n"
            "                 when neither --pty nor --tcp is given)\n"
            "  --control PORT JSON-lines control channel on 127.0.0.1 (default 0 = free port)\n"
            "  --flash FILE   parameter flash file (created 0xFF-filled; default: temp dir)\n"
            "  --speed X      device time runs X times real time (default 1; 0 = max);\n"
            "                 with --clock lockstep a ceiling\n"
            "  --clock C      realtime (default): device time runs against the wall clock,\n"
            "                 bytes the host does not read in time are dropped; lockstep:\n"
            "                 device time moves only when the host grants it (control\n"
            "                 command run), nothing is dropped, the run is deterministic\n"
            "  --seed N       seed of the sensor models (default 1)\n"
            "  --truth T      default | random (the sensors' errors drawn from the seed)\n"
            "  --parts SPEC   the board's parts (protocol/parts.toml), e.g. accel=adxl359,gyro_z=adxrs453;\n"
            "                 slots accel, gyro (all three), gyro_x, gyro_y, gyro_z\n"
            "  --baud B       link speed that drains the TX buffer (default 2000000)\n"
            "  --uid HEX24    MCU unique id, 12 bytes in hex (default: from the seed)\n"
            "  --orphan-cleanup DIR  when the parent process dies (a host killed with\n"
            "                 SIGKILL cannot clean up), remove DIR's flash.bin, sim.log and\n"
            "                 owner.json and then DIR itself (the host's temporary folder)\n");
}

static int parse_u64(const char *s, uint64_t *out)
{
    char *end;
    errno = 0;
    unsigned long long v = strtoull(s, &end, 0);
    if (errno || end == s || *end || s[0] == '-') {
        return -1;
    }
    *out = v;
    return 0;
}

static int parse_uid(const char *s, uint8_t uid[12])
{
    if (strlen(s) != 24) {
        return -1;
    }
    for (int i = 0; i < 12; i++) {
        unsigned v;
        char two[3] = {s[2 * i], s[2 * i + 1], 0};
        char *end;
        v = (unsigned)strtoul(two, &end, 16);
        if (*end) {
            return -1;
        }
        uid[i] = (uint8_t)v;
    }
    return 0;
}

static void on_signal(int sig) { g_sim_signal = sig; }

static void print_startup_line(const char *flash_path)
{
    sim_t *s = &g_sim;
    char fp[4096];
    if (realpath(flash_path, fp) == NULL) {
        snprintf(fp, sizeof fp, "%s", flash_path);
    }
    sj_buf_t b = {0};
    sj_raw(&b, "{");
    sj_key(&b, "pty");
    if (s->link.pty_master >= 0) {
        sj_str(&b, s->link.pty_name);
    } else {
        sj_raw(&b, "null");
    }
    sj_key(&b, "port_url");
    if (s->link.tcp_listen >= 0) {
        sj_printf(&b, "\"socket://127.0.0.1:%d\"", s->link.tcp_port);
    } else {
        sj_str(&b, s->link.pty_name);
    }
    sj_key(&b, "tcp_port");
    if (s->link.tcp_listen >= 0) {
        sj_printf(&b, "%d", s->link.tcp_port);
    } else {
        sj_raw(&b, "null");
    }
    sj_key(&b, "control");
    sj_printf(&b, "\"127.0.0.1:%d\"", s->control_port);
    sj_key(&b, "control_port");
    sj_printf(&b, "%d", s->control_port);
    sj_key(&b, "pid");
    sj_printf(&b, "%ld", (long)getpid());
    sj_key(&b, "flash");
    sj_str(&b, fp);
    sj_key(&b, "seed");
    sj_printf(&b, "%llu", (unsigned long long)s->seed);
    sj_key(&b, "speed");
    sj_num(&b, s->speed);
    sj_key(&b, "clock");
    sj_str(&b, s->lockstep ? "lockstep" : "realtime");
    sj_key(&b, "baud");
    sj_printf(&b, "%u", s->baud);
    sj_key(&b, "truth");
    sj_str(&b, s->truth_random ? "random" : "default");
    char uid[25];
    for (int i = 0; i < 12; i++) {
        snprintf(uid + 2 * i, 3, "%02x", s->uid[i]);
    }
    sj_key(&b, "uid");
    sj_str(&b, uid);
    sj_key(&b, "build");
    sj_str(&b, SIM_BUILD_ID);
    sj_raw(&b, "}\n");
    fputs(b.p ? b.p : "{}\n", stdout);
    fflush(stdout);
    sj_buf_free(&b);
}

static char g_tmpdir[256];
static char g_tmpflash[300];

static void cleanup_tmp(void)
{
    if (g_tmpflash[0]) {
        unlink(g_tmpflash);
    }
    if (g_tmpdir[0]) {
        rmdir(g_tmpdir);
    }
    if (g_orphan_dir && g_sim_parent_gone) {
        /* only the files the host puts there: a folder holding anything else stays */
        static const char *const names[] = {"flash.bin", "sim.log", "owner.json"};
        char p[1024];
        for (size_t k = 0; k < sizeof names / sizeof names[0]; k++) {
            snprintf(p, sizeof p, "%s/%s", g_orphan_dir, names[k]);
            unlink(p);
        }
        rmdir(g_orphan_dir);
    }
}

/* No orphans: exit when the parent process dies. PR_SET_PDEATHSIG alone would also fire when
 * the parent THREAD that started us ends (e.g. a Python worker thread), so the loop checks
 * getppid() instead, at least every 100 ms. SIGTERM/INT/HUP end the loop (no SA_RESTART:
 * poll() returns EINTR). */
static void watch_parent_and_signals(void)
{
    g_sim_parent = getppid();
    if (g_sim_parent == 1) {
        g_sim_parent = 0; /* started by init / a daemon: nothing to watch */
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
}

/* No --flash: a flash file in a temporary directory of our own (removed at exit); NULL when
 * it cannot be made (said on stderr). */
static const char *temp_flash_path(void)
{
    const char *tmp = getenv("TMPDIR");
    snprintf(g_tmpdir, sizeof g_tmpdir, "%s/imubench-sim-XXXXXX", tmp && *tmp ? tmp : "/tmp");
    if (mkdtemp(g_tmpdir) == NULL) {
        fprintf(stderr, "imubench-sim: cannot create a temp dir: %s\n", strerror(errno));
        return NULL;
    }
    snprintf(g_tmpflash, sizeof g_tmpflash, "%s/flash.bin", g_tmpdir);
    return g_tmpflash;
}

int main(int argc, char **argv)
{
    sim_t *s = &g_sim;
    int want_pty = 0, tcp_port = -1, control_port = 0, have_uid = 0;
    const char *flash_path = NULL;
    uint8_t uid[12];
    double speed = 1.0;
    uint64_t seed = 1, v;
    s->baud = SIM_DEFAULT_BAUD;

    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *val = i + 1 < argc ? argv[i + 1] : NULL;
        int need = 1;
        if (!strcmp(a, "--help") || !strcmp(a, "-h")) {
            usage(stdout);
            return 0;
        } else if (!strcmp(a, "--pty")) {
            want_pty = 1;
            need = 0;
        } else if (val == NULL) {
            fprintf(stderr, "imubench-sim: %s needs a value\n", a);
            return 2;
        } else if (!strcmp(a, "--tcp") && parse_u64(val, &v) == 0 && v <= 65535) {
            tcp_port = (int)v;
        } else if (!strcmp(a, "--control") && parse_u64(val, &v) == 0 && v <= 65535) {
            control_port = (int)v;
        } else if (!strcmp(a, "--flash")) {
            flash_path = val;
        } else if (!strcmp(a, "--speed")) {
            char *end;
            speed = strtod(val, &end);
            if (*end || !(speed >= 0.0) || !isfinite(speed)) {
                fprintf(stderr, "imubench-sim: bad --speed %s\n", val);
                return 2;
            }
        } else if (!strcmp(a, "--seed") && parse_u64(val, &v) == 0) {
            seed = v;
        } else if (!strcmp(a, "--truth") && (!strcmp(val, "default") || !strcmp(val, "random"))) {
            s->truth_random = !strcmp(val, "random");
        } else if (!strcmp(a, "--baud") && parse_u64(val, &v) == 0 && v >= 1200 && v <= 100000000) {
            s->baud = (uint32_t)v;
        } else if (!strcmp(a, "--uid") && parse_uid(val, uid) == 0) {
            have_uid = 1;
        } else if (!strcmp(a, "--clock") && (!strcmp(val, "realtime") || !strcmp(val, "lockstep"))) {
            s->lockstep = !strcmp(val, "lockstep");
        } else if (!strcmp(a, "--orphan-cleanup")) {
            g_orphan_dir = val;
        } else if (!strcmp(a, "--parts")) {
            char err[160];
            if (sim_set_parts(val, err, sizeof err) != 0) {
                fprintf(stderr, "imubench-sim: --parts %s\n", err);
                return 2;
            }
        } else {
            fprintf(stderr, "imubench-sim: bad option or value: %s %s\n", a, val);
            usage(stderr);
            return 2;
        }
        i += need;
    }
    if (!want_pty && tcp_port < 0) {
        tcp_port = 0;
    }

    watch_parent_and_signals();

    s->seed = seed;
    s->speed = speed;
    if (flash_path == NULL && (flash_path = temp_flash_path()) == NULL) {
        return 1;
    }
    int rc = 1;
    sim_board_flash_hooks();
    if (sim_flash_open(&s->flash, flash_path) != 0) {
        goto out;
    }
    if (sim_link_open(&s->link, want_pty, tcp_port, s->baud) != 0) {
        goto out;
    }
    if (sim_control_open(control_port) != 0) {
        goto out;
    }
    sim_seed_models(seed, s->truth_random, "host");
    if (have_uid) {
        memcpy(s->uid, uid, sizeof uid);
    }
    sim_phys_init(&s->phys);
    sim_board_setup();

    print_startup_line(flash_path);

    s->anchor_wall_ns = sim_wall_ns();
    s->anchor_dev_us = 0;
    boot(SIM_RESET_NONE);
    sim_main_loop();
    rc = 0;
    sim_log("exiting (%s)", g_sim_signal ? strsignal(g_sim_signal) : (s->quit ? "quit" : "parent gone"));
out:
    sim_control_close();
    sim_link_close(&s->link);
    sim_flash_close(&s->flash);
    cleanup_tmp();
    return rc;
}
