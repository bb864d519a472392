#include "test_hal.h"

#include <string.h>

static void log_call(test_hal_t *th, enum th_call type, uint8_t kind, uint8_t index, uint16_t v)
{
    if (th->n_calls < TH_MAX_CALLS) {
        th_call_t *c = &th->calls[th->n_calls++];
        c->type = type;
        c->t = th->now;
        c->kind = kind;
        c->index = index;
        c->value = v;
    }
}

uint16_t th_src(uint8_t kind, uint8_t index)
{
    switch (kind) {
    case DS_SRC_LED: return index;
    case DS_SRC_BACKLIGHT: return (uint16_t)(DS_N_LEDS + index);
    default: return (uint16_t)(DS_N_LEDS + DS_N_BACKLIGHTS + index);
    }
}

static void h_uart(void *ctx, const uint8_t *buf, uint16_t len)
{
    test_hal_t *th = ctx;
    memcpy(th->uart, buf, len);
    th->uart_len = len;
    th->uart_frames++;
    log_call(th, TH_UART, 0, 0, len);
}

static void h_format(void *ctx, uint8_t parity, uint8_t stop_bits)
{
    test_hal_t *th = ctx;
    th->parity = parity;
    th->stop_bits = stop_bits;
    th->formats++;
    log_call(th, TH_FORMAT, parity, stop_bits, 0);
}

static void h_light(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    test_hal_t *th = ctx;
    uint16_t s = th_src(kind, index);
    th->light[s] = intensity;
    th->shadow[s] = intensity;
    log_call(th, TH_LIGHT, kind, index, intensity);
}

static void h_preload(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    test_hal_t *th = ctx;
    th->shadow[th_src(kind, index)] = intensity;
    log_call(th, TH_PRELOAD, kind, index, intensity);
}

static void h_latch(void *ctx)
{
    test_hal_t *th = ctx;
    memcpy(th->light, th->shadow, sizeof th->light);
    log_call(th, TH_LATCH, 0, 0, 0);
}

static void h_polarizer(void *ctx, uint16_t cdeg)
{
    test_hal_t *th = ctx;
    th->polarizer = cdeg;
    log_call(th, TH_POLARIZER, 0, 0, cdeg);
}

static void h_triggers(void *ctx, uint8_t mask)
{
    test_hal_t *th = ctx;
    th->triggers = mask;
    log_call(th, TH_TRIGGERS, 0, 0, mask);
}

static void h_event(void *ctx, const ds_event_t *e)
{
    test_hal_t *th = ctx;
    if (th->n_events < TH_MAX_EVENTS) {
        th->events[th->n_events].kind_arg = e->kind_arg;
        th->events[th->n_events].step = e->step;
        th->events[th->n_events].ts = e->ts_us;
        th->n_events++;
    }
}

void th_init(test_hal_t *th, int with_preload)
{
    memset(th, 0, sizeof *th);
    th->hal.ctx = th;
    th->hal.uart_write = h_uart;
    th->hal.light_set = h_light;
    th->hal.light_preload = with_preload ? h_preload : NULL;
    th->hal.light_latch = with_preload ? h_latch : NULL;
    th->hal.polarizer_set = h_polarizer;
    th->hal.triggers_write = h_triggers;
    th->hal.on_event = h_event;
    th->hal.uart_format = h_format;
}

void th_clear_log(test_hal_t *th)
{
    th->n_calls = 0;
    th->n_events = 0;
}

int th_lights_on(const test_hal_t *th)
{
    for (size_t i = 0; i < DS_N_SOURCES; i++) {
        if (th->light[i]) {
            return 1;
        }
    }
    return 0;
}

size_t th_adu(uint8_t *out, uint8_t addr, const uint8_t *pdu, size_t pdu_len)
{
    out[0] = addr;
    memcpy(&out[1], pdu, pdu_len);
    uint16_t crc = ds_crc16(out, pdu_len + 1u);
    out[pdu_len + 1u] = (uint8_t)(crc & 0xFFu);
    out[pdu_len + 2u] = (uint8_t)(crc >> 8);
    return pdu_len + 3u;
}

size_t th_request(ds_core_t *c, test_hal_t *th, const uint8_t *pdu, size_t pdu_len, uint8_t *resp)
{
    uint8_t req[300];
    size_t n = th_adu(req, 1, pdu, pdu_len);
    return ds_core_handle_frame(c, req, n, resp, th->now);
}

static int result(const uint8_t *resp, size_t n)
{
    if (n == 0u) {
        return -1;
    }
    return (resp[1] & 0x80u) ? resp[2] : 0;
}

int th_write1(ds_core_t *c, test_hal_t *th, uint16_t addr, uint16_t value)
{
    uint8_t pdu[5] = {0x06, (uint8_t)(addr >> 8), (uint8_t)addr, (uint8_t)(value >> 8), (uint8_t)value};
    uint8_t resp[256];
    return result(resp, th_request(c, th, pdu, sizeof pdu, resp));
}

int th_writen(ds_core_t *c, test_hal_t *th, uint16_t addr, const uint16_t *v, uint16_t n)
{
    uint8_t pdu[260];
    uint8_t resp[256];
    pdu[0] = 0x10;
    pdu[1] = (uint8_t)(addr >> 8);
    pdu[2] = (uint8_t)addr;
    pdu[3] = (uint8_t)(n >> 8);
    pdu[4] = (uint8_t)n;
    pdu[5] = (uint8_t)(2u * n);
    for (uint16_t i = 0; i < n; i++) {
        pdu[6 + 2 * i] = (uint8_t)(v[i] >> 8);
        pdu[7 + 2 * i] = (uint8_t)v[i];
    }
    return result(resp, th_request(c, th, pdu, 6u + 2u * n, resp));
}

int th_read(ds_core_t *c, test_hal_t *th, uint8_t fc, uint16_t addr, uint16_t n, uint16_t *out)
{
    uint8_t pdu[5] = {fc, (uint8_t)(addr >> 8), (uint8_t)addr, (uint8_t)(n >> 8), (uint8_t)n};
    uint8_t resp[256];
    size_t len = th_request(c, th, pdu, sizeof pdu, resp);
    int r = result(resp, len);
    if (r == 0) {
        for (uint16_t i = 0; i < n; i++) {
            out[i] = (uint16_t)(resp[3 + 2 * i] << 8 | resp[4 + 2 * i]);
        }
    }
    return r;
}

uint16_t th_ir(ds_core_t *c, test_hal_t *th, uint16_t addr)
{
    uint16_t v = 0xDEADu;
    th_read(c, th, 0x04, addr, 1, &v);
    return v;
}

int th_coil(ds_core_t *c, test_hal_t *th, uint16_t addr, int on)
{
    uint8_t pdu[5] = {0x05, (uint8_t)(addr >> 8), (uint8_t)addr, on ? 0xFF : 0x00, 0x00};
    uint8_t resp[256];
    return result(resp, th_request(c, th, pdu, sizeof pdu, resp));
}

int th_upload(ds_core_t *c, test_hal_t *th, const th_step_t *steps, uint16_t n)
{
    for (uint16_t k = 0; k < n; k++) {
        const th_step_t *s = &steps[k];
        uint16_t w[10] = {s->source, s->intensity, s->polarizer,
                          (uint16_t)(s->settle >> 16), (uint16_t)s->settle,
                          (uint16_t)(s->exposure >> 16), (uint16_t)s->exposure,
                          s->pulse, (uint16_t)(s->ev << 8 | s->count), s->triggers};
        int r = th_writen(c, th, (uint16_t)(DS_STEP_TABLE_ADDR + 10u * k), w, 10);
        if (r != 0) {
            return r;
        }
    }
    return th_write1(c, th, DS_HR_SEQ_LEN, n);
}

size_t th_count_events(const test_hal_t *th, uint8_t kind)
{
    size_t n = 0;
    for (size_t i = 0; i < th->n_events; i++) {
        if ((th->events[i].kind_arg & 0xFFu) == kind) {
            n++;
        }
    }
    return n;
}

void th_boot(ds_core_t *c, test_hal_t *th, int preload, uint64_t now)
{
    th_init(th, preload);
    th->now = now;
    ds_core_init(c, &th->hal, 1, th->now);
}

unsigned th_feed_with_error(ds_core_t *c, test_hal_t *th, const uint8_t *pdu, size_t pdu_len,
                            size_t bad_at, uint8_t errors)
{
    uint8_t req[300];
    size_t n = th_adu(req, 1, pdu, pdu_len);
    unsigned before = th->uart_frames;
    for (size_t i = 0; i < n; i++) {
        if (i == bad_at) {
            ds_core_rx_error(c, errors, th->now);
        } else {
            ds_core_rx(c, &req[i], 1, th->now);
        }
        th->now += 87u;
        ds_core_poll(c, th->now);
    }
    th->now += 1750u;
    ds_core_poll(c, th->now);
    return th->uart_frames - before;
}
