/*
 * sim_control.c - the control channel of the virtual device: JSON lines over TCP on
 * 127.0.0.1 (several clients may connect; each line is one request, answered by one line).
 *
 * Request:  {"cmd": "<name>", ...arguments..., "id": <optional, echoed>}
 * Reply:    {"ok": true, ...} or {"ok": false, "error": "..."}
 * Unknown commands and unknown argument names are refused. Requests on one connection are
 * executed in order; "wait" and "wait_idle" reply later (in device time), and later lines
 * of that connection wait for them.
 *
 * Commands (angles in degrees, rates in deg/s unless the name says rad; device time in us):
 *   status
 *   set_orientation   {gravity: [x,y,z]}  direction of the measured specific force in the
 *                                         board frame (level: [0,0,1]); or
 *                     {roll_deg, pitch_deg, yaw_deg}  ZYX (sim_physics.c); missing = 0
 *   rotate            {axis: [x,y,z] | "x"|"y"|"z"|"-x"|"-y"|"-z", rate_dps, duration_s}
 *                     turn about a board-frame axis; replaces a move in progress
 *   set_rate          {rate_dps: [x,y,z]} or {rate_rad_s: [x,y,z]}  constant rate (rate
 *                     table), [0,0,0] stops
 *   path              {legs: [{duration_s, move_m: [dx,dy,dz] (level frame, optional),
 *                      axis, turn_deg (optional)}, ...]}  up to SIM_PATH_MAX_LEGS legs
 *                     back to back, each rest to rest on a minimum-jerk profile (a cart or
 *                     gantry driving a path); replaces a move in progress. status and
 *                     every world reply carry position_m, velocity_mps, acceleration_mps2
 *   set_temperature   {c, ramp_c_per_s (optional; absent/0 = at once), soak: bool}
 *                     the chamber (ambient). soak: the chamber AND every die at c at once
 *                     (as after hours in a fridge); self-heating builds up again from there
 *   set_thermal       {enabled: bool (default true), tau_s: [4] | number,
 *                      self_heat_c: [4] | number}  the dies' thermal model (sim_physics.c):
 *                     die i (0 ADXL355, 1..3 gyro X, Y, Z) lags the ambient with tau_s[i]
 *                     plus self_heat_c[i]; omitted figures keep theirs (nominal, or drawn
 *                     with the random truth). Off (the default) every die is at the ambient.
 *                     Switching on starts every die at the ambient (as a power-up)
 *   set_speed         {speed}  (0 = as fast as possible; in lockstep a ceiling)
 *   run               {until_us, stop: "idle"|"temperature"|"dies" (optional),
 *                      die_tolerance_c, link_rx}  LOCKSTEP (--clock lockstep): the device is
 *                     frozen except while a run is granted. It first receives link_rx bytes
 *                     (what the host wrote on its link connection so far), then runs to
 *                     device time until_us (or, with stop, to the first device time the
 *                     wait_idle condition holds, at most until_us), hands every link byte
 *                     produced up to then to the host (waiting for the host to take them:
 *                     nothing is dropped), and replies {time_us, link_tx (bytes written on
 *                     the link connection so far), done (stop: the condition holds)}.
 *                     Refused in the real-time clock
 *   wait              {device_s}  reply after that much device time (lockstep: a run)
 *   wait_idle         {temperature: bool (also wait for a ramp to end; default false),
 *                      die_tolerance_c: number (also wait until every die is within this of
 *                      its steady temperature, ambient + self-heating; implies temperature)}
 *   set_truth         {accel: {m: 3x3 | 9, bias_mps2, noise_n, rw_k, bias_tc, scale_tc,
 *                      bias_tc2, bias_tc3, hysteresis, hysteresis_width_c, st_force_g},
 *                      gyro: [{sens: [3], bias_rad_s, noise_n, bias_rw_k,
 *                      bias_instability_rad_s, bias_tempco_rad_s_per_c, scale_tempco_per_c, gsens_rad_s_per_mps2,
 *                      bias_tc2, bias_tc3, hysteresis, hysteresis_width_c} | null, x3] or
 *                      {x: {...}, y: ..., z: ...}}  partial updates; accel vectors may be
 *                      given as one number for all three axes. The temperature terms are
 *                      about 25 degC (bias_tc2 per degC^2, bias_tc3 per degC^3, in the
 *                      bias's unit); hysteresis is half the gap between the warming and the
 *                      cooling branch, hysteresis_width_c the play operator's dead band
 *   randomize_truth   {seed (default: the process seed)}  also draws the dies' tau_s and
 *                     self_heat_c (set_thermal); whether the model is on stays as it is
 *   get_truth         the truths, each sensor's die_temperature_c and hysteresis_branch,
 *                     thermal {enabled, tau_s, self_heat_c} and the world
 *   inject            {fault: "gyro_fault_bits", sensor: "gyro_x"|"gyro_y"|"gyro_z",
 *                      bits: N, persistent: bool}
 *                     {fault: "gyro_parity", sensor, count, mask (default 1: P1 wrong)}
 *                     {fault: "missing", sensor: "accel"|"gyro_*", on: bool (default true)}
 *                     {fault: "spi_error", sensor, count} or {..., probability}
 *                     {fault: "link_drop", count}   drop the next count bytes sent
 *                     {fault: "link_flip", count}   flip a random bit in each of the next
 *                                                   count bytes sent
 *                     {fault: "accel_stuck", on}  {fault: "accel_shadow", on}
 *                     {fault: "accel_wrong_id", on}  the ADXL355 answers PARTID 0xEE
 *                     {fault: "clear"}  everything off (also an armed power cut)
 *   power_cut         {after_flash_ops: N}  during the N-th next flash op (N >= 1);
 *                     omitted, null or 0: now
 *   flash_ops         -> {flash_ops (since boot), flash_ops_total, power_cut_armed}
 *   quit
 */
#define _GNU_SOURCE
#include "sim.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include "sim_json.h"

#define CTL_MAX_CONN 8
#define CTL_LINE_MAX 65536
#define DEG (M_PI / 180.0)

enum { WAIT_NONE = 0, WAIT_TIME, WAIT_IDLE, WAIT_IDLE_TEMP, WAIT_IDLE_DIES, WAIT_RUN };

typedef struct {
    int fd;
    char *in;
    size_t in_len;
    sj_buf_t out;
    size_t out_off;
    int wait;
    uint64_t wait_until;
    double wait_tol_c;  /* WAIT_IDLE_DIES: tolerance of every die */
    int run_stop;       /* WAIT_RUN: WAIT_NONE (run to wait_until) or WAIT_IDLE* (stop when idle) */
    uint64_t run_link_rx; /* WAIT_RUN: link bytes the host wrote before it asked (received first) */
    char wait_id[80]; /* JSON of the id to echo in the deferred reply ("" = none) */
} conn_t;

static conn_t g_conn[CTL_MAX_CONN];
static int g_map[CTL_MAX_CONN + 1]; /* pollfd slot -> connection index, -1 = listener */
static char g_err[256];
static conn_t *run_conn(void);

static int fail(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static int fail(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(g_err, sizeof g_err, fmt, ap);
    va_end(ap);
    return -1;
}

int sim_control_open(int port)
{
    for (int i = 0; i < CTL_MAX_CONN; i++) {
        g_conn[i].fd = -1;
    }
    g_sim.control_listen = sim_listen_tcp(port, &g_sim.control_port);
    if (g_sim.control_listen < 0) {
        sim_log("control: cannot listen on 127.0.0.1:%d: %s", port, strerror(errno));
        return -1;
    }
    return 0;
}

static void conn_close(conn_t *c)
{
    if (c->fd >= 0) {
        close(c->fd);
    }
    free(c->in);
    sj_buf_free(&c->out);
    memset(c, 0, sizeof *c);
    c->fd = -1;
}

static void conn_flush(conn_t *c)
{
    while (c->fd >= 0 && c->out_off < c->out.len) {
        ssize_t n = send(c->fd, c->out.p + c->out_off, c->out.len - c->out_off, MSG_NOSIGNAL);
        if (n > 0) {
            c->out_off += (size_t)n;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            return;
        }
        conn_close(c);
        return;
    }
    if (c->fd >= 0) {
        c->out.len = 0;
        c->out_off = 0;
    }
}

void sim_control_close(void)
{
    for (int i = 0; i < CTL_MAX_CONN; i++) {
        conn_t *c = &g_conn[i];
        if (c->fd >= 0 && c->out_off < c->out.len) {
            struct timeval tv = {0, 200000};
            setsockopt(c->fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);
            int flags = fcntl(c->fd, F_GETFL);
            fcntl(c->fd, F_SETFL, flags & ~O_NONBLOCK);
            conn_flush(c);
        }
        if (c->fd >= 0) {
            conn_close(c);
        }
    }
    if (g_sim.control_listen >= 0) {
        close(g_sim.control_listen);
        g_sim.control_listen = -1;
    }
}

int sim_control_pollfds(struct pollfd *pfd, int max)
{
    int n = 0;
    if (g_sim.control_listen >= 0 && n < max) {
        g_map[n] = -1;
        pfd[n++] = (struct pollfd){g_sim.control_listen, POLLIN, 0};
    }
    for (int i = 0; i < CTL_MAX_CONN && n < max; i++) {
        conn_t *c = &g_conn[i];
        if (c->fd < 0) {
            continue;
        }
        short ev = 0;
        if (c->in_len < CTL_LINE_MAX) {
            ev |= POLLIN;
        }
        if (c->out_off < c->out.len) {
            ev |= POLLOUT;
        }
        g_map[n] = i;
        pfd[n++] = (struct pollfd){c->fd, ev, 0};
    }
    return n;
}

/* ------------------------------------------------------------------ helpers */

typedef struct {
    sj_doc_t *d;
    int root;
    sj_buf_t *r; /* reply under construction: starts with {"ok": true */
    conn_t *c;
} req_t;

static int check_keys(req_t *q, int obj, const char *allowed)
{
    const sj_doc_t *d = q->d;
    for (int ch = d->nodes[obj].first; ch >= 0; ch = d->nodes[ch].next) {
        const char *k = d->nodes[ch].key;
        size_t kl = strlen(k);
        const char *p = allowed;
        int found = 0;
        while (*p) {
            const char *e = strchr(p, ',');
            size_t l = e ? (size_t)(e - p) : strlen(p);
            if (l == kl && strncmp(p, k, l) == 0) {
                found = 1;
                break;
            }
            p += l + (e ? 1 : 0);
        }
        if (!found) {
            return fail("unknown field '%s' (allowed: %s)", k, allowed);
        }
    }
    return 0;
}

static int is_null(const sj_doc_t *d, int n) { return n < 0 || d->nodes[n].type == SJ_NULL; }

static int node_num(const sj_doc_t *d, int n, const char *what, double *out)
{
    if (n < 0 || d->nodes[n].type != SJ_NUM || !isfinite(d->nodes[n].num)) {
        return fail("%s must be a finite number", what);
    }
    *out = d->nodes[n].num;
    return 0;
}

/* Optional number: 0 = absent (out untouched), 1 = read, -1 = error. */
static int opt_num(req_t *q, int obj, const char *key, double *out)
{
    int n = sj_get(q->d, obj, key);
    if (is_null(q->d, n)) {
        return 0;
    }
    return node_num(q->d, n, key, out) == 0 ? 1 : -1;
}

static int req_num(req_t *q, int obj, const char *key, double *out)
{
    int r = opt_num(q, obj, key, out);
    if (r == 0) {
        return fail("missing '%s'", key);
    }
    return r < 0 ? -1 : 0;
}

static int node_vec(const sj_doc_t *d, int n, const char *what, double *out, int len,
                    int scalar_ok)
{
    if (n >= 0 && scalar_ok && d->nodes[n].type == SJ_NUM) {
        double v = 0.0;
        if (node_num(d, n, what, &v) != 0) {
            return -1;
        }
        for (int i = 0; i < len; i++) {
            out[i] = v;
        }
        return 0;
    }
    if (n < 0 || d->nodes[n].type != SJ_ARR || d->nodes[n].count != len) {
        return fail("%s must be an array of %d numbers%s", what, len, scalar_ok ? " (or one number)" : "");
    }
    for (int i = 0; i < len; i++) {
        if (node_num(d, sj_at(d, n, i), what, &out[i]) != 0) {
            return -1;
        }
    }
    return 0;
}

static int node_mat3(const sj_doc_t *d, int n, const char *what, double m[3][3])
{
    if (n >= 0 && d->nodes[n].type == SJ_ARR && d->nodes[n].count == 9) {
        double f[9];
        if (node_vec(d, n, what, f, 9, 0) != 0) {
            return -1;
        }
        memcpy(m, f, sizeof f);
        return 0;
    }
    if (n < 0 || d->nodes[n].type != SJ_ARR || d->nodes[n].count != 3) {
        return fail("%s must be a 3x3 array (or 9 numbers, row-major)", what);
    }
    for (int i = 0; i < 3; i++) {
        if (node_vec(d, sj_at(d, n, i), what, m[i], 3, 0) != 0) {
            return -1;
        }
    }
    return 0;
}

static int sensor_cs(req_t *q, int obj, int allow_accel)
{
    int n = sj_get(q->d, obj, "sensor");
    if (n < 0 || q->d->nodes[n].type != SJ_STR) {
        return fail("missing 'sensor' (\"accel\", \"gyro_x\", \"gyro_y\" or \"gyro_z\")");
    }
    const char *s = q->d->nodes[n].str;
    if (!strcmp(s, "accel") && allow_accel) {
        return IB_CS_ACCEL;
    }
    if (!strcmp(s, "gyro_x")) {
        return IB_CS_GYRO_X;
    }
    if (!strcmp(s, "gyro_y")) {
        return IB_CS_GYRO_Y;
    }
    if (!strcmp(s, "gyro_z")) {
        return IB_CS_GYRO_Z;
    }
    return fail("bad sensor '%s' (%s\"gyro_x\", \"gyro_y\" or \"gyro_z\")", s,
                allow_accel ? "\"accel\", " : "");
}

static int opt_bool(req_t *q, int obj, const char *key, int dflt, int *out)
{
    int n = sj_get(q->d, obj, key);
    if (is_null(q->d, n)) {
        *out = dflt;
        return 0;
    }
    if (q->d->nodes[n].type != SJ_BOOL && q->d->nodes[n].type != SJ_NUM) {
        return fail("%s must be true or false", key);
    }
    *out = q->d->nodes[n].num != 0.0;
    return 0;
}

static void put_vec(sj_buf_t *r, const char *key, const double *v, int n)
{
    sj_key(r, key);
    sj_vec(r, v, n);
}

static void put_num(sj_buf_t *r, const char *key, double v)
{
    sj_key(r, key);
    sj_num(r, v);
}

static void put_u64(sj_buf_t *r, const char *key, uint64_t v)
{
    sj_key(r, key);
    sj_printf(r, "%llu", (unsigned long long)v);
}

static void put_bool(sj_buf_t *r, const char *key, int v)
{
    sj_key(r, key);
    sj_raw(r, v ? "true" : "false");
}

/* ------------------------------------------------------------------ commands */

static void put_world(sj_buf_t *r)
{
    const sim_physics_t *p = &g_sim.phys;
    uint64_t t = g_sim.t_us;
    double g[3], f[3], w[3], wd[3], rm[3][3], roll, pitch, yaw, pos[3], vel[3], acc[3];
    sim_phys_gravity_dir(p, t, g);
    sim_phys_specific_force(p, t, f);
    sim_phys_omega(p, t, w);
    sim_phys_orientation(p, t, rm);
    sim_phys_rpy(rm, &roll, &pitch, &yaw);
    sim_phys_kinematics(p, t, pos, vel, acc);
    for (int i = 0; i < 3; i++) {
        wd[i] = w[i] / DEG;
    }
    put_vec(r, "gravity_board", g, 3);
    put_vec(r, "specific_force_mps2", f, 3);
    put_vec(r, "rate_rad_s", w, 3);
    put_vec(r, "rate_dps", wd, 3);
    put_num(r, "temperature_c", sim_phys_temperature(p, t));
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&g_sim.thermal, p, i, t);
    }
    put_vec(r, "die_temperature_c", die, SIM_DIES);
    put_num(r, "roll_deg", roll / DEG);
    put_num(r, "pitch_deg", pitch / DEG);
    put_num(r, "yaw_deg", yaw / DEG);
    put_vec(r, "position_m", pos, 3);
    put_vec(r, "velocity_mps", vel, 3);
    put_vec(r, "acceleration_mps2", acc, 3);
}

/* "thermal": {enabled, tau_s [4], self_heat_c [4]} (die order: ADXL355, gyro X, Y, Z) */
static void put_thermal(sj_buf_t *r)
{
    const sim_thermal_t *th = &g_sim.thermal;
    sj_key(r, "thermal");
    sj_raw(r, "{");
    put_bool(r, "enabled", th->enabled);
    put_vec(r, "tau_s", th->tau_s, SIM_DIES);
    put_vec(r, "self_heat_c", th->self_heat_c, SIM_DIES);
    sj_raw(r, "}");
}

static int cmd_status(req_t *q)
{
    sim_t *s = &g_sim;
    sj_buf_t *r = q->r;
    const sim_physics_t *p = &s->phys;
    if (check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    put_u64(r, "time_us", s->t_us);
    put_num(r, "time_s", (double)s->t_us * 1e-6);
    put_bool(r, "streaming", sim_streaming());
    put_u64(r, "stream_state", s->core.stream_state);
    put_u64(r, "tick_hz", s->tick_hz);
    put_num(r, "speed", s->speed);
    put_world(r);
    int moving = sim_phys_moving(p, s->t_us);
    put_bool(r, "moving", moving);
    sj_key(r, "move");
    if (p->kind == SIM_MOTION_NONE || (p->kind != SIM_MOTION_RATE && !moving)) {
        sj_raw(r, "null");
    } else {
        sj_raw(r, "{");
        sj_key(r, "kind");
        sj_str(r, p->kind == SIM_MOTION_ROTATE ? "rotate" : p->kind == SIM_MOTION_PATH ? "path" : "rate");
        if (p->kind == SIM_MOTION_PATH) {
            put_u64(r, "leg", (uint64_t)sim_phys_path_leg(p, s->t_us));
            put_u64(r, "legs", (uint64_t)p->n_legs);
        } else {
            put_vec(r, "axis", p->axis, 3);
            put_num(r, "rate_dps", p->rate_rad_s / DEG);
        }
        if (p->kind != SIM_MOTION_RATE) {
            put_num(r, "remaining_s", (double)(p->t_end_us - s->t_us) * 1e-6);
            put_u64(r, "t_end_us", p->t_end_us);
        }
        sj_raw(r, "}");
    }
    put_bool(r, "temperature_ramping", sim_phys_temperature(p, s->t_us) != p->temp_target_c);
    put_thermal(r);
    put_u64(r, "boots", s->boots);
    put_u64(r, "power_cuts", s->power_cuts);
    put_u64(r, "reboots", s->reboots);
    put_u64(r, "flash_ops", s->flash.ops_since_boot);
    put_u64(r, "flash_ops_total", s->flash.ops_total);
    put_u64(r, "ticks", s->ticks);
    put_u64(r, "ticks_missed", s->ticks_missed);
    put_u64(r, "pacing_slips", s->slips);
    put_u64(r, "samples_dropped", s->core.stats.samples_dropped); /* by the core: TX ring full */
    put_u64(r, "spi_transfers", s->spi_transfers);
    double inj[IB_CS_COUNT];
    for (int i = 0; i < IB_CS_COUNT; i++) {
        inj[i] = (double)s->spi_faults.errors_injected[i];
    }
    put_vec(r, "spi_errors_injected", inj, IB_CS_COUNT);
    sj_key(r, "target");
    sj_str(r, s->target[0] ? s->target : "host");
    if (s->target[0]) { /* the exact ARM image under the emulator (host/imubench/device/arm) */
        sj_key(r, "arm");
        sj_raw(r, "{");
        put_u64(r, "instructions", s->arm_instructions);
        put_u64(r, "faults", s->arm_faults);
        put_u64(r, "unmodelled_accesses", s->arm_unmodelled);
        put_u64(r, "spi_peek_mismatches", s->arm_spi_mismatch);
        put_num(r, "idle_s", s->arm_idle_s);
        put_num(r, "sysclk_hz", s->arm_sysclk_hz);
        put_num(r, "cpi", s->arm_cpi);
        put_u64(r, "idle_loop_instructions", s->arm_idle_instructions);
        put_num(r, "busy_wait_s", s->arm_busy_s);
        put_num(r, "flash_stall_s", s->arm_stall_s);
        put_num(r, "spi_bus_s", s->arm_spi_bus_s);
        put_u64(r, "spi_bytes", s->arm_spi_bytes);
        put_u64(r, "spi_transactions", s->arm_spi_transactions);
        sj_key(r, "instructions_by_range");
        sj_raw(r, "{");
        static const char *const names[5] = {"other", "core", "drivers", "board", "lib"};
        for (int i = 0; i < 5; i++) {
            put_u64(r, names[i], s->arm_regions[i]);
        }
        sj_raw(r, "}");
        sj_raw(r, "}");
    }
    sim_link_t *l = &s->link;
    sj_key(r, "link");
    sj_raw(r, "{");
    put_bool(r, "tcp_client", l->tcp_client >= 0);
    put_u64(r, "tx_queued", sim_link_queued(l));
    put_u64(r, "tx_staged", sim_link_staged(l));
    put_u64(r, "tx_free", sim_link_tx_free(l));
    put_u64(r, "bytes_sent", l->bytes_written_os);
    put_u64(r, "bytes_discarded", l->bytes_discarded);
    put_u64(r, "bytes_dropped", l->bytes_dropped);
    put_u64(r, "bytes_flipped", l->bytes_flipped);
    put_u64(r, "bytes_received", l->bytes_received);
    put_u64(r, "drop_pending", l->drop_remaining);
    put_u64(r, "flip_pending", l->flip_remaining);
    sj_raw(r, "}");
    return 0;
}

static int cmd_set_orientation(req_t *q)
{
    sim_t *s = &g_sim;
    if (check_keys(q, q->root, "cmd,id,gravity,roll_deg,pitch_deg,yaw_deg") != 0) {
        return -1;
    }
    int gn = sj_get(q->d, q->root, "gravity");
    double roll = 0, pitch = 0, yaw = 0;
    int nr = opt_num(q, q->root, "roll_deg", &roll);
    int np = opt_num(q, q->root, "pitch_deg", &pitch);
    int ny = opt_num(q, q->root, "yaw_deg", &yaw);
    if (nr < 0 || np < 0 || ny < 0) {
        return -1;
    }
    if (!is_null(q->d, gn)) {
        if (nr || np || ny) {
            return fail("give either gravity or roll_deg/pitch_deg/yaw_deg, not both");
        }
        double g[3];
        if (node_vec(q->d, gn, "gravity", g, 3, 0) != 0) {
            return -1;
        }
        if (sim_phys_set_gravity(&s->phys, s->t_us, g) != 0) {
            return fail("gravity must be a non-zero vector");
        }
    } else if (nr || np || ny) {
        sim_phys_set_rpy(&s->phys, s->t_us, roll * DEG, pitch * DEG, yaw * DEG);
    } else {
        return fail("give gravity: [x, y, z] or roll_deg/pitch_deg/yaw_deg");
    }
    put_world(q->r);
    return 0;
}

static int parse_axis(req_t *q, double axis[3])
{
    int n = sj_get(q->d, q->root, "axis");
    if (n >= 0 && q->d->nodes[n].type == SJ_STR) {
        const char *a = q->d->nodes[n].str;
        double sign = 1.0;
        if (*a == '-' || *a == '+') {
            sign = *a == '-' ? -1.0 : 1.0;
            a++;
        }
        memset(axis, 0, 3 * sizeof(double));
        if ((a[0] == 'x' || a[0] == 'X') && !a[1]) {
            axis[0] = sign;
        } else if ((a[0] == 'y' || a[0] == 'Y') && !a[1]) {
            axis[1] = sign;
        } else if ((a[0] == 'z' || a[0] == 'Z') && !a[1]) {
            axis[2] = sign;
        } else {
            return fail("axis must be \"x\", \"y\", \"z\" (optionally signed) or [x, y, z]");
        }
        return 0;
    }
    if (node_vec(q->d, n, "axis", axis, 3, 0) != 0) {
        return -1;
    }
    double norm = sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    if (!(norm > 1e-9)) {
        return fail("axis must be a non-zero vector");
    }
    return 0;
}

static int cmd_rotate(req_t *q)
{
    sim_t *s = &g_sim;
    double axis[3], rate, dur;
    if (check_keys(q, q->root, "cmd,id,axis,rate_dps,duration_s") != 0 || parse_axis(q, axis) != 0 ||
        req_num(q, q->root, "rate_dps", &rate) != 0 || req_num(q, q->root, "duration_s", &dur) != 0) {
        return -1;
    }
    if (dur < 0.0 || dur > 1e6) {
        return fail("duration_s must be in 0 .. 1e6");
    }
    if (fabs(rate) > 1e5) {
        return fail("rate_dps out of range");
    }
    if (sim_phys_rotate(&s->phys, s->t_us, axis, rate * DEG, dur) != 0) {
        return fail("bad rotation");
    }
    put_u64(q->r, "t_start_us", s->t_us);
    put_u64(q->r, "t_end_us", s->t_us + (uint64_t)llround(dur * 1e6));
    put_num(q->r, "angle_deg", rate * dur);
    return 0;
}

static int cmd_set_rate(req_t *q)
{
    sim_t *s = &g_sim;
    double w[3];
    if (check_keys(q, q->root, "cmd,id,rate_dps,rate_rad_s") != 0) {
        return -1;
    }
    int nd = sj_get(q->d, q->root, "rate_dps"), nr = sj_get(q->d, q->root, "rate_rad_s");
    if ((nd >= 0) == (nr >= 0)) {
        return fail("give rate_dps: [x, y, z] or rate_rad_s: [x, y, z]");
    }
    if (node_vec(q->d, nd >= 0 ? nd : nr, nd >= 0 ? "rate_dps" : "rate_rad_s", w, 3, 0) != 0) {
        return -1;
    }
    for (int i = 0; i < 3; i++) {
        w[i] *= nd >= 0 ? DEG : 1.0;
        if (fabs(w[i]) > 1e4) {
            return fail("rate out of range");
        }
    }
    sim_phys_set_rate(&s->phys, s->t_us, w);
    put_world(q->r);
    return 0;
}

/* {"cmd": "path", "legs": [{"duration_s": T, "move_m": [dx, dy, dz], "axis": "z",
 *   "turn_deg": A}, ...]}: drive the legs back to back, each rest to rest on a minimum-jerk
 * profile; move_m in the level frame, the turn about a board axis (sim_physics.c). */
static int cmd_path(req_t *q)
{
    sim_t *s = &g_sim;
    static sim_leg_t legs[SIM_PATH_MAX_LEGS];
    if (check_keys(q, q->root, "cmd,id,legs") != 0) {
        return -1;
    }
    int arr = sj_get(q->d, q->root, "legs");
    if (arr < 0 || q->d->nodes[arr].type != SJ_ARR || q->d->nodes[arr].count < 1 ||
        q->d->nodes[arr].count > SIM_PATH_MAX_LEGS) {
        return fail("legs must be an array of 1 .. %d legs", SIM_PATH_MAX_LEGS);
    }
    int n = q->d->nodes[arr].count;
    double total_s = 0.0;
    for (int i = 0; i < n; i++) {
        int o = sj_at(q->d, arr, i);
        sim_leg_t *l = &legs[i];
        memset(l, 0, sizeof *l);
        if (q->d->nodes[o].type != SJ_OBJ) {
            return fail("leg %d must be an object", i);
        }
        if (check_keys(q, o, "duration_s,move_m,axis,turn_deg") != 0) {
            return -1;
        }
        double dur, turn = 0.0;
        if (req_num(q, o, "duration_s", &dur) != 0) {
            return -1;
        }
        if (!(dur >= 0.01 && dur <= 3600.0)) {
            return fail("leg %d: duration_s must be in 0.01 .. 3600", i);
        }
        int mn = sj_get(q->d, o, "move_m");
        if (!is_null(q->d, mn) && node_vec(q->d, mn, "move_m", l->dp_m, 3, 0) != 0) {
            return -1;
        }
        for (int j = 0; j < 3; j++) {
            if (fabs(l->dp_m[j]) > 1000.0) {
                return fail("leg %d: move_m components must be within +-1000 m", i);
            }
        }
        int nt = opt_num(q, o, "turn_deg", &turn);
        if (nt < 0) {
            return -1;
        }
        if (fabs(turn) > 36000.0) {
            return fail("leg %d: turn_deg must be within +-36000", i);
        }
        if (turn != 0.0) {
            /* parse_axis reads q->root: look at this leg instead */
            req_t lq = *q;
            lq.root = o;
            if (sj_get(q->d, o, "axis") < 0) {
                return fail("leg %d: a turn needs an axis", i);
            }
            if (parse_axis(&lq, l->axis) != 0) {
                return -1;
            }
        } else if (nt == 0 && sj_get(q->d, o, "axis") >= 0) {
            return fail("leg %d: axis given without turn_deg", i);
        }
        l->angle_rad = turn * DEG;
        l->dur_us = (uint64_t)llround(dur * 1e6);
        total_s += (double)l->dur_us * 1e-6;
    }
    if (sim_phys_path(&s->phys, s->t_us, legs, n) != 0) {
        return fail("bad path");
    }
    put_u64(q->r, "t_start_us", s->t_us);
    put_u64(q->r, "t_end_us", s->phys.t_end_us);
    put_num(q->r, "duration_s", total_s);
    return 0;
}

static int cmd_set_temperature(req_t *q)
{
    sim_t *s = &g_sim;
    double c, ramp = 0.0;
    int soak;
    if (check_keys(q, q->root, "cmd,id,c,ramp_c_per_s,soak") != 0 || req_num(q, q->root, "c", &c) != 0 ||
        opt_num(q, q->root, "ramp_c_per_s", &ramp) < 0 || opt_bool(q, q->root, "soak", 0, &soak) != 0) {
        return -1;
    }
    if (c < -100.0 || c > 200.0) {
        return fail("c must be in -100 .. 200");
    }
    if (ramp < 0.0) {
        return fail("ramp_c_per_s must be >= 0");
    }
    if (soak && ramp > 0.0) {
        return fail("a soak puts the board at c at once: give soak or ramp_c_per_s, not both");
    }
    /* every die has seen the old ambient up to now (the models, as before, take the world
     * at their next advance) */
    sim_thermal_sync(&s->thermal, &s->phys, s->t_us);
    if (soak) {
        sim_thermal_soak(&s->thermal, &s->phys, s->t_us, c);
    } else {
        sim_phys_set_temperature(&s->phys, s->t_us, c, ramp);
    }
    put_u64(q->r, "time_us", s->t_us);
    put_num(q->r, "temperature_c", sim_phys_temperature(&s->phys, s->t_us));
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&s->thermal, &s->phys, i, s->t_us);
    }
    put_vec(q->r, "die_temperature_c", die, SIM_DIES);
    return 0;
}

static int cmd_set_thermal(req_t *q)
{
    sim_t *s = &g_sim;
    int enabled;
    double tau[SIM_DIES], heat[SIM_DIES];
    if (check_keys(q, q->root, "cmd,id,enabled,tau_s,self_heat_c") != 0 ||
        opt_bool(q, q->root, "enabled", 1, &enabled) != 0) {
        return -1;
    }
    int tn = sj_get(q->d, q->root, "tau_s"), hn = sj_get(q->d, q->root, "self_heat_c");
    int have_t = !is_null(q->d, tn), have_h = !is_null(q->d, hn);
    if ((have_t && node_vec(q->d, tn, "tau_s", tau, SIM_DIES, 1) != 0) ||
        (have_h && node_vec(q->d, hn, "self_heat_c", heat, SIM_DIES, 1) != 0)) {
        return -1;
    }
    for (int i = 0; i < SIM_DIES; i++) {
        if (have_t && !(tau[i] >= 1.0 && tau[i] <= 1e6)) {
            return fail("tau_s must be in 1 .. 1e6 s");
        }
        if (have_h && !(heat[i] >= -50.0 && heat[i] <= 100.0)) {
            return fail("self_heat_c must be in -50 .. 100 degC");
        }
    }
    if (sim_thermal_set(&s->thermal, &s->phys, s->t_us, enabled, have_t ? tau : NULL,
                        have_h ? heat : NULL) != 0) {
        return fail("bad thermal figures");
    }
    put_u64(q->r, "time_us", s->t_us);
    put_thermal(q->r);
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&s->thermal, &s->phys, i, s->t_us);
    }
    put_vec(q->r, "die_temperature_c", die, SIM_DIES);
    return 0;
}

static int cmd_set_speed(req_t *q)
{
    double v;
    if (check_keys(q, q->root, "cmd,id,speed") != 0 || req_num(q, q->root, "speed", &v) != 0) {
        return -1;
    }
    if (v < 0.0 || v > 1e6) {
        return fail("speed must be in 0 .. 1e6 (0 = as fast as possible)");
    }
    sim_set_speed(v);
    put_num(q->r, "speed", v);
    return 0;
}

/* Returns 1: deferred. */
static int cmd_wait(req_t *q)
{
    double sec;
    if (check_keys(q, q->root, "cmd,id,device_s") != 0 || req_num(q, q->root, "device_s", &sec) != 0) {
        return -1;
    }
    if (sec < 0.0 || sec > 1e7) {
        return fail("device_s must be in 0 .. 1e7");
    }
    q->c->wait = WAIT_TIME;
    q->c->wait_until = g_sim.t_us + (uint64_t)llround(sec * 1e6);
    if (g_sim.lockstep) { /* a run of that length */
        q->c->wait = WAIT_RUN;
        q->c->run_stop = WAIT_NONE;
        q->c->run_link_rx = 0;
    }
    return 1;
}

/* The wait_idle condition of `kind` (WAIT_IDLE, _TEMP, _DIES) at the current device time. */
static int idle_reached(int kind, double tol_c)
{
    sim_t *s = &g_sim;
    int idle = !sim_phys_moving(&s->phys, s->t_us);
    if (kind == WAIT_IDLE) {
        return idle;
    }
    idle = idle && sim_phys_temperature(&s->phys, s->t_us) == s->phys.temp_target_c;
    if (kind == WAIT_IDLE_DIES) {
        idle = idle && sim_thermal_settle_time(&s->thermal, &s->phys, s->t_us, tol_c) <= s->t_us;
    }
    return idle;
}

/* The next device time the wait_idle condition of `kind` may start to hold (a move's or a
 * ramp's end, the dies' settling), UINT64_MAX when nothing is due. */
static uint64_t idle_next(int kind, double tol_c)
{
    sim_t *s = &g_sim;
    uint64_t t = sim_phys_next_event(&s->phys, s->t_us);
    if (kind == WAIT_IDLE_DIES) {
        uint64_t d = sim_thermal_settle_time(&s->thermal, &s->phys, s->t_us, tol_c);
        if (d > s->t_us && d < t) {
            t = d;
        }
    }
    return t;
}

/* Returns 1: deferred. */
static int cmd_run(req_t *q)
{
    double until, rx = 0.0, tol = 0.0;
    int ns, nt;
    if (!g_sim.lockstep) {
        return fail("run is a command of the lockstep clock (this device runs on the real-time clock)");
    }
    if (check_keys(q, q->root, "cmd,id,until_us,stop,die_tolerance_c,link_rx") != 0 ||
        req_num(q, q->root, "until_us", &until) != 0 || opt_num(q, q->root, "link_rx", &rx) < 0 ||
        (nt = opt_num(q, q->root, "die_tolerance_c", &tol)) < 0) {
        return -1;
    }
    if (!(until >= 0.0 && until < 1.8e19) || !(rx >= 0.0 && rx < 1.8e19)) {
        return fail("until_us and link_rx must be counts >= 0");
    }
    int stop = WAIT_NONE;
    ns = sj_get(q->d, q->root, "stop");
    if (ns >= 0 && !is_null(q->d, ns)) {
        const char *v = q->d->nodes[ns].type == SJ_STR ? q->d->nodes[ns].str : "";
        stop = !strcmp(v, "idle") ? WAIT_IDLE : !strcmp(v, "temperature") ? WAIT_IDLE_TEMP
             : !strcmp(v, "dies") ? WAIT_IDLE_DIES : -1;
        if (stop < 0) {
            return fail("stop must be \"idle\", \"temperature\" or \"dies\"");
        }
    }
    if (nt && (stop != WAIT_IDLE_DIES || !(tol > 0.0 && tol <= 100.0))) {
        return fail("die_tolerance_c goes with stop \"dies\" and must be in (0, 100] degC");
    }
    if (stop == WAIT_IDLE_DIES && !nt) {
        return fail("stop \"dies\" needs die_tolerance_c");
    }
    q->c->wait = WAIT_RUN;
    q->c->run_stop = stop;
    q->c->wait_tol_c = tol;
    q->c->wait_until = (uint64_t)until;
    q->c->run_link_rx = (uint64_t)rx;
    return 1;
}

static int cmd_wait_idle(req_t *q)
{
    int temp;
    double tol = 0.0;
    int nt;
    if (check_keys(q, q->root, "cmd,id,temperature,die_tolerance_c") != 0 ||
        opt_bool(q, q->root, "temperature", 0, &temp) != 0 ||
        (nt = opt_num(q, q->root, "die_tolerance_c", &tol)) < 0) {
        return -1;
    }
    if (nt && !(tol > 0.0 && tol <= 100.0)) {
        return fail("die_tolerance_c must be in (0, 100] degC");
    }
    q->c->wait = nt ? WAIT_IDLE_DIES : temp ? WAIT_IDLE_TEMP : WAIT_IDLE;
    q->c->wait_tol_c = tol;
    if (g_sim.lockstep) { /* a run to the first time it holds (at most 1e7 s) */
        q->c->run_stop = q->c->wait;
        q->c->wait = WAIT_RUN;
        q->c->wait_until = g_sim.t_us + 10000000000000ull;
        q->c->run_link_rx = 0;
    }
    return 1;
}

static int parse_accel_truth(req_t *q, int n, adxl355_truth_t *t, double st[3])
{
    const sj_doc_t *d = q->d;
    if (d->nodes[n].type != SJ_OBJ) {
        return fail("accel must be an object");
    }
    if (check_keys(q, n, "m,bias_mps2,noise_n,rw_k,bias_tc,scale_tc,bias_tc2,bias_tc3,hysteresis,"
                         "hysteresis_width_c,st_force_g") != 0) {
        return -1;
    }
    int k;
    if ((k = sj_get(d, n, "m")) >= 0 && node_mat3(d, k, "accel.m", t->m) != 0) {
        return -1;
    }
    static const char *names[] = {"bias_mps2", "noise_n", "rw_k", "bias_tc", "scale_tc", "bias_tc2",
                                  "bias_tc3", "hysteresis", "hysteresis_width_c", "st_force_g"};
    double *dst[] = {t->bias_mps2, t->noise_n, t->rw_k, t->bias_tc, t->scale_tc, t->bias_tc2,
                     t->bias_tc3, t->hysteresis, t->hysteresis_width_c, st};
    for (int i = 0; i < 10; i++) {
        if ((k = sj_get(d, n, names[i])) >= 0 && node_vec(d, k, names[i], dst[i], 3, 1) != 0) {
            return -1;
        }
    }
    for (int i = 0; i < 3; i++) {
        if (t->noise_n[i] < 0.0 || t->rw_k[i] < 0.0) {
            return fail("accel noise_n and rw_k must be >= 0");
        }
        if (!(t->hysteresis_width_c[i] >= 0.0 && t->hysteresis_width_c[i] <= 50.0)) {
            return fail("accel hysteresis_width_c must be in 0 .. 50 degC");
        }
    }
    return 0;
}

static int parse_gyro_truth(req_t *q, int n, sim_adxrs450_truth_t *t, const char *who)
{
    const sj_doc_t *d = q->d;
    if (is_null(d, n)) {
        return 0;
    }
    if (d->nodes[n].type != SJ_OBJ) {
        return fail("%s must be an object or null", who);
    }
    if (check_keys(q, n, "sens,bias_rad_s,noise_n,bias_rw_k,bias_instability_rad_s,bias_tempco_rad_s_per_c,"
                         "scale_tempco_per_c,gsens_rad_s_per_mps2,bias_tc2,bias_tc3,hysteresis,"
                         "hysteresis_width_c") != 0) {
        return -1;
    }
    int k;
    if ((k = sj_get(d, n, "sens")) >= 0 && node_vec(d, k, "sens", t->sens, 3, 0) != 0) {
        return -1;
    }
    if ((k = sj_get(d, n, "gsens_rad_s_per_mps2")) >= 0 &&
        node_vec(d, k, "gsens_rad_s_per_mps2", t->gsens_rad_s_per_mps2, 3, 0) != 0) {
        return -1;
    }
    static const char *names[] = {"bias_rad_s", "noise_n", "bias_rw_k", "bias_tempco_rad_s_per_c",
                                  "scale_tempco_per_c", "bias_tc2", "bias_tc3", "hysteresis",
                                  "hysteresis_width_c", "bias_instability_rad_s"};
    double *dst[] = {&t->bias_rad_s, &t->noise_n, &t->bias_rw_k, &t->bias_tempco_rad_s_per_c,
                     &t->scale_tempco_per_c, &t->bias_tc2, &t->bias_tc3, &t->hysteresis,
                     &t->hysteresis_width_c, &t->bias_instability_rad_s};
    for (int i = 0; i < 10; i++) {
        if ((k = sj_get(d, n, names[i])) >= 0 && node_num(d, k, names[i], dst[i]) != 0) {
            return -1;
        }
    }
    if (t->noise_n < 0.0 || t->bias_rw_k < 0.0 || t->bias_instability_rad_s < 0.0) {
        return fail("gyro noise_n, bias_rw_k and bias_instability_rad_s must be >= 0");
    }
    if (!(t->hysteresis_width_c >= 0.0 && t->hysteresis_width_c <= 50.0)) {
        return fail("gyro hysteresis_width_c must be in 0 .. 50 degC");
    }
    return 0;
}

static int cmd_set_truth(req_t *q)
{
    sim_t *s = &g_sim;
    const sj_doc_t *d = q->d;
    if (check_keys(q, q->root, "cmd,id,accel,gyro") != 0) {
        return -1;
    }
    adxl355_truth_t at;
    adxl355_model_get_truth(&s->accel, &at);
    double st[3];
    memcpy(st, s->accel.st_force_g, sizeof st);
    sim_adxrs450_truth_t gt[3];
    for (int i = 0; i < 3; i++) {
        gt[i] = *sim_adxrs450_get_truth(&s->gyro[i]);
    }
    int an = sj_get(d, q->root, "accel"), gn = sj_get(d, q->root, "gyro");
    if (!is_null(d, an) && parse_accel_truth(q, an, &at, st) != 0) {
        return -1;
    }
    if (!is_null(d, gn)) {
        if (d->nodes[gn].type == SJ_ARR) {
            if (d->nodes[gn].count > 3) {
                return fail("gyro: at most 3 entries (x, y, z)");
            }
            for (int i = 0; i < d->nodes[gn].count; i++) {
                if (parse_gyro_truth(q, sj_at(d, gn, i), &gt[i], "gyro[i]") != 0) {
                    return -1;
                }
            }
        } else if (d->nodes[gn].type == SJ_OBJ) {
            if (check_keys(q, gn, "x,y,z") != 0) {
                return -1;
            }
            static const char *ax[] = {"x", "y", "z"};
            for (int i = 0; i < 3; i++) {
                if (parse_gyro_truth(q, sj_get(d, gn, ax[i]), &gt[i], ax[i]) != 0) {
                    return -1;
                }
            }
        } else {
            return fail("gyro must be a list of 3 objects or {x, y, z}");
        }
    }
    sim_models_sync(); /* the old truth holds up to now */
    adxl355_model_set_truth(&s->accel, &at);
    memcpy(s->accel.st_force_g, st, sizeof st);
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_set_truth(&s->gyro[i], &gt[i]);
    }
    return 0;
}

static int cmd_randomize_truth(req_t *q)
{
    double seed = (double)g_sim.seed;
    if (check_keys(q, q->root, "cmd,id,seed") != 0 || opt_num(q, q->root, "seed", &seed) < 0) {
        return -1;
    }
    if (seed < 0 || seed > 18446744073709549568.0 || seed != floor(seed)) {
        return fail("seed must be a non-negative integer");
    }
    sim_models_sync();
    sim_randomize_truth((uint64_t)seed);
    put_u64(q->r, "seed", (uint64_t)seed);
    return 0;
}

static int cmd_get_truth(req_t *q)
{
    sim_t *s = &g_sim;
    sj_buf_t *r = q->r;
    if (check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    /* Current true biases. The accelerometer can be advanced to now at no cost to its
     * noise sequence (it draws per output sample); a gyro draws its random walk per
     * advance, so it only gets the current world (temperature) at its own time. */
    sim_model_advance(IB_CS_ACCEL);
    sim_world_t w;
    sim_phys_specific_force(&s->phys, s->t_us, w.specific_force_mps2);
    sim_phys_omega(&s->phys, s->t_us, w.rate_rad_s);
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die(&s->thermal, &s->phys, i, s->t_us);
    }

    put_u64(r, "time_us", s->t_us);
    adxl355_truth_t at;
    adxl355_model_get_truth(&s->accel, &at);
    double tb[3]; /* adxl355_model_true_bias() at the current temperature (the model only
                     takes the temperature when it advances, and time may not have moved) */
    for (int i = 0; i < 3; i++) {
        tb[i] = at.bias_mps2[i] + adxl355_truth_thermal_bias(&at, i, die[IB_CS_ACCEL], s->accel.hyst_h[i]) +
                s->accel.rw_bias[i];
    }
    sj_key(r, "accel");
    sj_raw(r, "{");
    sj_key(r, "m");
    sj_raw(r, "[");
    for (int i = 0; i < 3; i++) {
        if (i) {
            sj_raw(r, ", ");
        }
        sj_vec(r, at.m[i], 3);
    }
    sj_raw(r, "]");
    put_vec(r, "bias_mps2", at.bias_mps2, 3);
    put_vec(r, "noise_n", at.noise_n, 3);
    put_vec(r, "rw_k", at.rw_k, 3);
    put_vec(r, "bias_tc", at.bias_tc, 3);
    put_vec(r, "scale_tc", at.scale_tc, 3);
    put_vec(r, "bias_tc2", at.bias_tc2, 3);
    put_vec(r, "bias_tc3", at.bias_tc3, 3);
    put_vec(r, "hysteresis", at.hysteresis, 3);
    put_vec(r, "hysteresis_width_c", at.hysteresis_width_c, 3);
    put_vec(r, "hysteresis_branch", s->accel.hyst_h, 3);
    put_num(r, "die_temperature_c", die[IB_CS_ACCEL]);
    put_vec(r, "st_force_g", s->accel.st_force_g, 3);
    put_vec(r, "true_bias_mps2", tb, 3);
    put_vec(r, "rw_bias_mps2", s->accel.rw_bias, 3);
    put_bool(r, "missing", s->accel.fault.missing);
    sj_raw(r, "}");
    sj_key(r, "gyro");
    sj_raw(r, "[");
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_t *m = &s->gyro[i];
        w.temperature_c = die[1 + i];
        sim_adxrs450_advance(m, m->t_us, &w); /* same time: only the world changes */
        const sim_adxrs450_truth_t *t = sim_adxrs450_get_truth(m);
        if (i) {
            sj_raw(r, ", ");
        }
        sj_raw(r, "{");
        put_u64(r, "axis", (uint64_t)m->axis);
        put_vec(r, "sens", t->sens, 3);
        put_num(r, "bias_rad_s", t->bias_rad_s);
        put_num(r, "noise_n", t->noise_n);
        put_num(r, "bias_rw_k", t->bias_rw_k);
        put_num(r, "bias_instability_rad_s", t->bias_instability_rad_s);
        put_num(r, "bias_tempco_rad_s_per_c", t->bias_tempco_rad_s_per_c);
        put_num(r, "scale_tempco_per_c", t->scale_tempco_per_c);
        put_vec(r, "gsens_rad_s_per_mps2", t->gsens_rad_s_per_mps2, 3);
        put_num(r, "bias_tc2", t->bias_tc2);
        put_num(r, "bias_tc3", t->bias_tc3);
        put_num(r, "hysteresis", t->hysteresis);
        put_num(r, "hysteresis_width_c", t->hysteresis_width_c);
        put_num(r, "hysteresis_branch", m->hyst_h);
        put_num(r, "die_temperature_c", die[1 + i]);
        put_num(r, "true_bias_rad_s", sim_adxrs450_true_bias_rad_s(m));
        put_num(r, "rw_bias_rad_s", m->bias_rw_rad_s);
        put_num(r, "bi_bias_rad_s", sim_adxrs450_flicker_bias_rad_s(m));
        put_u64(r, "serial", m->serial);
        put_bool(r, "missing", m->missing);
        put_u64(r, "persistent_faults", m->fault_persistent);
        sj_raw(r, "}");
    }
    sj_raw(r, "]");
    put_thermal(r);
    sj_key(r, "world");
    sj_raw(r, "{");
    put_world(r);
    sj_raw(r, "}");
    return 0;
}

static int cmd_inject(req_t *q)
{
    sim_t *s = &g_sim;
    const sj_doc_t *d = q->d;
    int fn = sj_get(d, q->root, "fault");
    if (fn < 0 || d->nodes[fn].type != SJ_STR) {
        return fail("missing 'fault'");
    }
    const char *f = d->nodes[fn].str;
    double count = 0, bits = 0, mask = 1, prob = 0;
    int cs, on, persistent;
    if (!strcmp(f, "gyro_fault_bits")) {
        if (check_keys(q, q->root, "cmd,id,fault,sensor,bits,persistent") != 0 ||
            (cs = sensor_cs(q, q->root, 0)) < 0 || req_num(q, q->root, "bits", &bits) != 0 ||
            opt_bool(q, q->root, "persistent", 0, &persistent) != 0) {
            return -1;
        }
        if (bits < 0 || bits > 0xFFFF || bits != floor(bits) || ((unsigned)bits & ~SIM_ADXRS450_FAULT_ALL)) {
            return fail("bits must be FAULT register bits (mask 0x%03X)", SIM_ADXRS450_FAULT_ALL);
        }
        if (persistent) {
            sim_adxrs450_set_persistent_faults(&s->gyro[cs - 1], (uint16_t)bits);
        } else {
            sim_adxrs450_inject_faults(&s->gyro[cs - 1], (uint16_t)bits);
        }
    } else if (!strcmp(f, "gyro_parity")) {
        if (check_keys(q, q->root, "cmd,id,fault,sensor,count,mask") != 0 ||
            (cs = sensor_cs(q, q->root, 0)) < 0 || req_num(q, q->root, "count", &count) != 0 ||
            opt_num(q, q->root, "mask", &mask) < 0) {
            return -1;
        }
        if (count < 0 || count > 1e9 || mask < 0 || mask > 4294967295.0) {
            return fail("bad count or mask");
        }
        sim_adxrs450_corrupt_responses(&s->gyro[cs - 1], (uint32_t)count, (uint32_t)mask);
    } else if (!strcmp(f, "missing")) {
        if (check_keys(q, q->root, "cmd,id,fault,sensor,on") != 0 || (cs = sensor_cs(q, q->root, 1)) < 0 ||
            opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        if (cs == IB_CS_ACCEL) {
            adxl355_model_set_missing(&s->accel, on);
        } else {
            sim_adxrs450_set_missing(&s->gyro[cs - 1], on);
        }
    } else if (!strcmp(f, "spi_error")) {
        if (check_keys(q, q->root, "cmd,id,fault,sensor,count,probability") != 0 ||
            (cs = sensor_cs(q, q->root, 1)) < 0) {
            return -1;
        }
        int hc = opt_num(q, q->root, "count", &count), hp = opt_num(q, q->root, "probability", &prob);
        if (hc < 0 || hp < 0) {
            return -1;
        }
        if (!hc && !hp) {
            return fail("give count or probability");
        }
        if (count < 0 || count > 1e9 || prob < 0.0 || prob > 1.0) {
            return fail("count must be >= 0, probability in 0 .. 1");
        }
        if (hc) {
            s->spi_faults.error_count[cs] = (uint32_t)count;
        }
        if (hp) {
            s->spi_faults.error_prob[cs] = prob;
        }
    } else if (!strcmp(f, "link_drop") || !strcmp(f, "link_flip")) {
        if (check_keys(q, q->root, "cmd,id,fault,count") != 0 || req_num(q, q->root, "count", &count) != 0) {
            return -1;
        }
        if (count < 0 || count > 1e9) {
            return fail("count must be in 0 .. 1e9");
        }
        if (f[5] == 'd') {
            s->link.drop_remaining = (uint32_t)count;
        } else {
            s->link.flip_remaining = (uint32_t)count;
        }
    } else if (!strcmp(f, "accel_stuck") || !strcmp(f, "accel_shadow")) {
        if (check_keys(q, q->root, "cmd,id,fault,on") != 0 || opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        if (f[6] == 's' && f[7] == 't') {
            adxl355_model_set_stuck_data(&s->accel, on);
        } else {
            adxl355_model_set_shadow_corrupt(&s->accel, on);
        }
    } else if (!strcmp(f, "accel_wrong_id")) {
        /* a part that answers with another PARTID (0xEE instead of 0xED): a different or
         * counterfeit chip; takes effect at the driver's next probe (power cut / reboot) */
        if (check_keys(q, q->root, "cmd,id,fault,on") != 0 || opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        s->accel.id[2] = on ? 0xEE : 0xED;
    } else if (!strcmp(f, "clear")) {
        if (check_keys(q, q->root, "cmd,id,fault") != 0) {
            return -1;
        }
        s->accel.fault.missing = s->accel.fault.stuck_data = s->accel.fault.shadow_corrupt = 0;
        s->accel.id[2] = 0xED;
        for (int i = 0; i < 3; i++) {
            sim_adxrs450_set_persistent_faults(&s->gyro[i], 0);
            sim_adxrs450_corrupt_responses(&s->gyro[i], 0, 0);
            sim_adxrs450_set_missing(&s->gyro[i], 0);
        }
        memset(s->spi_faults.error_count, 0, sizeof s->spi_faults.error_count);
        memset(s->spi_faults.error_prob, 0, sizeof s->spi_faults.error_prob);
        s->link.drop_remaining = s->link.flip_remaining = 0;
        s->flash.cut_after = 0;
    } else {
        return fail("unknown fault '%s' (gyro_fault_bits, gyro_parity, missing, spi_error, "
                    "link_drop, link_flip, accel_stuck, accel_shadow, accel_wrong_id, clear)", f);
    }
    sj_key(q->r, "fault");
    sj_str(q->r, f);
    return 0;
}

static int cmd_power_cut(req_t *q)
{
    sim_t *s = &g_sim;
    double n = 0;
    if (check_keys(q, q->root, "cmd,id,after_flash_ops") != 0 ||
        opt_num(q, q->root, "after_flash_ops", &n) < 0) {
        return -1;
    }
    if (n < 0 || n > 1e9 || n != floor(n)) {
        return fail("after_flash_ops must be a whole number >= 1 (or omitted for now)");
    }
    if (n == 0) {
        s->flash.cut_after = 0;
        sim_request_reset(SIM_RESET_POWER_CUT); /* outside the core: taken by the loop */
        sj_key(q->r, "when");
        sj_str(q->r, "now");
    } else {
        s->flash.cut_after = (int64_t)n;
        sj_key(q->r, "when");
        sj_printf(q->r, "\"during flash op %lld from now\"", (long long)n);
    }
    return 0;
}

static int cmd_flash_ops(req_t *q)
{
    if (check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    put_u64(q->r, "flash_ops", g_sim.flash.ops_since_boot);
    put_u64(q->r, "flash_ops_total", g_sim.flash.ops_total);
    put_u64(q->r, "power_cut_armed", (uint64_t)(g_sim.flash.cut_after > 0 ? g_sim.flash.cut_after : 0));
    put_u64(q->r, "power_cuts", g_sim.power_cuts);
    put_u64(q->r, "boots", g_sim.boots);
    return 0;
}

static int cmd_quit(req_t *q)
{
    if (check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    g_sim.quit = 1;
    return 0;
}

static const struct {
    const char *name;
    int (*fn)(req_t *q);
} g_cmds[] = {
    {"status", cmd_status},
    {"set_orientation", cmd_set_orientation},
    {"rotate", cmd_rotate},
    {"set_rate", cmd_set_rate},
    {"path", cmd_path},
    {"set_temperature", cmd_set_temperature},
    {"set_thermal", cmd_set_thermal},
    {"set_speed", cmd_set_speed},
    {"wait", cmd_wait},
    {"wait_idle", cmd_wait_idle},
    {"run", cmd_run},
    {"set_truth", cmd_set_truth},
    {"randomize_truth", cmd_randomize_truth},
    {"get_truth", cmd_get_truth},
    {"inject", cmd_inject},
    {"power_cut", cmd_power_cut},
    {"flash_ops", cmd_flash_ops},
    {"quit", cmd_quit},
};

/* ------------------------------------------------------------------ dispatch */

static void send_line(conn_t *c, sj_buf_t *b)
{
    sj_raw(b, "\n");
    if (b->oom) {
        return;
    }
    sj_raw(&c->out, b->p);
    conn_flush(c);
}

static void id_json(const sj_doc_t *d, int n, char *out, size_t cap)
{
    out[0] = '\0';
    if (n < 0) {
        return;
    }
    sj_buf_t b = {0};
    if (d->nodes[n].type == SJ_NUM) {
        sj_num(&b, d->nodes[n].num);
    } else if (d->nodes[n].type == SJ_STR) {
        sj_str(&b, d->nodes[n].str);
    }
    if (b.p && b.len < cap) {
        memcpy(out, b.p, b.len + 1);
    }
    sj_buf_free(&b);
}

static sj_doc_t g_doc;

static void handle_line(conn_t *c, char *line)
{
    sj_buf_t r = {0};
    char id[80] = "";
    int rc;
    int root = sj_parse(&g_doc, line);
    if (root < 0) {
        rc = fail("bad JSON: %s", g_doc.error ? g_doc.error : "?");
    } else if (g_doc.nodes[root].type != SJ_OBJ) {
        rc = fail("a request is a JSON object");
    } else {
        id_json(&g_doc, sj_get(&g_doc, root, "id"), id, sizeof id);
        int cn = sj_get(&g_doc, root, "cmd");
        if (cn < 0 || g_doc.nodes[cn].type != SJ_STR) {
            rc = fail("missing \"cmd\"");
        } else {
            const char *name = g_doc.nodes[cn].str;
            rc = fail("unknown cmd '%s'", name);
            for (size_t i = 0; i < sizeof g_cmds / sizeof g_cmds[0]; i++) {
                if (!strcmp(name, g_cmds[i].name)) {
                    sj_raw(&r, "{\"ok\": true");
                    req_t q = {&g_doc, root, &r, c};
                    rc = g_cmds[i].fn(&q);
                    break;
                }
            }
        }
    }
    if (rc == 1) { /* deferred */
        snprintf(c->wait_id, sizeof c->wait_id, "%s", id);
        sj_buf_free(&r);
        return;
    }
    if (rc != 0) {
        r.len = 0;
        sj_raw(&r, "{\"ok\": false, \"error\": ");
        sj_str(&r, g_err);
    }
    if (id[0]) {
        sj_key(&r, "id");
        sj_raw(&r, id);
    }
    sj_raw(&r, "}");
    send_line(c, &r);
    sj_buf_free(&r);
}

static void process_lines(conn_t *c)
{
    while (c->fd >= 0 && c->wait == WAIT_NONE && !g_sim.quit) {
        char *nl = memchr(c->in, '\n', c->in_len);
        if (nl == NULL) {
            if (c->in_len >= CTL_LINE_MAX) {
                sj_buf_t r = {0};
                sj_raw(&r, "{\"ok\": false, \"error\": \"request line too long\"}");
                send_line(c, &r);
                sj_buf_free(&r);
                c->in_len = 0;
            }
            return;
        }
        *nl = '\0';
        size_t used = (size_t)(nl - c->in) + 1;
        if (nl > c->in && nl[-1] == '\r') {
            nl[-1] = '\0';
        }
        char *line = c->in;
        while (*line == ' ' || *line == '\t') {
            line++;
        }
        if (*line) {
            handle_line(c, line);
        }
        if (c->fd < 0) {
            return;
        }
        memmove(c->in, c->in + used, c->in_len - used);
        c->in_len -= used;
    }
}

static void finish_wait(conn_t *c)
{
    sj_buf_t r = {0};
    sj_raw(&r, "{\"ok\": true");
    put_u64(&r, "time_us", g_sim.t_us);
    if (c->wait == WAIT_RUN) {
        put_u64(&r, "link_tx", g_sim.link.conn_tx);
        put_bool(&r, "done", c->run_stop != WAIT_NONE && idle_reached(c->run_stop, c->wait_tol_c));
    }
    if (c->wait_id[0]) {
        sj_key(&r, "id");
        sj_raw(&r, c->wait_id);
    }
    sj_raw(&r, "}");
    c->wait = WAIT_NONE;
    send_line(c, &r);
    sj_buf_free(&r);
    process_lines(c);
}

void sim_control_check_waits(void)
{
    sim_t *s = &g_sim;
    for (int i = 0; i < CTL_MAX_CONN; i++) {
        conn_t *c = &g_conn[i];
        if (c->fd < 0 || c->wait == WAIT_NONE) {
            continue;
        }
        int done;
        if (c->wait == WAIT_TIME) {
            done = s->t_us >= c->wait_until;
        } else if (c->wait == WAIT_RUN) {
            /* ran to its end (or its condition holds) and every link byte up to now is out */
            done = sim_control_run_target(NULL) == 1 && c == run_conn() &&
                   (s->t_us >= c->wait_until || (c->run_stop != WAIT_NONE && idle_reached(c->run_stop, c->wait_tol_c))) &&
                   sim_link_staged(&s->link) == 0;
        } else {
            done = idle_reached(c->wait, c->wait_tol_c);
        }
        if (done) {
            finish_wait(c);
        }
    }
}

uint64_t sim_control_next_deadline(void)
{
    uint64_t t = UINT64_MAX;
    for (int i = 0; i < CTL_MAX_CONN; i++) {
        if (g_conn[i].fd >= 0 && g_conn[i].wait == WAIT_TIME && g_conn[i].wait_until < t) {
            t = g_conn[i].wait_until;
        }
        if (g_conn[i].fd >= 0 && g_conn[i].wait == WAIT_IDLE_DIES) {
            /* when the dies will have settled (a ramp's end is a world event of its own) */
            uint64_t d = sim_thermal_settle_time(&g_sim.thermal, &g_sim.phys, g_sim.t_us, g_conn[i].wait_tol_c);
            if (d > g_sim.t_us && d < t) {
                t = d;
            }
        }
    }
    return t;
}

/* The connection whose run is granted: the first one with a run pending. */
static conn_t *run_conn(void)
{
    for (int i = 0; i < CTL_MAX_CONN; i++) {
        if (g_conn[i].fd >= 0 && g_conn[i].wait == WAIT_RUN) {
            return &g_conn[i];
        }
    }
    return NULL;
}

int sim_control_run_target(uint64_t *target)
{
    sim_t *s = &g_sim;
    conn_t *c = run_conn();
    if (c == NULL) {
        return 0;
    }
    /* the host's link bytes first (or as many as the device can hold) */
    if (s->link.conn_rx < c->run_link_rx && (s->link.rx_head - s->link.rx_tail) < SIM_RX_RING) {
        return 2;
    }
    if (target != NULL) {
        uint64_t t = c->wait_until;
        if (c->run_stop != WAIT_NONE && !idle_reached(c->run_stop, c->wait_tol_c)) {
            uint64_t e = idle_next(c->run_stop, c->wait_tol_c);
            if (e < t) {
                t = e;
            }
        } else if (c->run_stop != WAIT_NONE) {
            t = s->t_us; /* holds already: no further */
        }
        *target = t < s->t_us ? s->t_us : t;
    }
    return 1;
}

static void accept_conn(void)
{
    for (;;) {
        int fd = accept4(g_sim.control_listen, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
        if (fd < 0) {
            return;
        }
        conn_t *c = NULL;
        for (int i = 0; i < CTL_MAX_CONN; i++) {
            if (g_conn[i].fd < 0) {
                c = &g_conn[i];
                break;
            }
        }
        if (c == NULL) {
            const char *msg = "{\"ok\": false, \"error\": \"too many control connections\"}\n";
            (void)!send(fd, msg, strlen(msg), MSG_NOSIGNAL);
            close(fd);
            continue;
        }
        memset(c, 0, sizeof *c);
        c->in = malloc(CTL_LINE_MAX + 1);
        if (c->in == NULL) {
            close(fd);
            c->fd = -1;
            continue;
        }
        c->fd = fd;
    }
}

static void conn_read(conn_t *c)
{
    for (;;) {
        if (c->in_len >= CTL_LINE_MAX) {
            break;
        }
        ssize_t n = recv(c->fd, c->in + c->in_len, CTL_LINE_MAX - c->in_len, 0);
        if (n > 0) {
            c->in_len += (size_t)n;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            break;
        }
        /* EOF or error: answer what is complete, then close */
        process_lines(c);
        conn_flush(c);
        conn_close(c);
        return;
    }
    process_lines(c);
}

void sim_control_handle(struct pollfd *pfd, int n)
{
    for (int i = 0; i < n; i++) {
        if (!pfd[i].revents) {
            continue;
        }
        if (g_map[i] < 0) {
            accept_conn();
            continue;
        }
        conn_t *c = &g_conn[g_map[i]];
        if (c->fd != pfd[i].fd) {
            continue;
        }
        if (pfd[i].revents & POLLOUT) {
            conn_flush(c);
        }
        if (c->fd >= 0 && (pfd[i].revents & (POLLIN | POLLHUP | POLLERR))) {
            conn_read(c);
        }
        if (g_sim.quit) {
            return;
        }
    }
}
