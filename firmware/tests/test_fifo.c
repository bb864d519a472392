/* The event FIFO (PROTOCOL.md §4): SEQ numbering and wrap, non-consuming reads, idempotent
 * acks, overflow counting, the 20-event window. */
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

static void push(uint8_t kind, uint16_t step, uint64_t ts)
{
    ds_evt_push(&core, kind, (uint8_t)(step & 0x7F), step, ts);
}

static void test_window_shows_oldest_events_with_48_bit_timestamps(void **state)
{
    (void)state;
    push(DS_EVT_STEP_START, 3, 0x123456789ABCull);
    push(DS_EVT_TRIGGER, 4, 0xFFFF000000000001ull); /* only 48 bits go on the wire */
    uint16_t w[18];
    assert_int_equal(th_read(&core, &th, 0x04, DS_IR_EVT_WINDOW, 18, w), 0);
    const uint16_t want[18] = {0, DS_EVT_STEP_START | 3 << 8, 3, 0x1234, 0x5678, 0x9ABC,
                               1, DS_EVT_TRIGGER | 4 << 8, 4, 0x0000, 0x0000, 0x0001,
                               0, 0, 0, 0, 0, 0};
    assert_memory_equal(w, want, sizeof want);
    /* reading does not consume */
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 2);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ), 0);
}

static void test_ack_frees_up_to_and_including_seq(void **state)
{
    (void)state;
    for (int i = 0; i < 10; i++) {
        push(DS_EVT_CAMERA_EDGE, (uint16_t)i, (uint64_t)i);
    }
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 3), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 6);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ), 4);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_WINDOW), 4);
    /* the same ack again (a lost response) and an ack of the future are ignored */
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 3), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 10), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 6);
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 9), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ), 10);
}

static void test_full_fifo_drops_and_counts(void **state)
{
    (void)state;
    for (unsigned i = 0; i < DS_FIFO_DEPTH + 3u; i++) {
        push(DS_EVT_CAMERA_EDGE, 0, i);
    }
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), DS_FIFO_DEPTH);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_DROPPED), 3);
    assert_int_equal(th.n_events, DS_FIFO_DEPTH); /* on_event only for stored events */
    /* dropped events use no SEQ: after freeing one, the next event is SEQ 512 */
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 0), 0);
    push(DS_EVT_WATCHDOG, 0, 0);
    assert_int_equal(core.fifo[(core.fifo_head + core.fifo_count - 1u) % DS_FIFO_DEPTH].seq, DS_FIFO_DEPTH);
    for (unsigned i = 0; i < 70000u; i++) {
        push(DS_EVT_CAMERA_EDGE, 0, i);
    }
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_DROPPED), 0xFFFF); /* saturates */
}

static void test_seq_wraps_and_acks_work_across_the_wrap(void **state)
{
    (void)state;
    uint16_t last = 0;
    for (unsigned i = 0; i < 65530u; i++) {
        push(DS_EVT_CAMERA_EDGE, 0, i);
        if (core.fifo_count == 100) {
            last = (uint16_t)(ds_fifo_first_seq(&core) + 99u);
            ds_fifo_ack(&core, last);
        }
    }
    ds_fifo_ack(&core, (uint16_t)(ds_fifo_first_seq(&core) + core.fifo_count - 1u));
    assert_int_equal(core.fifo_count, 0);
    for (int i = 0; i < 12; i++) {
        push(DS_EVT_CAMERA_EDGE, 0, 0);
    }
    uint16_t first = th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ);
    assert_int_equal(first, 65530);
    /* ack SEQ 2 (after the wrap): frees 65530..65535, 0, 1, 2 */
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 2), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 3);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ), 3);
    /* an ack of 65535 now lies outside the pending range */
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 65535), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 3);
}

static void test_clear_events(void **state)
{
    (void)state;
    for (int i = 0; i < 30; i++) {
        push(DS_EVT_CAMERA_EDGE, 0, 0);
    }
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_CLEAR_EVENTS), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_COUNT), 0);
    assert_int_equal(th_ir(&core, &th, DS_IR_EVT_FIRST_SEQ), 30);
    uint16_t w[6];
    assert_int_equal(th_read(&core, &th, 0x04, DS_IR_EVT_WINDOW, 6, w), 0);
    for (int i = 0; i < 6; i++) {
        assert_int_equal(w[i], 0);
    }
}

static void test_reconnecting_host_loses_nothing(void **state)
{
    (void)state;
    /* host reads the window, stores events, its ack response is lost, it re-reads */
    for (int i = 0; i < 25; i++) {
        push(DS_EVT_CAMERA_EDGE, (uint16_t)i, 0);
    }
    enum { WIN = DS_IR_EVT_WINDOW_COUNT * DS_EVENT_WORDS }; /* the whole window */
    uint16_t w[WIN];
    assert_int_equal(th_read(&core, &th, 0x04, DS_IR_EVT_WINDOW, WIN, w), 0);
    assert_int_equal(w[19 * DS_EVENT_WORDS], 19);
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 19), 0); /* host never sees this reply */
    assert_int_equal(th_write1(&core, &th, DS_HR_EVT_ACK, 19), 0); /* retried after reconnect */
    assert_int_equal(th_read(&core, &th, 0x04, DS_IR_EVT_WINDOW, WIN, w), 0);
    assert_int_equal(w[0], 20);
    assert_int_equal(w[4 * DS_EVENT_WORDS], 24);
    assert_int_equal(w[5 * DS_EVENT_WORDS + 1], 0); /* kind NONE beyond EVT_COUNT */
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_window_shows_oldest_events_with_48_bit_timestamps, setup),
        cmocka_unit_test_setup(test_ack_frees_up_to_and_including_seq, setup),
        cmocka_unit_test_setup(test_full_fifo_drops_and_counts, setup),
        cmocka_unit_test_setup(test_seq_wraps_and_acks_work_across_the_wrap, setup),
        cmocka_unit_test_setup(test_clear_events, setup),
        cmocka_unit_test_setup(test_reconnecting_host_loses_nothing, setup),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
