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
#include "sim_control_priv.h"

static conn_t g_conn[CTL_MAX_CONN];
static int g_map[CTL_MAX_CONN + 1]; /* pollfd slot -> connection index, -1 = listener */
static char g_err[256];

static conn_t *run_conn(void);

int ctl_fail(const char *fmt, ...)
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

static const struct {
    const char *name;
    int (*fn)(req_t *q);
} g_cmds[] = {
    {"status", ctl_cmd_status},
    {"set_orientation", ctl_cmd_set_orientation},
    {"rotate", ctl_cmd_rotate},
    {"set_rate", ctl_cmd_set_rate},
    {"path", ctl_cmd_path},
    {"set_temperature", ctl_cmd_set_temperature},
    {"set_thermal", ctl_cmd_set_thermal},
    {"set_speed", ctl_cmd_set_speed},
    {"wait", ctl_cmd_wait},
    {"wait_idle", ctl_cmd_wait_idle},
    {"run", ctl_cmd_run},
    {"set_truth", ctl_cmd_set_truth},
    {"randomize_truth", ctl_cmd_randomize_truth},
    {"get_truth", ctl_cmd_get_truth},
    {"inject", ctl_cmd_inject},
    {"power_cut", ctl_cmd_power_cut},
    {"flash_ops", ctl_cmd_flash_ops},
    {"quit", ctl_cmd_quit},
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
        rc = ctl_fail("bad JSON: %s", g_doc.error ? g_doc.error : "?");
    } else if (g_doc.nodes[root].type != SJ_OBJ) {
        rc = ctl_fail("a request is a JSON object");
    } else {
        id_json(&g_doc, sj_get(&g_doc, root, "id"), id, sizeof id);
        int cn = sj_get(&g_doc, root, "cmd");
        if (cn < 0 || g_doc.nodes[cn].type != SJ_STR) {
            rc = ctl_fail("missing \"cmd\"");
        } else {
            const char *name = g_doc.nodes[cn].str;
            rc = ctl_fail("unknown cmd '%s'", name);
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
    ctl_put_u64(&r, "time_us", g_sim.t_us);
    if (c->wait == WAIT_RUN) {
        ctl_put_u64(&r, "link_tx", g_sim.link.conn_tx);
        ctl_put_bool(&r, "done", c->run_stop != WAIT_NONE && ctl_idle_reached(c->run_stop, c->wait_tol_c));
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
                   (s->t_us >= c->wait_until || (c->run_stop != WAIT_NONE && ctl_idle_reached(c->run_stop, c->wait_tol_c))) &&
                   sim_link_staged(&s->link) == 0;
        } else {
            done = ctl_idle_reached(c->wait, c->wait_tol_c);
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
        if (c->run_stop != WAIT_NONE && !ctl_idle_reached(c->run_stop, c->wait_tol_c)) {
            uint64_t e = ctl_idle_next(c->run_stop, c->wait_tol_c);
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
