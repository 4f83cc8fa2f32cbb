/*
 * sim_board.c - the ib_board_t and ib_spi_bus_t the simulator hands to the firmware core.
 *
 * Device time (g_sim.t_us) is owned here: time_us() returns its low 32 bits; delay_us()
 * and every SPI transfer advance it (the core is "busy" for that long; the main loop then
 * waits for the wall clock to catch up, sim_main.c).
 *
 * SPI: chip select IB_CS_ACCEL goes to the ADXL355 model, IB_CS_GYRO_X/Y/Z to three
 * ADXRS450 models (axis 0/1/2, different seeds). Before each transaction the addressed
 * model is advanced to the current device time with the current world; the transaction
 * then takes SIM_SPI_US_PER_BYTE per byte plus SIM_SPI_CS_US (8 MHz SCK: 1 us per byte),
 * so a 4 kHz sample read (13 + 6 x 4 bytes in 7 transactions) costs 44 us of device time.
 * The gyro models get the exact MEAN angular rate over the interval they are advanced by
 * (from the integral of omega kept by sim_physics.c), so a rate-integrating test sees the
 * exact angle turned, however the reads fall. The accelerometer model produces each
 * output sample with the specific force at that sample's own time.
 */
#define _GNU_SOURCE
#include "sim.h"

#include <stdio.h>
#include <string.h>

#define SIM_SPI_US_PER_BYTE 1u
#define SIM_SPI_CS_US 1u
#define SIM_SPIN_LIMIT 2000u /* board calls with no progress inside one core call before
                                each further call is charged 1 us (a busy-wait loop) */

void sim_spin_reset(void) { g_sim.spin = 0; }

void sim_advance_to(uint64_t t_us)
{
    if (t_us > g_sim.t_us) {
        g_sim.t_us = t_us;
        sim_link_uart_update(&g_sim.link, t_us);
    }
}

/* A core polling time_us()/link_tx_free() in a loop is busy-waiting: charge it time so the
 * loop ends as it would on hardware. Normal code calls these a few times per call. */
static void spin_check(void)
{
    if (g_sim.in_core && ++g_sim.spin > SIM_SPIN_LIMIT) {
        sim_advance_to(g_sim.t_us + 1);
    }
}

static uint64_t model_time(int cs)
{
    return cs == IB_CS_ACCEL ? g_sim.accel.t_us : g_sim.gyro[cs - 1].t_us;
}

void sim_model_world(int cs, sim_world_t *w)
{
    const sim_physics_t *p = &g_sim.phys;
    uint64_t t = g_sim.t_us, last = model_time(cs);
    double wi[3];
    sim_phys_specific_force(p, t, w->specific_force_mps2);
    sim_phys_omega_integral(p, t, wi);
    if (t > last) {
        double dt = (double)(t - last) * 1e-6;
        for (int i = 0; i < 3; i++) {
            w->rate_rad_s[i] = (wi[i] - g_sim.omega_int_at[cs][i]) / dt;
        }
        memcpy(g_sim.omega_int_at[cs], wi, sizeof wi);
    } else {
        sim_phys_omega(p, t, w->rate_rad_s);
    }
    w->temperature_c = sim_thermal_die(&g_sim.thermal, p, cs, t); /* this sensor's die */
}

void sim_model_advance(int cs)
{
    sim_world_t w;
    if (cs == IB_CS_ACCEL) {
        /* each output sample sees the world at its own sample time (a path's specific
         * force changes between reads), then the model is brought up to now */
        adxl355_model_t *m = &g_sim.accel;
        const sim_physics_t *p = &g_sim.phys;
        while (m->measuring && m->next_sample_us > m->t_us && m->next_sample_us < g_sim.t_us) {
            uint64_t ts = m->next_sample_us;
            sim_world_t ws;
            sim_phys_specific_force(p, ts, ws.specific_force_mps2);
            sim_phys_omega(p, ts, ws.rate_rad_s);
            ws.temperature_c = sim_thermal_die(&g_sim.thermal, p, IB_CS_ACCEL, ts);
            adxl355_model_advance(m, ts, &ws);
        }
        sim_model_world(cs, &w); /* after the samples: the die is stepped forward in time */
        adxl355_model_advance(m, g_sim.t_us, &w);
    } else {
        sim_model_world(cs, &w);
        sim_adxrs450_advance(&g_sim.gyro[cs - 1], g_sim.t_us, &w);
    }
}

void sim_models_sync(void)
{
    for (int cs = 0; cs < IB_CS_COUNT; cs++) {
        sim_model_advance(cs);
    }
}

/* ---- derived seeds ---- */

static uint64_t derive(uint64_t seed, uint64_t k)
{
    sim_rng_t r;
    sim_rng_seed(&r, seed ^ (0x9E3779B97F4A7C15ull * (k + 1)));
    return sim_rng_u64(&r);
}

void sim_randomize_truth(uint64_t seed)
{
    sim_rng_t r;
    sim_rng_seed(&r, derive(seed, 100));
    adxl355_truth_t at;
    adxl355_model_random_truth(&at, &r);
    adxl355_model_set_truth(&g_sim.accel, &at);
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_truth_t gt;
        sim_adxrs450_random_truth(&gt, &r, i);
        sim_adxrs450_set_truth(&g_sim.gyro[i], &gt);
    }
    /* the dies' thermal figures, from an rng of their own (the truths above stay those of
     * the same seed before the thermal model existed) */
    sim_rng_seed(&r, derive(seed, 101));
    sim_thermal_random(&g_sim.thermal, &r);
}

/* The seed a board's identity (MCU UID, gyro serial numbers) is derived from: the seed
 * itself on the host build, the seed XOR a 64-bit FNV-1a hash of the target's name on the
 * ARM targets, so an F103 and an F4 (and the host build) of the same seed are different
 * boards, each the same board on every run. */
uint64_t sim_identity_seed(uint64_t seed, const char *target)
{
    if (target == NULL || target[0] == '\0' || strcmp(target, "host") == 0) {
        return seed;
    }
    uint64_t h = 0xCBF29CE484222325ull;
    for (const char *c = target; *c; c++) {
        h = (h ^ (uint8_t)*c) * 0x100000001B3ull;
    }
    return seed ^ h;
}

void sim_seed_models(uint64_t seed, int random_truth, const char *target)
{
    adxl355_model_init(&g_sim.accel, derive(seed, 1));
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_init(&g_sim.gyro[i], derive(seed, 2 + (uint64_t)i), i);
    }
    memset(g_sim.omega_int_at, 0, sizeof g_sim.omega_int_at);
    sim_thermal_init(&g_sim.thermal);
    if (random_truth) {
        sim_randomize_truth(seed);
    }
    sim_rng_seed(&g_sim.spi_fault_rng, derive(seed, 10));
    sim_rng_seed(&g_sim.link.fault_rng, derive(seed, 11));
    /* identity: the UID and the gyros' serial numbers of (target, seed); on the host build
     * the serials are the ones the gyros' own seeds gave them (as before targets counted) */
    uint64_t id = sim_identity_seed(seed, target);
    if (id != seed) {
        for (int i = 0; i < 3; i++) {
            sim_rng_t r;
            sim_rng_seed(&r, derive(id, 2 + (uint64_t)i));
            uint32_t sn = (uint32_t)(sim_rng_u64(&r) >> 32);
            g_sim.gyro[i].serial = sn != 0u ? sn : 1u;
        }
    }
    uint64_t u0 = derive(id, 200), u1 = derive(id, 201);
    for (int i = 0; i < 8; i++) {
        g_sim.uid[i] = (uint8_t)(u0 >> (8 * i));
    }
    for (int i = 0; i < 4; i++) {
        g_sim.uid[8 + i] = (uint8_t)(u1 >> (8 * i));
    }
    sim_apply_parts();
}

/* ---- the board's parts (--parts), kept across the models' re-seeding ---- */

static uint8_t g_parts[4] = {IB_PART_ADXL355, IB_PART_ADXRS450, IB_PART_ADXRS450, IB_PART_ADXRS450};

void sim_apply_parts(void)
{
    adxl355_model_set_part(&g_sim.accel, ib_part_by_id(g_parts[0]));
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_set_part(&g_sim.gyro[i], ib_part_by_id(g_parts[1 + i]));
    }
}

const uint8_t *sim_parts(void) { return g_parts; }

static const char *const SLOT_NAMES[4] = {"accel", "gyro_x", "gyro_y", "gyro_z"};

/* One "slot=part" item of length n into out[]; 0, or -1 with the reason in err. */
static int parse_part_item(const char *item, size_t n, uint8_t out[4], char *err, size_t errlen)
{
    const char *eq = memchr(item, '=', n);
    size_t kl = eq ? (size_t)(eq - item) : n;
    int slot = -1;
    for (int i = 0; i < 4; i++) {
        if (strlen(SLOT_NAMES[i]) == kl && strncmp(item, SLOT_NAMES[i], kl) == 0) {
            slot = i;
        }
    }
    if (!strncmp(item, "gyro", kl) && kl == 4) {
        slot = 4; /* every gyro */
    }
    if (eq == NULL || slot < 0) {
        snprintf(err, errlen, "'%.*s': expected SLOT=PART with SLOT one of accel, gyro, gyro_x, gyro_y, gyro_z",
                 (int)n, item);
        return -1;
    }
    const char *v = eq + 1;
    size_t vl = n - kl - 1u;
    const uint8_t kind = slot == 0 ? IB_PART_KIND_ACCEL_TRIAD : IB_PART_KIND_GYRO_AXIS;
    for (size_t i = 0; i < IB_PART_COUNT; i++) {
        const ib_part_desc_t *d = &ib_parts[i];
        int same = strlen(d->name) == vl;
        for (size_t j = 0; same && j < vl; j++) {
            same = (v[j] | 0x20) == (d->name[j] | 0x20);
        }
        if (same && d->kind == kind) {
            for (int k = slot == 4 ? 1 : slot; k <= (slot == 4 ? 3 : slot); k++) {
                out[k] = d->part;
            }
            return 0;
        }
    }
    char names[96] = "";
    for (size_t i = 0; i < IB_PART_COUNT; i++) {
        if (ib_parts[i].kind == kind) {
            size_t used = strlen(names);
            snprintf(names + used, sizeof names - used, "%s%s", used ? ", " : "", ib_parts[i].name);
        }
    }
    snprintf(err, errlen, "'%.*s': no such %s part (known: %s)", (int)vl, v, slot == 0 ? "accelerometer" : "gyro",
             names);
    return -1;
}

int sim_set_parts(const char *spec, char *err, size_t errlen)
{
    uint8_t parts[4] = {IB_PART_ADXL355, IB_PART_ADXRS450, IB_PART_ADXRS450, IB_PART_ADXRS450};
    const char *p = spec ? spec : "";
    while (*p) {
        const char *end = strchr(p, ',');
        size_t n = end ? (size_t)(end - p) : strlen(p);
        if (n > 0 && parse_part_item(p, n, parts, err, errlen) != 0) {
            return -1;
        }
        p += n + (end ? 1u : 0u);
    }
    memcpy(g_parts, parts, sizeof parts);
    return 0;
}

void sim_power_cycle_models(void)
{
    sim_models_sync();
    /* ADXL355: back to its power-on registers; the part itself (truth, factory bytes,
     * noise generator, random-walk bias, injected faults) stays the same part. */
    adxl355_model_t *m = &g_sim.accel;
    adxl355_model_t keep = *m;
    adxl355_model_init(m, 0);
    m->truth = keep.truth;
    memcpy(m->st_force_g, keep.st_force_g, sizeof m->st_force_g);
    memcpy(m->id, keep.id, sizeof m->id);
    memcpy(m->shadow, keep.shadow, sizeof m->shadow);
    m->reset_busy_us = keep.reset_busy_us;
    m->fault = keep.fault;
    m->rng = keep.rng;
    memcpy(m->rw_bias, keep.rw_bias, sizeof m->rw_bias);
    m->rw_last_us = keep.rw_last_us;
    m->rw_started = keep.rw_started;
    m->samples = keep.samples;
    m->temp_c = keep.temp_c;
    memcpy(m->hyst_y, keep.hyst_y, sizeof m->hyst_y); /* the die's thermal history */
    memcpy(m->hyst_h, keep.hyst_h, sizeof m->hyst_h);
    m->hyst_started = keep.hyst_started;
    m->t_us = keep.t_us;
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_power_cycle(&g_sim.gyro[i]);
    }
}

/* ---- ib_spi_bus_t ---- */

/* One SPI transaction against the addressed model at the current device time, with the
 * injected bus faults applied (shared with the ARM emulator's SPI peripheral through
 * sim_lib.c). Returns 0, or -1 when an injected bus error ate it (rx all 0xFF). Does not
 * advance device time: the caller charges the transfer time. */
int sim_spi_exchange(uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    sim_t *s = &g_sim;
    s->spi_transfers++;
    if (cs >= IB_CS_COUNT) {
        return -1;
    }
    int fail = 0;
    if (s->spi_faults.error_count[cs] > 0) {
        s->spi_faults.error_count[cs]--;
        fail = 1;
    } else if (s->spi_faults.error_prob[cs] > 0.0 &&
               sim_rng_uniform(&s->spi_fault_rng) < s->spi_faults.error_prob[cs]) {
        fail = 1;
    }
    if (fail) {
        s->spi_faults.errors_injected[cs]++;
        if (rx != NULL) {
            memset(rx, 0xFF, len);
        }
        return -1;
    }
    sim_model_advance(cs);
    if (cs == IB_CS_ACCEL) {
        adxl355_model_spi(&s->accel, tx, rx, len);
    } else {
        /* A frame of another length than 4 is answered by the model as the part would
         * (not a bus error), so the return value is not passed on. */
        (void)sim_adxrs450_spi(&s->gyro[cs - 1], tx, rx, len);
    }
    return 0;
}

static int spi_transfer(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    sim_t *s = ctx;
    s->spin = 0;
    if (cs >= IB_CS_COUNT) {
        s->spi_transfers++;
        return -1;
    }
    uint64_t t_end = s->t_us + (uint64_t)len * SIM_SPI_US_PER_BYTE + SIM_SPI_CS_US;
    int rc = sim_spi_exchange(cs, tx, rx, len);
    sim_advance_to(t_end);
    return rc;
}

static void spi_delay_us(void *ctx, uint32_t us)
{
    sim_t *s = ctx;
    s->spin = 0;
    sim_advance_to(s->t_us + us);
}

/* ---- ib_board_t ---- */

static uint32_t b_time_us(void *ctx)
{
    (void)ctx;
    spin_check();
    return (uint32_t)g_sim.t_us;
}

static void b_set_tick_hz(void *ctx, uint32_t rate_hz)
{
    sim_t *s = ctx;
    s->tick_hz = rate_hz;
    if (rate_hz != 0) {
        s->tick_base_us = s->t_us;
        s->tick_n = 1;
        s->next_tick_us = s->tick_base_us + 1000000u / rate_hz;
    }
}

static size_t b_link_tx_free(void *ctx)
{
    sim_t *s = ctx;
    spin_check();
    sim_link_uart_update(&s->link, s->t_us);
    return sim_link_tx_free(&s->link);
}

static size_t b_link_write(void *ctx, const uint8_t *data, size_t len)
{
    sim_t *s = ctx;
    s->spin = 0;
    sim_link_uart_update(&s->link, s->t_us);
    return sim_link_write(&s->link, data, len);
}

static size_t b_link_read(void *ctx, uint8_t *buf, size_t cap)
{
    sim_t *s = ctx;
    size_t n = sim_link_read(&s->link, buf, cap);
    if (n > 0) {
        s->spin = 0;
    }
    return n;
}

static void b_reboot(void *ctx)
{
    (void)ctx;
    sim_request_reset(SIM_RESET_REBOOT); /* does not return when called from the core */
}

/* The flash's hooks (sim_flash.h): device time, the power cut, the log. */
static void flash_busy_us(uint32_t us) { sim_advance_to(g_sim.t_us + us); }
static void flash_power_cut(void) { sim_request_reset(SIM_RESET_POWER_CUT); }

void sim_board_flash_hooks(void)
{
    static const sim_flash_hooks_t hooks = {flash_busy_us, flash_power_cut, sim_log};
    sim_flash_set_hooks(&g_sim.flash, &hooks);
}

void sim_board_setup(void)
{
    sim_t *s = &g_sim;
    memset(&s->spi, 0, sizeof s->spi);
    s->spi.transfer = spi_transfer;
    s->spi.delay_us = spi_delay_us;
    s->spi.ctx = s;
    s->spi.start = NULL; /* transfers run synchronously in the simulator */
    sim_flash_setup_if(&s->flash, &s->flash_if);

    ib_board_t *b = &s->board;
    memset(b, 0, sizeof *b);
    b->board_id = IB_BOARD_SIM;
    b->clock_source = IB_CLOCK_SOURCE_NONE;
    b->baud = s->baud;
    memcpy(b->uid, s->uid, sizeof b->uid);
    b->build = SIM_BUILD_ID;
    b->time_us = b_time_us;
    b->set_tick_hz = b_set_tick_hz;
    b->link_tx_free = b_link_tx_free;
    b->link_write = b_link_write;
    b->link_read = b_link_read;
    b->spi = &s->spi;
    b->flash = &s->flash_if;
    b->reboot = b_reboot;
    b->ctx = s;
}
