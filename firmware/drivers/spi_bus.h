/*
 * spi_bus.h - the small SPI interface the sensor drivers are written against.
 *
 * A board (STM32 or the simulator) supplies one ib_spi_bus_t. Drivers never touch
 * registers; they only call transfer() and delay_us().
 *
 * Chip-select numbering is fixed for the whole product (docs/conventions.md):
 *   IB_CS_ACCEL  ADXL355
 *   IB_CS_GYRO_X ADXRS450 measuring rotation about the board X axis
 *   IB_CS_GYRO_Y ADXRS450 about board Y
 *   IB_CS_GYRO_Z ADXRS450 about board Z
 */
#ifndef IB_SPI_BUS_H
#define IB_SPI_BUS_H

#include <stddef.h>
#include <stdint.h>

enum {
    IB_CS_ACCEL = 0,
    IB_CS_GYRO_X = 1,
    IB_CS_GYRO_Y = 2,
    IB_CS_GYRO_Z = 3,
    IB_CS_COUNT = 4
};

typedef struct ib_spi_bus {
    /*
     * One full-duplex transaction: chip select `cs` is driven low, `len` bytes are
     * clocked (tx[i] out, rx[i] in; tx == NULL sends 0x00, rx == NULL discards),
     * then chip select goes high again. Returns 0 on success, a negative value on a
     * bus error (timeout, mode fault); rx contents are then undefined.
     */
    int (*transfer)(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);
    /* Busy-wait or sleep at least `us` microseconds of device time. */
    void (*delay_us)(void *ctx, uint32_t us);
    void *ctx;
    /*
     * Optional (NULL when the board has none, e.g. the QEMU images and the simulator): start
     * the same transaction and return at once (0; negative if it cannot start, e.g. one is
     * already running). The board clocks it without the CPU (DMA) and, once chip select is
     * high again, calls done(arg, rc) from its interrupt, rc as transfer() returns; done may
     * start the next transaction (a chain). tx and rx must stay valid until then, and no
     * transfer() may be called while one runs.
     */
    int (*start)(void *ctx, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len,
                 void (*done)(void *arg, int rc), void *arg);
} ib_spi_bus_t;

#endif
