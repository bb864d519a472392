/* dualscale controller, STM32F405 target: the portable core behind this board's hooks.
 *
 * One super-loop, no RTOS: interrupts only queue bytes and time-stamped camera edges; all
 * decisions are the core's, made here in thread mode. The loop sleeps (WFI) only when the next
 * deadline is more than a SysTick period away, since WFI can otherwise overshoot a deadline by
 * up to the 1 ms tick; close to a deadline it spins on the µs clock. */
#include <stddef.h>

#include "board.h"
#include "ds_core.h"
#include "stm32f405.h"

#define TARGET_NAME "stm32f405"
#define SLEEP_MARGIN_US 1500u

static ds_core_t core;

static void hal_uart_write(void *ctx, const uint8_t *buf, uint16_t len)
{
    (void)ctx;
    uart_write(buf, len);
}

static void hal_uart_format(void *ctx, uint8_t parity, uint8_t stop_bits)
{
    (void)ctx;
    uart_set_format(parity, stop_bits);
}

static void hal_light_set(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    (void)ctx;
    leds_set(leds_channel(kind, index), intensity);
}

static void hal_light_preload(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    (void)ctx;
    leds_preload(leds_channel(kind, index), intensity);
}

static void hal_light_latch(void *ctx)
{
    (void)ctx;
    leds_latch();
}

static void hal_polarizer_set(void *ctx, uint16_t cdeg)
{
    (void)ctx;
    servo_set_cdeg(cdeg);
}

static void hal_triggers_write(void *ctx, uint8_t mask)
{
    (void)ctx;
    triggers_write(mask);
}

static const ds_hal_t board_hal = {
    .ctx = NULL,
    .uart_write = hal_uart_write,
    .light_set = hal_light_set,
    .light_preload = hal_light_preload,
    .light_latch = hal_light_latch,
    .polarizer_set = hal_polarizer_set,
    .triggers_write = hal_triggers_write,
    .uart_format = hal_uart_format,
    .on_event = NULL,
};

int main(void)
{
    clock_init();
    systick_init();
    io_init();     /* trigger lines low first */
    leds_init();   /* chain configured and dark */
    uart_init(DS_DEFAULT_BAUD);

    ds_core_init(&core, &board_hal, DS_DEFAULT_ADDRESS, clock_now_us());
    ds_core_set_target(&core, TARGET_NAME);
    ds_core_set_baud(&core, DS_DEFAULT_BAUD);
    leds_flush();

    uint8_t buf[64];
    for (;;) {
        /* Edges first, then sample the clock: every edge then carries a time no later than the
         * `now` used below, so the core sees time move forward only. */
        uint8_t cam;
        uint64_t t_edge;
        while (camera_edge_pop(&cam, &t_edge)) {
            ds_core_camera_edge(&core, cam, t_edge);
            leds_flush();
        }
        uint64_t now = clock_now_us();
        size_t n;
        uint8_t errors;
        while ((n = uart_read(buf, sizeof buf, &errors)) > 0 || errors) {
            ds_core_rx(&core, buf, n, now);
            if (errors) {
                ds_core_rx_error(&core, errors, now); /* the frame is dropped and counted */
            }
        }
        ds_core_poll(&core, now);
        leds_flush();
        uart_tx_pump();

        uint64_t d = ds_core_next_deadline(&core);
        irq_disable();
        if (!uart_rx_pending() && !uart_tx_pending() && !camera_edge_pending() &&
            (d == DS_NO_DEADLINE || d > clock_now_us() + SLEEP_MARGIN_US)) {
            wfi(); /* any interrupt (SysTick each ms, a byte, an edge) ends the sleep */
        }
        irq_enable();
    }
}
