/*
 * sim_flash.h - the virtual device's parameter flash (sim_flash.c): an ib_flash_if_t on a file.
 * It knows nothing of the rest of the simulator: the board gives it its clock and its power
 * (sim_flash_hooks_t), so sim_flash.c includes only this header and flash_if.h.
 */
#ifndef SIM_FLASH_H
#define SIM_FLASH_H

#include <stddef.h>
#include <stdint.h>

#include "flash_if.h"

#define SIM_FLASH_SLOT_SIZE 2048u
#define SIM_FLASH_SIZE (2u * SIM_FLASH_SLOT_SIZE)
#define SIM_FLASH_PROGRAM_UNIT 4u

/* What the flash needs from its board: the device time an operation takes (busy_us: the core
 * is blocked that long, as on hardware), the power cut (power_cut: does not return), a log. */
typedef struct sim_flash_hooks {
    void (*busy_us)(uint32_t us);
    void (*power_cut)(void);
    void (*log)(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
} sim_flash_hooks_t;

typedef struct sim_flash {
    int fd;
    char path[512];
    uint8_t mem[SIM_FLASH_SIZE]; /* mirror of the file */
    uint64_t ops_since_boot;
    uint64_t ops_total;
    int64_t cut_after;           /* > 0: power cut during the cut_after-th next op; 0 off */
    uint64_t cuts;
    sim_flash_hooks_t hooks;     /* set by the board (sim_flash_set_hooks) before any operation */
} sim_flash_t;

int sim_flash_open(sim_flash_t *f, const char *path);
void sim_flash_close(sim_flash_t *f);
void sim_flash_set_hooks(sim_flash_t *f, const sim_flash_hooks_t *hooks);
void sim_flash_setup_if(sim_flash_t *f, ib_flash_if_t *fi);

#endif
