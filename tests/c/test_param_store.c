/*
 * test_param_store.c - parameter store (firmware/core/param_store.c) against a simulated
 * NOR flash: erased = 0xFF, erase sets a whole page to 0xFF, program only clears bits
 * (F1 mode: only on an erased half-word, else an error like PGERR, except 0x0000), and a
 * power cut after exactly K primitive steps (one program unit or one erase), the
 * interrupted step leaving its unit/page partly done or garbled. Also a QEMU-like flash
 * (reads 0x00 outside the loaded image, writes dropped).
 */
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "crc32c.h"
#include "ctest.h"
#include "flash_if.h"
#include "param_store.h"

/* ---------------------------------------------------------------- simulated flash */

#define SIM_PAGES 4u       /* pages 0-1: "code" that must never change; 2-3: the slots */
#define SIM_PAGE_MAX 2048u
#define SIM_BASE 0x0801F000u
#define VER 1u             /* payload version used by most tests */
#define PAY_MAX 1024u

enum { CUT_CLEAN, CUT_PARTIAL, CUT_GARBLE, CUT_MODES };
static const char *const cut_names[CUT_MODES] = {"clean", "partial", "garble"};

typedef struct {
    const char *name;
    uint32_t page_size;
    uint32_t slot_size; /* <= page_size */
    uint32_t pu;
    bool strict;  /* program only on an erased unit (STM32F1, ECC flashes) */
    bool zero_ok; /* ... except an all-zero unit (STM32F1 0x0000 rule) */
} sim_cfg_t;

static const sim_cfg_t CFG_F1 = {"f1", 1024u, 1024u, 2u, true, true};
static const sim_cfg_t CFG_F4 = {"f4", 2048u, 512u, 4u, false, false};
static const sim_cfg_t CFG_BYTE = {"byte", 1024u, 1024u, 1u, false, false};
static const sim_cfg_t CFG_ECC8 = {"ecc8", 2048u, 2048u, 8u, true, false};

typedef struct {
    uint8_t mem[SIM_PAGES * SIM_PAGE_MAX];
    sim_cfg_t cfg;
    bool qemu; /* reads return mem (zeros = outside the image), writes dropped */
    /* power cut */
    long budget; /* steps left before the cut; < 0: none */
    int cut_mode;
    bool off;     /* power is off: everything fails */
    bool cut_hit; /* the cut happened */
    uint32_t rng;
    /* counters */
    unsigned long steps, erase_calls, program_calls, read_calls;
    unsigned long misaligned_data, bad_erase_addr, bad_range;
    /* faults */
    bool fail_erase;
    bool fail_read;
    unsigned long fail_program_call; /* 1-based program() call that fails; 0: none */
    uint32_t stuck_addr;             /* bits of stuck_mask at stuck_addr never clear */
    uint8_t stuck_mask;
    uint32_t flip_addr; /* once steps >= flip_after_steps, one read of flip_addr is wrong */
    unsigned long flip_after_steps;
    bool flip_armed;
} sim_t;

static uint32_t xorshift(uint32_t *s)
{
    uint32_t x = *s ? *s : 0x9E3779B9u;
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    *s = x;
    return x;
}

static uint8_t code_byte(size_t i) { return (uint8_t)(i * 7u + 3u); }

static void sim_init(sim_t *s, const sim_cfg_t *cfg)
{
    memset(s, 0, sizeof *s);
    s->cfg = *cfg;
    s->budget = -1;
    memset(s->mem, 0xFF, sizeof s->mem);
    for (size_t i = 0; i < 2u * cfg->page_size; i++) {
        s->mem[i] = code_byte(i);
    }
}

/* QEMU: nothing loaded in the slot pages -> they read 0x00; writes dropped. */
static void sim_init_qemu(sim_t *s, const sim_cfg_t *cfg)
{
    sim_init(s, cfg);
    s->qemu = true;
    memset(s->mem + 2u * cfg->page_size, 0x00, 2u * cfg->page_size);
}

static bool sim_code_intact(const sim_t *s)
{
    for (size_t i = 0; i < 2u * s->cfg.page_size; i++) {
        if (s->mem[i] != code_byte(i)) {
            return false;
        }
    }
    return true;
}

static uint8_t *sim_slot(sim_t *s, int slot)
{
    return s->mem + (size_t)(2 + slot) * s->cfg.page_size;
}

/* Arm a power cut: K full steps run, then (CUT_CLEAN) power dies at once, or
 * (CUT_PARTIAL / CUT_GARBLE) it dies during step K+1, which is left half done. */
static void sim_arm(sim_t *s, long k, int mode, uint32_t seed)
{
    s->budget = k;
    s->cut_mode = mode;
    s->rng = seed * 2654435761u + 12345u;
    s->off = false;
    s->cut_hit = false;
    if (mode == CUT_CLEAN && k == 0) {
        s->off = true;
        s->cut_hit = true;
    }
}

static void sim_reboot(sim_t *s)
{
    s->off = false;
    s->budget = -1;
}

/* 1: run the step; 0: power dies during it. */
static int sim_step(sim_t *s)
{
    if (s->budget == 0) {
        s->off = true;
        s->cut_hit = true;
        return 0;
    }
    if (s->budget > 0) {
        s->budget--;
    }
    s->steps++;
    if (s->budget == 0 && s->cut_mode == CUT_CLEAN) {
        s->off = true;
        s->cut_hit = true;
    }
    return 1;
}

static bool sim_range(sim_t *s, uint32_t addr, size_t len, size_t *off)
{
    if (addr < SIM_BASE || (uint64_t)addr - SIM_BASE + len > (uint64_t)SIM_PAGES * s->cfg.page_size) {
        s->bad_range++;
        return false;
    }
    *off = addr - SIM_BASE;
    return true;
}

static int sim_erase(void *ctx, uint32_t addr)
{
    sim_t *s = (sim_t *)ctx;
    size_t off;
    s->erase_calls++;
    if (s->off) {
        return IB_FLASH_ERR;
    }
    if (!sim_range(s, addr, s->cfg.page_size, &off) || off % s->cfg.page_size != 0u) {
        return IB_FLASH_ERR_RANGE;
    }
    if (off < 2u * s->cfg.page_size) {
        s->bad_erase_addr++;
    }
    if (s->qemu) {
        return IB_FLASH_OK;
    }
    if (s->fail_erase) {
        return IB_FLASH_ERR_TIMEOUT;
    }
    uint8_t *p = s->mem + off;
    if (!sim_step(s)) {
        for (size_t i = 0; i < s->cfg.page_size; i++) {
            if (s->cut_mode == CUT_PARTIAL) {
                if (i < s->cfg.page_size / 2u) {
                    p[i] = 0xFFu;
                }
            } else if (s->cut_mode == CUT_GARBLE) {
                p[i] |= (uint8_t)xorshift(&s->rng); /* random bits on their way to 1 */
            }
        }
        return IB_FLASH_ERR;
    }
    memset(p, 0xFF, s->cfg.page_size);
    return IB_FLASH_OK;
}

static int sim_program(void *ctx, uint32_t addr, const void *data, size_t len)
{
    sim_t *s = (sim_t *)ctx;
    const uint8_t *d = (const uint8_t *)data;
    const uint32_t pu = s->cfg.pu;
    size_t off;
    s->program_calls++;
    if (((uintptr_t)data & 3u) != 0u) {
        s->misaligned_data++;
    }
    if (s->off) {
        return IB_FLASH_ERR;
    }
    if (!sim_range(s, addr, len, &off) || addr % pu != 0u || len % pu != 0u || len == 0u ||
        off / s->cfg.page_size != (off + len - 1u) / s->cfg.page_size) {
        return IB_FLASH_ERR_RANGE;
    }
    if (s->qemu) {
        return IB_FLASH_OK;
    }
    if (s->fail_program_call != 0u && s->program_calls == s->fail_program_call) {
        return IB_FLASH_ERR_PROTECTED;
    }
    for (size_t u = 0; u < len; u += pu) {
        uint8_t *m = s->mem + off + u;
        const uint8_t *v = d + u;
        if (s->cfg.strict) {
            bool erased = true, zero = true;
            for (size_t i = 0; i < pu; i++) {
                erased = erased && m[i] == 0xFFu;
                zero = zero && v[i] == 0x00u;
            }
            if (!erased && !(s->cfg.zero_ok && zero)) {
                return IB_FLASH_ERR_NOT_ERASED; /* PGERR: the unit is skipped */
            }
        }
        if (!sim_step(s)) {
            for (size_t i = 0; i < pu; i++) {
                if (s->cut_mode == CUT_PARTIAL) {
                    if (pu == 1u) {
                        m[i] &= (uint8_t)(v[i] | 0xF0u); /* low nibble done */
                    } else if (i < pu / 2u) {
                        m[i] &= v[i];
                    }
                } else if (s->cut_mode == CUT_GARBLE) {
                    uint8_t to_clear = (uint8_t)(m[i] & ~v[i]);
                    m[i] &= (uint8_t)~(to_clear & (uint8_t)xorshift(&s->rng));
                }
            }
            return IB_FLASH_ERR;
        }
        for (size_t i = 0; i < pu; i++) {
            uint8_t nv = (uint8_t)(m[i] & v[i]);
            if (s->stuck_mask != 0u && off + u + i == s->stuck_addr - SIM_BASE) {
                nv |= (uint8_t)(m[i] & s->stuck_mask);
            }
            m[i] = nv;
        }
    }
    return IB_FLASH_OK;
}

static int sim_read(void *ctx, uint32_t addr, void *data, size_t len)
{
    sim_t *s = (sim_t *)ctx;
    size_t off;
    s->read_calls++;
    if (s->off || s->fail_read) {
        return IB_FLASH_ERR;
    }
    if (!sim_range(s, addr, len, &off)) {
        return IB_FLASH_ERR_RANGE;
    }
    memcpy(data, s->mem + off, len);
    if (s->flip_armed && s->steps >= s->flip_after_steps && s->flip_addr >= addr &&
        s->flip_addr - addr < len) {
        ((uint8_t *)data)[s->flip_addr - addr] ^= 0x10u;
        s->flip_armed = false;
    }
    return IB_FLASH_OK;
}

static ib_flash_if_t sim_if(sim_t *s)
{
    ib_flash_if_t f;
    memset(&f, 0, sizeof f);
    f.slot_addr[0] = SIM_BASE + 2u * s->cfg.page_size;
    f.slot_addr[1] = SIM_BASE + 3u * s->cfg.page_size;
    f.slot_size = s->cfg.slot_size;
    f.program_unit = s->cfg.pu;
    f.erase = sim_erase;
    f.program = sim_program;
    f.read = sim_read;
    f.ctx = s;
    return f;
}

/* ------------------------------------------------- independent record builder (docs) */

/* Builds a record exactly as param_store.h documents it, for crafted flash states. */
static size_t build_record(uint8_t *out, uint32_t pu, uint16_t format, uint16_t ver,
                           uint32_t gen, uint8_t flags, const uint8_t *p, size_t len)
{
    const size_t a = pu > 4u ? pu : 4u;
    const size_t crc_off = (16u + len + a - 1u) / a * a;
    const size_t size = crc_off + a;
    memset(out, 0, size);
    const uint8_t magic[4] = {'I', 'B', 'P', 'S'};
    memcpy(out, magic, 4);
    out[4] = (uint8_t)format;
    out[5] = (uint8_t)(format >> 8);
    out[6] = (uint8_t)ver;
    out[7] = (uint8_t)(ver >> 8);
    for (int i = 0; i < 4; i++) {
        out[8 + i] = (uint8_t)(gen >> (8 * i));
    }
    out[12] = (uint8_t)len;
    out[13] = (uint8_t)(len >> 8);
    out[14] = flags;
    if (len != 0u) {
        memcpy(out + 16, p, len);
    }
    uint32_t crc = 0;
    for (uint8_t salt = 0; salt < 3u; salt++) {
        out[15] = salt;
        crc = ib_crc32c(0, out, crc_off);
        if (crc != 0u && crc != 0xFFFFFFFFu) {
            break;
        }
    }
    for (int i = 0; i < 4; i++) {
        out[crc_off + (size_t)i] = (uint8_t)(crc >> (8 * i));
    }
    return size;
}

/* Put raw bytes in a slot page as if erased then programmed (bypasses NOR rules). */
static void sim_set_slot(sim_t *s, int slot, const uint8_t *data, size_t n)
{
    uint8_t *p = sim_slot(s, slot);
    memset(p, s->qemu ? 0x00 : 0xFF, s->cfg.page_size);
    if (n != 0u) {
        memcpy(p, data, n);
    }
}

static void put_record(sim_t *s, int slot, uint32_t gen, uint8_t flags, const uint8_t *p,
                       size_t len)
{
    static uint8_t rec[SIM_PAGE_MAX];
    size_t n = build_record(rec, s->cfg.pu, 1u, VER, gen, flags, p, len);
    sim_set_slot(s, slot, rec, n);
}

/* ------------------------------------------------------------------------- helpers */

static void fill_payload(uint8_t *p, size_t n, uint32_t seed)
{
    uint32_t r = seed;
    for (size_t i = 0; i < n; i++) {
        p[i] = (uint8_t)xorshift(&r);
    }
}

typedef struct {
    ib_ps_status_t rc;
    uint32_t gen;
    uint16_t ver;
    uint16_t len;
    int slot;
    uint8_t data[PAY_MAX];
} outcome_t;

static void observe(sim_t *s, outcome_t *o)
{
    ib_flash_if_t f = sim_if(s);
    ib_ps_info_t info;
    memset(o, 0, sizeof *o);
    o->rc = ib_ps_load(&f, VER, o->data, sizeof o->data, &info);
    o->gen = info.generation;
    o->ver = info.payload_version;
    o->len = info.payload_len;
    o->slot = info.slot;
    if (o->rc != IB_PS_OK && o->rc != IB_PS_ERR_PAYLOAD_VERSION) {
        memset(o->data, 0, sizeof o->data);
    }
}

static bool outcome_eq(const outcome_t *a, const outcome_t *b)
{
    return a->rc == b->rc && a->gen == b->gen && a->ver == b->ver && a->len == b->len &&
           memcmp(a->data, b->data, a->len) == 0;
}

static uint32_t next_gen(const outcome_t *o)
{
    if (o->rc == IB_PS_ERR_NO_VALID_SLOT) {
        return 1u;
    }
    return o->gen == 0xFFFFFFFFu ? 1u : o->gen + 1u;
}

/* ------------------------------------------------------------------------- tests */

static sim_t g_sim, g_base, g_ref, g_work, g_mid;
static uint8_t g_pa[PAY_MAX], g_pb[PAY_MAX], g_pc[PAY_MAX];
static unsigned long g_cut_points;

static void roundtrip_cfg(const sim_cfg_t *cfg)
{
    sim_t *s = &g_sim;
    sim_init(s, cfg);
    ib_flash_if_t f = sim_if(s);
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    static const size_t lens[] = {0u, 1u, 7u, 160u, 333u};

    for (size_t i = 0; i < sizeof lens / sizeof lens[0]; i++) {
        size_t n = lens[i];
        fill_payload(g_pa, n, (uint32_t)(i + 1u));
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, n, &info), IB_PS_OK);
        CHECK_EQ_INT(info.generation, i + 1u);
        memset(out, 0xA5, sizeof out);
        CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
        CHECK_EQ_INT(info.payload_len, n);
        CHECK_EQ_INT(info.payload_version, VER);
        CHECK_EQ_INT(info.generation, i + 1u);
        CHECK(!info.cleared);
        CHECK(memcmp(out, g_pa, n) == 0);
        CHECK_EQ_INT(out[n], 0xA5); /* nothing written past the payload */
    }
    CHECK(sim_code_intact(s));
    CHECK_EQ_INT(s->misaligned_data, 0);
    CHECK_EQ_INT(s->bad_erase_addr, 0);
    CHECK_EQ_INT(s->bad_range, 0);
}

static void test_roundtrip(void)
{
    roundtrip_cfg(&CFG_F1);
    roundtrip_cfg(&CFG_F4);
    roundtrip_cfg(&CFG_BYTE);
    roundtrip_cfg(&CFG_ECC8);
}

/* What save writes is byte for byte the documented layout. */
static void test_layout_matches_doc(void)
{
    const sim_cfg_t *cfgs[] = {&CFG_F1, &CFG_F4, &CFG_BYTE, &CFG_ECC8};
    static uint8_t rec[SIM_PAGE_MAX];
    for (size_t c = 0; c < 4u; c++) {
        sim_t *s = &g_sim;
        sim_init(s, cfgs[c]);
        ib_flash_if_t f = sim_if(s);
        fill_payload(g_pa, 101u, 77u);
        CHECK_EQ_INT(ib_ps_save(&f, 0x1234u, g_pa, 101u, NULL), IB_PS_OK);
        size_t n = build_record(rec, cfgs[c]->pu, 1u, 0x1234u, 1u, 0u, g_pa, 101u);
        CHECK_EQ_INT(n, ib_ps_record_size(101u, cfgs[c]->pu));
        CHECK(memcmp(sim_slot(s, 0), rec, n) == 0);
        CHECK_EQ_INT(sim_slot(s, 0)[n], 0xFF); /* nothing beyond the record */
        CHECK_EQ_INT(sim_slot(s, 0)[0], 'I');
    }
    /* A crafted record is accepted. */
    sim_init(&g_sim, &CFG_F1);
    ib_flash_if_t f = sim_if(&g_sim);
    uint8_t out[64];
    put_record(&g_sim, 1, 42u, 0u, (const uint8_t *)"hello", 5u);
    ib_ps_info_t info;
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);
    CHECK_EQ_INT(info.generation, 42u);
    CHECK(memcmp(out, "hello", 5) == 0);
    CHECK_EQ_INT(ib_ps_record_size(0u, 2u), 20u);
    CHECK_EQ_INT(ib_ps_record_size(5u, 2u), 28u);
    CHECK_EQ_INT(ib_ps_record_size(5u, 8u), 32u);
    CHECK_EQ_INT(ib_ps_record_size(5u, 3u), 0u);
}

static void test_generations_alternate(void)
{
    sim_t *s = &g_sim;
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    for (uint32_t i = 0; i < 7u; i++) {
        fill_payload(g_pa, 160u, 100u + i);
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, &info), IB_PS_OK);
        CHECK_EQ_INT(info.slot, (int)(i % 2u));
        CHECK_EQ_INT(info.generation, i + 1u);
        CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
        CHECK_EQ_INT(info.slot, (int)(i % 2u));
        CHECK_EQ_INT(info.generation, i + 1u);
        CHECK(memcmp(out, g_pa, 160u) == 0);
        if (i > 0u) {
            CHECK_EQ_INT(info.slot_state[0], IB_PS_SLOT_VALID);
            CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_VALID);
            CHECK_EQ_INT(info.slot_generation[1 - (int)(i % 2u)], i);
        }
    }
    CHECK_EQ_INT(s->erase_calls, 7);
}

/* Flash wear: saving the block the store already holds changes nothing (no erase, no
 * program), says so, and keeps the generation; a different block is still saved; a payload of
 * another version or length is not taken for the same. */
static void test_unchanged_save_does_not_touch_flash(void)
{
    sim_t *s = &g_sim;
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    ib_ps_info_t info;
    fill_payload(g_pa, 160u, 7u);
    fill_payload(g_pb, 160u, 8u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, &info), IB_PS_OK);
    CHECK(!info.unchanged);
    const unsigned long erases = s->erase_calls, programs = s->program_calls;
    for (int i = 0; i < 1000; i++) {
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, &info), IB_PS_OK);
    }
    CHECK(info.unchanged);
    CHECK_EQ_INT(info.generation, 1u);
    CHECK_EQ_INT(info.slot, 0);
    CHECK_EQ_INT(s->erase_calls, erases);
    CHECK_EQ_INT(s->program_calls, programs);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_OK); /* changed: saved */
    CHECK(!info.unchanged);
    CHECK_EQ_INT(info.generation, 2u);
    CHECK_EQ_INT(s->erase_calls, erases + 1u);
    CHECK_EQ_INT(ib_ps_save(&f, (uint16_t)(VER + 1u), g_pb, 160u, &info), IB_PS_OK); /* other version */
    CHECK(!info.unchanged);
    CHECK_EQ_INT(info.generation, 3u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 159u, &info), IB_PS_OK); /* other length */
    CHECK(!info.unchanged);
    CHECK_EQ_INT(info.generation, 4u);
}

static void test_load_picks_newer(void)
{
    sim_t *s = &g_sim;
    uint8_t out[64];
    ib_ps_info_t info;
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    put_record(s, 0, 10u, 0u, (const uint8_t *)"AAAA", 4u);
    put_record(s, 1, 9u, 0u, (const uint8_t *)"BBBB", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 0);
    CHECK(memcmp(out, "AAAA", 4) == 0);
    put_record(s, 1, 11u, 0u, (const uint8_t *)"BBBB", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);
    CHECK(memcmp(out, "BBBB", 4) == 0);
    /* The next save goes to the slot NOT holding the newest record. */
    CHECK_EQ_INT(ib_ps_save(&f, VER, "CCCC", 4u, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 0);
    CHECK_EQ_INT(info.generation, 12u);
    /* Equal generations (never written by save): deterministic, slot 0. */
    put_record(s, 0, 5u, 0u, (const uint8_t *)"AAAA", 4u);
    put_record(s, 1, 5u, 0u, (const uint8_t *)"BBBB", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 0);
}

static void test_generation_wraparound(void)
{
    sim_t *s = &g_sim;
    uint8_t out[64];
    ib_ps_info_t info;
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);

    put_record(s, 0, 0xFFFFFFFFu, 0u, (const uint8_t *)"OLD!", 4u);
    put_record(s, 1, 0u, 0u, (const uint8_t *)"NEW!", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);
    CHECK(memcmp(out, "NEW!", 4) == 0);

    put_record(s, 0, 0xFFFFFFFFu, 0u, (const uint8_t *)"NEW!", 4u);
    put_record(s, 1, 0xFFFFFFFEu, 0u, (const uint8_t *)"OLD!", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 0);

    put_record(s, 0, 0x7FFFFFF0u, 0u, (const uint8_t *)"OLD!", 4u);
    put_record(s, 1, 0x80000005u, 0u, (const uint8_t *)"NEW!", 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);

    /* Save through the wrap: ...FFFE -> FFFF -> 1 (0 is skipped: it means "none") -> 2. */
    sim_init(s, &CFG_F1);
    put_record(s, 1, 0xFFFFFFFEu, 0u, (const uint8_t *)"OLD!", 4u);
    static const uint32_t want[] = {0xFFFFFFFFu, 1u, 2u, 3u};
    for (int i = 0; i < 4; i++) {
        fill_payload(g_pa, 20u, (uint32_t)i + 5u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 20u, &info), IB_PS_OK);
        CHECK_EQ_INT(info.generation, want[i]);
        CHECK_EQ_INT(info.slot, i % 2);
        CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
        CHECK_EQ_INT(info.generation, want[i]);
        CHECK(memcmp(out, g_pa, 20u) == 0);
    }
}

/* Every single flipped bit of the newer record makes load fall back to the older one. */
static void bitflip_cfg(const sim_cfg_t *cfg)
{
    sim_t *s = &g_sim;
    uint8_t out[PAY_MAX];
    ib_ps_info_t info;
    sim_init(s, cfg);
    ib_flash_if_t f = sim_if(s);
    fill_payload(g_pa, 61u, 1u);
    fill_payload(g_pb, 61u, 2u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 61u, NULL), IB_PS_OK);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 61u, NULL), IB_PS_OK); /* slot 1, newer */
    const size_t n = ib_ps_record_size(61u, cfg->pu);
    int bad = 0;
    for (size_t byte = 0; byte < n; byte++) {
        for (int bit = 0; bit < 8; bit++) {
            sim_slot(s, 1)[byte] ^= (uint8_t)(1u << bit);
            ib_ps_status_t rc = ib_ps_load(&f, VER, out, sizeof out, &info);
            if (rc != IB_PS_OK || info.slot != 0 || info.generation != 1u ||
                memcmp(out, g_pa, 61u) != 0 || info.slot_state[1] == IB_PS_SLOT_VALID) {
                bad++;
            }
            sim_slot(s, 1)[byte] ^= (uint8_t)(1u << bit);
        }
    }
    CHECK_EQ_INT(bad, 0);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);
    /* A flipped payload bit is reported as a CRC failure. */
    sim_slot(s, 1)[20] ^= 1u;
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_CRC);
    CHECK(memcmp(out, g_pa, 61u) == 0);
}

static void test_bitflip_falls_back(void)
{
    bitflip_cfg(&CFG_F1);
    bitflip_cfg(&CFG_ECC8);
    bitflip_cfg(&CFG_BYTE);
}

static void test_blank_flash_ff(void)
{
    sim_t *s = &g_sim;
    uint8_t out[64];
    ib_ps_info_t info;
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    unsigned long steps = s->steps;
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_NO_VALID_SLOT);
    CHECK_EQ_INT(info.slot, -1);
    CHECK_EQ_INT(info.generation, 0);
    CHECK_EQ_INT(info.slot_state[0], IB_PS_SLOT_BLANK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BLANK);
    CHECK_EQ_INT(s->steps, steps); /* load never writes */
    CHECK_EQ_INT(s->program_calls + s->erase_calls, 0);
    /* A header written but no CRC yet: incomplete. */
    static uint8_t rec[64];
    size_t n = build_record(rec, 2u, 1u, VER, 1u, 0u, (const uint8_t *)"abcd", 4u);
    memset(rec + n - 4u, 0xFF, 4u);
    sim_set_slot(s, 0, rec, n);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_NO_VALID_SLOT);
    CHECK_EQ_INT(info.slot_state[0], IB_PS_SLOT_INCOMPLETE);
}

static void test_qemu_flash(void)
{
    sim_t *s = &g_sim;
    uint8_t out[PAY_MAX];
    ib_ps_info_t info;
    sim_init_qemu(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_NO_VALID_SLOT);
    CHECK_EQ_INT(info.slot_state[0], IB_PS_SLOT_BLANK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BLANK);
    fill_payload(g_pa, 160u, 3u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, &info), IB_PS_ERR_VERIFY);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_NO_VALID_SLOT);
    CHECK_EQ_INT(ib_ps_clear(&f, &info), IB_PS_ERR_VERIFY);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_NO_VALID_SLOT);
    CHECK(sim_code_intact(s));

    /* A page preloaded with -device loader (made by a real save) is used; saving fails
     * with a verify error and leaves it current. */
    sim_init(&g_ref, &CFG_F1);
    ib_flash_if_t fr = sim_if(&g_ref);
    CHECK_EQ_INT(ib_ps_save(&fr, VER, g_pa, 160u, NULL), IB_PS_OK);
    sim_init_qemu(s, &CFG_F1);
    memcpy(sim_slot(s, 0), sim_slot(&g_ref, 0), ib_ps_record_size(160u, 2u));
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK(memcmp(out, g_pa, 160u) == 0);
    fill_payload(g_pb, 160u, 4u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_VERIFY);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.generation, 1u);
    CHECK(memcmp(out, g_pa, 160u) == 0);
    CHECK_EQ_INT(ib_ps_clear(&f, &info), IB_PS_ERR_VERIFY);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
}

/* ------------------------------------------------------------- power-cut sweeps */

typedef enum { OP_SAVE, OP_CLEAR } op_t;

static ib_ps_status_t do_op(sim_t *s, op_t op, const uint8_t *p, size_t len)
{
    ib_flash_if_t f = sim_if(s);
    return op == OP_SAVE ? ib_ps_save(&f, VER, p, len, NULL) : ib_ps_clear(&f, NULL);
}

/*
 * From the state in *base, run `op` with a power cut after every K = 0..N steps (N = the
 * steps of the uncut operation) in every cut mode; after each cut reboot and load: the
 * result must be the old or the new state, bit-exact; then a fresh save and load work.
 * Returns the number of failing cut points.
 */
static int sweep(const sim_t *base, op_t op, const uint8_t *p, size_t len, const char *what)
{
    static outcome_t old_o, new_o, got, after;
    int failures = 0;

    g_ref = *base;
    observe(&g_ref, &old_o);
    g_ref.steps = 0;
    ib_ps_status_t rc = do_op(&g_ref, op, p, len);
    CHECK_EQ_INT(rc, IB_PS_OK);
    const long n_steps = (long)g_ref.steps;
    observe(&g_ref, &new_o);
    if (op == OP_SAVE) {
        CHECK_EQ_INT(new_o.rc, IB_PS_OK);
        CHECK_EQ_INT(new_o.len, len);
        CHECK(memcmp(new_o.data, p, len) == 0);
    } else {
        CHECK_EQ_INT(new_o.rc, IB_PS_CLEARED);
    }

    for (int mode = 0; mode < CUT_MODES; mode++) {
        for (long k = 0; k <= n_steps; k++) {
            sim_t *w = &g_work;
            *w = *base;
            sim_arm(w, k, mode, (uint32_t)(k * 7 + mode));
            rc = do_op(w, op, p, len);
            const bool cut = w->cut_hit;
            sim_reboot(w);
            observe(w, &got);
            g_cut_points++;
            bool ok = outcome_eq(&got, &old_o) || outcome_eq(&got, &new_o);
            if (!cut && rc != IB_PS_OK) {
                ok = false; /* no cut: must succeed */
            }
            if (k >= n_steps && !outcome_eq(&got, &new_o)) {
                ok = false; /* every step done: must be the new state */
            }
            if (!sim_code_intact(w)) {
                ok = false;
            }
            /* The store still works: a fresh save, then load. */
            fill_payload(g_pc, 33u, (uint32_t)k + 999u);
            ib_flash_if_t f = sim_if(w);
            ib_ps_info_t info;
            if (ib_ps_save(&f, VER, g_pc, 33u, &info) != IB_PS_OK ||
                info.generation != next_gen(&got)) {
                ok = false;
            }
            observe(w, &after);
            if (after.rc != IB_PS_OK || after.len != 33u || memcmp(after.data, g_pc, 33u) != 0 ||
                after.gen != next_gen(&got)) {
                ok = false;
            }
            if (!ok) {
                failures++;
                if (failures <= 5) {
                    printf("  %s/%s: cut at K=%ld (%s) of %ld: save rc %d, load rc %d gen %u "
                           "(old rc %d gen %u, new rc %d gen %u), then rc %d gen %u\n",
                           w->cfg.name, what, k, cut_names[mode], n_steps, (int)rc,
                           (int)got.rc, (unsigned)got.gen, (int)old_o.rc, (unsigned)old_o.gen,
                           (int)new_o.rc, (unsigned)new_o.gen, (int)after.rc,
                           (unsigned)after.gen);
                }
            }
        }
    }
    return failures;
}

enum { ST_EMPTY, ST_ONE, ST_TWO, ST_CLEARED, ST_WRAP, ST_GARBAGE, ST_QEMU_ZERO_SLOT, ST_COUNT };
static const char *const st_names[ST_COUNT] = {"empty", "one", "two", "cleared", "wrap",
                                               "garbage", "zeroed-slot"};

static void make_state(sim_t *s, const sim_cfg_t *cfg, int st)
{
    sim_init(s, cfg);
    ib_flash_if_t f = sim_if(s);
    uint8_t tmp[200];
    switch (st) {
    case ST_EMPTY:
        break;
    case ST_ONE:
        fill_payload(tmp, 160u, 11u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, tmp, 160u, NULL), IB_PS_OK);
        break;
    case ST_TWO:
        fill_payload(tmp, 160u, 12u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, tmp, 160u, NULL), IB_PS_OK);
        fill_payload(tmp, 150u, 13u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, tmp, 150u, NULL), IB_PS_OK);
        break;
    case ST_CLEARED:
        fill_payload(tmp, 160u, 14u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, tmp, 160u, NULL), IB_PS_OK);
        CHECK_EQ_INT(ib_ps_clear(&f, NULL), IB_PS_OK);
        break;
    case ST_WRAP:
        fill_payload(tmp, 160u, 15u);
        put_record(s, 0, 0xFFFFFFFEu, 0u, tmp, 160u);
        fill_payload(tmp, 160u, 16u);
        put_record(s, 1, 0xFFFFFFFFu, 0u, tmp, 160u);
        break;
    case ST_GARBAGE: {
        fill_payload(tmp, 160u, 17u);
        put_record(s, 1, 5u, 0u, tmp, 160u);
        uint8_t *g = sim_slot(s, 0);
        fill_payload(g, cfg->page_size, 18u);
        memcpy(g, "IBPS\x01\x00", 6); /* plausible header start, garbage after */
        break;
    }
    case ST_QEMU_ZERO_SLOT: /* one record, the other slot reads 0x00 (all bits programmed) */
        fill_payload(tmp, 160u, 19u);
        CHECK_EQ_INT(ib_ps_save(&f, VER, tmp, 160u, NULL), IB_PS_OK);
        memset(sim_slot(s, 1), 0x00, cfg->page_size);
        break;
    default:
        break;
    }
}

static void cut_save_cfg(const sim_cfg_t *cfg)
{
    int failures = 0;
    for (int st = 0; st < ST_COUNT; st++) {
        make_state(&g_base, cfg, st);
        fill_payload(g_pb, 101u, 1000u + (uint32_t)st);
        failures += sweep(&g_base, OP_SAVE, g_pb, 101u, st_names[st]);
        /* A zero-length payload too (only the header and the CRC). */
        failures += sweep(&g_base, OP_SAVE, g_pb, 0u, st_names[st]);
    }
    CHECK_EQ_INT(failures, 0);
}

static void test_power_cut_save_f1(void) { cut_save_cfg(&CFG_F1); }
static void test_power_cut_save_f4(void) { cut_save_cfg(&CFG_F4); }
static void test_power_cut_save_byte(void) { cut_save_cfg(&CFG_BYTE); }
static void test_power_cut_save_ecc8(void) { cut_save_cfg(&CFG_ECC8); }

static void cut_clear_cfg(const sim_cfg_t *cfg)
{
    int failures = 0;
    for (int st = 0; st < ST_COUNT; st++) {
        make_state(&g_base, cfg, st);
        failures += sweep(&g_base, OP_CLEAR, NULL, 0u, st_names[st]);
    }
    CHECK_EQ_INT(failures, 0);
}

static void test_power_cut_clear(void)
{
    cut_clear_cfg(&CFG_F1);
    cut_clear_cfg(&CFG_F4);
    cut_clear_cfg(&CFG_BYTE);
    cut_clear_cfg(&CFG_ECC8);
}

/* A cut during a save, reboot, then a cut at every step of the next save. */
static void double_cut_cfg(const sim_cfg_t *cfg)
{
    int failures = 0;
    make_state(&g_base, cfg, ST_TWO);
    fill_payload(g_pa, 101u, 2001u);
    fill_payload(g_pb, 77u, 2002u);
    g_ref = g_base;
    g_ref.steps = 0;
    CHECK_EQ_INT(do_op(&g_ref, OP_SAVE, g_pa, 101u), IB_PS_OK);
    const long n1 = (long)g_ref.steps;
    for (int mode = CUT_PARTIAL; mode <= CUT_GARBLE; mode++) {
        for (long k1 = 0; k1 < n1; k1++) {
            g_mid = g_base;
            sim_arm(&g_mid, k1, mode, (uint32_t)(k1 * 13 + 5));
            (void)do_op(&g_mid, OP_SAVE, g_pa, 101u);
            sim_reboot(&g_mid);
            g_mid.steps = 0;
            failures += sweep(&g_mid, OP_SAVE, g_pb, 77u, "second save");
        }
    }
    CHECK_EQ_INT(failures, 0);
}

static void test_power_cut_twice(void)
{
    double_cut_cfg(&CFG_F1);
    double_cut_cfg(&CFG_ECC8);
}

/* ------------------------------------------------------- errors and arguments */

static void test_too_large(void)
{
    sim_t *s = &g_sim;
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    sim_init(s, &CFG_F4); /* 512-byte slots */
    ib_flash_if_t f = sim_if(s);
    const size_t max = ib_ps_max_payload(&f);
    CHECK_EQ_INT(max, 512u - 4u - 16u);
    CHECK(ib_ps_record_size(max, 4u) <= 512u);
    CHECK(ib_ps_record_size(max + 1u, 4u) > 512u);
    fill_payload(g_pa, max + 1u, 9u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, max + 1u, &info), IB_PS_ERR_TOO_LARGE);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 100000u, &info), IB_PS_ERR_TOO_LARGE);
    CHECK_EQ_INT(s->erase_calls + s->program_calls, 0);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, max, &info), IB_PS_OK);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.payload_len, max);
    CHECK(memcmp(out, g_pa, max) == 0);
    /* Load into a buffer that is too small: refused, nothing copied. */
    memset(out, 0x5A, sizeof out);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, max - 1u, &info), IB_PS_ERR_TOO_LARGE);
    CHECK_EQ_INT(info.payload_len, max);
    CHECK_EQ_INT(out[0], 0x5A);
    /* F1 1 KiB page. */
    sim_init(s, &CFG_F1);
    f = sim_if(s);
    CHECK_EQ_INT(ib_ps_max_payload(&f), 1024u - 4u - 16u);
}

static void test_payload_version_mismatch(void)
{
    sim_t *s = &g_sim;
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    fill_payload(g_pa, 160u, 21u);
    CHECK_EQ_INT(ib_ps_save(&f, 1u, g_pa, 160u, NULL), IB_PS_OK);
    fill_payload(g_pb, 120u, 22u);
    CHECK_EQ_INT(ib_ps_save(&f, 2u, g_pb, 120u, NULL), IB_PS_OK);
    /* Firmware expecting layout 1 sees the newest record is layout 2: reported, not
     * silently replaced by the older layout-1 record; the bytes are there to migrate. */
    CHECK_EQ_INT(ib_ps_load(&f, 1u, out, sizeof out, &info), IB_PS_ERR_PAYLOAD_VERSION);
    CHECK_EQ_INT(info.payload_version, 2u);
    CHECK_EQ_INT(info.payload_len, 120u);
    CHECK_EQ_INT(info.generation, 2u);
    CHECK(memcmp(out, g_pb, 120u) == 0);
    CHECK_EQ_INT(ib_ps_load(&f, 2u, out, sizeof out, &info), IB_PS_OK);
}

static void test_rejected_headers(void)
{
    sim_t *s = &g_sim;
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    static uint8_t rec[SIM_PAGE_MAX];
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    put_record(s, 0, 1u, 0u, (const uint8_t *)"good", 4u);

    /* Unsupported store format in the newer slot: ignored, older one used. */
    size_t n = build_record(rec, 2u, 2u, VER, 2u, 0u, (const uint8_t *)"fmt2", 4u);
    sim_set_slot(s, 1, rec, n);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 0);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_FORMAT);
    /* Unknown flag bit. */
    n = build_record(rec, 2u, 1u, VER, 2u, 0x80u, (const uint8_t *)"flag", 4u);
    sim_set_slot(s, 1, rec, n);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_HEADER);
    /* Cleared record with a payload. */
    n = build_record(rec, 2u, 1u, VER, 2u, IB_PS_FLAG_CLEARED, (const uint8_t *)"clrd", 4u);
    sim_set_slot(s, 1, rec, n);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_HEADER);
    /* Length beyond the slot, with a matching CRC over what is there. */
    n = build_record(rec, 2u, 1u, VER, 2u, 0u, g_pa, 1020u);
    CHECK(n > 1024u);
    sim_set_slot(s, 1, rec, 1024u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_LENGTH);
    /* Bad magic. */
    n = build_record(rec, 2u, 1u, VER, 2u, 0u, (const uint8_t *)"mgc!", 4u);
    rec[0] = 'X';
    sim_set_slot(s, 1, rec, n);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_BAD_MAGIC);
    CHECK(strcmp(ib_ps_slot_state_name(info.slot_state[1]), "bad magic") == 0);
    CHECK(strcmp(ib_ps_status_name(IB_PS_ERR_VERIFY), "verify error") == 0);
}

static void test_clear(void)
{
    sim_t *s = &g_sim;
    ib_ps_info_t info;
    uint8_t out[PAY_MAX];
    sim_init(s, &CFG_F1);
    ib_flash_if_t f = sim_if(s);
    fill_payload(g_pa, 160u, 31u);
    fill_payload(g_pb, 160u, 32u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, NULL), IB_PS_OK);
    CHECK_EQ_INT(ib_ps_clear(&f, &info), IB_PS_OK);
    CHECK_EQ_INT(info.generation, 3u);
    CHECK(info.cleared);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_CLEARED);
    CHECK(info.cleared);
    CHECK_EQ_INT(info.generation, 3u);
    CHECK_EQ_INT(info.payload_len, 0u);
    /* The older record (gen 2, g_pb) is still in the other slot but not used. */
    CHECK_EQ_INT(info.slot_state[1], IB_PS_SLOT_VALID);
    /* Clearing again writes nothing. */
    unsigned long writes = s->erase_calls + s->program_calls;
    CHECK_EQ_INT(ib_ps_clear(&f, &info), IB_PS_OK);
    CHECK_EQ_INT(s->erase_calls + s->program_calls, writes);
    /* And a save after a clear. */
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, &info), IB_PS_OK);
    CHECK_EQ_INT(info.generation, 4u);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK(memcmp(out, g_pa, 160u) == 0);
    /* Clear on empty flash leaves a cleared record. */
    sim_init(s, &CFG_F1);
    CHECK_EQ_INT(ib_ps_clear(&f, &info), IB_PS_OK);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_CLEARED);
    CHECK_EQ_INT(info.generation, 1u);
}

static void check_old_kept(sim_t *s, uint32_t gen)
{
    uint8_t out[PAY_MAX];
    ib_ps_info_t info;
    ib_flash_if_t f = sim_if(s);
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_OK);
    CHECK_EQ_INT(info.generation, gen);
    CHECK(memcmp(out, g_pa, 160u) == 0);
}

static void flash_faults_cfg(const sim_cfg_t *cfg)
{
    sim_t *s = &g_sim;
    ib_ps_info_t info;
    fill_payload(g_pa, 160u, 41u);
    fill_payload(g_pb, 160u, 42u);
    const size_t rec = ib_ps_record_size(160u, cfg->pu);
    const size_t a = cfg->pu > 4u ? cfg->pu : 4u;
    const unsigned long data_calls = (unsigned long)((rec - a + 63u) / 64u);

    /* Erase fails. */
    sim_init(s, cfg);
    ib_flash_if_t f = sim_if(s);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
    s->fail_erase = true;
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_FLASH_ERASE);
    check_old_kept(s, 1u);
    s->fail_erase = false;
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_OK);
    CHECK_EQ_INT(info.generation, 2u);

    /* Program fails on the header, then on the CRC unit. */
    for (unsigned long which = 1; which <= data_calls + 1u; which += data_calls) {
        sim_init(s, cfg);
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
        s->fail_program_call = s->program_calls + which;
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_FLASH_PROGRAM);
        check_old_kept(s, 1u);
        s->fail_program_call = 0;
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_OK);
    }

    /* A bit that will not program, in the payload and in the CRC: verify error. */
    for (int where = 0; where < 2; where++) {
        sim_init(s, cfg);
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
        size_t off = where == 0 ? 16u + 50u : rec - a;
        s->stuck_addr = f.slot_addr[1] + (uint32_t)off;
        s->stuck_mask = 0xFF; /* nothing programs at that byte */
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_VERIFY);
        check_old_kept(s, 1u);
        s->stuck_mask = 0;
        CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_OK);
    }

    /* Flash written perfectly but the final read-back is wrong once: save reports the
     * error, and the new record must NOT become current (it is invalidated). */
    sim_init(s, cfg);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
    s->steps = 0;
    s->flip_addr = f.slot_addr[1] + 16u + 3u;
    s->flip_after_steps = 1u + (unsigned long)(rec / cfg->pu);
    s->flip_armed = true;
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_VERIFY);
    check_old_kept(s, 1u);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_OK);
    CHECK_EQ_INT(info.slot, 1);
    CHECK_EQ_INT(info.generation, 2u);

    /* Read errors: load reports them; save refuses to write anything. */
    sim_init(s, cfg);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pa, 160u, NULL), IB_PS_OK);
    s->fail_read = true;
    unsigned long writes = s->erase_calls + s->program_calls;
    uint8_t out[PAY_MAX];
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, &info), IB_PS_ERR_FLASH_READ);
    CHECK_EQ_INT(info.slot_state[0], IB_PS_SLOT_READ_ERROR);
    CHECK_EQ_INT(ib_ps_save(&f, VER, g_pb, 160u, &info), IB_PS_ERR_FLASH_READ);
    CHECK_EQ_INT(s->erase_calls + s->program_calls, writes);
    s->fail_read = false;
    check_old_kept(s, 1u);
    CHECK(sim_code_intact(s));
    CHECK_EQ_INT(s->misaligned_data, 0);
}

static void test_flash_faults(void)
{
    flash_faults_cfg(&CFG_F1);
    flash_faults_cfg(&CFG_F4);
    flash_faults_cfg(&CFG_ECC8);
}

static void test_bad_args(void)
{
    sim_t *s = &g_sim;
    uint8_t out[16];
    sim_init(s, &CFG_F1);
    ib_flash_if_t good = sim_if(s);
    ib_flash_if_t f;
    ib_ps_info_t info;

    CHECK_EQ_INT(ib_ps_load(NULL, VER, out, sizeof out, &info), IB_PS_ERR_BAD_ARG);
    CHECK_EQ_INT(ib_ps_save(NULL, VER, out, 4u, &info), IB_PS_ERR_BAD_ARG);
    CHECK_EQ_INT(ib_ps_clear(NULL, &info), IB_PS_ERR_BAD_ARG);
    CHECK_EQ_INT(ib_ps_save(&good, VER, NULL, 4u, &info), IB_PS_ERR_BAD_ARG);
    CHECK_EQ_INT(ib_ps_load(&good, VER, NULL, 4u, &info), IB_PS_ERR_BAD_ARG);
    CHECK_EQ_INT(ib_ps_load(&good, VER, NULL, 0u, NULL), IB_PS_ERR_NO_VALID_SLOT);
    CHECK_EQ_INT(ib_ps_save(&good, VER, NULL, 0u, NULL), IB_PS_OK); /* empty payload */
    CHECK_EQ_INT(ib_ps_load(&good, VER, NULL, 0u, NULL), IB_PS_OK);

    static const uint32_t bad_pu[] = {0u, 3u, 6u, 64u};
    for (size_t i = 0; i < 4u; i++) {
        f = good;
        f.program_unit = bad_pu[i];
        CHECK_EQ_INT(ib_ps_save(&f, VER, out, 4u, NULL), IB_PS_ERR_BAD_ARG);
        CHECK_EQ_INT(ib_ps_max_payload(&f), 0u);
    }
    f = good;
    f.slot_addr[1] = f.slot_addr[0] + 512u; /* overlapping */
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, NULL), IB_PS_ERR_BAD_ARG);
    f = good;
    f.slot_size = 19u; /* smaller than an empty record */
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, NULL), IB_PS_ERR_BAD_ARG);
    f = good;
    f.slot_addr[0] += 1u; /* misaligned */
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, NULL), IB_PS_ERR_BAD_ARG);
    f = good;
    f.slot_addr[1] = 0xFFFFFF00u; /* wraps past 4 GiB */
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, NULL), IB_PS_ERR_BAD_ARG);
    f = good;
    f.read = NULL;
    CHECK_EQ_INT(ib_ps_load(&f, VER, out, sizeof out, NULL), IB_PS_ERR_BAD_ARG);
    f = good;
    f.erase = NULL;
    CHECK_EQ_INT(ib_ps_clear(&f, NULL), IB_PS_ERR_BAD_ARG);
}

int main(void)
{
    RUN(test_roundtrip);
    RUN(test_layout_matches_doc);
    RUN(test_generations_alternate);
    RUN(test_unchanged_save_does_not_touch_flash);
    RUN(test_load_picks_newer);
    RUN(test_generation_wraparound);
    RUN(test_bitflip_falls_back);
    RUN(test_blank_flash_ff);
    RUN(test_qemu_flash);
    RUN(test_power_cut_save_f1);
    RUN(test_power_cut_save_f4);
    RUN(test_power_cut_save_byte);
    RUN(test_power_cut_save_ecc8);
    RUN(test_power_cut_clear);
    RUN(test_power_cut_twice);
    RUN(test_too_large);
    RUN(test_payload_version_mismatch);
    RUN(test_rejected_headers);
    RUN(test_clear);
    RUN(test_flash_faults);
    RUN(test_bad_args);
    printf("power-cut points exercised: %lu\n", g_cut_points);
    return ctest_summary();
}
