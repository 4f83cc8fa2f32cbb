/* sim_loop.c - the simulator's main loop: the lockstep runs the host grants, or paced rounds
 * against the wall clock; between them poll() on the link, its listener and the control
 * channel (sim_main.c starts it; the design is described at the top of sim_main.c). */
#define _GNU_SOURCE
#include "sim.h"

#include <errno.h>
#include <math.h>
#include <poll.h>
#include <string.h>
#include <unistd.h>

#include "sim_main_priv.h"

static uint64_t min_u64(uint64_t a, uint64_t b) { return a < b ? a : b; }

/* One lockstep iteration: run as far as the granted run allows (and the speed ceiling),
 * flush, answer finished runs. Returns 1 when more can be done at once. */
static int lockstep_step(uint64_t now, int *was_active)
{
    sim_t *s = &g_sim;
    uint64_t until;
    int st = sim_control_run_target(&until);
    if (st == 2) {
        /* the host's link bytes first: a new connection is accepted before it is counted */
        while (s->link.tcp_listen >= 0 && sim_link_accept(&s->link) == 0) {
            sim_log("link: TCP client connected");
        }
        sim_link_receive(&s->link);
        st = sim_control_run_target(&until);
    }
    if (st != 1) {
        *was_active = 0;
        return 0;
    }
    if (!*was_active) { /* the ceiling counts from the grant: frozen time is not credit */
        s->anchor_dev_us = s->t_us;
        s->anchor_wall_ns = now;
        *was_active = 1;
    }
    uint64_t target = until;
    if (s->speed > 0.0) {
        uint64_t ceiling = sim_pace_target(now);
        if (ceiling < target) {
            target = ceiling;
        }
    }
    int more = sim_run_device_to(target, now + BUDGET_NS, target == until);
    sim_flush_blocking(0);
    sim_control_check_waits();
    if (sim_control_run_target(NULL) != 1) {
        *was_active = 0;
        return 0;
    }
    return more || s->speed <= 0.0;
}

/* Lockstep: how long poll() may sleep (ms). A granted run under the speed ceiling sleeps
 * until its next tick is due on the wall clock; a frozen device until I/O arrives. */
static int lockstep_sleep_ms(void)
{
    sim_t *s = &g_sim;
    uint64_t until;
    if (sim_control_run_target(&until) != 1) {
        return IDLE_POLL_MS;
    }
    uint64_t tgt = sim_pace_target(sim_wall_ns());
    uint64_t next = s->tick_hz != 0 && s->next_tick_us < until ? s->next_tick_us : until;
    if (next <= tgt || !(s->speed > 0.0)) {
        return 0;
    }
    double ms = (double)(next - tgt) / s->speed / 1000.0;
    return ms >= IDLE_POLL_MS ? IDLE_POLL_MS : (int)ceil(ms);
}

/* What the main loop keeps between its rounds. */
typedef struct {
    uint64_t last_wall;       /* wall time of the previous round, ns */
    uint64_t bp_since;        /* speed 0: when the link back-pressure wait began (0: none) */
    uint64_t last_slip_log;
    uint64_t last_parent_check;
    int run_was_active;       /* lockstep: a granted run was in progress */
} loop_state_t;

/* The device time to run to this round (real-time clock): paced by the speed, or as fast as
 * possible at speed 0; *bp_wait = 1 when the link's back-pressure says wait. */
static uint64_t round_target(loop_state_t *ls, uint64_t now, int *bp_wait)
{
    sim_t *s = &g_sim;
    uint64_t target;
    if (s->speed > 0.0) {
        target = sim_pace_target(now);
        double max_lag = MAX_LAG_WALL_US * s->speed;
        if (target > s->t_us && (double)(target - s->t_us) > max_lag) {
            s->anchor_dev_us = s->t_us;
            s->anchor_wall_ns = now;
            target = s->t_us;
            s->slips++;
            if (s->slips == 1 || now - ls->last_slip_log > 10000000000ull) {
                sim_log("cannot keep up with speed %g: running slower (slip %llu)", s->speed,
                        (unsigned long long)s->slips);
                ls->last_slip_log = now;
            }
        }
        return target;
    }
    /* as fast as possible */
    uint64_t idle = s->t_us + (now - ls->last_wall) / 1000u;
    if (s->tick_hz == 0) {
        uint64_t ev = min_u64(sim_control_next_deadline(), sim_phys_next_event(&s->phys, s->t_us));
        return ev != UINT64_MAX && ev > idle ? ev : idle;
    }
    target = s->next_tick_us + 50000u;
    if (s->link.os_blocked && sim_link_staged(&s->link) > (SIM_TX_STORE - SIM_TX_RING) / 2) {
        if (ls->bp_since == 0) {
            ls->bp_since = now;
        }
        if (now - ls->bp_since < 50000000ull) {
            *bp_wait = 1;
            target = s->t_us;
        }
    } else {
        ls->bp_since = 0;
    }
    return target;
}

/* How long poll() may sleep this round, ms. */
static int round_sleep_ms(int more, int bp_wait)
{
    sim_t *s = &g_sim;
    if (more) {
        return 0;
    }
    if (s->lockstep) {
        return lockstep_sleep_ms();
    }
    if (s->speed > 0.0) {
        uint64_t tgt = sim_pace_target(sim_wall_ns());
        uint64_t wait_dev;
        if (s->t_us > tgt) {
            wait_dev = s->t_us - tgt;
        } else {
            uint64_t ev = UINT64_MAX;
            if (s->tick_hz != 0) {
                ev = s->next_tick_us;
            }
            ev = min_u64(ev, sim_control_next_deadline());
            ev = min_u64(ev, sim_phys_next_event(&s->phys, s->t_us));
            uint64_t drain = sim_link_next_drain_us(&s->link);
            if (drain) {
                ev = min_u64(ev, s->t_us + drain);
            }
            wait_dev = ev == UINT64_MAX ? UINT64_MAX : (ev > tgt ? ev - tgt : 0);
        }
        double wall_ms = wait_dev == UINT64_MAX ? IDLE_POLL_MS : (double)wait_dev / s->speed / 1000.0;
        int timeout_ms = wall_ms >= IDLE_POLL_MS ? IDLE_POLL_MS : (int)ceil(wall_ms);
        return timeout_ms < 1 ? 1 : timeout_ms;
    }
    if (bp_wait) {
        return 5;
    }
    if (s->tick_hz != 0 || sim_control_next_deadline() != UINT64_MAX ||
        sim_phys_next_event(&s->phys, s->t_us) != UINT64_MAX) {
        return 0;
    }
    return sim_link_queued(&s->link) ? 1 : IDLE_POLL_MS;
}

/* Wait up to timeout_ms for the link, its listener and the control channel, and serve them.
 * -1 when poll() failed (the loop ends), else 0. */
static int round_io(int timeout_ms)
{
    sim_t *s = &g_sim;
    struct pollfd pfd[64];
    int n = 0;
    sim_link_t *l = &s->link;
    int i_listen = -1, i_client = -1, i_pty = -1;
    if (l->tcp_listen >= 0) {
        i_listen = n;
        pfd[n++] = (struct pollfd){l->tcp_listen, POLLIN, 0};
    }
    int want_out = l->os_blocked && sim_link_staged(l) > 0;
    short in = (l->rx_head - l->rx_tail) < SIM_RX_RING ? POLLIN : 0; /* room to receive */
    if (l->tcp_client >= 0) {
        i_client = n;
        pfd[n++] = (struct pollfd){l->tcp_client, (short)(in | (want_out ? POLLOUT : 0)), 0};
    }
    if (l->pty_master >= 0) {
        i_pty = n;
        pfd[n++] = (struct pollfd){l->pty_master, (short)(in | (want_out && l->tcp_client < 0 ? POLLOUT : 0)), 0};
    }
    int n_ctl = sim_control_pollfds(pfd + n, (int)(sizeof pfd / sizeof pfd[0]) - n);
    int r = poll(pfd, (nfds_t)(n + n_ctl), timeout_ms);
    if (r < 0) {
        if (errno == EINTR) {
            return 0;
        }
        sim_log("poll failed: %s", strerror(errno));
        return -1;
    }
    if (r == 0) {
        return 0;
    }
    if (i_listen >= 0 && (pfd[i_listen].revents & POLLIN)) {
        if (sim_link_accept(l) == 0) {
            sim_log("link: TCP client connected");
        }
    }
    if ((i_client >= 0 && (pfd[i_client].revents & (POLLIN | POLLHUP | POLLERR))) ||
        (i_pty >= 0 && (pfd[i_pty].revents & POLLIN))) {
        sim_link_receive(l);
    }
    sim_control_handle(pfd + n, n_ctl);
    return 0;
}

/* 1 when the process that started us is gone (checked at most every 100 ms). */
static int parent_gone(loop_state_t *ls, uint64_t now)
{
    if (g_sim_parent == 0 || now - ls->last_parent_check <= 100000000ull) {
        return 0;
    }
    ls->last_parent_check = now;
    if (getppid() != g_sim_parent) {
        sim_log("parent process %ld is gone: exiting", (long)g_sim_parent);
        g_sim_parent_gone = 1;
        return 1;
    }
    return 0;
}

void sim_main_loop(void)
{
    sim_t *s = &g_sim;
    loop_state_t ls = {sim_wall_ns(), 0, 0, 0, 0};
    while (!s->quit && !g_sim_signal) {
        uint64_t now = sim_wall_ns();
        if (parent_gone(&ls, now)) {
            break;
        }
        int more = 0, bp_wait = 0;
        if (s->lockstep) {
            more = lockstep_step(now, &ls.run_was_active);
        } else {
            uint64_t target = round_target(&ls, now, &bp_wait);
            ls.last_wall = now;
            if (!bp_wait) {
                more = sim_run_device(target, now + BUDGET_NS);
            }
            if (sim_link_staged(&s->link) > 0) {
                sim_link_flush(&s->link);
            }
            sim_control_check_waits();
        }
        if (s->quit || g_sim_signal || round_io(round_sleep_ms(more, bp_wait)) < 0) {
            break;
        }
    }
}

