/* sim_main_priv.h - what sim_main.c (options, resets, pacing, main) and sim_loop.c (the main
 * loop: lockstep runs, paced rounds, poll) share. Not an interface. */
#ifndef SIM_MAIN_PRIV_H
#define SIM_MAIN_PRIV_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

#define MAX_LAG_WALL_US 200000.0 /* CPU behind by more than this (wall) -> slip the anchor */
#define IDLE_POLL_MS 20
#define BUDGET_NS 5000000ull     /* wall time spent running ticks before serving I/O */

extern volatile sig_atomic_t g_sim_signal; /* SIGTERM/INT/HUP received: leave the loop */
extern pid_t g_sim_parent;                 /* the parent watched (0: none) */
extern int g_sim_parent_gone;

uint64_t sim_pace_target(uint64_t now_ns); /* device time due at wall time now_ns (sim_main.c) */
int sim_run_device(uint64_t target, uint64_t budget_end_ns); /* run the core towards target */
int sim_run_device_to(uint64_t target, uint64_t budget_end_ns, int final);
void sim_flush_blocking(size_t keep);   /* flush the link, waiting while more than keep is staged */
void sim_main_loop(void);                  /* sim_loop.c: until quit, a signal or the parent goes */

#endif
