/* Sequencer timing (PROTOCOL.md §3): the device-master schedule driven in virtual time by
 * jumping to ds_core_next_deadline, late polling, and camera-master latching. */
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

static int setup_preload(void **state)
{
    (void)state;
    th_boot(&core, &th, 1, 5000000u);
    return 0;
}

static int setup_plain(void **state)
{
    (void)state;
    th_boot(&core, &th, 0, 5000000u);
    return 0;
}

static uint64_t deadlines[1024];
static size_t n_deadlines;

/* Runs the core in virtual time: jump to each deadline (+ latency) until nothing is pending. */
static void run_virtual(uint64_t latency)
{
    n_deadlines = 0;
    for (int guard = 0; guard < 100000; guard++) {
        uint64_t d = ds_core_next_deadline(&core);
        if (d == DS_NO_DEADLINE) {
            return;
        }
        if (n_deadlines < 1024) {
            deadlines[n_deadlines++] = d;
        }
        th.now = d + latency;
        ds_core_poll(&core, th.now);
    }
    fail_msg("sequence did not finish");
}

typedef struct {
    uint8_t kind, arg;
    uint16_t step;
    uint64_t ts;
} expect_t;

/* The schedule of PROTOCOL.md §3.1, computed independently of the core. */
static size_t schedule(const th_step_t *s, size_t n, uint64_t t0, uint32_t gap, uint16_t pol0,
                       expect_t *ev, uint64_t *falls, size_t *n_falls, uint64_t *end)
{
    size_t k = 0;
    uint64_t t = t0;
    uint16_t pol = pol0;
    *n_falls = 0;
    ev[k++] = (expect_t){DS_EVT_SEQ_START, 0, 0xFFFF, t0};
    for (uint16_t i = 0; i < n; i++) {
        if (s[i].polarizer != 0xFFFF && s[i].polarizer != pol) {
            ev[k++] = (expect_t){DS_EVT_POLARIZER, 0, i, t};
            pol = s[i].polarizer;
        }
        ev[k++] = (expect_t){DS_EVT_STEP_START, 0, i, t};
        uint64_t tb = t + s[i].settle;
        for (uint8_t b = 0; b < s[i].count; b++) {
            uint64_t e = (uint64_t)s[i].exposure << (b * s[i].ev);
            if (s[i].triggers) {
                ev[k++] = (expect_t){DS_EVT_TRIGGER, b, i, tb};
                falls[(*n_falls)++] = tb + (s[i].pulse ? s[i].pulse : e);
            }
            tb += e + gap;
        }
        t = tb;
        ev[k++] = (expect_t){DS_EVT_STEP_END, 0, i, t};
    }
    ev[k++] = (expect_t){DS_EVT_SEQ_DONE, 0, 0xFFFF, t};
    *end = t;
    return k;
}

static const th_step_t MIXED[] = {
    /* LED 3, servo 0 -> 4000 cdeg (100 ms at 40 cdeg/ms), 3 brackets 1 EV apart, 50 us pulses */
    {0x0103, 1000, 4000, 100000, 1000, 50, 3, 1, 0x3},
    /* back light 2, keep angle, gate mode (one bracket: with no frame gap a second gate would
     * leave the line no time low, which validation refuses: see test_trigger_gap_is_enforced) */
    {0x0202, 2000, 0xFFFF, 500, 300, 0, 1, 2, 0x4},
    /* dark frame with the servo back to 0 */
    {0x0000, 0, 0, 100000, 777, 10, 1, 0, 0x8},
    /* diffuse, pulse half the exposure (10 us low between pulses), 4 equal brackets */
    {0x0300, 65535, 0xFFFF, 0, 20, 10, 4, 0, 0x1},
    /* LED 3 again, gate mode, exposure 1 us */
    {0x0103, 7, 0xFFFF, 0, 1, 0, 1, 0, 0x2},
};
#define N_MIXED (sizeof MIXED / sizeof MIXED[0])

static void check_schedule(uint32_t gap, uint64_t latency)
{
    uint16_t g[2] = {(uint16_t)(gap >> 16), (uint16_t)gap};
    assert_int_equal(th_writen(&core, &th, DS_HR_FRAME_GAP_US, g, 2), 0);
    assert_int_equal(th_upload(&core, &th, MIXED, N_MIXED), 0);
    th_clear_log(&th);
    uint64_t t0 = th.now;
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    run_virtual(latency);

    static expect_t want[256];
    uint64_t falls[64], end;
    size_t n_falls;
    size_t n = schedule(MIXED, N_MIXED, t0, gap, 0, want, falls, &n_falls, &end);
    assert_int_equal(th.n_events, n);
    for (size_t i = 0; i < n; i++) {
        assert_int_equal(th.events[i].kind_arg & 0xFF, want[i].kind);
        assert_int_equal(th.events[i].kind_arg >> 8, want[i].arg);
        assert_int_equal(th.events[i].step, want[i].step);
        if (latency == 0) {
            assert_int_equal(th.events[i].ts, want[i].ts);
        } else { /* performed at the first poll at or after its scheduled time */
            assert_true(th.events[i].ts >= want[i].ts);
            assert_true(th.events[i].ts <= want[i].ts + latency);
        }
    }
    /* every deadline the core asked for is a scheduled instant: nothing drifts */
    for (size_t i = 0; i < n_deadlines; i++) {
        int found = 0;
        for (size_t j = 0; j < n && !found; j++) {
            found = deadlines[i] == want[j].ts;
        }
        for (size_t j = 0; j < n_falls && !found; j++) {
            found = deadlines[i] == falls[j];
        }
        assert_true(found);
    }
    /* trigger falls (PULSE_US, or the whole exposure in gate mode) */
    size_t f = 0;
    int high = 0;
    for (size_t i = 0; i < th.n_calls; i++) {
        if (th.calls[i].type != TH_TRIGGERS) {
            continue;
        }
        if (th.calls[i].value == 0 && high) { /* a falling edge (START's all-off is not one) */
            assert_true(f < n_falls);
            assert_true(th.calls[i].t >= falls[f]);
            assert_true(th.calls[i].t <= falls[f] + latency);
            f++;
        }
        high = th.calls[i].value != 0;
    }
    assert_int_equal(f, n_falls);
    /* the duration register and the end state */
    uint16_t d[3];
    assert_int_equal(th_read(&core, &th, 0x04, DS_IR_SEQ_DURATION_US, 3, d), 0);
    uint64_t dur = (uint64_t)d[0] << 32 | (uint64_t)d[1] << 16 | d[2];
    assert_int_equal(dur, end - t0);
    /* the sequence lasts SEQ_DURATION_US plus the latency of the very last action */
    assert_true(th.events[n - 1].ts >= t0 + dur);
    assert_true(th.events[n - 1].ts <= t0 + dur + latency);
    assert_int_equal(ds_core_state(&core), DS_STATE_DONE);
    assert_false(th_lights_on(&th));
    assert_int_equal(th.triggers, 0);
    assert_int_equal(th.polarizer, 0);
}

static void test_device_master_events_land_exactly_on_schedule(void **state)
{
    (void)state;
    check_schedule(0, 0);
}

static void test_device_master_schedule_with_frame_gap(void **state)
{
    (void)state;
    check_schedule(2500, 0);
}

static void test_late_polls_do_not_accumulate_latency(void **state)
{
    (void)state;
    check_schedule(1234, 37);
}

static void test_device_master_lights_follow_steps(void **state)
{
    (void)state;
    assert_int_equal(th_upload(&core, &th, MIXED, N_MIXED), 0);
    th_clear_log(&th);
    uint64_t t0 = th.now;
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    /* step 0: LED 3 on at t0, nothing else */
    assert_int_equal(th.light[3], 1000);
    assert_int_equal(th.polarizer, 4000);
    int lit = 0;
    for (size_t i = 0; i < DS_N_SOURCES; i++) {
        lit += th.light[i] != 0;
    }
    assert_int_equal(lit, 1);
    /* at step 1's start the back light replaces the LED */
    uint64_t t1 = t0 + 100000 + 1000 + 2000 + 4000;
    th.now = t1 - 1;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.light[3], 1000);
    th.now = t1;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.light[3], 0);
    assert_int_equal(th.light[th_src(DS_SRC_BACKLIGHT, 2)], 2000);
    uint16_t cur = th_ir(&core, &th, DS_IR_CUR_STEP);
    assert_int_equal(cur, 1);
    uint8_t pdu[5] = {0x01, 0x00, 0x80, 0x00, 0x04}; /* coils show the sequencer light */
    uint8_t resp[256];
    assert_int_equal(th_request(&core, &th, pdu, 5, resp), 6);
    assert_int_equal(resp[3], 0x04);
    run_virtual(0);
    assert_false(th_lights_on(&th));
}

static void test_abort_mid_sequence_switches_everything_off(void **state)
{
    (void)state;
    assert_int_equal(th_upload(&core, &th, MIXED, N_MIXED), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    th.now += 100000 + 10; /* inside bracket 0 of step 0: trigger high */
    ds_core_poll(&core, th.now);
    assert_int_equal(th.triggers, 0x3);
    assert_true(th_lights_on(&th));
    th_clear_log(&th);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
    assert_false(th_lights_on(&th));
    assert_int_equal(th.triggers, 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_ABORTED);
    assert_int_equal(th.n_events, 1);
    assert_int_equal(th.events[0].kind_arg, DS_EVT_SEQ_ABORT | DS_ABORT_HOST << 8);
    assert_int_equal(th.events[0].step, 0);
    assert_int_equal(ds_core_next_deadline(&core), DS_NO_DEADLINE);
}

static void test_start_while_running_is_busy(void **state)
{
    (void)state;
    assert_int_equal(th_upload(&core, &th, MIXED, N_MIXED), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_BUSY);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_BUSY);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_CLEAR_EVENTS), DS_EX_BUSY);
    assert_int_equal(th_write1(&core, &th, DS_HR_POLARIZER_CDEG, 100), DS_EX_BUSY);
    assert_int_equal(th_write1(&core, &th, DS_STEP_TABLE_ADDR, 0), DS_EX_BUSY);
    assert_int_equal(th_coil(&core, &th, 0, 1), DS_EX_BUSY);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
}

static void test_start_switches_manual_lights_off(void **state)
{
    (void)state;
    assert_int_equal(th_coil(&core, &th, 100, 1), 0);
    assert_int_not_equal(th.light[100], 0);
    assert_int_equal(th_upload(&core, &th, MIXED, 1), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(th.light[100], 0);
    assert_int_equal(th.light[3], 1000);
}

/* ---- camera-master ------------------------------------------------------------------- */

static const th_step_t CAM[] = {
    /* LED 1, no settle: the latching edge is bracket 0; 2 frames */
    {0x0101, 100, 0xFFFF, 0, 1000, 0, 2, 0, 0},
    /* LED 2, servo 0 -> 40 cdeg needs 1 ms: edges within 1 ms of the latch are ignored */
    {0x0102, 200, 40, 1000, 1000, 0, 1, 0, 0},
};

static void cam_start(void)
{
    assert_int_equal(th_write1(&core, &th, DS_HR_TRIGGER_MODE, DS_MODE_CAMERA_MASTER), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_MASTER_CAMERA, 2), 0);
    assert_int_equal(th_upload(&core, &th, CAM, 2), 0);
    th_clear_log(&th);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_ARMED);
}

static void edge(uint8_t cam, uint64_t t)
{
    th.now = t;
    ds_core_camera_edge(&core, cam, t);
}

static void expect_event(size_t i, uint8_t kind, uint8_t arg, uint16_t step, uint64_t ts)
{
    assert_true(i < th.n_events);
    assert_int_equal(th.events[i].kind_arg, kind | arg << 8);
    assert_int_equal(th.events[i].step, step);
    assert_int_equal(th.events[i].ts, ts);
}

static void check_camera_master(int preload)
{
    uint64_t t0 = th.now;
    cam_start();
    assert_false(th_lights_on(&th)); /* preloaded, not latched */
    if (preload) {
        assert_int_equal(th.shadow[1], 100);
    }
    edge(0, t0 + 10); /* another camera: ignored, no event */
    assert_int_equal(ds_core_state(&core), DS_STATE_ARMED);
    uint64_t e0 = t0 + 1000;
    edge(2, e0); /* latch step 0; counts as bracket 0 (settle 0) */
    assert_int_equal(ds_core_state(&core), DS_STATE_RUNNING);
    assert_int_equal(th.light[1], 100);
    if (preload) {
        assert_int_equal(th.shadow[2], 200); /* step 1 preloaded ... */
        assert_int_equal(th.shadow[1], 0);
        assert_int_equal(th.light[2], 0);    /* ... but not shown */
    }
    edge(2, e0 + 33000); /* bracket 1 */
    assert_int_equal(th.light[1], 100);
    uint64_t e2 = e0 + 66000;
    edge(2, e2); /* latch step 1: servo turns, this edge is inside SETTLE_US */
    assert_int_equal(th.light[1], 0);
    assert_int_equal(th.light[2], 200);
    assert_int_equal(th.polarizer, 40);
    edge(2, e2 + 999);  /* still settling */
    edge(2, e2 + 1000); /* counted: step 1's only bracket */
    uint64_t e5 = e2 + 34000;
    edge(2, e5); /* ends the sequence */
    assert_int_equal(ds_core_state(&core), DS_STATE_DONE);
    assert_false(th_lights_on(&th));

    size_t i = 0;
    expect_event(i++, DS_EVT_SEQ_START, 1, 0xFFFF, t0);
    expect_event(i++, DS_EVT_STEP_START, 0, 0, e0);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 2, 0, e0);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 2, 0, e0 + 33000);
    expect_event(i++, DS_EVT_STEP_END, 0, 0, e2);
    expect_event(i++, DS_EVT_POLARIZER, 0, 1, e2);
    expect_event(i++, DS_EVT_STEP_START, 0, 1, e2);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 0x82, 1, e2);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 0x82, 1, e2 + 999);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 2, 1, e2 + 1000);
    expect_event(i++, DS_EVT_CAMERA_EDGE, 0x82, 1, e5);
    expect_event(i++, DS_EVT_STEP_END, 0, 1, e5);
    expect_event(i++, DS_EVT_SEQ_DONE, 0, 0xFFFF, e5);
    assert_int_equal(th.n_events, i);
    for (size_t c = 0; c < th.n_calls; c++) { /* trigger outputs stay low */
        if (th.calls[c].type == TH_TRIGGERS) {
            assert_int_equal(th.calls[c].value, 0);
        }
    }
}

static void test_camera_master_with_preload_chain(void **state)
{
    (void)state;
    check_camera_master(1);
    size_t latches = 0;
    for (size_t c = 0; c < th.n_calls; c++) {
        latches += th.calls[c].type == TH_LATCH;
    }
    assert_int_equal(latches, 2);
}

static void test_camera_master_without_preload_hooks(void **state)
{
    (void)state;
    check_camera_master(0);
}

static void test_camera_timeout_faults(void **state)
{
    (void)state;
    uint64_t t0 = th.now;
    cam_start();
    edge(2, t0 + 100);
    assert_true(th_lights_on(&th));
    uint64_t deadline = t0 + 100 + DS_CAMERA_TIMEOUT_MS_DEFAULT * 1000u;
    assert_int_equal(ds_core_next_deadline(&core), deadline);
    th.now = deadline - 1;
    ds_core_poll(&core, th.now);
    assert_true(th_lights_on(&th));
    th_clear_log(&th);
    th.now = deadline;
    ds_core_poll(&core, th.now);
    assert_false(th_lights_on(&th));
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_CAMERA_TIMEOUT);
    expect_event(0, DS_EVT_SEQ_ABORT, DS_ABORT_FAULT, 0, deadline);
    expect_event(1, DS_EVT_FAULT, DS_ERR_CAMERA_TIMEOUT, 0, deadline);
    /* a fault needs CLEAR_ERROR before the next START */
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_BUSY);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_CLEAR_ERROR), 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_IDLE);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
}

static void test_camera_timeout_while_armed(void **state)
{
    (void)state;
    uint64_t t0 = th.now;
    cam_start();
    th.now = t0 + DS_CAMERA_TIMEOUT_MS_DEFAULT * 1000u;
    ds_core_poll(&core, th.now);
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th.events[th.n_events - 1].kind_arg, DS_EVT_FAULT | DS_ERR_CAMERA_TIMEOUT << 8);
}

static void test_camera_master_light_is_held_to_its_bucket(void **state)
{
    (void)state;
    /* a camera that stops mid-step must not keep the LED on past LED_MAX_ON_MS */
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 50), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_CAMERA_TIMEOUT_MS, 60000), 0);
    uint64_t t0 = th.now;
    cam_start();
    edge(2, t0 + 100);
    assert_int_equal(ds_core_next_deadline(&core), t0 + 100 + 50000);
    th.now = t0 + 100 + 50000;
    ds_core_poll(&core, th.now);
    assert_false(th_lights_on(&th));
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_LED_LIMIT);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_device_master_events_land_exactly_on_schedule, setup_preload),
        cmocka_unit_test_setup(test_device_master_schedule_with_frame_gap, setup_preload),
        cmocka_unit_test_setup(test_late_polls_do_not_accumulate_latency, setup_plain),
        cmocka_unit_test_setup(test_device_master_lights_follow_steps, setup_plain),
        cmocka_unit_test_setup(test_abort_mid_sequence_switches_everything_off, setup_plain),
        cmocka_unit_test_setup(test_start_while_running_is_busy, setup_plain),
        cmocka_unit_test_setup(test_start_switches_manual_lights_off, setup_plain),
        cmocka_unit_test_setup(test_camera_master_with_preload_chain, setup_preload),
        cmocka_unit_test_setup(test_camera_master_without_preload_hooks, setup_plain),
        cmocka_unit_test_setup(test_camera_timeout_faults, setup_preload),
        cmocka_unit_test_setup(test_camera_timeout_while_armed, setup_preload),
        cmocka_unit_test_setup(test_camera_master_light_is_held_to_its_bucket, setup_preload),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
