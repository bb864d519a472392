/* The core's entry points: init, poll, deadlines, camera edges. */
#include <string.h>

#include "ds_priv.h"

void ds_core_set_target(ds_core_t *c, const char *name)
{
    size_t i = 0;
    if (name != NULL) {
        for (; i < DS_TARGET_NAME_MAX && name[i] != '\0'; i++) {
            c->target[i] = name[i];
        }
    }
    c->target[i] = '\0';
}

uint16_t ds_core_state(const ds_core_t *c)
{
    return c->state;
}

void ds_core_init(ds_core_t *c, const ds_hal_t *hal, uint8_t address, uint64_t now_us)
{
    memset(c, 0, sizeof *c);
    c->hal = hal;
    c->address = address;
    c->t35_us = ds_rtu_t35_us(DS_DEFAULT_BAUD);
    ds_core_set_target(c, "unknown");

    /* reset values of the holding registers: the table protocol/gen.py generates from the
     * `default` of each register in registers.toml */
    _Static_assert(sizeof c->hr == sizeof DS_HR_DEFAULTS, "hr[] and DS_HR_DEFAULTS differ");
    memcpy(c->hr, DS_HR_DEFAULTS, sizeof c->hr);

    c->state = DS_STATE_IDLE;
    c->error = DS_ERR_NONE;
    c->error_step = DS_STEP_NONE;
    c->polarizer_now = c->hr[DS_HR_POLARIZER_CDEG];
    c->last_host_us = now_us;
    c->last_edge_us = now_us;
    c->seq_light = DS_NO_SOURCE;
    c->preload_light = DS_NO_SOURCE;
    for (uint16_t i = 0; i < DS_N_SOURCES; i++) {
        c->lights[i].since_us = now_us;
    }
    ds_fifo_reset(c);

    /* put the hardware in the state the model describes: dark, triggers low, servo at 0 */
    for (uint16_t i = 0; i < DS_N_SOURCES; i++) {
        uint8_t kind, index;
        ds_src_split(i, &kind, &index);
        ds_hal_light(c, kind, index, 0u);
    }
    ds_hal_triggers(c, 0u);
    ds_hal_polarizer(c, c->polarizer_now);
    c->line_format_pending = 1u; /* the serial line starts in the reset format */
    ds_line_format_apply(c);
}

void ds_run_timers(ds_core_t *c, uint64_t now)
{
    ds_seq_run(c, now);
    ds_safety_run(c, now);
}

void ds_core_poll(ds_core_t *c, uint64_t now_us)
{
    ds_rtu_check_end(c, now_us);
    ds_run_timers(c, now_us);
}

uint64_t ds_core_next_deadline(const ds_core_t *c)
{
    uint64_t d = ds_rtu_deadline(c);
    uint64_t s = ds_seq_deadline(c);
    uint64_t f = ds_safety_deadline(c);
    if (s < d) {
        d = s;
    }
    if (f < d) {
        d = f;
    }
    return d;
}

void ds_core_camera_edge(ds_core_t *c, uint8_t camera, uint64_t now_us)
{
    ds_run_timers(c, now_us); /* a timeout that was due wins over a late edge */
    if (camera < DS_N_CAMERAS) {
        ds_seq_edge(c, camera, now_us);
    }
}

size_t ds_core_handle_frame(ds_core_t *c, const uint8_t *req, size_t n, uint8_t *resp, uint64_t now_us)
{
    ds_run_timers(c, now_us);
    size_t r = ds_modbus_process(c, req, n, resp, now_us);
    ds_line_format_apply(c); /* the caller sends resp before the line changes, as ds_core_rx does */
    return r;
}
