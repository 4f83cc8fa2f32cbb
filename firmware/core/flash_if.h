/*
 * flash_if.h - the flash abstraction every board supplies to the parameter store
 * (param_store.h). Nothing in firmware/core touches a register: a board fills in one
 * ib_flash_if_t and passes a pointer to it.
 *
 * Two slots, each at the START of its own erase unit (page / sector), neither sharing
 * that unit with code, data or the other slot. The store only ever calls:
 *
 *   erase(ctx, addr)              addr == slot_addr[0] or slot_addr[1]: erase the whole
 *                                 erase unit that begins there. Blocking.
 *   program(ctx, addr, data, len) addr and len are multiples of program_unit, the range
 *                                 lies inside one slot; data is 4-byte aligned. Normally
 *                                 the range was erased since the last erase of the slot.
 *                                 One exception: to invalidate a record after a failed
 *                                 verify the store programs ALL-ZERO units over already
 *                                 programmed ones (NOR clears bits only; STM32F1 allows
 *                                 0x0000 over any half-word; STM32F4 allows any 1->0).
 *                                 A flash that cannot (ECC, e.g. STM32L4/H7) returns an
 *                                 error and the store falls back to erasing the slot.
 *                                 Blocking.
 *   read(ctx, addr, data, len)    any addr/len inside a slot, any alignment of data.
 *
 * Each returns IB_FLASH_OK (0) or a negative IB_FLASH_ERR_*. Every wait on hardware must
 * be bounded (timeout -> IB_FLASH_ERR_TIMEOUT): under QEMU the FLASH block is a stub
 * (BSY never set, EOP never set, SR reads 0, writes silently dropped) and unprogrammed
 * flash reads 0x00, not 0xFF. The store copes with that by design: it never relies on the
 * erased value and verifies by reading back, so a QEMU board implements the SAME driver as
 * the real chip and gets IB_PS_ERR_VERIFY from a save. Do not wait for EOP.
 *
 * Board notes (see also param_store.h):
 *  - STM32F1 (C8 64 KiB / RB 128 KiB: 1 KiB pages; high density xC/xD/xE: 2 KiB pages):
 *    use the last two pages, e.g. 0x0800F800 / 0x0800FC00 on a C8, 0x0801F800 /
 *    0x0801FC00 on an RB and on QEMU's stm32vldiscovery (128 KB). Exclude them from the
 *    linker script. program_unit = 2 (half-word writes only; PGERR when the half-word is
 *    not erased, except 0x0000). Check PGERR/WRPRTERR after each half-word; clear them
 *    first. Unlock with KEYR 0x45670123, 0xCDEF89AB; lock again afterwards.
 *  - STM32F4 (F405/F407 1 MiB: 16 KiB sectors 0-3, 64 KiB sector 4, 128 KiB 5-11):
 *    e.g. sectors 10/11 at 0x080C0000 / 0x080E0000 (slot_size may be far less than the
 *    sector), or two 16 KiB sectors carved out of the image (much faster erase: a 128 KiB
 *    sector erase takes 1-2 s typ., up to 4 s, and stalls every fetch from flash, i.e. all
 *    interrupts running from flash - do not save while streaming; mind the watchdog).
 *    program_unit 1, 2 or 4 (PSIZE; 4 = x32 needs VDD 2.7-3.6 V). Check PGSERR, PGPERR,
 *    PGAERR, WRPERR, OPERR.
 *  - Simulator: a file of 2 * slot_size bytes; a missing file is created filled with 0xFF;
 *    program should AND into the existing bytes (NOR semantics) and return an error when
 *    outside the file; erase fills the slot with 0xFF.
 */
#ifndef IB_FLASH_IF_H
#define IB_FLASH_IF_H

#include <stddef.h>
#include <stdint.h>

/* Return codes of the three callbacks. */
enum {
    IB_FLASH_OK = 0,
    IB_FLASH_ERR = -1,            /* unspecified failure */
    IB_FLASH_ERR_RANGE = -2,      /* address / length outside the flash or misaligned */
    IB_FLASH_ERR_NOT_ERASED = -3, /* programming a unit that is not erased (F1 PGERR) */
    IB_FLASH_ERR_PROTECTED = -4,  /* write protected (F1 WRPRTERR, F4 WRPERR) */
    IB_FLASH_ERR_TIMEOUT = -5,    /* busy never cleared within the bounded wait */
    IB_FLASH_ERR_IO = -6          /* simulator: file I/O failed */
};

/* Largest program unit the store supports (bytes; must be a power of two). */
#define IB_FLASH_MAX_PROGRAM_UNIT 32u

typedef struct ib_flash_if {
    uint32_t slot_addr[2]; /* base of each slot = start of its own erase unit */
    uint32_t slot_size;    /* bytes usable in each slot (<= the erase unit) */
    uint32_t program_unit; /* bytes: 1, 2, 4, ... IB_FLASH_MAX_PROGRAM_UNIT */
    int (*erase)(void *ctx, uint32_t addr);
    int (*program)(void *ctx, uint32_t addr, const void *data, size_t len);
    int (*read)(void *ctx, uint32_t addr, void *data, size_t len);
    void *ctx; /* passed back to the callbacks unchanged */
} ib_flash_if_t;

#endif
