/* Modbus RTU server (PROTOCOL.md §1-2): CRC, t3.5 framing through ds_core_rx, silence rules,
 * malformed PDUs, response bounds, garbage. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
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
    const char *text = "dualscale fw=0.1.0 proto=1.0 target=stm32f405";
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
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
