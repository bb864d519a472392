/* A recording HAL for the unit tests: every light, trigger, polarizer, UART and event call is
 * logged with the time the test set in th->now before calling into the core. */
#ifndef TEST_HAL_H
#define TEST_HAL_H

#include <stddef.h>
#include <stdint.h>

#include "ds_core.h"

enum th_call { TH_LIGHT, TH_PRELOAD, TH_LATCH, TH_POLARIZER, TH_TRIGGERS, TH_UART, TH_EVENT,
               TH_FORMAT };

typedef struct {
    enum th_call type;
    uint64_t t;
    uint8_t kind, index;
    uint16_t value; /* intensity, cdeg or trigger mask; TH_FORMAT: kind = parity, index = stop bits */
} th_call_t;

typedef struct {
    uint16_t kind_arg, step;
    uint64_t ts;
} th_event_t;

#define TH_MAX_CALLS 8192u
#define TH_MAX_EVENTS 8192u

typedef struct {
    uint64_t now;                     /* set by the test before each core call */
    th_call_t calls[TH_MAX_CALLS];
    size_t n_calls;
    th_event_t events[TH_MAX_EVENTS];
    size_t n_events;
    uint16_t light[DS_N_SOURCES];     /* live hardware state */
    uint16_t shadow[DS_N_SOURCES];    /* preloaded (chain) state */
    uint8_t triggers;
    uint16_t polarizer;
    uint8_t uart[512];
    size_t uart_len;                  /* last frame written */
    unsigned uart_frames;
    uint8_t parity, stop_bits;        /* serial-line format last set through uart_format */
    unsigned formats;                 /* uart_format calls */
    ds_hal_t hal;
} test_hal_t;

/* with_preload: provide light_preload/light_latch (a shift-register chain) or leave them NULL */
void th_init(test_hal_t *th, int with_preload);

/* Feed one request PDU (CRC appended) byte by byte through ds_core_rx, 87 us apart (115200
 * baud), replacing character `bad_at` (or none if >= the ADU length) by ds_core_rx_error with
 * `errors`; then let t3.5 pass. Returns the number of frames the core wrote meanwhile. */
unsigned th_feed_with_error(ds_core_t *c, test_hal_t *th, const uint8_t *pdu, size_t pdu_len,
                            size_t bad_at, uint8_t errors);

/* th_init, then a fresh core at address 1 booted at `now` (µs). */
void th_boot(ds_core_t *c, test_hal_t *th, int preload, uint64_t now);
void th_clear_log(test_hal_t *th);
uint16_t th_src(uint8_t kind, uint8_t index);
int th_lights_on(const test_hal_t *th);

/* Modbus helpers: build a request ADU (CRC appended), run it through ds_core_handle_frame. */
size_t th_adu(uint8_t *out, uint8_t addr, const uint8_t *pdu, size_t pdu_len);
size_t th_request(ds_core_t *c, test_hal_t *th, const uint8_t *pdu, size_t pdu_len, uint8_t *resp);
/* FC 06 / FC 10 / FC 03 / FC 04 helpers; return the exception code (0 = OK). */
int th_write1(ds_core_t *c, test_hal_t *th, uint16_t addr, uint16_t value);
int th_writen(ds_core_t *c, test_hal_t *th, uint16_t addr, const uint16_t *v, uint16_t n);
int th_read(ds_core_t *c, test_hal_t *th, uint8_t fc, uint16_t addr, uint16_t n, uint16_t *out);
uint16_t th_ir(ds_core_t *c, test_hal_t *th, uint16_t addr);
int th_coil(ds_core_t *c, test_hal_t *th, uint16_t addr, int on);

/* Step-table helper */
typedef struct {
    uint16_t source, intensity, polarizer;
    uint32_t settle, exposure;
    uint16_t pulse;
    uint8_t count, ev;
    uint16_t triggers;
} th_step_t;
int th_upload(ds_core_t *c, test_hal_t *th, const th_step_t *steps, uint16_t n);
size_t th_count_events(const test_hal_t *th, uint8_t kind);

#endif
