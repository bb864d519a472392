/* The hardware abstraction the portable core talks through.
 *
 * One ds_hal_t per target (STM32F405, POSIX simulator, unit tests). The core never touches
 * hardware or global state: everything goes through these hooks, which keeps it heap-free,
 * re-entrant per instance and testable over a socketpair or ctypes.
 * Times are microseconds on the device clock passed to ds_core_*(now_us). */
#ifndef DS_HAL_H
#define DS_HAL_H

#include <stdint.h>

struct ds_event; /* ds_core.h */

typedef struct ds_hal {
    void *ctx; /* passed back to every hook */

    /* Send one complete RTU frame (address .. CRC). Must not block longer than the frame. */
    void (*uart_write)(void *ctx, const uint8_t *buf, uint16_t len);

    /* Drive one light source. kind is DS_SRC_*, intensity 0 = off. Takes effect at once.
     * The core guarantees at most one sequencer light; manual coils may add more. */
    void (*light_set)(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity);

    /* Camera-master: shift the next light state into the LED-driver chain without latching it.
     * light_latch() then applies it at the camera edge. May be NULL (light_set is used). */
    void (*light_preload)(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity);
    void (*light_latch)(void *ctx);

    /* Command the analyzer servo (centidegrees). */
    void (*polarizer_set)(void *ctx, uint16_t cdeg);

    /* Set the trigger outputs: bit i of mask = trigger line i level. */
    void (*triggers_write)(void *ctx, uint8_t mask);

    /* Serial-line format: 8 data bits, parity DS_PARITY_NONE/ODD/EVEN, 1 or 2 stop bits. Called by
     * ds_core_init with the reset values (rig.toml [serial]) and after a write of SERIAL_PARITY /
     * SERIAL_STOP_BITS, once the response to that write has been handed to uart_write: the target
     * switches when that response has left the line. May be NULL (fixed format). */
    void (*uart_format)(void *ctx, uint8_t parity, uint8_t stop_bits);

    /* Optional: an event was stored in the FIFO (the simulator mirrors it on its side channel). */
    void (*on_event)(void *ctx, const struct ds_event *e);
} ds_hal_t;

#endif /* DS_HAL_H */
