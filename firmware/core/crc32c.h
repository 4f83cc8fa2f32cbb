/*
 * crc32c.h - CRC-32C (Castagnoli), the checksum of every protocol frame and of the
 * parameter store's slots. Parameters as crcmod.predefined 'crc-32c': reflected
 * polynomial 0x82F63B78, init 0xFFFFFFFF, final xor 0xFFFFFFFF; check value over
 * "123456789" is 0xE3069283.
 */
#ifndef IB_CRC32C_H
#define IB_CRC32C_H

#include <stddef.h>
#include <stdint.h>

/* CRC of `len` bytes. To continue a running CRC, pass the previous result as `crc`;
 * start with 0. */
uint32_t ib_crc32c(uint32_t crc, const void *data, size_t len);

#endif
