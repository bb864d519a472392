/* Modbus RTU framing: bytes accumulate until t3.5 of silence ends the frame. A character with
 * a UART error (parity, framing, noise, overrun) marks the frame bad: it is dropped at its end. */
#include "ds_priv.h"

uint32_t ds_rtu_t35_us(uint32_t baud)
{
    if (baud == 0u || baud > 19200u) {
        return 1750u;
    }
    /* 3.5 characters of 11 bits = 38.5 bit times, rounded up */
    return (uint32_t)((38500000u + baud - 1u) / baud);
}

void ds_core_set_baud(ds_core_t *c, uint32_t baud)
{
    c->t35_us = ds_rtu_t35_us(baud);
}

static uint64_t frame_end_us(const ds_core_t *c)
{
    uint32_t t = c->hr[DS_HR_FRAME_TIMEOUT_US];
    return c->rx_last_us + (t > c->t35_us ? t : c->t35_us);
}

/* Deadline of the frame being received, DS_NO_DEADLINE if none. */
uint64_t ds_rtu_deadline(const ds_core_t *c)
{
    return c->rx_len ? frame_end_us(c) : DS_NO_DEADLINE;
}

/* End the pending frame if its t3.5 has elapsed at now: handle it and send the response. */
void ds_rtu_check_end(ds_core_t *c, uint64_t now)
{
    if (c->rx_len == 0u || now < frame_end_us(c)) {
        return;
    }
    uint64_t end = frame_end_us(c);
    uint16_t len = c->rx_len;
    uint8_t dropped = c->rx_overflow | c->rx_bad;
    c->rx_len = 0u;
    c->rx_overflow = 0u;
    c->rx_bad = 0u;
    /* timers due before the frame ended act first, then the frame is handled now */
    ds_run_timers(c, end);
    if (dropped) {
        c->frames_bad++;
        return;
    }
    size_t r = ds_modbus_process(c, c->rx, len, c->tx, now);
    if (r != 0u && c->hal && c->hal->uart_write) {
        c->hal->uart_write(c->hal->ctx, c->tx, (uint16_t)r);
    }
    ds_line_format_apply(c); /* a new line format takes effect after its response */
}

void ds_line_format_apply(ds_core_t *c)
{
    if (c->line_format_pending) {
        c->line_format_pending = 0u;
        if (c->hal && c->hal->uart_format) {
            c->hal->uart_format(c->hal->ctx, (uint8_t)c->hr[DS_HR_SERIAL_PARITY],
                                (uint8_t)c->hr[DS_HR_SERIAL_STOP_BITS]);
        }
    }
}

int ds_core_set_line_format(ds_core_t *c, uint8_t parity, uint8_t stop_bits)
{
    if (!ds_line_format_ok(parity, stop_bits)) { /* the checks of a Modbus write of the pair */
        return -1;
    }
    c->hr[DS_HR_SERIAL_PARITY] = parity;
    c->hr[DS_HR_SERIAL_STOP_BITS] = stop_bits;
    c->line_format_pending = 1u;
    ds_line_format_apply(c);
    return 0;
}

static void count_error(uint16_t *counter)
{
    *counter = (uint16_t)(*counter + 1u);
}

void ds_core_rx_error(ds_core_t *c, uint8_t errors, uint64_t now_us)
{
    ds_rtu_check_end(c, now_us); /* a gap >= t3.5 ended the previous frame */
    if (c->rx_len < DS_RTU_MAX_ADU) {
        c->rx[c->rx_len++] = 0u; /* a character all the same: it extends the frame's timing */
    } else {
        c->rx_overflow = 1u;
    }
    c->rx_bad = 1u;
    c->rx_last_us = now_us;
    if (errors & DS_UART_ERR_PARITY) {
        count_error(&c->uart_parity_errors);
    }
    if (errors & DS_UART_ERR_FRAMING) {
        count_error(&c->uart_framing_errors);
    }
    if (errors & DS_UART_ERR_NOISE) {
        count_error(&c->uart_noise_errors);
    }
    if (errors & DS_UART_ERR_OVERRUN) {
        count_error(&c->uart_overruns);
    }
}

void ds_core_rx(ds_core_t *c, const uint8_t *buf, size_t n, uint64_t now_us)
{
    if (n == 0u || buf == NULL) {
        return;
    }
    ds_rtu_check_end(c, now_us); /* a gap >= t3.5 ended the previous frame */
    for (size_t i = 0; i < n; i++) {
        if (c->rx_len < DS_RTU_MAX_ADU) {
            c->rx[c->rx_len++] = buf[i];
        } else {
            c->rx_overflow = 1u;
        }
    }
    c->rx_last_us = now_us;
}
