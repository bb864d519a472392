/* The sequencer (PROTOCOL.md §3): validation at START, device-master schedule, camera-master
 * latching. Device-master deadlines chain from the schedule (next_us), never from the time an
 * action happened to run. */
#include "ds_priv.h"

enum { PH_NONE = 0, PH_STEP_START, PH_RISE, PH_FALL, PH_STEP_END };

typedef struct {
    uint16_t source, intensity, polarizer, pulse, triggers;
    uint32_t settle, exposure;
    uint8_t count, ev;
} step_view_t;

static step_view_t step_at(const ds_core_t *c, uint16_t k)
{
    const uint16_t *w = &c->steps[(uint32_t)k * DS_STEP_WORDS];
    step_view_t s;
    s.source = w[DS_STEP_SOURCE];
    s.intensity = w[DS_STEP_INTENSITY];
    s.polarizer = w[DS_STEP_POLARIZER];
    s.settle = ((uint32_t)w[DS_STEP_SETTLE_US] << 16) | w[DS_STEP_SETTLE_US + 1u];
    s.exposure = ((uint32_t)w[DS_STEP_EXPOSURE_US] << 16) | w[DS_STEP_EXPOSURE_US + 1u];
    s.pulse = w[DS_STEP_PULSE_US];
    s.count = (uint8_t)(w[DS_STEP_BRACKETS] & 0xFFu);
    s.ev = (uint8_t)(w[DS_STEP_BRACKETS] >> 8);
    s.triggers = w[DS_STEP_TRIGGERS];
    return s;
}

/* Exposure of bracket b; only called on validated steps (shift <= 28, result <= 60 s). */
static uint64_t bracket_us(const step_view_t *s, uint8_t b)
{
    return (uint64_t)s->exposure << ((unsigned)b * s->ev);
}

int ds_seq_active(const ds_core_t *c)
{
    return c->state == DS_STATE_ARMED || c->state == DS_STATE_RUNNING;
}

uint16_t ds_seq_validate(ds_core_t *c, uint16_t len, uint8_t mode, uint32_t gap_us,
                         uint16_t *err_step, uint64_t *duration_us)
{
    *err_step = DS_STEP_NONE;
    *duration_us = 0u;
    if (len == 0u) {
        return DS_ERR_SEQ_EMPTY;
    }
    if (len > DS_MAX_STEPS) {
        return DS_ERR_SEQ_TOO_LONG;
    }
    const uint64_t cap = ds_bucket_cap_us(c);
    const uint16_t permille = c->hr[DS_HR_LED_DUTY_PERMILLE];
    const uint16_t smin = c->hr[DS_HR_SERVO_MIN_CDEG], smax = c->hr[DS_HR_SERVO_MAX_CDEG];
    for (uint16_t i = 0; i < DS_N_SOURCES; i++) {
        c->sim_level[i] = 0u;
        c->sim_since[i] = 0u;
    }
    uint16_t angle = c->polarizer_now;
    uint64_t t = 0u;
    /* Per trigger line: when it last fell (device-master), so every rise can be checked to come
     * at least DS_TRIGGER_MIN_LOW_US later; UINT64_MAX = never raised yet. */
    uint64_t fell[DS_N_TRIGGERS];
    for (uint16_t i = 0; i < DS_N_TRIGGERS; i++) {
        fell[i] = UINT64_MAX;
    }
    for (uint16_t k = 0; k < len; k++) {
        step_view_t s = step_at(c, k);
        uint16_t src = DS_NO_SOURCE;
        *err_step = k;
        if (!ds_src_word_valid(s.source)) {
            return DS_ERR_BAD_SOURCE;
        }
        int lit = ds_src_from_word(s.source, &src);
        if (lit ? s.intensity == 0u : s.intensity != 0u) {
            return DS_ERR_BAD_INTENSITY;
        }
        if (s.polarizer != DS_POL_KEEP && (s.polarizer < smin || s.polarizer > smax)) {
            return DS_ERR_POLARIZER_RANGE;
        }
        if (s.count < 1u || s.count > DS_MAX_BRACKETS || s.ev > DS_MAX_EV_STEP) {
            return DS_ERR_BRACKETS_RANGE;
        }
        uint64_t body = 0u;
        for (uint8_t b = 0; b < s.count; b++) {
            uint64_t e = bracket_us(&s, b);
            if (s.exposure == 0u || e > DS_MAX_PHASE_US) {
                return DS_ERR_EXPOSURE_RANGE;
            }
            body += e + gap_us;
        }
        if (s.settle > DS_MAX_PHASE_US) {
            return DS_ERR_SETTLE_RANGE;
        }
        if (s.pulse > s.exposure) {
            return DS_ERR_PULSE_RANGE;
        }
        if ((s.triggers >> DS_N_TRIGGERS) != 0u ||
            (mode == DS_MODE_DEVICE_MASTER && lit && s.triggers == 0u)) {
            return DS_ERR_TRIGGER_MASK;
        }
        if (mode == DS_MODE_DEVICE_MASTER && s.triggers != 0u) {
            uint64_t rise = t + s.settle;
            for (uint8_t b = 0; b < s.count; b++) {
                uint64_t e = bracket_us(&s, b);
                uint64_t fall = rise + (s.pulse != 0u ? s.pulse : e);
                for (uint16_t i = 0; i < DS_N_TRIGGERS; i++) {
                    if ((s.triggers >> i) & 1u) {
                        if (fell[i] != UINT64_MAX && rise < fell[i] + DS_TRIGGER_MIN_LOW_US) {
                            return DS_ERR_TRIGGER_GAP;
                        }
                        fell[i] = fall;
                    }
                }
                rise += e + gap_us;
            }
        }
        if (s.polarizer != DS_POL_KEEP) {
            uint32_t delta = s.polarizer > angle ? (uint32_t)(s.polarizer - angle)
                                                 : (uint32_t)(angle - s.polarizer);
            /* settle_us >= delta / slew, slew in cdeg per ms */
            if ((uint64_t)s.settle * DS_POL_SLEW_CDEG_PER_MS < (uint64_t)delta * 1000u) {
                return DS_ERR_SERVO_SETTLE;
            }
            angle = s.polarizer;
        }
        uint64_t dur = (uint64_t)s.settle + body;
        if (lit) {
            if (dur > cap) {
                return DS_ERR_LED_ON_TIME;
            }
            uint64_t level = ds_bucket_drain(c->sim_level[src], t - c->sim_since[src], permille);
            level += dur;
            if (level > cap) {
                return DS_ERR_LED_DUTY;
            }
            c->sim_level[src] = level;
            c->sim_since[src] = t + dur;
        }
        t += dur;
    }
    *err_step = DS_STEP_NONE;
    *duration_us = t;
    return DS_ERR_NONE;
}

static void set_polarizer(ds_core_t *c, const step_view_t *s, uint16_t k, uint64_t now)
{
    if (s->polarizer != DS_POL_KEEP && s->polarizer != c->polarizer_now) {
        ds_hal_polarizer(c, s->polarizer);
        c->polarizer_now = s->polarizer;
        ds_evt_push(c, (uint8_t)DS_EVT_POLARIZER, 0u, k, now);
    }
}

/* Device-master: switch to step k's light (every other sequencer light off). */
static void latch_direct(ds_core_t *c, const step_view_t *s, uint64_t now)
{
    uint16_t src = DS_NO_SOURCE;
    int lit = ds_src_from_word(s->source, &src);
    if (c->seq_light != DS_NO_SOURCE && c->seq_light != src) {
        ds_light_set(c, c->seq_light, 0u, 0u, now);
    }
    if (lit) {
        ds_light_set(c, src, s->intensity, 0u, now);
        c->seq_light = src;
    } else {
        c->seq_light = DS_NO_SOURCE;
    }
}

/* Camera-master: shift step k's light state into the driver chain (applied by latch). */
static void preload(ds_core_t *c, uint16_t k)
{
    step_view_t s = step_at(c, k);
    uint16_t src = DS_NO_SOURCE;
    int lit = ds_src_from_word(s.source, &src);
    c->preload_light = lit ? src : DS_NO_SOURCE;
    c->preload_intensity = lit ? s.intensity : 0u;
    if (!ds_hal_has_preload(c)) {
        return;
    }
    uint8_t kind, index;
    if (c->seq_light != DS_NO_SOURCE && c->seq_light != c->preload_light) {
        ds_src_split(c->seq_light, &kind, &index);
        c->hal->light_preload(c->hal->ctx, kind, index, 0u);
    }
    if (lit) {
        ds_src_split(src, &kind, &index);
        c->hal->light_preload(c->hal->ctx, kind, index, s.intensity);
    }
}

static void finish(ds_core_t *c, uint64_t now)
{
    ds_all_off(c, now);
    c->phase = PH_NONE;
    c->state = DS_STATE_DONE;
    ds_evt_push(c, (uint8_t)DS_EVT_SEQ_DONE, 0u, DS_STEP_NONE, now);
}

/* Camera-master: the light switches on the edge (data already shifted in). */
static void latch_camera(ds_core_t *c, uint16_t k, uint64_t now)
{
    step_view_t s = step_at(c, k);
    c->cur_step = k;
    c->latch_us = now;
    c->edges_in_step = 0u;
    set_polarizer(c, &s, k, now);
    if (ds_hal_has_preload(c)) {
        c->hal->light_latch(c->hal->ctx);
        if (c->seq_light != DS_NO_SOURCE && c->seq_light != c->preload_light) {
            ds_light_track(c, c->seq_light, 0u, 0u, now);
        }
        if (c->preload_light != DS_NO_SOURCE) {
            ds_light_track(c, c->preload_light, c->preload_intensity, 0u, now);
        }
        c->seq_light = c->preload_light;
    } else {
        latch_direct(c, &s, now);
    }
    c->preload_light = DS_NO_SOURCE;
    ds_evt_push(c, (uint8_t)DS_EVT_STEP_START, 0u, k, now);
    if ((uint16_t)(k + 1u) < c->seq_len_run) {
        preload(c, (uint16_t)(k + 1u));
    }
}

uint8_t ds_seq_start(ds_core_t *c, uint64_t now)
{
    if (ds_seq_active(c)) {
        c->error = DS_ERR_BUSY;
        c->error_step = DS_STEP_NONE;
        return DS_EX_BUSY;
    }
    if (c->state == DS_STATE_FAULT) {
        return DS_EX_BUSY; /* CLEAR_ERROR first */
    }
    uint16_t len = c->hr[DS_HR_SEQ_LEN];
    uint8_t mode = (uint8_t)c->hr[DS_HR_TRIGGER_MODE];
    uint32_t gap = ((uint32_t)c->hr[DS_HR_FRAME_GAP_US] << 16) | c->hr[DS_HR_FRAME_GAP_US + 1u];
    uint16_t err_step;
    uint64_t duration;
    uint16_t err = ds_seq_validate(c, len, mode, gap, &err_step, &duration);
    if (err != DS_ERR_NONE) {
        c->error = err;
        c->error_step = err_step;
        return DS_EX_ILLEGAL_VALUE;
    }
    c->error = DS_ERR_NONE;
    c->error_step = DS_STEP_NONE;
    c->seq_duration_us = duration;
    ds_all_off(c, now); /* the sequence owns the lights: manual lights go off */
    c->seq_len_run = len;
    c->run_mode = mode;
    c->run_gap_us = gap;
    c->run_camera = (uint8_t)c->hr[DS_HR_MASTER_CAMERA];
    c->cur_step = 0u;
    c->bracket = 0u;
    c->edges_in_step = 0u;
    c->last_edge_us = now;
    c->preload_light = DS_NO_SOURCE;
    ds_evt_push(c, (uint8_t)DS_EVT_SEQ_START, mode, DS_STEP_NONE, now);
    if (mode == DS_MODE_CAMERA_MASTER) {
        c->state = DS_STATE_ARMED;
        c->phase = PH_NONE;
        preload(c, 0u);
    } else {
        c->state = DS_STATE_RUNNING;
        c->phase = PH_STEP_START;
        c->next_us = now;
        ds_seq_run(c, now);
    }
    return DS_EX_NONE;
}

void ds_seq_stop(ds_core_t *c, uint8_t abort_reason, uint64_t now)
{
    if (!ds_seq_active(c)) {
        return;
    }
    uint16_t step = c->state == DS_STATE_RUNNING ? c->cur_step : DS_STEP_NONE;
    if (c->preload_light != DS_NO_SOURCE && ds_hal_has_preload(c)) {
        uint8_t kind, index; /* leave nothing lit in the chain's shadow register */
        ds_src_split(c->preload_light, &kind, &index);
        c->hal->light_preload(c->hal->ctx, kind, index, 0u);
    }
    c->preload_light = DS_NO_SOURCE;
    ds_all_off(c, now);
    c->phase = PH_NONE;
    c->state = DS_STATE_ABORTED; /* callers that fault overwrite it */
    ds_evt_push(c, (uint8_t)DS_EVT_SEQ_ABORT, abort_reason, step, now);
}

static void device_step(ds_core_t *c, uint64_t now)
{
    uint16_t k = c->cur_step;
    step_view_t s = step_at(c, k);
    switch (c->phase) {
    case PH_STEP_START:
        c->step_start_us = c->next_us;
        set_polarizer(c, &s, k, now);
        latch_direct(c, &s, now);
        ds_evt_push(c, (uint8_t)DS_EVT_STEP_START, 0u, k, now);
        c->bracket = 0u;
        c->next_us = c->step_start_us + s.settle;
        c->phase = PH_RISE;
        break;
    case PH_RISE:
        c->bracket_start_us = c->next_us;
        if (s.triggers) {
            c->trig_level = (uint8_t)s.triggers;
            ds_hal_triggers(c, c->trig_level);
            ds_evt_push(c, (uint8_t)DS_EVT_TRIGGER, c->bracket, k, now);
        }
        c->next_us = c->bracket_start_us + (s.pulse ? s.pulse : bracket_us(&s, c->bracket));
        c->phase = PH_FALL;
        break;
    case PH_FALL:
        if (c->trig_level) {
            c->trig_level = 0u;
            ds_hal_triggers(c, 0u);
        }
        c->next_us = c->bracket_start_us + bracket_us(&s, c->bracket) + c->run_gap_us;
        c->bracket++;
        c->phase = c->bracket < s.count ? PH_RISE : PH_STEP_END;
        break;
    case PH_STEP_END:
        ds_evt_push(c, (uint8_t)DS_EVT_STEP_END, 0u, k, now);
        if ((uint16_t)(k + 1u) < c->seq_len_run) {
            c->cur_step = (uint16_t)(k + 1u);
            c->phase = PH_STEP_START; /* same instant */
        } else {
            finish(c, now);
        }
        break;
    default:
        c->phase = PH_NONE;
        break;
    }
}

void ds_seq_run(ds_core_t *c, uint64_t now)
{
    if (!ds_seq_active(c)) {
        return;
    }
    if (c->run_mode == DS_MODE_CAMERA_MASTER) {
        uint64_t timeout = (uint64_t)c->hr[DS_HR_CAMERA_TIMEOUT_MS] * 1000u;
        if (now >= c->last_edge_us + timeout) {
            ds_fault(c, DS_ERR_CAMERA_TIMEOUT, now);
        }
        return;
    }
    while (c->state == DS_STATE_RUNNING && c->phase != PH_NONE && c->next_us <= now) {
        device_step(c, now);
    }
}

uint64_t ds_seq_deadline(const ds_core_t *c)
{
    if (!ds_seq_active(c)) {
        return DS_NO_DEADLINE;
    }
    if (c->run_mode == DS_MODE_CAMERA_MASTER) {
        return c->last_edge_us + (uint64_t)c->hr[DS_HR_CAMERA_TIMEOUT_MS] * 1000u;
    }
    return c->phase != PH_NONE ? c->next_us : DS_NO_DEADLINE;
}

/* Report an edge of the latched step: counted unless it falls inside SETTLE_US after the latch
 * (the latching edge itself counts as bracket 0 exactly when SETTLE_US = 0). */
static void count_edge(ds_core_t *c, uint8_t camera, uint64_t now)
{
    step_view_t s = step_at(c, c->cur_step);
    if (now < c->latch_us + s.settle) {
        ds_evt_push(c, (uint8_t)DS_EVT_CAMERA_EDGE, (uint8_t)(camera | DS_EDGE_IGNORED), c->cur_step, now);
        return;
    }
    c->edges_in_step++;
    ds_evt_push(c, (uint8_t)DS_EVT_CAMERA_EDGE, camera, c->cur_step, now);
}

void ds_seq_edge(ds_core_t *c, uint8_t camera, uint64_t now)
{
    if (!ds_seq_active(c) || c->run_mode != DS_MODE_CAMERA_MASTER || camera != c->run_camera) {
        return;
    }
    c->last_edge_us = now;
    if (c->state == DS_STATE_ARMED) {
        c->state = DS_STATE_RUNNING;
        latch_camera(c, 0u, now);
        count_edge(c, camera, now);
        return;
    }
    step_view_t s = step_at(c, c->cur_step);
    if (now < c->latch_us + s.settle || c->edges_in_step < s.count) {
        count_edge(c, camera, now);
        return;
    }
    /* the step has all its frames: this edge starts the next step or ends the sequence */
    uint16_t k = c->cur_step;
    if ((uint16_t)(k + 1u) < c->seq_len_run) {
        ds_evt_push(c, (uint8_t)DS_EVT_STEP_END, 0u, k, now);
        latch_camera(c, (uint16_t)(k + 1u), now);
        count_edge(c, camera, now);
    } else {
        ds_evt_push(c, (uint8_t)DS_EVT_CAMERA_EDGE, (uint8_t)(camera | DS_EDGE_IGNORED), k, now);
        ds_evt_push(c, (uint8_t)DS_EVT_STEP_END, 0u, k, now);
        finish(c, now);
    }
}
