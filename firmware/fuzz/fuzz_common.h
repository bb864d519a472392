/* Shared pieces of the libFuzzer harnesses: a model HAL and the invariants every input must
 * keep. Header-only so that each harness is one translation unit plus the core. */
#ifndef FUZZ_COMMON_H
#define FUZZ_COMMON_H

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "ds_core.h"

#define FZ_CHECK(cond) do { if (!(cond)) { __builtin_trap(); } } while (0)

/* The harness's own checks are not code under test: no coverage counters and no comparison
 * tracing in them (ASan/UBSan stay on). Without this, the per-source loops below, run at every
 * deadline, cost more than the core itself and flood libFuzzer's feature set with harness
 * branches. */
#if defined(__clang__)
#define FZ_HARNESS __attribute__((no_sanitize("coverage")))
#else
#define FZ_HARNESS
#endif

typedef struct {
    uint64_t now;
    /* A lower bound of ds_core_next_deadline(core), or 0 when unknown. Valid while only
     * ds_core_rx() (through fz_rx) has been called since it was computed: bytes only append to
     * the frame being received, whose end lies at least t3.5 after them. It spares the scan of
     * every light source that ds_core_next_deadline() does, once per byte fed. */
    uint64_t next;
    uint16_t light[DS_N_SOURCES];
    uint16_t shadow[DS_N_SOURCES];
    uint64_t on_since[DS_N_SOURCES];
    uint32_t max_cap_ms[DS_N_SOURCES]; /* largest LED_MAX_ON_MS seen while the light was on */
    uint8_t triggers;
    const ds_core_t *core;
    ds_hal_t hal;
    uint8_t uart[DS_RTU_MAX_ADU + 1];
    size_t uart_len;
} fz_t;

FZ_HARNESS static uint16_t fz_src(uint8_t kind, uint8_t index)
{
    switch (kind) {
    case DS_SRC_LED: FZ_CHECK(index < DS_N_LEDS); return index;
    case DS_SRC_BACKLIGHT: FZ_CHECK(index < DS_N_BACKLIGHTS); return (uint16_t)(DS_N_LEDS + index);
    case DS_SRC_DIFFUSE: FZ_CHECK(index < DS_N_DIFFUSE); return (uint16_t)(DS_N_LEDS + DS_N_BACKLIGHTS + index);
    default: FZ_CHECK(0); return 0;
    }
}

FZ_HARNESS static void fz_apply(fz_t *f, uint16_t s, uint16_t intensity)
{
    if (intensity && !f->light[s]) {
        f->on_since[s] = f->now;
        f->max_cap_ms[s] = f->core->hr[DS_HR_LED_MAX_ON_MS];
    }
    f->light[s] = intensity;
}

FZ_HARNESS static void fz_light(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    fz_t *f = ctx;
    uint16_t s = fz_src(kind, index);
    fz_apply(f, s, intensity);
    f->shadow[s] = intensity;
}

FZ_HARNESS static void fz_preload(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    fz_t *f = ctx;
    f->shadow[fz_src(kind, index)] = intensity;
}

FZ_HARNESS static void fz_latch(void *ctx)
{
    fz_t *f = ctx;
    for (uint16_t s = 0; s < DS_N_SOURCES; s++) {
        fz_apply(f, s, f->shadow[s]);
    }
}

FZ_HARNESS static void fz_uart(void *ctx, const uint8_t *buf, uint16_t len)
{
    fz_t *f = ctx;
    FZ_CHECK(len <= DS_RTU_MAX_ADU);
    memcpy(f->uart, buf, len);
    f->uart_len = len;
}

FZ_HARNESS static void fz_polarizer(void *ctx, uint16_t cdeg)
{
    (void)ctx;
    FZ_CHECK(cdeg <= DS_POL_MAX_CDEG);
}

FZ_HARNESS static void fz_triggers(void *ctx, uint8_t mask)
{
    fz_t *f = ctx;
    FZ_CHECK((mask >> DS_N_TRIGGERS) == 0);
    f->triggers = mask;
}

/* The line format the core hands the UART: only what a Modbus write of the pair may set
 * (Modbus over Serial Line v1.02 §2.5.1: no parity needs two stop bits). */
FZ_HARNESS static void fz_uart_format(void *ctx, uint8_t parity, uint8_t stop_bits)
{
    (void)ctx;
    FZ_CHECK(parity == DS_PARITY_NONE || parity == DS_PARITY_ODD || parity == DS_PARITY_EVEN);
    FZ_CHECK(stop_bits == 1u || stop_bits == 2u);
    FZ_CHECK(parity != DS_PARITY_NONE || stop_bits == 2u);
}

FZ_HARNESS static void fz_init_slow(fz_t *f, ds_core_t *c)
{
    memset(f, 0, sizeof *f);
    f->core = c;
    f->hal.ctx = f;
    f->hal.uart_write = fz_uart;
    f->hal.light_set = fz_light;
    f->hal.light_preload = fz_preload;
    f->hal.light_latch = fz_latch;
    f->hal.polarizer_set = fz_polarizer;
    f->hal.triggers_write = fz_triggers;
    f->hal.uart_format = fz_uart_format;
    f->now = 1000;
    ds_core_init(c, &f->hal, 1, f->now);
    ds_core_set_target(c, "posix");
}

/* Reset core and model to the power-on state for the next input. ds_core_init() runs once; each
 * input then starts from a byte copy of that state (the core holds no state outside ds_core_t
 * and its HAL context is `f`, which does not move), so a reset is two memcpy()s and costs no
 * coverage of the init path on every input. */
FZ_HARNESS static void fz_init(fz_t *f, ds_core_t *c)
{
    static ds_core_t core0;
    static fz_t fz0;
    static const fz_t *owner;
    if (owner != f) {
        fz_init_slow(f, c);
        memcpy(&core0, c, sizeof core0);
        memcpy(&fz0, f, sizeof fz0);
        owner = f;
        return;
    }
    memcpy(c, &core0, sizeof *c);
    memcpy(f, &fz0, sizeof *f);
}

/* A response is a valid RTU frame from server 1 with a correct CRC. */
FZ_HARNESS static void fz_check_response(const uint8_t *r, size_t n)
{
    if (n == 0) {
        return;
    }
    FZ_CHECK(n >= 5 && n <= DS_RTU_MAX_ADU);
    FZ_CHECK(r[0] == 1);
    FZ_CHECK(ds_crc16(r, n) == 0);
    if (r[1] & 0x80) {
        FZ_CHECK(n == 5);
        FZ_CHECK(r[2] == 1 || r[2] == 2 || r[2] == 3 || r[2] == 4 || r[2] == 6);
    }
}

/* Invariants that hold between any two calls into the core. Run at every deadline, so it is
 * also free of ASan/UBSan checks: it reads fixed-size arrays with constant bounds. */
FZ_HARNESS __attribute__((no_sanitize("address", "undefined"))) static void fz_check_state(fz_t *f)
{
    const ds_core_t *c = f->core;
    for (uint16_t s = 0; s < DS_N_SOURCES; s++) {
        FZ_CHECK(f->light[s] == c->lights[s].intensity); /* hardware = model */
        if (f->light[s]) {
            uint32_t cap = c->hr[DS_HR_LED_MAX_ON_MS];
            if (cap > f->max_cap_ms[s]) {
                f->max_cap_ms[s] = cap;
            }
            /* no light (manual or sequenced) stays on longer than LED_MAX_ON_MS */
            FZ_CHECK(f->now - f->on_since[s] <= (uint64_t)f->max_cap_ms[s] * 1000u);
        }
    }
    if (c->state != DS_STATE_RUNNING) {
        FZ_CHECK(f->triggers == 0); /* trigger lines low outside a run */
    }
    if (c->state == DS_STATE_ARMED) {
        FZ_CHECK(!ds_core_any_light_on(c));
    }
    FZ_CHECK(c->fifo_count <= DS_FIFO_DEPTH);
    FZ_CHECK(c->rx_len <= DS_RTU_MAX_ADU);
    FZ_CHECK(c->state <= DS_STATE_FAULT);
}

/* Advance to `t` the way a target must: poll at every deadline on the way, each at exactly its
 * time, then at `t` itself if something is due there. No poll where nothing is due (the core
 * promises that ds_core_next_deadline() is the earliest time a poll has work): a poll costs a
 * scan of every light source, and the byte-by-byte feeding of fuzz_rtu advances ~70 times per
 * frame. fz_poll_now() is the explicit "poll at an arbitrary time" that targets also do. */
FZ_HARNESS static void fz_advance(fz_t *f, ds_core_t *c, uint64_t t)
{
    if (f->next > t) { /* nothing can be due before t */
        f->now = t > f->now ? t : f->now;
        return;
    }
    uint64_t d = ds_core_next_deadline(c);
    for (int guard = 0; guard < 200000 && d <= t; guard++) {
        if (d > f->now) {
            f->now = d;
        }
        ds_core_poll(c, f->now);
        d = ds_core_next_deadline(c);
        FZ_CHECK(d > f->now); /* everything due was done: no busy loop */
        fz_check_state(f);
    }
    if (t > f->now) {
        f->now = t;
    }
    f->next = d;
}

/* Bytes on the line at the current time. Whatever was due has been polled (fz_advance), so
 * the core only appends them; the frame they belong to ends t3.5 or later from now. */
FZ_HARNESS static void fz_rx(fz_t *f, ds_core_t *c, const uint8_t *buf, size_t n)
{
    ds_core_rx(c, buf, n, f->now);
    uint64_t end = f->now + c->t35_us;
    if (n > 0 && f->next > end) {
        f->next = end;
    }
}

/* One character with UART errors (DS_UART_ERR_* mask): like a byte for the frame's timing. */
FZ_HARNESS static void fz_rx_error(fz_t *f, ds_core_t *c, uint8_t errors)
{
    ds_core_rx_error(c, errors, f->now);
    uint64_t end = f->now + c->t35_us;
    if (f->next > end) {
        f->next = end;
    }
}

/* The core was called otherwise (a frame, an edge, a poll): its next deadline is unknown. */
FZ_HARNESS static void fz_touched(fz_t *f)
{
    f->next = 0;
}

/* A poll at the current time, due or not: it must change nothing that was not due. */
FZ_HARNESS static void fz_poll_now(fz_t *f, ds_core_t *c)
{
    ds_core_poll(c, f->now);
    fz_touched(f);
    FZ_CHECK(ds_core_next_deadline(c) > f->now);
    fz_check_state(f);
}

/* After a successful ALL_OFF or ABORT response, nothing may be lit. */
FZ_HARNESS static void fz_check_command(fz_t *f, const uint8_t *req, size_t n, const uint8_t *resp, size_t rn)
{
    if (n < 8 || rn == 0 || (resp[1] & 0x80)) {
        return;
    }
    uint16_t cmd = 0xFFFF;
    if (req[1] == 0x06 && req[2] == 0 && req[3] == DS_HR_COMMAND) {
        cmd = (uint16_t)(req[4] << 8 | req[5]);
    } else if ((req[1] == 0x10) && req[2] == 0 && req[3] == DS_HR_COMMAND && n >= 10) {
        cmd = (uint16_t)(req[7] << 8 | req[8]);
    }
    if (cmd == DS_CMD_ALL_OFF || cmd == DS_CMD_ABORT) {
        for (uint16_t s = 0; s < DS_N_SOURCES; s++) {
            FZ_CHECK(f->light[s] == 0);
        }
        FZ_CHECK(f->triggers == 0);
        FZ_CHECK(f->core->state != DS_STATE_RUNNING && f->core->state != DS_STATE_ARMED);
    }
}

#endif
