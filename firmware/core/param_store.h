/*
 * param_store.h - calibration parameters kept in flash across resets.
 *
 * Two slots (flash_if.h), each holding at most one record. A record carries a generation
 * counter; the valid record with the newer generation (serial-number arithmetic, so the
 * counter may wrap) is the current one. save() always writes the slot NOT holding the
 * current record, so the current record is never touched while the new one is being
 * written: a power cut at any point leaves either the previous record or the new one.
 * clear() writes a newer "cleared" record (no payload) instead of erasing: load() then
 * reports factory defaults, and a cut during clear() cannot resurrect older parameters.
 *
 * The payload is opaque (the caller owns its layout, e.g. struct params packed with
 * wire.h) and tagged with the caller's payload layout version.
 *
 * Slot layout, store format 1 (all fields little-endian; a = max(4, program_unit)):
 *
 *   offset        size  field
 *   0             4     magic            0x53504249 (bytes 'I' 'B' 'P' 'S')
 *   4             2     format           store format version, 1
 *   6             2     payload_version  caller's layout version
 *   8             4     generation       save writes newest+1 (1 on empty flash), skipping 0
 *   12            2     payload_len      N bytes
 *   14            1     flags            bit 0: CLEARED (factory reset; then N == 0);
 *                                        other bits 0 (a set unknown bit rejects the slot)
 *   15            1     crc_salt         smallest of 0, 1, 2 giving a CRC that is neither
 *                                        0x00000000 nor 0xFFFFFFFF
 *   16            N     payload
 *   16+N          P     zero padding up to crc_off = round_up(16 + N, a)
 *   crc_off       4     CRC-32C (ib_crc32c(0, bytes[0 .. crc_off)))
 *   crc_off+4     a-4   zero padding (only when program_unit > 4)
 *   record size = crc_off + a
 *
 * Rules that make it power-cut safe and blank-value agnostic:
 *  - the CRC unit is programmed last, in its own program operation(s); until then it reads
 *    as the erased value (0xFFFFFFFF, or 0x00000000 under QEMU), and a stored CRC of either
 *    value is always rejected (crc_salt guarantees a real record never has one), so a
 *    partially written record never validates, whatever the flash reads when blank;
 *  - no check ever compares against the erased value: validity = magic, format, flags,
 *    lengths, zero padding after the CRC, CRC;
 *  - a record is only ever written into the slot that does not hold the current record.
 *
 * All functions: no malloc, no floating point, bounded loops, under 512 bytes of stack.
 */
#ifndef IB_PARAM_STORE_H
#define IB_PARAM_STORE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "flash_if.h"

#define IB_PS_MAGIC 0x53504249u
#define IB_PS_FORMAT 1u
#define IB_PS_HEADER_SIZE 16u
#define IB_PS_FLAG_CLEARED 0x01u

/* Results. Negative values are errors; for load(), anything but IB_PS_OK means "use the
 * factory defaults" (IB_PS_CLEARED and IB_PS_ERR_NO_VALID_SLOT are the normal cases). */
typedef enum {
    IB_PS_OK = 0,
    IB_PS_CLEARED = 1,               /* load: newest record is a factory reset */
    IB_PS_ERR_BAD_ARG = -1,          /* NULL pointer, bad flash_if geometry, ... */
    IB_PS_ERR_FLASH_READ = -2,       /* a read callback failed */
    IB_PS_ERR_FLASH_ERASE = -3,      /* the erase callback failed */
    IB_PS_ERR_FLASH_PROGRAM = -4,    /* the program callback failed */
    IB_PS_ERR_VERIFY = -5,           /* read-back differs (e.g. QEMU drops writes) */
    IB_PS_ERR_TOO_LARGE = -6,        /* save: payload > max; load: payload > buffer */
    IB_PS_ERR_NO_VALID_SLOT = -7,    /* load: no valid record (blank, QEMU, corrupt) */
    IB_PS_ERR_PAYLOAD_VERSION = -8   /* load: newest record has another payload version */
} ib_ps_status_t;

/* Why a slot was accepted or rejected (diagnostics; only VALID counts). */
typedef enum {
    IB_PS_SLOT_NOT_CHECKED = 0,
    IB_PS_SLOT_VALID,
    IB_PS_SLOT_BLANK,        /* header reads all 0xFF or all 0x00 (erased / QEMU) */
    IB_PS_SLOT_BAD_MAGIC,
    IB_PS_SLOT_BAD_FORMAT,   /* unsupported store format version */
    IB_PS_SLOT_BAD_HEADER,   /* unknown flag bits, or a cleared record with a payload */
    IB_PS_SLOT_BAD_LENGTH,   /* payload_len does not fit the slot */
    IB_PS_SLOT_INCOMPLETE,   /* CRC field reads 0x00000000/0xFFFFFFFF: never finished */
    IB_PS_SLOT_BAD_CRC,      /* CRC mismatch or non-zero padding after the CRC */
    IB_PS_SLOT_READ_ERROR
} ib_ps_slot_state_t;

typedef struct {
    int slot;                          /* slot used (load) or written (save/clear); -1 none */
    uint32_t generation;               /* its generation; 0 when none */
    uint16_t payload_version;          /* its payload version */
    uint16_t payload_len;              /* its payload length in bytes */
    bool cleared;                      /* it is a "cleared" (factory reset) record */
    bool unchanged;                    /* save/clear: the current record already held it;
                                          nothing was erased or programmed */
    ib_ps_slot_state_t slot_state[2];  /* both slots as found (save/clear: before writing) */
    uint32_t slot_generation[2];       /* generation of each VALID slot, else 0 */
} ib_ps_info_t;

/* Largest payload this flash geometry can store (0 if the geometry is invalid). */
size_t ib_ps_max_payload(const ib_flash_if_t *fl);

/* Bytes a record with an n-byte payload occupies, for a given program unit. */
size_t ib_ps_record_size(size_t n, uint32_t program_unit);

/*
 * Load the current record. Never writes flash.
 *  IB_PS_OK                   payload[0 .. info.payload_len) holds the stored payload
 *  IB_PS_CLEARED              newest record is a factory reset: use factory defaults
 *  IB_PS_ERR_NO_VALID_SLOT    nothing valid: use factory defaults (info.slot_state says why)
 *  IB_PS_ERR_PAYLOAD_VERSION  newest record has payload_version != expected_version; its
 *                             payload IS copied (if it fits) for a caller that can migrate
 *  IB_PS_ERR_TOO_LARGE        stored payload longer than `capacity`; nothing copied
 *  IB_PS_ERR_FLASH_READ, IB_PS_ERR_BAD_ARG
 * `info` may be NULL. `payload` may be NULL only when capacity == 0.
 */
ib_ps_status_t ib_ps_load(const ib_flash_if_t *fl, uint16_t expected_version, void *payload,
                          size_t capacity, ib_ps_info_t *info);

/*
 * A save whose payload version and payload equal the current record's (byte for byte, read
 * back from flash) changes nothing: no erase, no program, IB_PS_OK with info.unchanged and the
 * current record's slot and generation (flash wear: saving the same block again costs nothing).
 * Likewise a clear when the current record is already a cleared one.
 *
 * Otherwise: store a new record (generation = current + 1) in the slot not holding the current one:
 * erase, program header+payload, read back, program the CRC unit, read back the whole
 * record. On any error the previous record stays intact and current (a half-written new
 * record is invalidated). `info` (may be NULL) reports the slot and generation written.
 * Errors: IB_PS_ERR_BAD_ARG, IB_PS_ERR_TOO_LARGE (nothing touched), IB_PS_ERR_FLASH_READ
 * (a slot could not be read: nothing touched), IB_PS_ERR_FLASH_ERASE,
 * IB_PS_ERR_FLASH_PROGRAM, IB_PS_ERR_VERIFY.
 */
ib_ps_status_t ib_ps_save(const ib_flash_if_t *fl, uint16_t payload_version, const void *payload,
                          size_t len, ib_ps_info_t *info);

/* Factory reset: save() of a newer record flagged CLEARED with no payload. Same errors. */
ib_ps_status_t ib_ps_clear(const ib_flash_if_t *fl, ib_ps_info_t *info);

/* Short names for logs and test output. */
const char *ib_ps_status_name(ib_ps_status_t st);
const char *ib_ps_slot_state_name(ib_ps_slot_state_t st);

#endif
