/*
 * board.h - what a board supplies to the firmware core.
 *
 * The core (scheduler, sample pipeline, commands, parameters, protocol) never touches a
 * register: everything it needs from the hardware comes through one ib_board_t. The
 * simulator (firmware/boards/sim) and the STM32 ports (firmware/boards/stm32f1, stm32f4)
 * each fill one in. A board contains no protocol or calibration logic.
 *
 * Main loop of every board:
 *     ib_core_init(&core, &board);
 *     for (;;) {
 *         if (a sample period elapsed) ib_core_tick(&core, periods_missed, due_time_us);
 *         ib_core_poll(&core);
 *     }
 */
#ifndef IB_BOARD_H
#define IB_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "flash_if.h"
#include "spi_bus.h"

typedef struct ib_board_if {
    /* identity, reported in the info message */
    uint8_t board_id;      /* enum ib_board (protocol_gen.h) */
    uint8_t clock_source;  /* enum ib_clock_source */
    uint32_t baud;         /* link baud rate, 0 if the link is not a UART */
    uint8_t uid[12];       /* MCU unique ID */
    const char *build;     /* build id, e.g. git describe; at most 15 characters are sent */

    /* Free-running device time in microseconds (wraps at 2^32). */
    uint32_t (*time_us)(void *ctx);

    /* The core asks for a sample tick at rate_hz (0 = none). The board then calls
     * ib_core_tick() once per period from the main loop, never from an interrupt, passing
     * how many periods it missed since the previous call and the time the tick fell due
     * (start + k x period in time_us() terms, not when the call is made). */
    void (*set_tick_hz)(void *ctx, uint32_t rate_hz);

    /* Link (serial port). link_write queues bytes for transmission and returns how many it
     * took; the core only writes a frame when link_tx_free() says the whole frame fits, so a
     * frame is never cut. link_read is non-blocking: it returns the number of received bytes
     * copied into buf (0 when none). */
    size_t (*link_tx_free)(void *ctx);
    size_t (*link_write)(void *ctx, const uint8_t *data, size_t len);
    size_t (*link_read)(void *ctx, uint8_t *buf, size_t cap);

    /* Sensors (chip selects in spi_bus.h) and parameter storage. */
    const ib_spi_bus_t *spi;
    const ib_flash_if_t *flash;

    /* Reset the device. Called after the reboot command's ack has been handed to link_write;
     * the board lets the link drain (bounded) before resetting. On hardware it does not
     * return; the simulator re-initialises the core and returns. */
    void (*reboot)(void *ctx);

    void *ctx;
} ib_board_t;

#endif
