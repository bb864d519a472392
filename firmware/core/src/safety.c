/* Safety (PROTOCOL.md §5): light bookkeeping, leaky buckets, host watchdog, faults. */
#include "ds_priv.h"

/* Source index: the DS_N_LEDS LEDs, then the back lights, then the diffuse group. */
void ds_src_split(uint16_t src, uint8_t *kind, uint8_t *index)
{
    if (src < DS_N_LEDS) {
        *kind = (uint8_t)DS_SRC_LED;
        *index = (uint8_t)src;
    } else if (src < DS_N_LEDS + DS_N_BACKLIGHTS) {
        *kind = (uint8_t)DS_SRC_BACKLIGHT;
        *index = (uint8_t)(src - DS_N_LEDS);
    } else {
        *kind = (uint8_t)DS_SRC_DIFFUSE;
        *index = (uint8_t)(src - DS_N_LEDS - DS_N_BACKLIGHTS);
    }
}

int ds_src_word_valid(uint16_t w)
{
    uint16_t kind = (uint16_t)(w >> 8), index = (uint16_t)(w & 0xFFu);
    switch (kind) {
    case DS_SRC_OFF: return index == 0u;
    case DS_SRC_LED: return index < DS_N_LEDS;
    case DS_SRC_BACKLIGHT: return index < DS_N_BACKLIGHTS;
    case DS_SRC_DIFFUSE: return index < DS_N_DIFFUSE;
    default: return 0;
    }
}

int ds_src_from_word(uint16_t w, uint16_t *src)
{
    uint16_t kind = (uint16_t)(w >> 8), index = (uint16_t)(w & 0xFFu);
    if (!ds_src_word_valid(w) || kind == DS_SRC_OFF) {
        return 0;
    }
    if (kind == DS_SRC_LED) {
        *src = index;
    } else if (kind == DS_SRC_BACKLIGHT) {
        *src = (uint16_t)(DS_N_LEDS + index);
    } else {
        *src = (uint16_t)(DS_N_LEDS + DS_N_BACKLIGHTS + index);
    }
    return 1;
}

uint16_t ds_src_from_coil(uint16_t coil)
{
    if ((uint16_t)(coil - DS_COIL_LED) < DS_N_LEDS) { /* wraps below DS_COIL_LED */
        return (uint16_t)(coil - DS_COIL_LED);
    }
    if (coil >= DS_COIL_BACKLIGHT && coil < DS_COIL_BACKLIGHT + DS_N_BACKLIGHTS) {
        return (uint16_t)(DS_N_LEDS + coil - DS_COIL_BACKLIGHT);
    }
    if (coil >= DS_COIL_DIFFUSE && coil < DS_COIL_DIFFUSE + DS_N_DIFFUSE) {
        return (uint16_t)(DS_N_LEDS + DS_N_BACKLIGHTS + coil - DS_COIL_DIFFUSE);
    }
    return DS_NO_SOURCE;
}

/* Drain of an off light over dt: d/(1-d) us per us, d = permille/1000; d = 1 drains at once. */
uint64_t ds_bucket_drain(uint64_t level, uint64_t dt, uint16_t permille)
{
    if (permille >= 1000u || dt >= UINT64_MAX / 1000u) {
        return 0u;
    }
    uint64_t drained = dt * permille / (uint64_t)(1000u - permille);
    return level > drained ? level - drained : 0u;
}

uint64_t ds_bucket_cap_us(const ds_core_t *c)
{
    return (uint64_t)c->hr[DS_HR_LED_MAX_ON_MS] * 1000u;
}

static void bucket_advance(ds_core_t *c, ds_light_t *l, uint64_t now)
{
    if (now <= l->since_us) {
        return;
    }
    uint64_t dt = now - l->since_us;
    if (l->intensity) {
        l->level_us = (l->level_us > UINT64_MAX - dt) ? UINT64_MAX : l->level_us + dt;
    } else {
        l->level_us = ds_bucket_drain(l->level_us, dt, c->hr[DS_HR_LED_DUTY_PERMILLE]);
    }
    l->since_us = now;
}

void ds_light_track(ds_core_t *c, uint16_t src, uint16_t intensity, uint8_t manual, uint64_t now)
{
    if (src >= DS_N_SOURCES) {
        return;
    }
    ds_light_t *l = &c->lights[src];
    bucket_advance(c, l, now);
    if (!l->intensity && intensity) {
        c->lit_count++;
    } else if (l->intensity && !intensity) {
        c->lit_count--;
    }
    l->intensity = intensity;
    l->manual = intensity ? manual : 0u;
}

void ds_light_set(ds_core_t *c, uint16_t src, uint16_t intensity, uint8_t manual, uint64_t now)
{
    if (src >= DS_N_SOURCES) {
        return;
    }
    uint8_t kind, index;
    ds_light_track(c, src, intensity, manual, now);
    ds_src_split(src, &kind, &index);
    ds_hal_light(c, kind, index, intensity);
}

void ds_all_off(ds_core_t *c, uint64_t now)
{
    for (uint16_t i = 0; c->lit_count != 0u && i < DS_N_SOURCES; i++) {
        if (c->lights[i].intensity) {
            ds_light_set(c, i, 0u, 0u, now);
        }
    }
    c->seq_light = DS_NO_SOURCE;
    c->trig_level = 0u;
    ds_hal_triggers(c, 0u);
}

int ds_core_any_light_on(const ds_core_t *c)
{
    return c->lit_count != 0u; /* ds_light_track keeps the count: no scan of every source per poll */
}

/* A light whose bucket is enforced at run time: manual lights, and in camera-master the
 * sequencer light (its on-time depends on the camera, so START cannot bound it). */
static int enforced(const ds_core_t *c, uint16_t src)
{
    const ds_light_t *l = &c->lights[src];
    if (!l->intensity) {
        return 0;
    }
    if (l->manual) {
        return 1;
    }
    return ds_seq_active(c) && c->run_mode == DS_MODE_CAMERA_MASTER && src == c->seq_light;
}

static uint64_t limit_time(const ds_core_t *c, uint16_t src)
{
    const ds_light_t *l = &c->lights[src];
    uint64_t cap = ds_bucket_cap_us(c);
    return l->level_us >= cap ? l->since_us : l->since_us + (cap - l->level_us);
}

static int watchdog_guarding(const ds_core_t *c)
{
    return c->hr[DS_HR_WATCHDOG_MS] != 0u && (ds_seq_active(c) || ds_core_any_light_on(c));
}

static uint64_t watchdog_time(const ds_core_t *c)
{
    return c->last_host_us + (uint64_t)c->hr[DS_HR_WATCHDOG_MS] * 1000u;
}

uint64_t ds_safety_deadline(const ds_core_t *c)
{
    uint64_t d = DS_NO_DEADLINE;
    if (watchdog_guarding(c)) {
        d = watchdog_time(c);
    }
    for (uint16_t i = 0; c->lit_count != 0u && i < DS_N_SOURCES; i++) {
        if (enforced(c, i)) {
            uint64_t t = limit_time(c, i);
            if (t < d) {
                d = t;
            }
        }
    }
    return d;
}

static void enter_fault(ds_core_t *c, uint16_t error, uint16_t error_step)
{
    c->state = DS_STATE_FAULT;
    c->error = error;
    c->error_step = error_step;
}

void ds_fault(ds_core_t *c, uint16_t error, uint64_t now)
{
    uint16_t step = ds_seq_active(c) ? c->cur_step : DS_STEP_NONE;
    ds_seq_stop(c, (uint8_t)DS_ABORT_FAULT, now);
    ds_all_off(c, now);
    ds_evt_push(c, (uint8_t)DS_EVT_FAULT, (uint8_t)error, step, now);
    enter_fault(c, error, step);
}

void ds_safety_run(ds_core_t *c, uint64_t now)
{
    if (watchdog_guarding(c) && now >= watchdog_time(c)) {
        ds_seq_stop(c, (uint8_t)DS_ABORT_WATCHDOG, now);
        ds_all_off(c, now);
        ds_evt_push(c, (uint8_t)DS_EVT_WATCHDOG, 0u, DS_STEP_NONE, now);
        c->watchdog_trips++;
        enter_fault(c, DS_ERR_WATCHDOG, DS_STEP_NONE);
    }
    for (uint16_t i = 0; c->lit_count != 0u && i < DS_N_SOURCES; i++) {
        if (enforced(c, i) && now >= limit_time(c, i)) {
            uint8_t kind, index;
            uint16_t step = (c->lights[i].manual || !ds_seq_active(c)) ? DS_STEP_NONE : c->cur_step;
            ds_src_split(i, &kind, &index);
            ds_seq_stop(c, (uint8_t)DS_ABORT_FAULT, now);
            ds_all_off(c, now);
            ds_evt_push(c, (uint8_t)DS_EVT_LED_LIMIT, kind, step, now);
            enter_fault(c, DS_ERR_LED_LIMIT, step);
            break; /* everything is off now */
        }
    }
}
