/* param_store.c - two-slot, power-cut safe parameter store; see param_store.h. */
#include "param_store.h"

#include <string.h>

#include "crc32c.h"
#include "wire.h"

/* Staging / read chunk: a multiple of every supported program unit. */
#define PS_CHUNK 64u
#define PS_READ_CHUNK 32u
#define PS_MAX_LEN 0xFFFFu /* payload_len is a u16 */

typedef struct {
    uint32_t generation;
    uint16_t payload_version;
    uint16_t payload_len;
    uint8_t flags;
} ps_hdr_t;

typedef struct {
    ib_ps_slot_state_t state[2];
    ps_hdr_t hdr[2];
    int newest; /* -1: no valid slot */
} ps_scan_t;

/* The record being written, generated on the fly for programming and verifying. */
typedef struct {
    uint8_t hdr[IB_PS_HEADER_SIZE];
    uint8_t crc[4];
    const uint8_t *payload;
    size_t len;
    size_t crc_off;
    size_t size;
} ps_rec_t;

/* 4-byte aligned buffer for program(). */
typedef struct {
    _Alignas(uint32_t) uint8_t b[PS_CHUNK];
} ps_stage_t;

static const uint8_t ps_zeros[IB_FLASH_MAX_PROGRAM_UNIT];

static bool ps_pu_ok(uint32_t pu)
{
    return pu != 0u && pu <= IB_FLASH_MAX_PROGRAM_UNIT && (pu & (pu - 1u)) == 0u;
}

/* Alignment of the CRC unit and of the record size: max(4, program unit). */
static size_t ps_align_of(uint32_t pu)
{
    return pu > 4u ? (size_t)pu : 4u;
}

static size_t ps_round_up(size_t x, size_t a)
{
    return (x + a - 1u) & ~(a - 1u);
}

size_t ib_ps_record_size(size_t n, uint32_t program_unit)
{
    if (!ps_pu_ok(program_unit) || n > PS_MAX_LEN) {
        return 0;
    }
    size_t a = ps_align_of(program_unit);
    return ps_round_up(IB_PS_HEADER_SIZE + n, a) + a;
}

static bool ps_geometry_ok(const ib_flash_if_t *fl)
{
    if (fl == NULL || fl->erase == NULL || fl->program == NULL || fl->read == NULL ||
        !ps_pu_ok(fl->program_unit)) {
        return false;
    }
    if (fl->slot_size < ib_ps_record_size(0, fl->program_unit)) {
        return false;
    }
    for (int i = 0; i < 2; i++) {
        if (fl->slot_addr[i] % fl->program_unit != 0u ||
            (uint64_t)fl->slot_addr[i] + fl->slot_size > 0x100000000ull) {
            return false;
        }
    }
    uint64_t a0 = fl->slot_addr[0], a1 = fl->slot_addr[1];
    return a0 + fl->slot_size <= a1 || a1 + fl->slot_size <= a0;
}

/* Max payload for a geometry already checked. */
static size_t ps_max_len(const ib_flash_if_t *fl)
{
    size_t a = ps_align_of(fl->program_unit);
    size_t n = ((fl->slot_size - a) / a) * a - IB_PS_HEADER_SIZE;
    return n > PS_MAX_LEN ? PS_MAX_LEN : n;
}

size_t ib_ps_max_payload(const ib_flash_if_t *fl)
{
    return ps_geometry_ok(fl) ? ps_max_len(fl) : 0u;
}

/* Serial-number arithmetic (RFC 1982 style): a is newer than b. */
static bool ps_newer(uint32_t a, uint32_t b)
{
    return a != b && (uint32_t)(a - b) < 0x80000000u;
}

/*
 * Validate one slot. Reads the header, then streams [16, crc_off) through the CRC, copying
 * the payload bytes into `copy` when non-NULL (the caller checked that they fit), so the
 * bytes handed out are exactly the bytes that matched the CRC.
 */
static ib_ps_slot_state_t ps_check_slot(const ib_flash_if_t *fl, int slot, ps_hdr_t *h,
                                        uint8_t *copy)
{
    uint8_t hdr[IB_PS_HEADER_SIZE];
    uint8_t buf[PS_READ_CHUNK];
    const uint32_t base = fl->slot_addr[slot];

    memset(h, 0, sizeof *h);
    if (fl->read(fl->ctx, base, hdr, sizeof hdr) != IB_FLASH_OK) {
        return IB_PS_SLOT_READ_ERROR;
    }
    /* Diagnostic only: validity below never depends on what blank flash reads. */
    bool same = true;
    for (size_t i = 1; i < sizeof hdr; i++) {
        same = same && hdr[i] == hdr[0];
    }
    if (same && (hdr[0] == 0x00u || hdr[0] == 0xFFu)) {
        return IB_PS_SLOT_BLANK;
    }
    if (ib_get_u32(hdr + 0) != IB_PS_MAGIC) {
        return IB_PS_SLOT_BAD_MAGIC;
    }
    if (ib_get_u16(hdr + 4) != IB_PS_FORMAT) {
        return IB_PS_SLOT_BAD_FORMAT;
    }
    h->payload_version = ib_get_u16(hdr + 6);
    h->generation = ib_get_u32(hdr + 8);
    h->payload_len = ib_get_u16(hdr + 12);
    h->flags = hdr[14];
    if ((h->flags & (uint8_t)~IB_PS_FLAG_CLEARED) != 0u ||
        ((h->flags & IB_PS_FLAG_CLEARED) != 0u && h->payload_len != 0u)) {
        return IB_PS_SLOT_BAD_HEADER;
    }
    if (h->payload_len > ps_max_len(fl)) {
        return IB_PS_SLOT_BAD_LENGTH;
    }

    const size_t a = ps_align_of(fl->program_unit);
    const size_t pay_end = IB_PS_HEADER_SIZE + (size_t)h->payload_len;
    const size_t crc_off = ps_round_up(pay_end, a);
    uint32_t crc = ib_crc32c(0, hdr, sizeof hdr);
    /* Bounded: crc_off <= slot_size, PS_READ_CHUNK bytes per pass. */
    for (size_t off = IB_PS_HEADER_SIZE; off < crc_off;) {
        size_t n = crc_off - off;
        if (n > sizeof buf) {
            n = sizeof buf;
        }
        if (fl->read(fl->ctx, base + (uint32_t)off, buf, n) != IB_FLASH_OK) {
            return IB_PS_SLOT_READ_ERROR;
        }
        crc = ib_crc32c(crc, buf, n);
        if (copy != NULL && off < pay_end) {
            size_t c = pay_end - off < n ? pay_end - off : n;
            memcpy(copy + (off - IB_PS_HEADER_SIZE), buf, c);
        }
        off += n;
    }
    /* The CRC unit: CRC, then zero padding up to a (a <= sizeof buf). */
    if (fl->read(fl->ctx, base + (uint32_t)crc_off, buf, a) != IB_FLASH_OK) {
        return IB_PS_SLOT_READ_ERROR;
    }
    const uint32_t stored = ib_get_u32(buf);
    if (stored == 0u || stored == 0xFFFFFFFFu) {
        return IB_PS_SLOT_INCOMPLETE;
    }
    for (size_t i = 4; i < a; i++) {
        if (buf[i] != 0u) {
            return IB_PS_SLOT_BAD_CRC;
        }
    }
    if (stored != crc) {
        return IB_PS_SLOT_BAD_CRC;
    }
    return IB_PS_SLOT_VALID;
}

static void ps_scan(const ib_flash_if_t *fl, ps_scan_t *sc)
{
    for (int i = 0; i < 2; i++) {
        sc->state[i] = ps_check_slot(fl, i, &sc->hdr[i], NULL);
    }
    const bool v0 = sc->state[0] == IB_PS_SLOT_VALID;
    const bool v1 = sc->state[1] == IB_PS_SLOT_VALID;
    if (v0 && v1) {
        /* Equal generations (never written by save) or exactly 2^31 apart: slot 0. */
        sc->newest = ps_newer(sc->hdr[1].generation, sc->hdr[0].generation) ? 1 : 0;
    } else if (v0) {
        sc->newest = 0;
    } else if (v1) {
        sc->newest = 1;
    } else {
        sc->newest = -1;
    }
}

static void ps_info_reset(ib_ps_info_t *info)
{
    if (info != NULL) {
        memset(info, 0, sizeof *info);
        info->slot = -1;
        info->slot_state[0] = IB_PS_SLOT_NOT_CHECKED;
        info->slot_state[1] = IB_PS_SLOT_NOT_CHECKED;
    }
}

static void ps_info_scan(ib_ps_info_t *info, const ps_scan_t *sc)
{
    if (info == NULL) {
        return;
    }
    for (int i = 0; i < 2; i++) {
        info->slot_state[i] = sc->state[i];
        info->slot_generation[i] = sc->state[i] == IB_PS_SLOT_VALID ? sc->hdr[i].generation : 0u;
    }
}

static void ps_info_record(ib_ps_info_t *info, int slot, const ps_hdr_t *h)
{
    if (info == NULL) {
        return;
    }
    info->slot = slot;
    info->generation = h->generation;
    info->payload_version = h->payload_version;
    info->payload_len = h->payload_len;
    info->cleared = (h->flags & IB_PS_FLAG_CLEARED) != 0u;
}

ib_ps_status_t ib_ps_load(const ib_flash_if_t *fl, uint16_t expected_version, void *payload,
                          size_t capacity, ib_ps_info_t *info)
{
    ps_scan_t sc;

    ps_info_reset(info);
    if (!ps_geometry_ok(fl) || (payload == NULL && capacity != 0u)) {
        return IB_PS_ERR_BAD_ARG;
    }
    ps_scan(fl, &sc);
    ps_info_scan(info, &sc);
    if (sc.newest < 0) {
        return (sc.state[0] == IB_PS_SLOT_READ_ERROR || sc.state[1] == IB_PS_SLOT_READ_ERROR)
                   ? IB_PS_ERR_FLASH_READ
                   : IB_PS_ERR_NO_VALID_SLOT;
    }
    const int s = sc.newest;
    const ps_hdr_t *h = &sc.hdr[s];
    ps_info_record(info, s, h);
    if ((h->flags & IB_PS_FLAG_CLEARED) != 0u) {
        return IB_PS_CLEARED;
    }
    if (h->payload_len > capacity) {
        return IB_PS_ERR_TOO_LARGE;
    }
    /* Second pass copies out exactly the bytes that match the CRC. */
    ps_hdr_t h2;
    ib_ps_slot_state_t st = ps_check_slot(fl, s, &h2, (uint8_t *)payload);
    if (st != IB_PS_SLOT_VALID || h2.generation != h->generation ||
        h2.payload_len != h->payload_len || h2.payload_version != h->payload_version) {
        if (info != NULL) {
            info->slot_state[s] = st == IB_PS_SLOT_VALID ? IB_PS_SLOT_READ_ERROR : st;
        }
        return IB_PS_ERR_FLASH_READ; /* flash read back differently twice */
    }
    if (h->payload_version != expected_version) {
        return IB_PS_ERR_PAYLOAD_VERSION;
    }
    return IB_PS_OK;
}

/* Bytes [off, off+n) of the record image. */
static void ps_rec_fill(const ps_rec_t *r, size_t off, uint8_t *dst, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        const size_t p = off + i;
        uint8_t v = 0u;
        if (p < IB_PS_HEADER_SIZE) {
            v = r->hdr[p];
        } else if (p - IB_PS_HEADER_SIZE < r->len) {
            v = r->payload[p - IB_PS_HEADER_SIZE];
        } else if (p >= r->crc_off && p - r->crc_off < sizeof r->crc) {
            v = r->crc[p - r->crc_off];
        }
        dst[i] = v;
    }
}

static int ps_program_range(const ib_flash_if_t *fl, uint32_t base, const ps_rec_t *r,
                            size_t from, size_t to)
{
    ps_stage_t st;
    for (size_t off = from; off < to;) {
        size_t n = to - off;
        if (n > sizeof st.b) {
            n = sizeof st.b;
        }
        ps_rec_fill(r, off, st.b, n);
        if (fl->program(fl->ctx, base + (uint32_t)off, st.b, n) != IB_FLASH_OK) {
            return -1;
        }
        off += n;
    }
    return 0;
}

static ib_ps_status_t ps_verify_range(const ib_flash_if_t *fl, uint32_t base, const ps_rec_t *r,
                                      size_t from, size_t to)
{
    uint8_t got[PS_READ_CHUNK];
    uint8_t want[PS_READ_CHUNK];
    for (size_t off = from; off < to;) {
        size_t n = to - off;
        if (n > sizeof got) {
            n = sizeof got;
        }
        if (fl->read(fl->ctx, base + (uint32_t)off, got, n) != IB_FLASH_OK) {
            return IB_PS_ERR_FLASH_READ;
        }
        ps_rec_fill(r, off, want, n);
        if (memcmp(got, want, n) != 0) {
            return IB_PS_ERR_VERIFY;
        }
        off += n;
    }
    return IB_PS_OK;
}

/* IB_PS_OK when the payload of the (valid) record in `slot` equals payload[0 .. len),
 * IB_PS_ERR_VERIFY when it differs, IB_PS_ERR_FLASH_READ when it cannot be read. */
static ib_ps_status_t ps_same_payload(const ib_flash_if_t *fl, int slot, const uint8_t *payload, size_t len)
{
    uint8_t buf[PS_READ_CHUNK];
    const uint32_t base = fl->slot_addr[slot] + IB_PS_HEADER_SIZE;
    for (size_t off = 0; off < len;) {
        size_t n = len - off < sizeof buf ? len - off : sizeof buf;
        if (fl->read(fl->ctx, base + (uint32_t)off, buf, n) != IB_FLASH_OK) {
            return IB_PS_ERR_FLASH_READ;
        }
        if (memcmp(buf, payload + off, n) != 0) {
            return IB_PS_ERR_VERIFY;
        }
        off += n;
    }
    return IB_PS_OK;
}

/* Make sure a half-written / unverified record in `slot` can never validate: zero its
 * CRC unit (NOR only clears bits); if that is refused or not enough, erase the slot. The
 * other slot, holding the previous record, is not touched. */
static void ps_invalidate(const ib_flash_if_t *fl, int slot, size_t crc_off)
{
    ps_stage_t st;
    ps_hdr_t h;
    const uint32_t base = fl->slot_addr[slot];
    const size_t a = ps_align_of(fl->program_unit);

    memcpy(st.b, ps_zeros, a);
    int rc = fl->program(fl->ctx, base + (uint32_t)crc_off, st.b, a);
    if (rc != IB_FLASH_OK || ps_check_slot(fl, slot, &h, NULL) == IB_PS_SLOT_VALID) {
        (void)fl->erase(fl->ctx, base);
    }
}

static ib_ps_status_t ps_write(const ib_flash_if_t *fl, uint16_t payload_version, uint8_t flags,
                               const void *payload, size_t len, ib_ps_info_t *info)
{
    ps_scan_t sc;
    ps_rec_t r;

    ps_info_reset(info);
    if (!ps_geometry_ok(fl) || (payload == NULL && len != 0u)) {
        return IB_PS_ERR_BAD_ARG;
    }
    if (len > ps_max_len(fl)) {
        return IB_PS_ERR_TOO_LARGE;
    }
    ps_scan(fl, &sc);
    ps_info_scan(info, &sc);
    if (sc.state[0] == IB_PS_SLOT_READ_ERROR || sc.state[1] == IB_PS_SLOT_READ_ERROR) {
        /* Could be the current record: never overwrite what we cannot see. */
        return IB_PS_ERR_FLASH_READ;
    }
    if ((flags & IB_PS_FLAG_CLEARED) != 0u && sc.newest >= 0 &&
        (sc.hdr[sc.newest].flags & IB_PS_FLAG_CLEARED) != 0u) {
        ps_info_record(info, sc.newest, &sc.hdr[sc.newest]); /* already cleared: no wear */
        if (info != NULL) {
            info->unchanged = true;
        }
        return IB_PS_OK;
    }
    if (flags == 0u && sc.newest >= 0 && sc.hdr[sc.newest].flags == 0u &&
        sc.hdr[sc.newest].payload_version == payload_version && sc.hdr[sc.newest].payload_len == len) {
        ib_ps_status_t same = ps_same_payload(fl, sc.newest, (const uint8_t *)payload, len);
        if (same == IB_PS_OK) {
            ps_info_record(info, sc.newest, &sc.hdr[sc.newest]); /* already stored: no wear */
            if (info != NULL) {
                info->unchanged = true;
            }
            return IB_PS_OK;
        }
        if (same == IB_PS_ERR_FLASH_READ) {
            return same; /* never overwrite what we cannot see */
        }
    }

    const int target = sc.newest < 0 ? 0 : 1 - sc.newest;
    uint32_t gen = sc.newest < 0 ? 1u : sc.hdr[sc.newest].generation + 1u;
    if (gen == 0u) {
        gen = 1u; /* 0 means "none" in the protocol */
    }
    const size_t a = ps_align_of(fl->program_unit);
    r.payload = (const uint8_t *)payload;
    r.len = len;
    r.crc_off = ps_round_up(IB_PS_HEADER_SIZE + len, a);
    r.size = r.crc_off + a;
    ib_put_u32(r.hdr + 0, IB_PS_MAGIC);
    ib_put_u16(r.hdr + 4, (uint16_t)IB_PS_FORMAT);
    ib_put_u16(r.hdr + 6, payload_version);
    ib_put_u32(r.hdr + 8, gen);
    ib_put_u16(r.hdr + 12, (uint16_t)len);
    r.hdr[14] = flags;
    /* Three salts give three different CRCs (a one-byte change always changes a CRC-32),
     * so at most two are tried in vain. */
    uint32_t crc = 0u;
    for (uint8_t salt = 0u; salt < 3u; salt++) {
        r.hdr[15] = salt;
        crc = ib_crc32c(0, r.hdr, sizeof r.hdr);
        if (len != 0u) {
            crc = ib_crc32c(crc, r.payload, len);
        }
        crc = ib_crc32c(crc, ps_zeros, r.crc_off - IB_PS_HEADER_SIZE - len);
        if (crc != 0u && crc != 0xFFFFFFFFu) {
            break;
        }
    }
    ib_put_u32(r.crc, crc);

    ps_hdr_t h = {gen, payload_version, (uint16_t)len, flags};
    ps_info_record(info, target, &h);

    const uint32_t base = fl->slot_addr[target];
    if (fl->erase(fl->ctx, base) != IB_FLASH_OK) {
        return IB_PS_ERR_FLASH_ERASE;
    }
    /* Header + payload + padding. Until the CRC unit is written the record is invalid
     * (INCOMPLETE), whatever the erased value, so a failure here needs no clean-up. */
    if (ps_program_range(fl, base, &r, 0u, r.crc_off) != 0) {
        return IB_PS_ERR_FLASH_PROGRAM;
    }
    ib_ps_status_t rc = ps_verify_range(fl, base, &r, 0u, r.crc_off);
    if (rc != IB_PS_OK) {
        return rc;
    }
    /* Commit: the CRC unit, last. */
    if (ps_program_range(fl, base, &r, r.crc_off, r.size) != 0) {
        ps_invalidate(fl, target, r.crc_off);
        return IB_PS_ERR_FLASH_PROGRAM;
    }
    rc = ps_verify_range(fl, base, &r, 0u, r.size);
    if (rc == IB_PS_OK) {
        ps_hdr_t back;
        if (ps_check_slot(fl, target, &back, NULL) != IB_PS_SLOT_VALID ||
            back.generation != gen) {
            rc = IB_PS_ERR_VERIFY;
        }
    }
    if (rc != IB_PS_OK) {
        ps_invalidate(fl, target, r.crc_off);
        return rc;
    }
    return IB_PS_OK;
}

ib_ps_status_t ib_ps_save(const ib_flash_if_t *fl, uint16_t payload_version, const void *payload,
                          size_t len, ib_ps_info_t *info)
{
    return ps_write(fl, payload_version, 0u, payload, len, info);
}

ib_ps_status_t ib_ps_clear(const ib_flash_if_t *fl, ib_ps_info_t *info)
{
    return ps_write(fl, 0u, IB_PS_FLAG_CLEARED, NULL, 0u, info);
}

const char *ib_ps_status_name(ib_ps_status_t st)
{
    switch (st) {
    case IB_PS_OK: return "ok";
    case IB_PS_CLEARED: return "cleared";
    case IB_PS_ERR_BAD_ARG: return "bad argument";
    case IB_PS_ERR_FLASH_READ: return "flash read error";
    case IB_PS_ERR_FLASH_ERASE: return "flash erase error";
    case IB_PS_ERR_FLASH_PROGRAM: return "flash program error";
    case IB_PS_ERR_VERIFY: return "verify error";
    case IB_PS_ERR_TOO_LARGE: return "too large";
    case IB_PS_ERR_NO_VALID_SLOT: return "no valid slot";
    case IB_PS_ERR_PAYLOAD_VERSION: return "payload version mismatch";
    }
    return "?";
}

const char *ib_ps_slot_state_name(ib_ps_slot_state_t st)
{
    switch (st) {
    case IB_PS_SLOT_NOT_CHECKED: return "not checked";
    case IB_PS_SLOT_VALID: return "valid";
    case IB_PS_SLOT_BLANK: return "blank";
    case IB_PS_SLOT_BAD_MAGIC: return "bad magic";
    case IB_PS_SLOT_BAD_FORMAT: return "unsupported format";
    case IB_PS_SLOT_BAD_HEADER: return "bad header";
    case IB_PS_SLOT_BAD_LENGTH: return "bad length";
    case IB_PS_SLOT_INCOMPLETE: return "incomplete";
    case IB_PS_SLOT_BAD_CRC: return "bad crc";
    case IB_PS_SLOT_READ_ERROR: return "read error";
    }
    return "?";
}
