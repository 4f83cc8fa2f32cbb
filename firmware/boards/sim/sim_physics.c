/*
 * sim_physics.c - the physical world of the virtual device: orientation on a turntable,
 * angular rate, temperature (climate chamber), all as functions of device time.
 *
 * Frames (docs/conventions.md): board X forward, Y left, Z up, right-handed. The level
 * (earth) frame has Z up. R maps board-frame vectors to the level frame, so the specific
 * force of a still board is f_board = R^T (0, 0, g0): third row of R times g0. Lying
 * level, R = I and f = (0, 0, +g0).
 *
 * "gravity" in the control channel (set_orientation {gravity}, status gravity_board) is the
 * DIRECTION OF THE MEASURED SPECIFIC FORCE in the board frame (the "up" direction, as
 * imubench.device.fake's gravity_board): level = [0, 0, 1], upside down = [0, 0, -1].
 *
 * Roll/pitch/yaw (degrees in the control channel): ZYX convention,
 *     R = Rz(yaw) * Ry(pitch) * Rx(roll),
 * each a right-handed rotation about the board axis (roll about X, pitch about Y, yaw
 * about Z). With Y to the left, a positive pitch lowers the nose (X goes down):
 * f_board = g0 * (-sin(pitch), sin(roll) cos(pitch), cos(roll) cos(pitch)).
 *
 * Motion: one motion at a time, about a fixed axis of the BOARD frame (a turntable with
 * the board mounted on it): R(t) = R0 * Rot(axis, angle(t)), angle(t) = rate * (t - t0)
 * up to the end of a finite move (rotate), or forever (set_rate). Body-fixed rotations
 * compose on the right. The closed form is exact at any t, so the world seen by the
 * sensors does not depend on how often it is evaluated. omega_board = rate * axis during
 * the motion, 0 otherwise; its time integral is kept so a gyro model advanced over any
 * interval gets the exact mean rate (sim_board.c).
 *
 * Path (translation): a list of legs driven back to back, each rest to rest on the
 * minimum-jerk profile h(s) = 10 s^3 - 15 s^4 + 6 s^5 (s = elapsed / duration), moving the
 * board's origin by dp (level frame, metres) and turning it by an angle about a board
 * axis, both on the same profile. In closed form per leg:
 *     p(t) = p0 + dp h(s),  v = dp h'(s) / T,  a = dp h''(s) / T^2,
 *     R(t) = R0 Rot(axis, angle h(s)),  omega_board = axis angle h'(s) / T,
 * and the specific force the accelerometer feels is f_board = R^T (a + (0, 0, g0)).
 * Position, velocity and acceleration are continuous at every leg boundary (all zero
 * there), so a path is what a cart or a gantry can drive. The position is kept in every
 * motion (rotations do not move the origin).
 */
#define _GNU_SOURCE
#include "sim.h"

#include <math.h>
#include <string.h>

static void mat_identity(double r[3][3])
{
    memset(r, 0, 9 * sizeof(double));
    r[0][0] = r[1][1] = r[2][2] = 1.0;
}

static void mat_mul(const double a[3][3], const double b[3][3], double out[3][3])
{
    double t[3][3];
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            t[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    memcpy(out, t, sizeof t);
}

/* Rodrigues: rotation matrix of angle th about unit axis k (right-handed). */
static void rot_matrix(const double k[3], double th, double r[3][3])
{
    double c = cos(th), s = sin(th), v = 1.0 - c;
    r[0][0] = c + k[0] * k[0] * v;
    r[0][1] = k[0] * k[1] * v - k[2] * s;
    r[0][2] = k[0] * k[2] * v + k[1] * s;
    r[1][0] = k[1] * k[0] * v + k[2] * s;
    r[1][1] = c + k[1] * k[1] * v;
    r[1][2] = k[1] * k[2] * v - k[0] * s;
    r[2][0] = k[2] * k[0] * v - k[1] * s;
    r[2][1] = k[2] * k[1] * v + k[0] * s;
    r[2][2] = c + k[2] * k[2] * v;
}

/* Rotate vector v by angle th about unit axis k. */
static void rot_vec(const double k[3], double th, const double v[3], double out[3])
{
    double c = cos(th), s = sin(th);
    double kv = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
    double cx = k[1] * v[2] - k[2] * v[1];
    double cy = k[2] * v[0] - k[0] * v[2];
    double cz = k[0] * v[1] - k[1] * v[0];
    out[0] = v[0] * c + cx * s + k[0] * kv * (1.0 - c);
    out[1] = v[1] * c + cy * s + k[1] * kv * (1.0 - c);
    out[2] = v[2] * c + cz * s + k[2] * kv * (1.0 - c);
}

static int normalize(const double v[3], double out[3])
{
    double n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (!(n > 1e-12) || !isfinite(n)) {
        return -1;
    }
    out[0] = v[0] / n;
    out[1] = v[1] / n;
    out[2] = v[2] / n;
    return 0;
}

/* Gram-Schmidt on the rows (keeps row 2, the up direction, exact). */
static void orthonormalize(double r[3][3])
{
    double z[3], x[3], y[3];
    if (normalize(r[2], z) != 0) {
        mat_identity(r);
        return;
    }
    double d = r[0][0] * z[0] + r[0][1] * z[1] + r[0][2] * z[2];
    double xr[3] = {r[0][0] - d * z[0], r[0][1] - d * z[1], r[0][2] - d * z[2]};
    if (normalize(xr, x) != 0) {
        mat_identity(r);
        return;
    }
    y[0] = z[1] * x[2] - z[2] * x[1];
    y[1] = z[2] * x[0] - z[0] * x[2];
    y[2] = z[0] * x[1] - z[1] * x[0];
    memcpy(r[0], x, sizeof x);
    memcpy(r[1], y, sizeof y);
    memcpy(r[2], z, sizeof z);
}

/* Minimum-jerk profile and its derivatives with respect to s. */
static double mj_h(double s) { return s * s * s * (10.0 + s * (-15.0 + 6.0 * s)); }
static double mj_h1(double s) { return 30.0 * s * s * (1.0 + s * (-2.0 + s)); }
static double mj_h2(double s) { return 60.0 * s * (1.0 + s * (-3.0 + 2.0 * s)); }

/* The leg in progress at t and its phase s in [0, 1]; past the end: the last leg, s = 1.
 * Before the path's start: the first leg, s = 0. */
static const sim_leg_t *path_leg(const sim_physics_t *p, uint64_t t_us, double *s)
{
    int i = sim_phys_path_leg(p, t_us);
    if (i < 0) {
        i = t_us < p->legs[0].t0_us ? 0 : p->n_legs - 1;
    }
    const sim_leg_t *l = &p->legs[i];
    if (t_us <= l->t0_us) {
        *s = 0.0;
    } else if (t_us >= l->t0_us + l->dur_us) {
        *s = 1.0;
    } else {
        *s = (double)(t_us - l->t0_us) / (double)l->dur_us;
    }
    return l;
}

int sim_phys_path_leg(const sim_physics_t *p, uint64_t t_us)
{
    if (p->kind != SIM_MOTION_PATH || p->n_legs <= 0 || t_us < p->legs[0].t0_us ||
        t_us >= p->t_end_us) {
        return -1;
    }
    int lo = 0, hi = p->n_legs - 1;
    while (lo < hi) { /* last leg with t0 <= t */
        int mid = (lo + hi + 1) / 2;
        if (p->legs[mid].t0_us <= t_us) {
            lo = mid;
        } else {
            hi = mid - 1;
        }
    }
    return lo;
}

/* r = r0 * Rot(axis, th): a body-fixed turn composed on the right (r0 itself at th = 0). */
static void turned(const double r0[3][3], const double axis[3], double th, double r[3][3])
{
    if (th == 0.0) {
        memcpy(r, r0, 9 * sizeof(double));
        return;
    }
    double m[3][3];
    rot_matrix(axis, th, m);
    mat_mul(r0, m, r);
}

static void path_orientation(const sim_leg_t *l, double s, double r[3][3])
{
    turned(l->r0, l->axis, l->angle_rad * mj_h(s), r);
}

void sim_phys_init(sim_physics_t *p)
{
    memset(p, 0, sizeof *p);
    mat_identity(p->r0);
    p->axis[2] = 1.0;
    p->kind = SIM_MOTION_NONE;
    p->temp0_c = p->temp_target_c = 25.0;
}

/* Motion time elapsed at t (clamped to the motion's interval), us. */
static uint64_t motion_elapsed_us(const sim_physics_t *p, uint64_t t_us)
{
    if (p->kind == SIM_MOTION_NONE || t_us <= p->t0_us) {
        return 0;
    }
    uint64_t end = t_us < p->t_end_us ? t_us : p->t_end_us;
    return end - p->t0_us;
}

static double motion_angle(const sim_physics_t *p, uint64_t t_us)
{
    if (p->kind == SIM_MOTION_ROTATE && t_us >= p->t_end_us) {
        return p->angle_total_rad;
    }
    return p->rate_rad_s * (double)motion_elapsed_us(p, t_us) * 1e-6;
}

void sim_phys_orientation(const sim_physics_t *p, uint64_t t_us, double r[3][3])
{
    if (p->kind == SIM_MOTION_PATH) {
        double s;
        const sim_leg_t *l = path_leg(p, t_us, &s);
        path_orientation(l, s, r);
        return;
    }
    turned(p->r0, p->axis, motion_angle(p, t_us), r);
}

void sim_phys_gravity_dir(const sim_physics_t *p, uint64_t t_us, double g[3])
{
    if (p->kind == SIM_MOTION_PATH) {
        double r[3][3];
        sim_phys_orientation(p, t_us, r);
        memcpy(g, r[2], 3 * sizeof(double));
        return;
    }
    double th = motion_angle(p, t_us);
    if (th == 0.0) {
        memcpy(g, p->r0[2], 3 * sizeof(double));
        return;
    }
    rot_vec(p->axis, -th, p->r0[2], g);
}

void sim_phys_omega(const sim_physics_t *p, uint64_t t_us, double w[3])
{
    if (p->kind == SIM_MOTION_PATH) {
        double s;
        const sim_leg_t *l = path_leg(p, t_us, &s);
        double k = sim_phys_path_leg(p, t_us) < 0
                       ? 0.0
                       : l->angle_rad * mj_h1(s) / ((double)l->dur_us * 1e-6);
        for (int i = 0; i < 3; i++) {
            w[i] = k * l->axis[i];
        }
        return;
    }
    int on = p->kind != SIM_MOTION_NONE && t_us >= p->t0_us && t_us < p->t_end_us;
    for (int i = 0; i < 3; i++) {
        w[i] = on ? p->rate_rad_s * p->axis[i] : 0.0;
    }
}

void sim_phys_omega_integral(const sim_physics_t *p, uint64_t t_us, double out[3])
{
    if (p->kind == SIM_MOTION_PATH) {
        double s;
        const sim_leg_t *l = path_leg(p, t_us, &s);
        double th = l->angle_rad * mj_h(s);
        for (int i = 0; i < 3; i++) {
            out[i] = l->wi0[i] + th * l->axis[i];
        }
        return;
    }
    double th = motion_angle(p, t_us);
    for (int i = 0; i < 3; i++) {
        out[i] = p->omega_int0[i] + th * p->axis[i];
    }
}

void sim_phys_kinematics(const sim_physics_t *p, uint64_t t_us, double pos[3], double vel[3],
                         double acc[3])
{
    if (p->kind != SIM_MOTION_PATH) {
        for (int i = 0; i < 3; i++) {
            pos[i] = p->pos0_m[i];
            vel[i] = acc[i] = 0.0;
        }
        return;
    }
    double s;
    const sim_leg_t *l = path_leg(p, t_us, &s);
    double T = (double)l->dur_us * 1e-6;
    int on = sim_phys_path_leg(p, t_us) >= 0;
    double h = mj_h(s), h1 = on ? mj_h1(s) / T : 0.0, h2 = on ? mj_h2(s) / (T * T) : 0.0;
    for (int i = 0; i < 3; i++) {
        pos[i] = l->p0_m[i] + l->dp_m[i] * h;
        vel[i] = l->dp_m[i] * h1;
        acc[i] = l->dp_m[i] * h2;
    }
}

void sim_phys_specific_force(const sim_physics_t *p, uint64_t t_us, double f[3])
{
    if (p->kind != SIM_MOTION_PATH) {
        double g[3];
        sim_phys_gravity_dir(p, t_us, g);
        for (int i = 0; i < 3; i++) {
            f[i] = SIM_G0_MPS2 * g[i];
        }
        return;
    }
    double r[3][3], pos[3], vel[3], acc[3];
    sim_phys_orientation(p, t_us, r);
    sim_phys_kinematics(p, t_us, pos, vel, acc);
    acc[2] += SIM_G0_MPS2;
    for (int i = 0; i < 3; i++) { /* R^T acc: column i of R */
        f[i] = r[0][i] * acc[0] + r[1][i] * acc[1] + r[2][i] * acc[2];
    }
}

double sim_phys_temperature(const sim_physics_t *p, uint64_t t_us)
{
    if (!(p->ramp_c_per_s > 0.0) || t_us <= p->temp_t0_us) {
        return p->ramp_c_per_s > 0.0 ? p->temp0_c : p->temp_target_c;
    }
    double span = p->temp_target_c - p->temp0_c;
    double done = p->ramp_c_per_s * (double)(t_us - p->temp_t0_us) * 1e-6;
    if (t_us >= p->temp_end_us || done >= fabs(span)) {
        return p->temp_target_c;
    }
    return p->temp0_c + (span >= 0.0 ? done : -done);
}

int sim_phys_moving(const sim_physics_t *p, uint64_t t_us)
{
    return (p->kind == SIM_MOTION_ROTATE || p->kind == SIM_MOTION_PATH) && t_us < p->t_end_us;
}

void sim_phys_settle(sim_physics_t *p, uint64_t t_us)
{
    if (p->kind == SIM_MOTION_NONE) {
        p->t0_us = t_us;
        return;
    }
    if (t_us < p->t0_us) {
        return;
    }
    if (p->kind == SIM_MOTION_PATH) {
        /* fold the state at t; a path cannot be resumed, so it ends here (at rest at
         * its end, or stopped dead where it was) */
        double r[3][3], wi[3], pos[3], vel[3], acc[3];
        sim_phys_orientation(p, t_us, r);
        sim_phys_omega_integral(p, t_us, wi);
        sim_phys_kinematics(p, t_us, pos, vel, acc);
        orthonormalize(r);
        memcpy(p->r0, r, sizeof r);
        memcpy(p->omega_int0, wi, sizeof wi);
        memcpy(p->pos0_m, pos, sizeof pos);
        p->kind = SIM_MOTION_NONE;
        p->n_legs = 0;
        p->rate_rad_s = 0.0;
        p->angle_total_rad = 0.0;
        p->t0_us = p->t_end_us = t_us;
        return;
    }
    double r[3][3], wi[3];
    sim_phys_orientation(p, t_us, r);
    sim_phys_omega_integral(p, t_us, wi);
    double done = motion_angle(p, t_us);
    orthonormalize(r);
    memcpy(p->r0, r, sizeof r);
    memcpy(p->omega_int0, wi, sizeof wi);
    if (p->kind == SIM_MOTION_ROTATE) {
        if (t_us >= p->t_end_us) {
            p->kind = SIM_MOTION_NONE;
            p->rate_rad_s = 0.0;
            p->angle_total_rad = 0.0;
        } else {
            p->angle_total_rad -= done;
        }
    }
    p->t0_us = t_us;
}

static void stop_motion(sim_physics_t *p, uint64_t t_us)
{
    sim_phys_settle(p, t_us);
    p->kind = SIM_MOTION_NONE;
    p->rate_rad_s = 0.0;
    p->angle_total_rad = 0.0;
    p->t0_us = p->t_end_us = t_us;
}

int sim_phys_set_gravity(sim_physics_t *p, uint64_t t_us, const double g_in[3])
{
    double g[3];
    if (normalize(g_in, g) != 0) {
        return -1;
    }
    stop_motion(p, t_us);
    /* Shortest arc: R^T = Rot(k, a) takes level up (0,0,1) to g; k = z x g. */
    double k[3] = {-g[1], g[0], 0.0};
    double s = sqrt(k[0] * k[0] + k[1] * k[1]);
    double a = atan2(s, g[2]);
    double rt[3][3];
    if (s < 1e-12) {
        if (g[2] > 0.0) {
            mat_identity(rt);
        } else {
            const double x[3] = {1.0, 0.0, 0.0}; /* upside down: roll 180 degrees */
            rot_matrix(x, M_PI, rt);
        }
    } else {
        k[0] /= s;
        k[1] /= s;
        rot_matrix(k, a, rt);
    }
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            p->r0[i][j] = rt[j][i];
        }
    }
    memcpy(p->r0[2], g, sizeof g); /* exact */
    orthonormalize(p->r0);
    return 0;
}

void sim_phys_set_rpy(sim_physics_t *p, uint64_t t_us, double roll, double pitch, double yaw)
{
    static const double ex[3] = {1, 0, 0}, ey[3] = {0, 1, 0}, ez[3] = {0, 0, 1};
    double rx[3][3], ry[3][3], rz[3][3], t[3][3];
    stop_motion(p, t_us);
    rot_matrix(ex, roll, rx);
    rot_matrix(ey, pitch, ry);
    rot_matrix(ez, yaw, rz);
    mat_mul(rz, ry, t);
    mat_mul(t, rx, p->r0);
}

void sim_phys_rpy(const double r[3][3], double *roll, double *pitch, double *yaw)
{
    double s = -r[2][0];
    s = s > 1.0 ? 1.0 : (s < -1.0 ? -1.0 : s);
    *pitch = asin(s);
    *roll = atan2(r[2][1], r[2][2]);
    *yaw = atan2(r[1][0], r[0][0]);
}

int sim_phys_rotate(sim_physics_t *p, uint64_t t_us, const double axis[3], double rate_rad_s,
                    double duration_s)
{
    double k[3];
    if (normalize(axis, k) != 0 || !isfinite(rate_rad_s) || !isfinite(duration_s) ||
        duration_s < 0.0 || duration_s > 1e7) {
        return -1;
    }
    stop_motion(p, t_us);
    uint64_t dur_us = (uint64_t)llround(duration_s * 1e6);
    if (dur_us == 0 || rate_rad_s == 0.0) {
        return 0;
    }
    memcpy(p->axis, k, sizeof k);
    p->angle_total_rad = rate_rad_s * duration_s;
    /* the rate that turns exactly angle_total over the whole microseconds of the move */
    p->rate_rad_s = p->angle_total_rad / ((double)dur_us * 1e-6);
    p->t0_us = t_us;
    p->t_end_us = t_us + dur_us;
    p->kind = SIM_MOTION_ROTATE;
    return 0;
}

void sim_phys_set_rate(sim_physics_t *p, uint64_t t_us, const double w[3])
{
    double n = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
    stop_motion(p, t_us);
    if (!(n > 0.0) || !isfinite(n)) {
        return;
    }
    for (int i = 0; i < 3; i++) {
        p->axis[i] = w[i] / n;
    }
    p->rate_rad_s = n;
    p->t0_us = t_us;
    p->t_end_us = UINT64_MAX;
    p->kind = SIM_MOTION_RATE;
}

int sim_phys_path(sim_physics_t *p, uint64_t t_us, const sim_leg_t *legs, int n)
{
    if (n < 1 || n > SIM_PATH_MAX_LEGS) {
        return -1;
    }
    for (int i = 0; i < n; i++) {
        const sim_leg_t *l = &legs[i];
        double k[3];
        if (l->dur_us == 0 || l->dur_us > 10000000000ull || !isfinite(l->angle_rad) ||
            (l->angle_rad != 0.0 && normalize(l->axis, k) != 0)) {
            return -1;
        }
        for (int j = 0; j < 3; j++) {
            if (!isfinite(l->dp_m[j])) {
                return -1;
            }
        }
    }
    stop_motion(p, t_us);
    double r[3][3], pos[3], wi[3];
    memcpy(r, p->r0, sizeof r);
    memcpy(pos, p->pos0_m, sizeof pos);
    memcpy(wi, p->omega_int0, sizeof wi);
    uint64_t t = t_us;
    for (int i = 0; i < n; i++) {
        sim_leg_t *l = &p->legs[i];
        *l = legs[i];
        l->t0_us = t;
        if (l->angle_rad != 0.0) {
            normalize(legs[i].axis, l->axis);
        } else {
            l->axis[0] = l->axis[1] = 0.0;
            l->axis[2] = 1.0;
        }
        memcpy(l->r0, r, sizeof r);
        memcpy(l->p0_m, pos, sizeof pos);
        memcpy(l->wi0, wi, sizeof wi);
        path_orientation(l, 1.0, r);
        orthonormalize(r);
        for (int j = 0; j < 3; j++) {
            pos[j] += l->dp_m[j];
            wi[j] += l->angle_rad * l->axis[j];
        }
        t += l->dur_us;
    }
    p->n_legs = n;
    p->t0_us = t_us;
    p->t_end_us = t;
    p->kind = SIM_MOTION_PATH;
    return 0;
}

void sim_phys_set_temperature(sim_physics_t *p, uint64_t t_us, double c, double ramp_c_per_s)
{
    p->temp0_c = sim_phys_temperature(p, t_us);
    p->temp_t0_us = t_us;
    p->temp_target_c = c;
    p->ramp_c_per_s = ramp_c_per_s > 0.0 ? ramp_c_per_s : 0.0;
    p->temp_end_us = t_us;
    if (p->ramp_c_per_s > 0.0) {
        double span_us = fabs(c - p->temp0_c) / p->ramp_c_per_s * 1e6;
        p->temp_end_us = t_us + (span_us < 1e15 ? (uint64_t)ceil(span_us) : (uint64_t)1e15);
    }
}

uint64_t sim_phys_next_event(const sim_physics_t *p, uint64_t t_us)
{
    uint64_t ev = UINT64_MAX;
    if ((p->kind == SIM_MOTION_ROTATE || p->kind == SIM_MOTION_PATH) && p->t_end_us > t_us) {
        ev = p->t_end_us;
    }
    if (p->ramp_c_per_s > 0.0 && p->temp_end_us > t_us && p->temp_end_us < ev) {
        ev = p->temp_end_us;
    }
    return ev;
}
