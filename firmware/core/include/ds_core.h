/* The portable dualscale core: Modbus RTU server, sequencer, event FIFO and safety logic.
 *
 * Usage from a target's main loop:
 *     ds_core_init(&core, &hal, DS_DEFAULT_ADDRESS, now);
 *     loop: ds_core_rx(&core, bytes, n, now) as bytes arrive;
 *           ds_core_camera_edge(&core, cam, t_edge) on camera edges;
 *           ds_core_poll(&core, now) often, and at the latest at ds_core_next_deadline().
 * The core never blocks and never allocates. All state lives in ds_core_t. */
#ifndef DS_CORE_H
#define DS_CORE_H

#include <stddef.h>
#include <stdint.h>

#include "ds_hal.h"
#include "ds_regmap.h"

#define DS_RTU_MAX_ADU 256u   /* address + 253-byte PDU + CRC */
#define DS_NO_DEADLINE UINT64_MAX
#define DS_N_SOURCES (DS_N_LEDS + DS_N_BACKLIGHTS + DS_N_DIFFUSE)
#define DS_NO_SOURCE 0xFFFFu
#define DS_TARGET_NAME_MAX 31u  /* longest target name kept by ds_core_set_target */

/* UART receive errors of one character (ds_core_rx_error), as a mask. */
#define DS_UART_ERR_PARITY 0x01u  /* parity bit wrong */
#define DS_UART_ERR_FRAMING 0x02u /* no stop bit where one was due (or a break) */
#define DS_UART_ERR_NOISE 0x04u   /* the oversampled bit values disagreed */
#define DS_UART_ERR_OVERRUN 0x08u /* characters were lost before this one (receiver or ring) */

typedef struct ds_event {
    uint16_t seq;      /* event sequence number, wraps */
    uint16_t kind_arg; /* kind | arg << 8 */
    uint16_t step;
    uint64_t ts_us;    /* 48 bits on the wire */
} ds_event_t;

typedef struct {
    uint16_t source, intensity, polarizer;
    uint32_t settle_us, exposure_us;
    uint16_t pulse_us, brackets, triggers;
} ds_step_t;

/* Leaky-bucket thermal state of one light source (see PROTOCOL.md, "Safety"). */
typedef struct {
    uint64_t level_us;   /* accumulated on-time credit used */
    uint64_t since_us;   /* time of the last update */
    uint16_t intensity;  /* 0 = off */
    uint8_t manual;      /* switched on by a coil */
} ds_light_t;

typedef struct ds_core {
    const ds_hal_t *hal;
    uint8_t address;
    uint32_t t35_us;                                 /* end-of-frame silence (ds_rtu_t35_us) */
    char target[DS_TARGET_NAME_MAX + 1];             /* FC 11 / 2B object 0x05 */

    /* RTU receiver */
    uint8_t rx[DS_RTU_MAX_ADU];
    uint16_t rx_len;
    uint8_t rx_overflow;
    uint8_t rx_bad;                                  /* a character had a UART error */
    uint64_t rx_last_us;
    uint8_t tx[DS_RTU_MAX_ADU];

    /* registers */
    uint16_t hr[DS_HR_COUNT];                        /* holding registers 0..DS_HR_COUNT-1 */
    uint16_t steps[DS_MAX_STEPS * DS_STEP_WORDS];    /* the step table */
    uint16_t state, error, error_step, cur_step;
    uint16_t polarizer_now;
    uint16_t frames_ok, frames_bad_crc, frames_bad, watchdog_trips;
    uint16_t uart_parity_errors, uart_framing_errors, uart_noise_errors, uart_overruns;
    uint8_t line_format_pending;                     /* SERIAL_* written: call uart_format */
    uint64_t seq_duration_us;
    uint64_t last_host_us;

    /* event FIFO (ring) */
    ds_event_t fifo[DS_FIFO_DEPTH];
    uint16_t fifo_head, fifo_count, next_seq, dropped;

    /* sequencer */
    uint16_t seq_len_run;      /* steps in the running sequence */
    uint8_t phase;             /* internal phase of the current step */
    uint8_t bracket;
    uint8_t edges_in_step;
    uint8_t trig_level;
    uint64_t step_start_us, next_us, last_edge_us;
    uint64_t bracket_start_us; /* device-master: t_b of the current bracket */
    uint64_t latch_us;         /* camera-master: time of the last latch */
    uint32_t run_gap_us;       /* FRAME_GAP_US snapshot taken at START */
    uint8_t run_mode;          /* TRIGGER_MODE snapshot taken at START */
    uint8_t run_camera;        /* MASTER_CAMERA snapshot taken at START */
    uint16_t seq_light;        /* source index lit by the sequencer, DS_NO_SOURCE if none */
    uint16_t preload_light;    /* camera-master: source preloaded for the next latch */
    uint16_t preload_intensity;

    ds_light_t lights[DS_N_SOURCES];
    uint16_t lit_count;        /* how many lights[] have a non-zero intensity (kept by ds_light_track) */

    /* scratch for the leaky-bucket replay at START (kept here: no big stack frames) */
    uint64_t sim_level[DS_N_SOURCES];
    uint64_t sim_since[DS_N_SOURCES];
} ds_core_t;

void ds_core_init(ds_core_t *c, const ds_hal_t *hal, uint8_t address, uint64_t now_us);

/* Bytes received on the serial line at now_us. A gap of t3.5 (ds_rtu_t35_us) ends a frame. */
void ds_core_rx(ds_core_t *c, const uint8_t *buf, size_t n, uint64_t now_us);

/* One character received at now_us with UART errors (DS_UART_ERR_* mask; its value is not
 * needed). It belongs to the frame being received (or starts one), which is then dropped in
 * silence at its end (FRAMES_BAD), and each error kind is counted in its input register
 * (UART_PARITY_ERRORS, UART_FRAMING_ERRORS, UART_NOISE_ERRORS, UART_OVERRUNS). */
void ds_core_rx_error(ds_core_t *c, uint8_t errors, uint64_t now_us);

/* Run everything due at now_us: frame end, sequencer phases, watchdog, light limits. */
void ds_core_poll(ds_core_t *c, uint64_t now_us);

/* Earliest time ds_core_poll must be called again; DS_NO_DEADLINE if nothing is pending. */
uint64_t ds_core_next_deadline(const ds_core_t *c);

/* An exposure-active / flash-sync edge from camera `camera` at now_us. */
void ds_core_camera_edge(ds_core_t *c, uint8_t camera, uint64_t now_us);

/* Process one complete RTU frame (address .. CRC) as if it had just ended at now_us.
 * Writes the response into resp and returns its length; 0 means silence
 * (bad CRC, other address, broadcast). Used by ds_core_rx, the vector tests and the fuzzers. */
size_t ds_core_handle_frame(ds_core_t *c, const uint8_t *req, size_t n, uint8_t *resp, uint64_t now_us);

/* Events waiting in the FIFO for the host's ack. */
uint16_t ds_core_events_pending(const ds_core_t *c);

/* Safety: true if any light is on. */
int ds_core_any_light_on(const ds_core_t *c);

/* CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF); low byte first on the wire. */
uint16_t ds_crc16(const uint8_t *buf, size_t n);

/* t3.5 silence for a baud rate: 3.5 characters (11 bits) up to 19200 baud, else 1750 us. */
uint32_t ds_rtu_t35_us(uint32_t baud);

/* Name of the target reported by FC 11 (`target=NAME`) and FC 2B object 0x05 (ModelName),
 * e.g. "posix" or "stm32f405". Copied (at most DS_TARGET_NAME_MAX chars). Default "unknown". */
void ds_core_set_target(ds_core_t *c, const char *name);

/* Serial baud rate: sets the t3.5 end-of-frame silence. Default DS_DEFAULT_BAUD. */
void ds_core_set_baud(ds_core_t *c, uint32_t baud);

/* Serial-line format set by the target at boot (a command-line option, a jumper), instead of the
 * reset value from rig.toml: SERIAL_PARITY / SERIAL_STOP_BITS take it and hal.uart_format is
 * called. Returns 0, or -1 (nothing changed) for a format the register map refuses: parity
 * beyond DS_PARITY_EVEN, stop bits other than 1 or 2, or no parity with 1 stop bit. */
int ds_core_set_line_format(ds_core_t *c, uint8_t parity, uint8_t stop_bits);

/* Sequencer state (DS_STATE_*), as in input register STATE. */
uint16_t ds_core_state(const ds_core_t *c);

#endif /* DS_CORE_H */
