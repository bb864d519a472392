/* Safety (PROTOCOL.md §5): one validation error code per fault kind, the leaky bucket at START
 * and at run time, the host watchdog, faults and CLEAR_ERROR. */
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

/* A valid device-master step: LED 0, 1 ms exposure, a 100 us pulse on trigger 0 (so two of them
 * in a row leave the line low 900 us). */
static th_step_t good(void)
{
    return (th_step_t){0x0100, 1000, 0xFFFF, 0, 1000, 100, 1, 0, 0x1};
}

/* Two steps, the second one `bad`: START must answer 03 with ERROR = code, ERROR_STEP = 1,
 * and switch nothing on. */
static void expect_invalid(th_step_t bad, uint16_t code)
{
    th_step_t s[2] = {good(), bad};
    assert_int_equal(th_upload(&core, &th, s, 2), 0);
    th_clear_log(&th);
    uint16_t before = ds_core_state(&core);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), code);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR_STEP), 1);
    assert_int_equal(ds_core_state(&core), before); /* a refused START changes no state */
    assert_int_equal(th.n_events, 0);
    for (size_t i = 0; i < th.n_calls; i++) {
        assert_false(th.calls[i].type == TH_LIGHT && th.calls[i].value != 0);
    }
}

static void expect_valid(th_step_t s1)
{
    th_step_t s[2] = {good(), s1};
    assert_int_equal(th_upload(&core, &th, s, 2), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
}

static void test_err_seq_empty(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_SEQ_EMPTY);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR_STEP), 0xFFFF);
}

static void test_err_seq_too_long(void **state)
{
    (void)state;
    /* SEQ_LEN cannot exceed MAX_STEPS through the register (03); the validator still checks */
    assert_int_equal(th_write1(&core, &th, DS_HR_SEQ_LEN, DS_MAX_STEPS + 1u), DS_EX_ILLEGAL_VALUE);
    uint16_t step;
    uint64_t dur;
    assert_int_equal(ds_seq_validate(&core, DS_MAX_STEPS + 1u, 0, 0, &step, &dur), DS_ERR_SEQ_TOO_LONG);
}

static void test_err_bad_source(void **state)
{
    (void)state;
    th_step_t s = good();
    s.source = 0x0400; /* unknown kind */
    expect_invalid(s, DS_ERR_BAD_SOURCE);
    s.source = 0x0100 | DS_N_LEDS;
    expect_invalid(s, DS_ERR_BAD_SOURCE);
    s.source = 0x0200 | DS_N_BACKLIGHTS;
    expect_invalid(s, DS_ERR_BAD_SOURCE);
    s.source = 0x0301;
    expect_invalid(s, DS_ERR_BAD_SOURCE);
    s.source = 0x0001; /* OFF with an index */
    s.intensity = 0;
    expect_invalid(s, DS_ERR_BAD_SOURCE);
    s.source = 0x0100 | (DS_N_LEDS - 1u);
    s.intensity = 1;
    expect_valid(s);
}

static void test_err_bad_intensity(void **state)
{
    (void)state;
    th_step_t s = good();
    s.intensity = 0;
    expect_invalid(s, DS_ERR_BAD_INTENSITY);
    s.source = 0x0000;
    s.intensity = 5;
    expect_invalid(s, DS_ERR_BAD_INTENSITY);
    s.intensity = 0;
    expect_valid(s); /* a dark frame */
}

static void test_err_polarizer_range(void **state)
{
    (void)state;
    th_step_t s = good();
    s.settle = 1000000;
    s.polarizer = 18001;
    expect_invalid(s, DS_ERR_POLARIZER_RANGE);
    assert_int_equal(th_write1(&core, &th, DS_HR_SERVO_MAX_CDEG, 9000), 0);
    s.polarizer = 9001;
    expect_invalid(s, DS_ERR_POLARIZER_RANGE);
    s.polarizer = 9000;
    expect_valid(s);
}

static void test_err_exposure_range(void **state)
{
    (void)state;
    th_step_t s = good();
    s.exposure = 0;
    expect_invalid(s, DS_ERR_EXPOSURE_RANGE);
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 60000), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_DUTY_PERMILLE, 1000), 0);
    s.exposure = DS_MAX_PHASE_US / 2u + 1u; /* bracket 1 = 2x: just over 60 s */
    s.count = 2;
    s.ev = 1;
    expect_invalid(s, DS_ERR_EXPOSURE_RANGE);
    s.source = 0x0000; /* dark: no on-time limit applies */
    s.intensity = 0;
    s.exposure = DS_MAX_PHASE_US / 2u;
    expect_valid(s);
    s.exposure = 1;
    s.count = 8;
    s.ev = 4; /* 1 << 28 us > 60 s */
    expect_invalid(s, DS_ERR_EXPOSURE_RANGE);
}

static void test_err_settle_range(void **state)
{
    (void)state;
    th_step_t s = good();
    s.source = 0x0000;
    s.intensity = 0;
    s.settle = DS_MAX_PHASE_US + 1u;
    expect_invalid(s, DS_ERR_SETTLE_RANGE);
    s.settle = DS_MAX_PHASE_US;
    expect_valid(s);
}

static void test_err_pulse_range(void **state)
{
    (void)state;
    th_step_t s = good();
    s.exposure = 100;
    s.pulse = 101;
    expect_invalid(s, DS_ERR_PULSE_RANGE);
    s.pulse = 100;
    expect_valid(s);
}

static void test_err_brackets_range(void **state)
{
    (void)state;
    th_step_t s = good();
    s.count = 0;
    expect_invalid(s, DS_ERR_BRACKETS_RANGE);
    s.count = DS_MAX_BRACKETS + 1u;
    expect_invalid(s, DS_ERR_BRACKETS_RANGE);
    s.count = 2;
    s.ev = DS_MAX_EV_STEP + 1u;
    expect_invalid(s, DS_ERR_BRACKETS_RANGE);
    s.ev = DS_MAX_EV_STEP;
    expect_valid(s);
}

static void test_err_trigger_mask(void **state)
{
    (void)state;
    th_step_t s = good();
    s.triggers = 1u << DS_N_TRIGGERS;
    expect_invalid(s, DS_ERR_TRIGGER_MASK);
    s.triggers = 0; /* a lit step in device-master must trigger a camera */
    expect_invalid(s, DS_ERR_TRIGGER_MASK);
    s.source = 0x0000;
    s.intensity = 0;
    expect_valid(s); /* a dark pause needs no trigger */
}

static void test_err_trigger_gap(void **state)
{
    (void)state;
    th_step_t s = good();
    s.pulse = 0; /* gate mode, 2 brackets, no frame gap: the line never goes low between them */
    s.count = 2;
    expect_invalid(s, DS_ERR_TRIGGER_GAP);
    s.pulse = 1000 - DS_TRIGGER_MIN_LOW_US + 1u; /* one microsecond too little low time */
    expect_invalid(s, DS_ERR_TRIGGER_GAP);
    s.pulse = 1000 - DS_TRIGGER_MIN_LOW_US; /* exactly the minimum */
    expect_valid(s);
    s = good();
    s.triggers = 0x2; /* another line: no constraint from step 0's pulse */
    s.pulse = 0;
    expect_valid(s);
    uint16_t gap[2] = {0, DS_TRIGGER_MIN_LOW_US}; /* a frame gap makes gate mode legal */
    assert_int_equal(th_writen(&core, &th, DS_HR_FRAME_GAP_US, gap, 2), 0);
    s = good();
    s.pulse = 0;
    s.count = 2;
    expect_valid(s);
}

static void test_trigger_mask_may_be_empty_in_camera_master(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_TRIGGER_MODE, DS_MODE_CAMERA_MASTER), 0);
    th_step_t s = good();
    s.triggers = 0;
    expect_valid(s);
    s.triggers = 0x10;
    expect_invalid(s, DS_ERR_TRIGGER_MASK);
}

static void test_err_led_on_time(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 10), 0);
    th_step_t s = good();
    s.settle = 2000;
    s.exposure = 8001; /* 10.001 ms */
    expect_invalid(s, DS_ERR_LED_ON_TIME);
    s.exposure = 7000; /* 9 ms; with step 0 (1 ms, another light) fine */
    s.source = 0x0105;
    expect_valid(s);
}

static void test_err_led_duty_leaky_bucket(void **state)
{
    (void)state;
    /* capacity 10 ms, duty 50 %: drains at 1 us/us while off */
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 10), 0);
    th_step_t on = {0x0107, 10, 0xFFFF, 0, 8000, 100, 1, 0, 1};
    th_step_t off = {0x0000, 0, 0xFFFF, 0, 1000, 0, 1, 0, 0};
    th_step_t seq[3] = {on, off, on}; /* 8 ms, 1 ms off -> 7 ms, + 8 ms = 15 ms > 10 ms */
    assert_int_equal(th_upload(&core, &th, seq, 3), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_LED_DUTY);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR_STEP), 2);
    /* 6 ms off drains to 2 ms: 2 + 8 = 10 ms, exactly the capacity, is allowed */
    seq[1].exposure = 6000;
    assert_int_equal(th_upload(&core, &th, seq, 3), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
    /* 5.999 ms off is 1 us short */
    seq[1].exposure = 5999;
    assert_int_equal(th_upload(&core, &th, seq, 3), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_LED_DUTY);
    /* consecutive steps of the same light add up without draining */
    th_step_t two[2] = {on, on};
    assert_int_equal(th_upload(&core, &th, two, 2), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_LED_DUTY);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR_STEP), 1);
}

static void test_err_servo_settle(void **state)
{
    (void)state;
    th_step_t s = good();
    s.polarizer = 4000; /* 4000 cdeg at 40 cdeg/ms = 100 ms */
    s.settle = 99999;
    expect_invalid(s, DS_ERR_SERVO_SETTLE);
    s.settle = 100000;
    expect_valid(s);
}

static void test_err_busy(void **state)
{
    (void)state;
    th_step_t s[1] = {good()};
    s[0].exposure = 1000000;
    assert_int_equal(th_upload(&core, &th, s, 1), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_BUSY);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_BUSY);
}

static void test_first_failure_wins(void **state)
{
    (void)state;
    /* step 0 has a bad pulse and a bad trigger mask: the pulse (earlier check) is reported */
    th_step_t s[2] = {good(), good()};
    s[0].pulse = 2000;
    s[0].triggers = 0x20;
    s[1].source = 0x0900;
    assert_int_equal(th_upload(&core, &th, s, 2), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), DS_EX_ILLEGAL_VALUE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_PULSE_RANGE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR_STEP), 0);
}

/* ---- run time ------------------------------------------------------------------------- */

static void test_manual_light_switched_off_when_bucket_fills(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 20), 0);
    uint64_t t_on = th.now;
    assert_int_equal(th_coil(&core, &th, DS_COIL_BACKLIGHT + 1, 1), 0);
    uint16_t bl1 = th_src(DS_SRC_BACKLIGHT, 1);
    assert_int_equal(th.light[bl1], DS_HR_MANUAL_INTENSITY_DEFAULT);
    assert_int_equal(ds_core_next_deadline(&core), t_on + 20000);
    th_clear_log(&th);
    th.now = t_on + 19999;
    ds_core_poll(&core, th.now);
    assert_int_not_equal(th.light[bl1], 0);
    th.now = t_on + 20000;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.light[bl1], 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th.n_events, 1);
    assert_int_equal(th.events[0].kind_arg, DS_EVT_LED_LIMIT | DS_SRC_BACKLIGHT << 8);
    assert_int_equal(th.events[0].ts, t_on + 20000);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_LED_LIMIT);

    /* coils stay writable in FAULT, but the bucket is full: off again at once */
    assert_int_equal(th_coil(&core, &th, DS_COIL_BACKLIGHT + 1, 1), 0);
    ds_core_poll(&core, th.now);
    assert_int_equal(th.light[bl1], 0);
    /* at 50 % duty the bucket drains at 1 us/us: after 15 ms off, 15 ms of light */
    th.now += 15000;
    uint64_t t2 = th.now;
    assert_int_equal(th_coil(&core, &th, DS_COIL_BACKLIGHT + 1, 1), 0);
    assert_int_equal(ds_core_next_deadline(&core), t2 + 15000);
}

static void test_duty_1000_drains_at_once(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_MAX_ON_MS, 20), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_LED_DUTY_PERMILLE, 1000), 0);
    assert_int_equal(th_coil(&core, &th, 9, 1), 0);
    th.now += 19000;
    ds_core_poll(&core, th.now);
    assert_int_equal(th_coil(&core, &th, 9, 0), 0);
    th.now += 1;
    assert_int_equal(th_coil(&core, &th, 9, 1), 0);
    assert_int_equal(ds_core_next_deadline(&core), th.now + 20000);
}

static void test_watchdog_host_silent_mid_sequence(void **state)
{
    (void)state;
    th_step_t s[10];
    for (int i = 0; i < 10; i++) {
        s[i] = good();
        s[i].source = (uint16_t)(0x0100 | i);
        s[i].exposure = 50000;
    }
    assert_int_equal(th_upload(&core, &th, s, 10), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_WATCHDOG_MS, 100), 0);
    uint64_t t0 = th.now;
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0); /* last frame */
    th_clear_log(&th);
    /* run in virtual time: the host says nothing any more */
    for (int guard = 0; guard < 1000 && ds_core_next_deadline(&core) != DS_NO_DEADLINE; guard++) {
        th.now = ds_core_next_deadline(&core);
        ds_core_poll(&core, th.now);
    }
    assert_int_equal(th.now, t0 + 100000);
    assert_false(th_lights_on(&th));
    assert_int_equal(th.triggers, 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_WATCHDOG);
    assert_int_equal(th_ir(&core, &th, DS_IR_WATCHDOG_TRIPS), 1);
    size_t n = th.n_events;
    assert_true(n >= 2);
    assert_int_equal(th.events[n - 2].kind_arg, DS_EVT_SEQ_ABORT | DS_ABORT_WATCHDOG << 8);
    assert_int_equal(th.events[n - 2].step, 2); /* steps are 50 ms: step 2 was running */
    assert_int_equal(th.events[n - 1].kind_arg, DS_EVT_WATCHDOG);
    assert_int_equal(th.events[n - 1].ts, t0 + 100000);
}

static void test_watchdog_fed_by_frames(void **state)
{
    (void)state;
    th_step_t s[4];
    for (int i = 0; i < 4; i++) {
        s[i] = good();
        s[i].exposure = 80000;
        s[i].source = (uint16_t)(0x0100 | (i * 2));
    }
    assert_int_equal(th_upload(&core, &th, s, 4), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_WATCHDOG_MS, 100), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    uint64_t end = th.now + 4 * 80000;
    while (th.now < end + 1000) { /* a status read every 60 ms keeps it alive */
        uint64_t next = th.now + 60000;
        for (uint64_t d = ds_core_next_deadline(&core); d <= next; d = ds_core_next_deadline(&core)) {
            th.now = d;
            ds_core_poll(&core, d);
        }
        th.now = next;
        (void)th_ir(&core, &th, DS_IR_STATE);
    }
    assert_int_equal(ds_core_state(&core), DS_STATE_DONE);
    assert_int_equal(th_ir(&core, &th, DS_IR_WATCHDOG_TRIPS), 0);
    /* nothing on, no sequence: the watchdog has nothing to guard */
    assert_int_equal(ds_core_next_deadline(&core), DS_NO_DEADLINE);
}

static void test_watchdog_guards_manual_lights_and_ignores_other_servers(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_WATCHDOG_MS, 50), 0);
    assert_int_equal(th_coil(&core, &th, 42, 1), 0);
    uint64_t t_last = th.now;
    /* a frame for server 7 is bus traffic, not the host talking to us */
    uint8_t pdu[5] = {0x03, 0, 0, 0, 1}, req[16], resp[256];
    size_t n = th_adu(req, 7, pdu, 5);
    th.now += 30000;
    assert_int_equal(ds_core_handle_frame(&core, req, n, resp, th.now), 0);
    th.now = t_last + 50000 - 1;
    ds_core_poll(&core, th.now);
    assert_int_not_equal(th.light[42], 0);
    th.now = t_last + 50000;
    ds_core_poll(&core, th.now);
    assert_int_equal(th.light[42], 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_FAULT);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), DS_ERR_WATCHDOG);
    /* FAULT keeps coils writable, and the watchdog keeps guarding them */
    assert_int_equal(th_coil(&core, &th, 42, 1), 0);
    assert_int_equal(ds_core_next_deadline(&core), th.now + 50000);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_CLEAR_ERROR), 0);
    assert_int_equal(ds_core_state(&core), DS_STATE_IDLE);
    assert_int_equal(th_ir(&core, &th, DS_IR_ERROR), 0);
}

static void test_broadcast_feeds_watchdog(void **state)
{
    (void)state;
    assert_int_equal(th_write1(&core, &th, DS_HR_WATCHDOG_MS, 50), 0);
    assert_int_equal(th_coil(&core, &th, 1, 1), 0);
    uint8_t pdu[5] = {0x06, 0, DS_HR_MANUAL_INTENSITY, 0, 9}, req[16], resp[256];
    size_t n = th_adu(req, 0, pdu, 5);
    th.now += 40000;
    assert_int_equal(ds_core_handle_frame(&core, req, n, resp, th.now), 0);
    assert_int_equal(ds_core_next_deadline(&core), th.now + 50000);
}

static void test_all_off_and_abort_switch_manual_lights_off(void **state)
{
    (void)state;
    assert_int_equal(th_coil(&core, &th, 0, 1), 0);
    assert_int_equal(th_coil(&core, &th, DS_COIL_DIFFUSE, 1), 0);
    assert_true(th_lights_on(&th));
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ALL_OFF), 0);
    assert_false(th_lights_on(&th));
    assert_false(ds_core_any_light_on(&core));
    assert_int_equal(th_coil(&core, &th, 5, 1), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
    assert_false(th_lights_on(&th));
    assert_int_equal(ds_core_state(&core), DS_STATE_IDLE); /* nothing was running */
}

/* lit_count (which spares every poll a scan of all sources) equals the lights actually on,
 * through manual coils, a running sequence, ALL_OFF and ABORT. */
static uint16_t count_lit(void)
{
    uint16_t n = 0;
    for (uint16_t i = 0; i < DS_N_SOURCES; i++) {
        n += core.lights[i].intensity != 0u;
    }
    return n;
}

static void test_lit_count_follows_the_lights(void **state)
{
    (void)state;
    assert_int_equal(core.lit_count, 0);
    assert_int_equal(th_coil(&core, &th, 0, 1), 0);
    assert_int_equal(th_coil(&core, &th, 3, 1), 0);
    assert_int_equal(th_coil(&core, &th, 3, 1), 0); /* on twice counts once */
    assert_int_equal(core.lit_count, 2);
    assert_int_equal(core.lit_count, count_lit());
    assert_int_equal(th_coil(&core, &th, 0, 0), 0);
    assert_int_equal(core.lit_count, 1);
    assert_true(ds_core_any_light_on(&core));
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ALL_OFF), 0);
    assert_int_equal(core.lit_count, 0);
    assert_false(ds_core_any_light_on(&core));
    th_step_t s[2] = {good(), good()};
    assert_int_equal(th_upload(&core, &th, s, 2), 0);
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_START), 0);
    ds_core_poll(&core, 1100u); /* the first step's light is on */
    assert_int_equal(core.lit_count, count_lit());
    assert_int_equal(th_write1(&core, &th, DS_HR_COMMAND, DS_CMD_ABORT), 0);
    assert_int_equal(core.lit_count, 0);
    assert_int_equal(core.lit_count, count_lit());
}

static void test_bucket_drain_math(void **state)
{
    (void)state;
    assert_int_equal(ds_bucket_drain(10000, 1000, 500), 9000);  /* d/(1-d) = 1 */
    assert_int_equal(ds_bucket_drain(10000, 1000, 250), 9667);  /* 1/3, rounded down */
    assert_int_equal(ds_bucket_drain(10000, 1000, 1000), 0);
    assert_int_equal(ds_bucket_drain(10000, 1000, 999), 0);     /* 999 us/us */
    assert_int_equal(ds_bucket_drain(10000, 1000, 1), 9999);
    assert_int_equal(ds_bucket_drain(10000, UINT64_MAX, 1), 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_err_seq_empty, setup),
        cmocka_unit_test_setup(test_err_seq_too_long, setup),
        cmocka_unit_test_setup(test_err_bad_source, setup),
        cmocka_unit_test_setup(test_err_bad_intensity, setup),
        cmocka_unit_test_setup(test_err_polarizer_range, setup),
        cmocka_unit_test_setup(test_err_exposure_range, setup),
        cmocka_unit_test_setup(test_err_settle_range, setup),
        cmocka_unit_test_setup(test_err_pulse_range, setup),
        cmocka_unit_test_setup(test_err_brackets_range, setup),
        cmocka_unit_test_setup(test_err_trigger_mask, setup),
        cmocka_unit_test_setup(test_err_trigger_gap, setup),
        cmocka_unit_test_setup(test_trigger_mask_may_be_empty_in_camera_master, setup),
        cmocka_unit_test_setup(test_err_led_on_time, setup),
        cmocka_unit_test_setup(test_err_led_duty_leaky_bucket, setup),
        cmocka_unit_test_setup(test_err_servo_settle, setup),
        cmocka_unit_test_setup(test_err_busy, setup),
        cmocka_unit_test_setup(test_first_failure_wins, setup),
        cmocka_unit_test_setup(test_manual_light_switched_off_when_bucket_fills, setup),
        cmocka_unit_test_setup(test_duty_1000_drains_at_once, setup),
        cmocka_unit_test_setup(test_watchdog_host_silent_mid_sequence, setup),
        cmocka_unit_test_setup(test_watchdog_fed_by_frames, setup),
        cmocka_unit_test_setup(test_watchdog_guards_manual_lights_and_ignores_other_servers, setup),
        cmocka_unit_test_setup(test_broadcast_feeds_watchdog, setup),
        cmocka_unit_test_setup(test_all_off_and_abort_switch_manual_lights_off, setup),
        cmocka_unit_test_setup(test_lit_count_follows_the_lights, setup),
        cmocka_unit_test_setup(test_bucket_drain_math, setup),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
