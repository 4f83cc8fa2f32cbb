/* sim_control_priv.h - what the control channel's files share: sim_control.c (connections,
 * dispatch, the command table), sim_control_args.c (reading a request, writing a reply),
 * sim_control_world.c (the world, motion, temperature and time commands), sim_control_truth.c
 * (the sensors' truth, faults, power and flash). Not an interface: only sim_control*.c include it. */
#ifndef SIM_CONTROL_PRIV_H
#define SIM_CONTROL_PRIV_H

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

typedef struct {
    sj_doc_t *d;
    int root;
    sj_buf_t *r; /* reply under construction: starts with {"ok": true */
    conn_t *c;
} req_t;

/* sim_control.c */
int ctl_fail(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
/* sim_control_args.c */
int ctl_check_keys(req_t *q, int obj, const char *allowed);
int ctl_is_null(const sj_doc_t *d, int n);
int ctl_node_num(const sj_doc_t *d, int n, const char *what, double *out);
int ctl_opt_num(req_t *q, int obj, const char *key, double *out);
int ctl_req_num(req_t *q, int obj, const char *key, double *out);
int ctl_node_vec(const sj_doc_t *d, int n, const char *what, double *out, int len,
                    int scalar_ok);
int ctl_node_mat3(const sj_doc_t *d, int n, const char *what, double m[3][3]);
int ctl_sensor_cs(req_t *q, int obj, int allow_accel);
int ctl_opt_bool(req_t *q, int obj, const char *key, int dflt, int *out);
void ctl_put_vec(sj_buf_t *r, const char *key, const double *v, int n);
void ctl_put_num(sj_buf_t *r, const char *key, double v);
void ctl_put_u64(sj_buf_t *r, const char *key, uint64_t v);
void ctl_put_bool(sj_buf_t *r, const char *key, int v);
/* sim_control_world.c */
void ctl_put_world(sj_buf_t *r);
void ctl_put_thermal(sj_buf_t *r);
int ctl_cmd_status(req_t *q);
int ctl_cmd_set_orientation(req_t *q);
int ctl_cmd_rotate(req_t *q);
int ctl_cmd_set_rate(req_t *q);
int ctl_cmd_path(req_t *q);
int ctl_cmd_set_temperature(req_t *q);
int ctl_cmd_set_thermal(req_t *q);
int ctl_cmd_set_speed(req_t *q);
int ctl_cmd_wait(req_t *q);
int ctl_idle_reached(int kind, double tol_c);
uint64_t ctl_idle_next(int kind, double tol_c);
int ctl_cmd_run(req_t *q);
int ctl_cmd_wait_idle(req_t *q);
/* sim_control_truth.c */
int ctl_cmd_set_truth(req_t *q);
int ctl_cmd_randomize_truth(req_t *q);
int ctl_cmd_get_truth(req_t *q);
int ctl_cmd_inject(req_t *q);
int ctl_cmd_power_cut(req_t *q);
int ctl_cmd_flash_ops(req_t *q);
int ctl_cmd_quit(req_t *q);

#endif
