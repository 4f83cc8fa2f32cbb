/*
 * sim_flash.c - the parameter flash of the virtual device: an ib_flash_if_t (flash_if.h)
 * on a file of 2 x 2 KiB.
 *
 *   slot 0 at address 0x000, slot 1 at 0x800, each its own 2 KiB erase unit;
 *   program_unit 4; NOR semantics: erase fills the slot with 0xFF, program ANDs the data
 *   into the existing bytes (bits only go 1 -> 0), so programming zeros over a programmed
 *   unit works, as on the STM32F4. A missing or empty file is created filled with 0xFF.
 *   Every operation is written through to the file at once (pwrite; no fsync needed), so
 *   the file is the flash: a restarted simulator with the same file boots with the
 *   parameters saved before.
 *
 * Timing: an erase takes SIM_FLASH_ERASE_US and each program unit SIM_FLASH_PROGRAM_US of
 * device time (STM32-like figures: a 2 KiB page erase ~20 ms, a word ~16 us), during which
 * the core is blocked as on hardware (sample ticks that fall due are reported as missed).
 *
 * Operations (one program() call or one erase() call = one op) are counted since boot and
 * in total. Power-cut injection: with cut_after = N > 0, the N-th following op is applied
 * only in part (the first half of its bytes; for an erase, the first half of the slot) and
 * the device loses power: the board's power_cut hook does not return, the main loop
 * re-initialises the core as after a real power cycle. The board gives the clock, the power
 * and the log (sim_flash.h, sim_flash_hooks_t); this file knows nothing else of it.
 */
#define _GNU_SOURCE
#include "sim_flash.h"

#include <errno.h>
#include <fcntl.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define SIM_FLASH_ERASE_US 20000u
#define SIM_FLASH_PROGRAM_US 16u /* per program unit */

static int write_through(sim_flash_t *f, uint32_t addr, size_t len)
{
    size_t done = 0;
    while (done < len) {
        ssize_t n = pwrite(f->fd, f->mem + addr + done, len - done, (off_t)(addr + done));
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            f->hooks.log("flash: write to %s failed: %s", f->path, strerror(errno));
            return IB_FLASH_ERR_IO;
        }
        done += (size_t)n;
    }
    return IB_FLASH_OK;
}

int sim_flash_open(sim_flash_t *f, const char *path)
{
    const sim_flash_hooks_t hooks = f->hooks; /* the board's, set before (sim_flash_set_hooks) */
    memset(f, 0, sizeof *f);
    f->hooks = hooks;
    f->fd = -1;
    if (strlen(path) >= sizeof f->path) {
        f->hooks.log("flash: path too long");
        return -1;
    }
    strcpy(f->path, path);
    int fd = open(path, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) {
        f->hooks.log("flash: cannot open %s: %s", path, strerror(errno));
        return -1;
    }
    f->fd = fd;
    struct stat st;
    if (fstat(fd, &st) != 0) {
        f->hooks.log("flash: cannot stat %s: %s", path, strerror(errno));
        return -1;
    }
    if (st.st_size == 0) {
        memset(f->mem, 0xFF, sizeof f->mem);
        if (write_through(f, 0, sizeof f->mem) != IB_FLASH_OK) {
            return -1;
        }
        f->hooks.log("flash: created %s (%u bytes of 0xFF)", path, SIM_FLASH_SIZE);
    } else if (st.st_size == (off_t)SIM_FLASH_SIZE) {
        size_t got = 0;
        while (got < sizeof f->mem) {
            ssize_t n = pread(fd, f->mem + got, sizeof f->mem - got, (off_t)got);
            if (n <= 0) {
                if (n < 0 && errno == EINTR) {
                    continue;
                }
                f->hooks.log("flash: cannot read %s", path);
                return -1;
            }
            got += (size_t)n;
        }
    } else {
        f->hooks.log("flash: %s has %lld bytes, expected %u (or an empty/missing file)", path,
                (long long)st.st_size, SIM_FLASH_SIZE);
        return -1;
    }
    return 0;
}

void sim_flash_close(sim_flash_t *f)
{
    if (f->fd >= 0) {
        close(f->fd);
        f->fd = -1;
    }
}

/* Count one op; returns 1 when this op is the one the power cut falls into. */
static int count_op(sim_flash_t *f)
{
    f->ops_since_boot++;
    f->ops_total++;
    if (f->cut_after > 0 && --f->cut_after == 0) {
        f->cuts++;
        return 1;
    }
    return 0;
}

static int slot_of(uint32_t addr)
{
    if (addr < SIM_FLASH_SLOT_SIZE) {
        return 0;
    }
    if (addr < SIM_FLASH_SIZE) {
        return 1;
    }
    return -1;
}

static int flash_erase(void *ctx, uint32_t addr)
{
    sim_flash_t *f = ctx;
    if (addr != 0 && addr != SIM_FLASH_SLOT_SIZE) {
        return IB_FLASH_ERR_RANGE;
    }
    int cut = count_op(f);
    size_t n = cut ? SIM_FLASH_SLOT_SIZE / 2 : SIM_FLASH_SLOT_SIZE;
    f->hooks.busy_us(cut ? SIM_FLASH_ERASE_US / 2 : SIM_FLASH_ERASE_US);
    memset(f->mem + addr, 0xFF, n);
    int rc = write_through(f, addr, n);
    if (cut) {
        f->hooks.log("flash: power cut during erase of 0x%03X (half erased)", (unsigned)addr);
        f->hooks.power_cut();
    }
    return rc;
}

static int flash_program(void *ctx, uint32_t addr, const void *data, size_t len)
{
    sim_flash_t *f = ctx;
    int s = slot_of(addr);
    if (s < 0 || data == NULL || addr % SIM_FLASH_PROGRAM_UNIT != 0 ||
        len % SIM_FLASH_PROGRAM_UNIT != 0 ||
        (uint64_t)addr + len > (uint64_t)(s + 1) * SIM_FLASH_SLOT_SIZE) {
        return IB_FLASH_ERR_RANGE;
    }
    int cut = count_op(f);
    size_t n = cut ? len / 2 : len;
    f->hooks.busy_us((uint32_t)((n + SIM_FLASH_PROGRAM_UNIT - 1) / SIM_FLASH_PROGRAM_UNIT) * SIM_FLASH_PROGRAM_US);
    const uint8_t *d = data;
    for (size_t i = 0; i < n; i++) {
        f->mem[addr + i] &= d[i];
    }
    int rc = write_through(f, addr, n);
    if (cut) {
        f->hooks.log("flash: power cut while programming %zu bytes at 0x%03X (%zu written)", len,
                (unsigned)addr, n);
        f->hooks.power_cut();
    }
    return rc;
}

static int flash_read(void *ctx, uint32_t addr, void *data, size_t len)
{
    sim_flash_t *f = ctx;
    int s = slot_of(addr);
    if (s < 0 || (data == NULL && len > 0) ||
        (uint64_t)addr + len > (uint64_t)(s + 1) * SIM_FLASH_SLOT_SIZE) {
        return IB_FLASH_ERR_RANGE;
    }
    if (len > 0) {
        memcpy(data, f->mem + addr, len);
    }
    return IB_FLASH_OK;
}

void sim_flash_set_hooks(sim_flash_t *f, const sim_flash_hooks_t *hooks) { f->hooks = *hooks; }

void sim_flash_setup_if(sim_flash_t *f, ib_flash_if_t *fi)
{
    memset(fi, 0, sizeof *fi);
    fi->slot_addr[0] = 0;
    fi->slot_addr[1] = SIM_FLASH_SLOT_SIZE;
    fi->slot_size = SIM_FLASH_SLOT_SIZE;
    fi->program_unit = SIM_FLASH_PROGRAM_UNIT;
    fi->erase = flash_erase;
    fi->program = flash_program;
    fi->read = flash_read;
    fi->ctx = f;
}
