/* Modbus RTU server (PROTOCOL.md §1-2): CRC, t3.5 framing through ds_core_rx, silence rules,
 * malformed PDUs, response bounds, garbage. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include <cmocka.h>

#include "ds_priv.h"
#include "test_hal.h"

static ds_core_t core;
static test_hal_t th;

static int setup(void **state)
{
    (void)state;
    th_boot(&core, &th, 0, 1000u);
    return 0;
}

static void test_crc16_check_value(void **state)
{
    (void)state;
    assert_int_equal(ds_crc16((const uint8_t *)"123456789", 9), 0x4B37);
    assert_int_equal(ds_crc16(NULL, 0), 0xFFFF);
    const uint8_t req[] = {0x01, 0x03, 0x00, 0x00, 0x00, 0x0A}; /* well-known: C5 CD */
    assert_int_equal(ds_crc16(req, sizeof req), 0xCDC5);
}

static void test_t35_by_baud_rate(void **state)
{
    (void)state;
    assert_int_equal(ds_rtu_t35_us(9600), 4011);  /* 38.5 bits / 9600, rounded up */
    assert_int_equal(ds_rtu_t35_us(19200), 2006);
    assert_int_equal(ds_rtu_t35_us(19201), 1750);
    assert_int_equal(ds_rtu_t35_us(115200), 1750);
    assert_int_equal(ds_rtu_t35_us(0), 1750);
    ds_core_set_baud(&core, 9600);
    uint8_t req[16], pdu[5] = {0x04, 0, 0, 0, 1};
    size_t n = th_adu(req, 1, pdu, 5);
    ds_core_rx(&core, req, n, th.now);
    assert_int_equal(ds_core_next_deadline(&core), th.now + 4011);
}

static void feed(const uint8_t *b, size_t n, uint64_t gap_us)
{
    for (size_t i = 0; i < n; i++) {
        ds_core_rx(&core, &b[i], 1, th.now);
        th.now += gap_us;
        ds_core_poll(&core, th.now);
    }
}

static void settle_line(void)
{
    th.now += 1750;
    ds_core_poll(&core, th.now);
}

static void test_gap_below_t35_continues_the_frame(void **state)
{
    (void)state;
    uint8_t req[16], pdu[5] = {0x04, 0, 0, 0, 1};
    size_t n = th_adu(req, 1, pdu, 5);
    feed(req, n, 1749); /* each gap just under t3.5 */
    settle_line();
    assert_int_equal(th.uart_frames, 1);
    assert_int_equal(th.uart[1], 0x04);
}

static void test_gap_of_t35_splits_the_frame(void **state)
{
    (void)state;
    uint8_t req[16], pdu[5] = {0x04, 0, 0, 0, 1};
    size_t n = th_adu(req, 1, pdu, 5);
    feed(req, 3, 10);
    th.now += 1750; /* t3.5 of silence in the middle: two bad frames */
    feed(&req[3], n - 3, 10);
    settle_line();
    assert_int_equal(th.uart_frames, 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_FRAMES_BAD), 1);     /* the first 3 bytes */
    assert_int_equal(th_ir(&core, &th, DS_IR_FRAMES_BAD_CRC), 1); /* the other 5 */
}

static void test_frame_timeout_register_tolerates_byte_gaps(void **state)
{
    (void)state;
    uint8_t req[16], pdu[5] = {0x04, 0, 0, 0, 1};
    size_t n = th_adu(req, 1, pdu, 5);
    feed(req, n, 3000); /* 3 ms between bytes: the standard t3.5 splits the frame */
    settle_line();
    assert_int_equal(th.uart_frames, 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_FRAME_TIMEOUT_US, 5000), 0);
    unsigned before = th.uart_frames;
    feed(req, n, 3000); /* now one frame, ended by 5 ms of silence, not by 3 ms */
    assert_int_equal(th.uart_frames, before);
    th.now += 5000;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.uart_frames, before + 1u);
    assert_int_equal(th.uart[1], 0x04);
    /* below t3.5 acts as t3.5; above the range is refused */
    assert_int_equal(th_write1(&core, &th, DS_HR_FRAME_TIMEOUT_US, 10), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_FRAME_TIMEOUT_US, DS_HR_FRAME_TIMEOUT_US_MAX + 1u),
                     DS_EX_ILLEGAL_VALUE);
}

static void test_back_to_back_frames_are_both_answered(void **state)
{
    (void)state;
    uint8_t a[16], b[16], pa[5] = {0x04, 0, 0, 0, 1}, pb[5] = {0x03, 0, DS_HR_MANUAL_INTENSITY, 0, 1};
    size_t na = th_adu(a, 1, pa, 5), nb = th_adu(b, 1, pb, 5);
    ds_core_rx(&core, a, na, th.now);
    th.now += 1750; /* the next frame starts exactly t3.5 later, before any poll */
    ds_core_rx(&core, b, nb, th.now);
    assert_int_equal(th.uart_frames, 1);
    assert_int_equal(th.uart[1], 0x04);
    settle_line();
    assert_int_equal(th.uart_frames, 2);
    assert_int_equal(th.uart[1], 0x03);
}

static void test_oversize_frame_dropped_then_recovers(void **state)
{
    (void)state;
    uint8_t junk[400];
    for (size_t i = 0; i < sizeof junk; i++) {
        junk[i] = (uint8_t)(i * 7u);
    }
    junk[0] = 1;
    ds_core_rx(&core, junk, sizeof junk, th.now);
    settle_line();
    assert_int_equal(th.uart_frames, 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_FRAMES_BAD), 1);
    uint8_t req[16], pdu[5] = {0x04, 0, 0, 0, 1};
    size_t n = th_adu(req, 1, pdu, 5);
    th.now += 5000;
    ds_core_rx(&core, req, n, th.now);
    settle_line();
    assert_int_equal(th.uart_frames, 1);
}

static void test_wrong_pdu_lengths_answer_03(void **state)
{
    (void)state;
    const uint8_t fcs[] = {0x01, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x11, 0x17, 0x2B};
    for (size_t i = 0; i < sizeof fcs; i++) {
        /* a PDU with one stray byte too many (or too few for 0x2B) */
        uint8_t pdu[12] = {fcs[i], 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0};
        size_t len = fcs[i] == 0x11 ? 2u : (fcs[i] == 0x2B ? 1u : 6u);
        if (fcs[i] == 0x0F || fcs[i] == 0x10) {
            pdu[5] = 2; /* byte count larger than the data that follows */
            len = 7;
        }
        if (fcs[i] == 0x17) {
            len = 9; /* shorter than the fixed header */
        }
        uint8_t resp[256];
        size_t n = th_request(&core, &th, pdu, len, resp);
        assert_int_equal(n, 5);
        assert_int_equal(resp[1], fcs[i] | 0x80);
        assert_int_equal(resp[2], 0x03);
    }
}

static void test_largest_responses_fit_in_256_bytes(void **state)
{
    (void)state;
    uint8_t resp[256];
    uint8_t rd[5] = {0x03, DS_STEP_TABLE_ADDR >> 8, DS_STEP_TABLE_ADDR & 0xFF, 0x00, 125};
    assert_int_equal(th_request(&core, &th, rd, 5, resp), 255);
    const unsigned win = DS_IR_EVT_WINDOW_COUNT * DS_EVENT_WORDS; /* <= 125: one read */
    uint8_t ev[5] = {0x04, DS_IR_EVT_WINDOW >> 8, DS_IR_EVT_WINDOW & 0xFF, 0x00, (uint8_t)win};
    assert_int_equal(th_request(&core, &th, ev, 5, resp), 5 + 2 * win);
    uint8_t coils[5] = {0x01, DS_COIL_LED >> 8, DS_COIL_LED & 0xFF, 0x00, DS_N_LEDS};
    assert_int_equal(th_request(&core, &th, coils, 5, resp), 5 + (DS_N_LEDS + 7) / 8);
    uint8_t id[4] = {0x2B, 0x0E, 0x03, 0x00};
    ds_core_set_target(&core, "a-target-name-much-longer-than-anything-real-0123456789");
    size_t n = th_request(&core, &th, id, 4, resp);
    assert_true(n > 0 && n <= 256);
    assert_int_equal(ds_crc16(resp, n), 0); /* CRC over a frame including its CRC is 0 */
}

static void test_broadcast_read_write_is_ignored(void **state)
{
    (void)state;
    uint8_t pdu[] = {0x17, 0, 0, 0, 1, 0, DS_HR_MANUAL_INTENSITY, 0, 1, 2, 0, 5};
    uint8_t req[32], resp[256];
    size_t n = th_adu(req, 0, pdu, sizeof pdu);
    assert_int_equal(ds_core_handle_frame(&core, req, n, resp, th.now), 0);
    uint16_t v;
    assert_int_equal(th_read(&core, &th, 0x03, DS_HR_MANUAL_INTENSITY, 1, &v), 0);
    assert_int_equal(v, DS_HR_MANUAL_INTENSITY_DEFAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_FRAMES_OK), 2); /* the two reads, this one included */
}

static void test_broadcast_coil_write_takes_effect(void **state)
{
    (void)state;
    uint8_t pdu[] = {0x05, 0, 17, 0xFF, 0};
    uint8_t req[16], resp[256];
    size_t n = th_adu(req, 0, pdu, sizeof pdu);
    assert_int_equal(ds_core_handle_frame(&core, req, n, resp, th.now), 0);
    assert_int_not_equal(th.light[17], 0);
}

static void test_server_id_run_indicator_follows_fault(void **state)
{
    (void)state;
    uint8_t pdu[1] = {0x11}, resp[256];
    ds_core_set_target(&core, "stm32f405");
    size_t n = th_request(&core, &th, pdu, 1, resp);
    char text[64];
    snprintf(text, sizeof text, "dualscale fw=%u.%u.%u proto=%u.%u target=stm32f405",
             DS_FW_VERSION_MAJOR, DS_FW_VERSION_MINOR, DS_FW_VERSION_PATCH,
             DS_PROTO_VERSION_MAJOR, DS_PROTO_VERSION_MINOR);
    assert_int_equal(n, 3 + 2 + strlen(text) + 2);
    assert_int_equal(resp[3], 1);
    assert_int_equal(resp[4], 0xFF);
    assert_memory_equal(&resp[5], text, strlen(text));
    assert_int_equal(th_write1(&core, &th, DS_HR_WATCHDOG_MS, 50), 0);
    assert_int_equal(th_coil(&core, &th, 3, 1), 0);
    th.now += 50000;
    ds_core_poll(&core, th.now);
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    n = th_request(&core, &th, pdu, 1, resp);
    assert_int_equal(resp[4], 0x00);
}

static void test_garbage_stream_never_lights_anything(void **state)
{
    (void)state;
    uint32_t x = 12345;
    for (int i = 0; i < 200000; i++) {
        x = x * 1103515245u + 12345u;
        uint8_t b = (uint8_t)(x >> 16);
        if ((x >> 8) % 5 == 0) {
            b = 1; /* our address, often */
        }
        ds_core_rx(&core, &b, 1, th.now);
        th.now += ((x >> 24) & 3) == 0 ? 2000 : 50;
        ds_core_poll(&core, th.now);
        if (th.uart_frames) {
            assert_true(th.uart_len >= 5 && th.uart_len <= 256);
            assert_int_equal(ds_crc16(th.uart, th.uart_len), 0);
        }
    }
    /* the hardware shows exactly what the core believes, and the line still answers */
    for (uint16_t i = 0; i < DS_N_SOURCES; i++) {
        assert_int_equal(th.light[i], core.lights[i].intensity);
    }
    assert_int_equal(th.triggers, core.trig_level);
    assert_int_equal(th_ir(&core, &th, DS_IR_MAGIC), DS_MAGIC);
}

static void test_holding_registers_reset_to_the_generated_defaults(void **state)
{
    (void)state;
    /* ds_core_init applies DS_HR_DEFAULTS (generated from registers.toml) to the whole direct
     * block; one past it is unmapped */
    uint16_t hr[DS_HR_COUNT];
    assert_int_equal(th_read(&core, &th, 0x03, 0, DS_HR_COUNT, hr), 0);
    for (unsigned a = 0; a < DS_HR_COUNT; a++) {
        assert_int_equal(hr[a], a == DS_HR_COMMAND ? 0u : DS_HR_DEFAULTS[a]); /* COMMAND: write-only */
    }
    assert_int_equal(hr[DS_HR_MANUAL_INTENSITY], DS_HR_MANUAL_INTENSITY_DEFAULT);
    assert_int_equal(hr[DS_HR_SERVO_MAX_CDEG], DS_HR_SERVO_MAX_CDEG_DEFAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_POLARIZER_NOW), DS_HR_POLARIZER_CDEG_DEFAULT);
    assert_int_equal(th_read(&core, &th, 0x03, 0, DS_HR_COUNT + 1u, hr), DS_EX_ILLEGAL_ADDRESS);
    uint16_t ir[DS_IR_COUNT + 1u];
    assert_int_equal(th_read(&core, &th, 0x04, 0, DS_IR_COUNT, ir), 0);
    assert_int_equal(th_read(&core, &th, 0x04, 0, DS_IR_COUNT + 1u, ir), DS_EX_ILLEGAL_ADDRESS);
}


/* ---- UART receive errors (PROTOCOL.md §1): the frame is dropped, each kind is counted ---- */

static const uint8_t read_magic[5] = {0x04, 0, 0, 0, 1};

static uint16_t ir_now(uint16_t addr)
{
    th.now += 20000u;
    ds_core_poll(&core, th.now);
    return th_ir(&core, &th, addr);
}

static void test_uart_error_kinds_drop_the_frame_and_are_counted(void **state)
{
    (void)state;
    const struct {
        uint8_t err;
        uint16_t reg;
    } kinds[] = {
        {DS_UART_ERR_PARITY, DS_IR_UART_PARITY_ERRORS},
        {DS_UART_ERR_FRAMING, DS_IR_UART_FRAMING_ERRORS},
        {DS_UART_ERR_NOISE, DS_IR_UART_NOISE_ERRORS},
        {DS_UART_ERR_OVERRUN, DS_IR_UART_OVERRUNS},
    };
    assert_int_equal(th_feed_with_error(&core, &th, read_magic, 5, 99, 0), 1); /* clean: answered */
    for (size_t k = 0; k < 4; k++) {
        for (size_t at = 0; at < 8; at++) { /* the first character, the CRC, and between */
            assert_int_equal(th_feed_with_error(&core, &th, read_magic, 5, at, kinds[k].err), 0);
        }
        assert_int_equal(ir_now(kinds[k].reg), 8);
        /* the line recovers at once: the next clean frame is answered */
        assert_int_equal(th_feed_with_error(&core, &th, read_magic, 5, 99, 0), 1);
    }
    assert_int_equal(ir_now(DS_IR_FRAMES_BAD), 32);
    assert_int_equal(ir_now(DS_IR_FRAMES_BAD_CRC), 0);
    /* one character with two errors counts in both registers, and drops one frame */
    assert_int_equal(th_feed_with_error(&core, &th, read_magic, 5, 3,
                                        DS_UART_ERR_PARITY | DS_UART_ERR_FRAMING), 0);
    assert_int_equal(ir_now(DS_IR_UART_PARITY_ERRORS), 9);
    assert_int_equal(ir_now(DS_IR_UART_FRAMING_ERRORS), 9);
    assert_int_equal(ir_now(DS_IR_UART_NOISE_ERRORS), 8);
    assert_int_equal(ir_now(DS_IR_FRAMES_BAD), 33);
}

static void test_uart_error_writes_nothing(void **state)
{
    (void)state;
    /* a write whose last CRC byte had a parity error is not executed, even though all its
     * bytes arrived (a UART that delivers the byte anyway must not make it count) */
    uint8_t wr[5] = {0x06, 0, DS_HR_MANUAL_INTENSITY, 0x12, 0x34};
    assert_int_equal(th_feed_with_error(&core, &th, wr, 5, 7, DS_UART_ERR_PARITY), 0);
    uint16_t v;
    assert_int_equal(th_read(&core, &th, 0x03, DS_HR_MANUAL_INTENSITY, 1, &v), 0);
    assert_int_equal(v, DS_HR_MANUAL_INTENSITY_DEFAULT);
}

static void test_uart_error_after_t35_starts_a_new_bad_frame(void **state)
{
    (void)state;
    /* a complete frame, then (after t3.5 of silence) a character with a framing error, e.g. a
     * break: the first frame is answered, the error only spoils what follows it */
    uint8_t req[16];
    size_t n = th_adu(req, 1, read_magic, 5);
    ds_core_rx(&core, req, n, th.now);
    th.now += 1750u;
    ds_core_rx_error(&core, DS_UART_ERR_FRAMING, th.now);
    assert_int_equal(th.uart_frames, 1);
    th.now += 87u;
    ds_core_rx(&core, req, n, th.now); /* within t3.5 of the bad character: same frame */
    th.now += 1750u;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.uart_frames, 1);
    assert_int_equal(ir_now(DS_IR_UART_FRAMING_ERRORS), 1);
    assert_int_equal(ir_now(DS_IR_FRAMES_BAD), 1);
}

static void test_uart_error_counters_wrap(void **state)
{
    (void)state;
    for (unsigned i = 0; i < 65536u; i++) {
        ds_core_rx_error(&core, DS_UART_ERR_NOISE, th.now);
    }
    assert_int_equal(ir_now(DS_IR_UART_NOISE_ERRORS), 0);
    assert_int_equal(ir_now(DS_IR_FRAMES_BAD), 1); /* all one over-long frame: dropped once */
}

/* ---- serial-line format (PROTOCOL.md §1) ---- */

static void test_line_format_resets_to_8e1(void **state)
{
    (void)state;
    assert_int_equal(DS_DEFAULT_PARITY, DS_PARITY_EVEN);
    assert_int_equal(DS_DEFAULT_STOP_BITS, 1);
    assert_int_equal(th.formats, 1); /* ds_core_init told the target */
    assert_int_equal(th.parity, DS_PARITY_EVEN);
    assert_int_equal(th.stop_bits, 1);
    uint16_t v[2];
    assert_int_equal(th_read(&core, &th, 0x03, DS_HR_SERIAL_PARITY, 2, v), 0);
    assert_int_equal(v[0], DS_PARITY_EVEN);
    assert_int_equal(v[1], 1);
}

static void test_line_format_changes_after_the_response(void **state)
{
    (void)state;
    uint8_t wr[10] = {0x10, 0, DS_HR_SERIAL_PARITY, 0, 2, 4, 0, DS_PARITY_NONE, 0, 2};
    th_clear_log(&th);
    assert_int_equal(th_feed_with_error(&core, &th, wr, 10, 99, 0), 1);
    assert_int_equal(th.n_calls, 2);
    assert_int_equal(th.calls[0].type, TH_UART); /* the response leaves in the old format */
    assert_int_equal(th.calls[1].type, TH_FORMAT);
    assert_int_equal(th.parity, DS_PARITY_NONE);
    assert_int_equal(th.stop_bits, 2);
    /* refused writes change nothing and call nothing */
    th_clear_log(&th);
    assert_int_equal(th_write1(&core, &th, DS_HR_SERIAL_STOP_BITS, 1), 3); /* 8N1 */
    assert_int_equal(th_write1(&core, &th, DS_HR_SERIAL_PARITY, 3), 3);
    for (size_t i = 0; i < th.n_calls; i++) {
        assert_int_not_equal(th.calls[i].type, TH_FORMAT);
    }
    assert_int_equal(th_write1(&core, &th, DS_HR_SERIAL_PARITY, DS_PARITY_ODD), 0);
    assert_int_equal(th.parity, DS_PARITY_ODD);
    assert_int_equal(th.stop_bits, 2);
    /* a broadcast write changes the format as well */
    uint8_t req[32], resp[256];
    size_t n = th_adu(req, 0, wr, 10);
    wr[7] = DS_PARITY_EVEN;
    wr[9] = 1;
    n = th_adu(req, 0, wr, 10);
    assert_int_equal(ds_core_handle_frame(&core, req, n, resp, th.now), 0);
    assert_int_equal(th.parity, DS_PARITY_EVEN);
    assert_int_equal(th.stop_bits, 1);
}

static void test_target_sets_the_line_format_at_boot(void **state)
{
    (void)state;
    assert_int_equal(ds_core_set_line_format(&core, DS_PARITY_NONE, 1), -1); /* 8N1 */
    assert_int_equal(ds_core_set_line_format(&core, 3, 1), -1);
    assert_int_equal(ds_core_set_line_format(&core, DS_PARITY_ODD, 0), -1);
    assert_int_equal(th.formats, 1);
    assert_int_equal(ds_core_set_line_format(&core, DS_PARITY_NONE, 2), 0);
    assert_int_equal(th.formats, 2);
    assert_int_equal(th.parity, DS_PARITY_NONE);
    assert_int_equal(th.stop_bits, 2);
    uint16_t v[2];
    assert_int_equal(th_read(&core, &th, 0x03, DS_HR_SERIAL_PARITY, 2, v), 0);
    assert_int_equal(v[0], DS_PARITY_NONE);
    assert_int_equal(v[1], 2);
}

/* ---- FC 2B stream access: read codes 01..03 restart at 0x00 on an unknown id ---- */

static void test_device_id_stream_restarts_for_every_id(void **state)
{
    (void)state;
    for (unsigned code = 1; code <= 4; code++) {
        for (unsigned id = 0; id < 256; id++) {
            uint8_t pdu[4] = {0x2B, 0x0E, (uint8_t)code, (uint8_t)id}, resp[256];
            size_t n = th_request(&core, &th, pdu, 4, resp);
            unsigned last = code == 1 ? 2u : 6u;
            if (code == 4) {
                if (id > 6) {
                    assert_int_equal(n, 5);
                    assert_int_equal(resp[2], 0x02);
                } else {
                    assert_int_equal(resp[7], 1);
                    assert_int_equal(resp[8], id);
                }
                continue;
            }
            unsigned first = id <= last ? id : 0u;
            assert_int_equal(resp[1], 0x2B);
            assert_int_equal(resp[5], 0x00); /* more follows: no */
            assert_int_equal(resp[6], 0x00); /* next object id */
            assert_int_equal(resp[7], last - first + 1u);
            assert_int_equal(resp[8], first);
        }
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_crc16_check_value, setup),
        cmocka_unit_test_setup(test_t35_by_baud_rate, setup),
        cmocka_unit_test_setup(test_gap_below_t35_continues_the_frame, setup),
        cmocka_unit_test_setup(test_gap_of_t35_splits_the_frame, setup),
        cmocka_unit_test_setup(test_frame_timeout_register_tolerates_byte_gaps, setup),
        cmocka_unit_test_setup(test_back_to_back_frames_are_both_answered, setup),
        cmocka_unit_test_setup(test_oversize_frame_dropped_then_recovers, setup),
        cmocka_unit_test_setup(test_wrong_pdu_lengths_answer_03, setup),
        cmocka_unit_test_setup(test_largest_responses_fit_in_256_bytes, setup),
        cmocka_unit_test_setup(test_broadcast_read_write_is_ignored, setup),
        cmocka_unit_test_setup(test_broadcast_coil_write_takes_effect, setup),
        cmocka_unit_test_setup(test_server_id_run_indicator_follows_fault, setup),
        cmocka_unit_test_setup(test_garbage_stream_never_lights_anything, setup),
        cmocka_unit_test_setup(test_holding_registers_reset_to_the_generated_defaults, setup),
        cmocka_unit_test_setup(test_uart_error_kinds_drop_the_frame_and_are_counted, setup),
        cmocka_unit_test_setup(test_uart_error_writes_nothing, setup),
        cmocka_unit_test_setup(test_uart_error_after_t35_starts_a_new_bad_frame, setup),
        cmocka_unit_test_setup(test_uart_error_counters_wrap, setup),
        cmocka_unit_test_setup(test_line_format_resets_to_8e1, setup),
        cmocka_unit_test_setup(test_line_format_changes_after_the_response, setup),
        cmocka_unit_test_setup(test_device_id_stream_restarts_for_every_id, setup),
        cmocka_unit_test_setup(test_target_sets_the_line_format_at_boot, setup),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
