/* sim_control_world.c - the control commands of the world: status, orientation, rotation,
 * paths, temperature and thermal model, speed, waits and the lockstep run. */
#define _GNU_SOURCE
#include "sim_control_priv.h"

/* ------------------------------------------------------------------ commands */

void ctl_put_world(sj_buf_t *r)
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
    ctl_put_vec(r, "gravity_board", g, 3);
    ctl_put_vec(r, "specific_force_mps2", f, 3);
    ctl_put_vec(r, "rate_rad_s", w, 3);
    ctl_put_vec(r, "rate_dps", wd, 3);
    ctl_put_num(r, "temperature_c", sim_phys_temperature(p, t));
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&g_sim.thermal, p, i, t);
    }
    ctl_put_vec(r, "die_temperature_c", die, SIM_DIES);
    ctl_put_num(r, "roll_deg", roll / DEG);
    ctl_put_num(r, "pitch_deg", pitch / DEG);
    ctl_put_num(r, "yaw_deg", yaw / DEG);
    ctl_put_vec(r, "position_m", pos, 3);
    ctl_put_vec(r, "velocity_mps", vel, 3);
    ctl_put_vec(r, "acceleration_mps2", acc, 3);
}

/* "thermal": {enabled, tau_s [4], self_heat_c [4]} (die order: ADXL355, gyro X, Y, Z) */
void ctl_put_thermal(sj_buf_t *r)
{
    const sim_thermal_t *th = &g_sim.thermal;
    sj_key(r, "thermal");
    sj_raw(r, "{");
    ctl_put_bool(r, "enabled", th->enabled);
    ctl_put_vec(r, "tau_s", th->tau_s, SIM_DIES);
    ctl_put_vec(r, "self_heat_c", th->self_heat_c, SIM_DIES);
    sj_raw(r, "}");
}

int ctl_cmd_status(req_t *q)
{
    sim_t *s = &g_sim;
    sj_buf_t *r = q->r;
    const sim_physics_t *p = &s->phys;
    if (ctl_check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    ctl_put_u64(r, "time_us", s->t_us);
    ctl_put_num(r, "time_s", (double)s->t_us * 1e-6);
    ctl_put_bool(r, "streaming", sim_streaming());
    ctl_put_u64(r, "stream_state", s->core.stream_state);
    ctl_put_u64(r, "tick_hz", s->tick_hz);
    ctl_put_num(r, "speed", s->speed);
    ctl_put_world(r);
    int moving = sim_phys_moving(p, s->t_us);
    ctl_put_bool(r, "moving", moving);
    sj_key(r, "move");
    if (p->kind == SIM_MOTION_NONE || (p->kind != SIM_MOTION_RATE && !moving)) {
        sj_raw(r, "null");
    } else {
        sj_raw(r, "{");
        sj_key(r, "kind");
        sj_str(r, p->kind == SIM_MOTION_ROTATE ? "rotate" : p->kind == SIM_MOTION_PATH ? "path" : "rate");
        if (p->kind == SIM_MOTION_PATH) {
            ctl_put_u64(r, "leg", (uint64_t)sim_phys_path_leg(p, s->t_us));
            ctl_put_u64(r, "legs", (uint64_t)p->n_legs);
        } else {
            ctl_put_vec(r, "axis", p->axis, 3);
            ctl_put_num(r, "rate_dps", p->rate_rad_s / DEG);
        }
        if (p->kind != SIM_MOTION_RATE) {
            ctl_put_num(r, "remaining_s", (double)(p->t_end_us - s->t_us) * 1e-6);
            ctl_put_u64(r, "t_end_us", p->t_end_us);
        }
        sj_raw(r, "}");
    }
    ctl_put_bool(r, "temperature_ramping", sim_phys_temperature(p, s->t_us) != p->temp_target_c);
    ctl_put_thermal(r);
    ctl_put_u64(r, "boots", s->boots);
    ctl_put_u64(r, "power_cuts", s->power_cuts);
    ctl_put_u64(r, "reboots", s->reboots);
    ctl_put_u64(r, "flash_ops", s->flash.ops_since_boot);
    ctl_put_u64(r, "flash_ops_total", s->flash.ops_total);
    ctl_put_u64(r, "ticks", s->ticks);
    ctl_put_u64(r, "ticks_missed", s->ticks_missed);
    ctl_put_u64(r, "pacing_slips", s->slips);
    ctl_put_u64(r, "samples_dropped", s->core.stats.samples_dropped); /* by the core: TX ring full */
    ctl_put_u64(r, "spi_transfers", s->spi_transfers);
    double inj[IB_CS_COUNT];
    for (int i = 0; i < IB_CS_COUNT; i++) {
        inj[i] = (double)s->spi_faults.errors_injected[i];
    }
    ctl_put_vec(r, "spi_errors_injected", inj, IB_CS_COUNT);
    sj_key(r, "target");
    sj_str(r, s->target[0] ? s->target : "host");
    if (s->target[0]) { /* the exact ARM image under the emulator (host/imubench/device/arm) */
        sj_key(r, "arm");
        sj_raw(r, "{");
        ctl_put_u64(r, "instructions", s->arm_instructions);
        ctl_put_u64(r, "faults", s->arm_faults);
        ctl_put_u64(r, "unmodelled_accesses", s->arm_unmodelled);
        ctl_put_u64(r, "spi_peek_mismatches", s->arm_spi_mismatch);
        ctl_put_num(r, "idle_s", s->arm_idle_s);
        ctl_put_num(r, "sysclk_hz", s->arm_sysclk_hz);
        ctl_put_num(r, "cpi", s->arm_cpi);
        ctl_put_u64(r, "idle_loop_instructions", s->arm_idle_instructions);
        ctl_put_num(r, "busy_wait_s", s->arm_busy_s);
        ctl_put_num(r, "flash_stall_s", s->arm_stall_s);
        ctl_put_num(r, "spi_bus_s", s->arm_spi_bus_s);
        ctl_put_u64(r, "spi_bytes", s->arm_spi_bytes);
        ctl_put_u64(r, "spi_transactions", s->arm_spi_transactions);
        sj_key(r, "instructions_by_range");
        sj_raw(r, "{");
        static const char *const names[5] = {"other", "core", "drivers", "board", "lib"};
        for (int i = 0; i < 5; i++) {
            ctl_put_u64(r, names[i], s->arm_regions[i]);
        }
        sj_raw(r, "}");
        sj_raw(r, "}");
    }
    sim_link_t *l = &s->link;
    sj_key(r, "link");
    sj_raw(r, "{");
    ctl_put_bool(r, "tcp_client", l->tcp_client >= 0);
    ctl_put_u64(r, "tx_queued", sim_link_queued(l));
    ctl_put_u64(r, "tx_staged", sim_link_staged(l));
    ctl_put_u64(r, "tx_free", sim_link_tx_free(l));
    ctl_put_u64(r, "bytes_sent", l->bytes_written_os);
    ctl_put_u64(r, "bytes_discarded", l->bytes_discarded);
    ctl_put_u64(r, "bytes_dropped", l->bytes_dropped);
    ctl_put_u64(r, "bytes_flipped", l->bytes_flipped);
    ctl_put_u64(r, "bytes_received", l->bytes_received);
    ctl_put_u64(r, "drop_pending", l->drop_remaining);
    ctl_put_u64(r, "flip_pending", l->flip_remaining);
    sj_raw(r, "}");
    return 0;
}

int ctl_cmd_set_orientation(req_t *q)
{
    sim_t *s = &g_sim;
    if (ctl_check_keys(q, q->root, "cmd,id,gravity,roll_deg,pitch_deg,yaw_deg") != 0) {
        return -1;
    }
    int gn = sj_get(q->d, q->root, "gravity");
    double roll = 0, pitch = 0, yaw = 0;
    int nr = ctl_opt_num(q, q->root, "roll_deg", &roll);
    int np = ctl_opt_num(q, q->root, "pitch_deg", &pitch);
    int ny = ctl_opt_num(q, q->root, "yaw_deg", &yaw);
    if (nr < 0 || np < 0 || ny < 0) {
        return -1;
    }
    if (!ctl_is_null(q->d, gn)) {
        if (nr || np || ny) {
            return ctl_fail("give either gravity or roll_deg/pitch_deg/yaw_deg, not both");
        }
        double g[3];
        if (ctl_node_vec(q->d, gn, "gravity", g, 3, 0) != 0) {
            return -1;
        }
        if (sim_phys_set_gravity(&s->phys, s->t_us, g) != 0) {
            return ctl_fail("gravity must be a non-zero vector");
        }
    } else if (nr || np || ny) {
        sim_phys_set_rpy(&s->phys, s->t_us, roll * DEG, pitch * DEG, yaw * DEG);
    } else {
        return ctl_fail("give gravity: [x, y, z] or roll_deg/pitch_deg/yaw_deg");
    }
    ctl_put_world(q->r);
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
            return ctl_fail("axis must be \"x\", \"y\", \"z\" (optionally signed) or [x, y, z]");
        }
        return 0;
    }
    if (ctl_node_vec(q->d, n, "axis", axis, 3, 0) != 0) {
        return -1;
    }
    double norm = sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    if (!(norm > 1e-9)) {
        return ctl_fail("axis must be a non-zero vector");
    }
    return 0;
}

int ctl_cmd_rotate(req_t *q)
{
    sim_t *s = &g_sim;
    double axis[3], rate, dur;
    if (ctl_check_keys(q, q->root, "cmd,id,axis,rate_dps,duration_s") != 0 || parse_axis(q, axis) != 0 ||
        ctl_req_num(q, q->root, "rate_dps", &rate) != 0 || ctl_req_num(q, q->root, "duration_s", &dur) != 0) {
        return -1;
    }
    if (dur < 0.0 || dur > 1e6) {
        return ctl_fail("duration_s must be in 0 .. 1e6");
    }
    if (fabs(rate) > 1e5) {
        return ctl_fail("rate_dps out of range");
    }
    if (sim_phys_rotate(&s->phys, s->t_us, axis, rate * DEG, dur) != 0) {
        return ctl_fail("bad rotation");
    }
    ctl_put_u64(q->r, "t_start_us", s->t_us);
    ctl_put_u64(q->r, "t_end_us", s->t_us + (uint64_t)llround(dur * 1e6));
    ctl_put_num(q->r, "angle_deg", rate * dur);
    return 0;
}

int ctl_cmd_set_rate(req_t *q)
{
    sim_t *s = &g_sim;
    double w[3];
    if (ctl_check_keys(q, q->root, "cmd,id,rate_dps,rate_rad_s") != 0) {
        return -1;
    }
    int nd = sj_get(q->d, q->root, "rate_dps"), nr = sj_get(q->d, q->root, "rate_rad_s");
    if ((nd >= 0) == (nr >= 0)) {
        return ctl_fail("give rate_dps: [x, y, z] or rate_rad_s: [x, y, z]");
    }
    if (ctl_node_vec(q->d, nd >= 0 ? nd : nr, nd >= 0 ? "rate_dps" : "rate_rad_s", w, 3, 0) != 0) {
        return -1;
    }
    for (int i = 0; i < 3; i++) {
        w[i] *= nd >= 0 ? DEG : 1.0;
        if (fabs(w[i]) > 1e4) {
            return ctl_fail("rate out of range");
        }
    }
    sim_phys_set_rate(&s->phys, s->t_us, w);
    ctl_put_world(q->r);
    return 0;
}

/* {"cmd": "path", "legs": [{"duration_s": T, "move_m": [dx, dy, dz], "axis": "z",
 *   "turn_deg": A}, ...]}: drive the legs back to back, each rest to rest on a minimum-jerk
 * profile; move_m in the level frame, the turn about a board axis (sim_physics.c). */
int ctl_cmd_path(req_t *q)
{
    sim_t *s = &g_sim;
    static sim_leg_t legs[SIM_PATH_MAX_LEGS];
    if (ctl_check_keys(q, q->root, "cmd,id,legs") != 0) {
        return -1;
    }
    int arr = sj_get(q->d, q->root, "legs");
    if (arr < 0 || q->d->nodes[arr].type != SJ_ARR || q->d->nodes[arr].count < 1 ||
        q->d->nodes[arr].count > SIM_PATH_MAX_LEGS) {
        return ctl_fail("legs must be an array of 1 .. %d legs", SIM_PATH_MAX_LEGS);
    }
    int n = q->d->nodes[arr].count;
    double total_s = 0.0;
    for (int i = 0; i < n; i++) {
        int o = sj_at(q->d, arr, i);
        sim_leg_t *l = &legs[i];
        memset(l, 0, sizeof *l);
        if (q->d->nodes[o].type != SJ_OBJ) {
            return ctl_fail("leg %d must be an object", i);
        }
        if (ctl_check_keys(q, o, "duration_s,move_m,axis,turn_deg") != 0) {
            return -1;
        }
        double dur, turn = 0.0;
        if (ctl_req_num(q, o, "duration_s", &dur) != 0) {
            return -1;
        }
        if (!(dur >= 0.01 && dur <= 3600.0)) {
            return ctl_fail("leg %d: duration_s must be in 0.01 .. 3600", i);
        }
        int mn = sj_get(q->d, o, "move_m");
        if (!ctl_is_null(q->d, mn) && ctl_node_vec(q->d, mn, "move_m", l->dp_m, 3, 0) != 0) {
            return -1;
        }
        for (int j = 0; j < 3; j++) {
            if (fabs(l->dp_m[j]) > 1000.0) {
                return ctl_fail("leg %d: move_m components must be within +-1000 m", i);
            }
        }
        int nt = ctl_opt_num(q, o, "turn_deg", &turn);
        if (nt < 0) {
            return -1;
        }
        if (fabs(turn) > 36000.0) {
            return ctl_fail("leg %d: turn_deg must be within +-36000", i);
        }
        if (turn != 0.0) {
            /* parse_axis reads q->root: look at this leg instead */
            req_t lq = *q;
            lq.root = o;
            if (sj_get(q->d, o, "axis") < 0) {
                return ctl_fail("leg %d: a turn needs an axis", i);
            }
            if (parse_axis(&lq, l->axis) != 0) {
                return -1;
            }
        } else if (nt == 0 && sj_get(q->d, o, "axis") >= 0) {
            return ctl_fail("leg %d: axis given without turn_deg", i);
        }
        l->angle_rad = turn * DEG;
        l->dur_us = (uint64_t)llround(dur * 1e6);
        total_s += (double)l->dur_us * 1e-6;
    }
    if (sim_phys_path(&s->phys, s->t_us, legs, n) != 0) {
        return ctl_fail("bad path");
    }
    ctl_put_u64(q->r, "t_start_us", s->t_us);
    ctl_put_u64(q->r, "t_end_us", s->phys.t_end_us);
    ctl_put_num(q->r, "duration_s", total_s);
    return 0;
}

int ctl_cmd_set_temperature(req_t *q)
{
    sim_t *s = &g_sim;
    double c, ramp = 0.0;
    int soak;
    if (ctl_check_keys(q, q->root, "cmd,id,c,ramp_c_per_s,soak") != 0 || ctl_req_num(q, q->root, "c", &c) != 0 ||
        ctl_opt_num(q, q->root, "ramp_c_per_s", &ramp) < 0 || ctl_opt_bool(q, q->root, "soak", 0, &soak) != 0) {
        return -1;
    }
    if (c < -100.0 || c > 200.0) {
        return ctl_fail("c must be in -100 .. 200");
    }
    if (ramp < 0.0) {
        return ctl_fail("ramp_c_per_s must be >= 0");
    }
    if (soak && ramp > 0.0) {
        return ctl_fail("a soak puts the board at c at once: give soak or ramp_c_per_s, not both");
    }
    /* every die has seen the old ambient up to now (the models, as before, take the world
     * at their next advance) */
    sim_thermal_sync(&s->thermal, &s->phys, s->t_us);
    if (soak) {
        sim_thermal_soak(&s->thermal, &s->phys, s->t_us, c);
    } else {
        sim_phys_set_temperature(&s->phys, s->t_us, c, ramp);
    }
    ctl_put_u64(q->r, "time_us", s->t_us);
    ctl_put_num(q->r, "temperature_c", sim_phys_temperature(&s->phys, s->t_us));
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&s->thermal, &s->phys, i, s->t_us);
    }
    ctl_put_vec(q->r, "die_temperature_c", die, SIM_DIES);
    return 0;
}

int ctl_cmd_set_thermal(req_t *q)
{
    sim_t *s = &g_sim;
    int enabled;
    double tau[SIM_DIES], heat[SIM_DIES];
    if (ctl_check_keys(q, q->root, "cmd,id,enabled,tau_s,self_heat_c") != 0 ||
        ctl_opt_bool(q, q->root, "enabled", 1, &enabled) != 0) {
        return -1;
    }
    int tn = sj_get(q->d, q->root, "tau_s"), hn = sj_get(q->d, q->root, "self_heat_c");
    int have_t = !ctl_is_null(q->d, tn), have_h = !ctl_is_null(q->d, hn);
    if ((have_t && ctl_node_vec(q->d, tn, "tau_s", tau, SIM_DIES, 1) != 0) ||
        (have_h && ctl_node_vec(q->d, hn, "self_heat_c", heat, SIM_DIES, 1) != 0)) {
        return -1;
    }
    for (int i = 0; i < SIM_DIES; i++) {
        if (have_t && !(tau[i] >= 1.0 && tau[i] <= 1e6)) {
            return ctl_fail("tau_s must be in 1 .. 1e6 s");
        }
        if (have_h && !(heat[i] >= -50.0 && heat[i] <= 100.0)) {
            return ctl_fail("self_heat_c must be in -50 .. 100 degC");
        }
    }
    if (sim_thermal_set(&s->thermal, &s->phys, s->t_us, enabled, have_t ? tau : NULL,
                        have_h ? heat : NULL) != 0) {
        return ctl_fail("bad thermal figures");
    }
    ctl_put_u64(q->r, "time_us", s->t_us);
    ctl_put_thermal(q->r);
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die_peek(&s->thermal, &s->phys, i, s->t_us);
    }
    ctl_put_vec(q->r, "die_temperature_c", die, SIM_DIES);
    return 0;
}

int ctl_cmd_set_speed(req_t *q)
{
    double v;
    if (ctl_check_keys(q, q->root, "cmd,id,speed") != 0 || ctl_req_num(q, q->root, "speed", &v) != 0) {
        return -1;
    }
    if (v < 0.0 || v > 1e6) {
        return ctl_fail("speed must be in 0 .. 1e6 (0 = as fast as possible)");
    }
    sim_set_speed(v);
    ctl_put_num(q->r, "speed", v);
    return 0;
}

/* Returns 1: deferred. */
int ctl_cmd_wait(req_t *q)
{
    double sec;
    if (ctl_check_keys(q, q->root, "cmd,id,device_s") != 0 || ctl_req_num(q, q->root, "device_s", &sec) != 0) {
        return -1;
    }
    if (sec < 0.0 || sec > 1e7) {
        return ctl_fail("device_s must be in 0 .. 1e7");
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
int ctl_idle_reached(int kind, double tol_c)
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
uint64_t ctl_idle_next(int kind, double tol_c)
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
int ctl_cmd_run(req_t *q)
{
    double until, rx = 0.0, tol = 0.0;
    int ns, nt;
    if (!g_sim.lockstep) {
        return ctl_fail("run is a command of the lockstep clock (this device runs on the real-time clock)");
    }
    if (ctl_check_keys(q, q->root, "cmd,id,until_us,stop,die_tolerance_c,link_rx") != 0 ||
        ctl_req_num(q, q->root, "until_us", &until) != 0 || ctl_opt_num(q, q->root, "link_rx", &rx) < 0 ||
        (nt = ctl_opt_num(q, q->root, "die_tolerance_c", &tol)) < 0) {
        return -1;
    }
    if (!(until >= 0.0 && until < 1.8e19) || !(rx >= 0.0 && rx < 1.8e19)) {
        return ctl_fail("until_us and link_rx must be counts >= 0");
    }
    int stop = WAIT_NONE;
    ns = sj_get(q->d, q->root, "stop");
    if (ns >= 0 && !ctl_is_null(q->d, ns)) {
        const char *v = q->d->nodes[ns].type == SJ_STR ? q->d->nodes[ns].str : "";
        stop = !strcmp(v, "idle") ? WAIT_IDLE : !strcmp(v, "temperature") ? WAIT_IDLE_TEMP
             : !strcmp(v, "dies") ? WAIT_IDLE_DIES : -1;
        if (stop < 0) {
            return ctl_fail("stop must be \"idle\", \"temperature\" or \"dies\"");
        }
    }
    if (nt && (stop != WAIT_IDLE_DIES || !(tol > 0.0 && tol <= 100.0))) {
        return ctl_fail("die_tolerance_c goes with stop \"dies\" and must be in (0, 100] degC");
    }
    if (stop == WAIT_IDLE_DIES && !nt) {
        return ctl_fail("stop \"dies\" needs die_tolerance_c");
    }
    q->c->wait = WAIT_RUN;
    q->c->run_stop = stop;
    q->c->wait_tol_c = tol;
    q->c->wait_until = (uint64_t)until;
    q->c->run_link_rx = (uint64_t)rx;
    return 1;
}

int ctl_cmd_wait_idle(req_t *q)
{
    int temp;
    double tol = 0.0;
    int nt;
    if (ctl_check_keys(q, q->root, "cmd,id,temperature,die_tolerance_c") != 0 ||
        ctl_opt_bool(q, q->root, "temperature", 0, &temp) != 0 ||
        (nt = ctl_opt_num(q, q->root, "die_tolerance_c", &tol)) < 0) {
        return -1;
    }
    if (nt && !(tol > 0.0 && tol <= 100.0)) {
        return ctl_fail("die_tolerance_c must be in (0, 100] degC");
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
