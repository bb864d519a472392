/* Register and coil semantics (PROTOCOL.md §2, §8): mapping, ranges, atomic writes, commands. */
#include <string.h>

#include "ds_priv.h"

static void put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v >> 8);
    p[1] = (uint8_t)(v & 0xFFu);
}

static uint16_t get16(const uint8_t *p)
{
    return (uint16_t)((uint16_t)(p[0] << 8) | p[1]);
}

/* ds_regs_write_holding marks the written registers in a 32-bit mask. */
_Static_assert(DS_HR_COUNT <= 32u, "more than 32 directly mapped holding registers");
_Static_assert(DS_HR_COUNT <= DS_STEP_TABLE_ADDR, "holding registers overlap the step table");

int ds_regs_holding_mapped(uint16_t addr, uint16_t n)
{
    uint32_t end = (uint32_t)addr + n; /* exclusive */
    if (n == 0u) {
        return 0;
    }
    if (end <= DS_HR_COUNT) {
        return 1;
    }
    return addr >= DS_STEP_TABLE_ADDR && end <= DS_STEP_TABLE_ADDR + DS_STEP_TABLE_WORDS;
}

int ds_regs_input_mapped(uint16_t addr, uint16_t n)
{
    uint32_t end = (uint32_t)addr + n;
    const uint32_t win_words = DS_IR_EVT_WINDOW_COUNT * DS_EVENT_WORDS;
    if (n == 0u) {
        return 0;
    }
    if (end <= DS_IR_COUNT) {
        return 1;
    }
    return addr >= DS_IR_EVT_WINDOW && end <= DS_IR_EVT_WINDOW + win_words;
}

int ds_coils_mapped(uint16_t addr, uint16_t n)
{
    if (n == 0u) {
        return 0;
    }
    for (uint32_t a = addr; a < (uint32_t)addr + n; a++) {
        if (a > 0xFFFFu || ds_src_from_coil((uint16_t)a) == DS_NO_SOURCE) {
            return 0;
        }
    }
    return 1;
}

uint16_t ds_seq_crc(const ds_core_t *c)
{
    uint16_t crc = 0xFFFFu;
    uint32_t words = (uint32_t)c->hr[DS_HR_SEQ_LEN] * DS_STEP_WORDS;
    if (words > DS_STEP_TABLE_WORDS) {
        words = DS_STEP_TABLE_WORDS;
    }
    for (uint32_t i = 0; i < words; i++) {
        uint8_t be[2];
        put16(be, c->steps[i]);
        crc = ds_crc16_update(crc, be, 2u);
    }
    return crc;
}

static uint16_t u48_word(uint64_t v, uint16_t w) /* w = 0: most significant */
{
    return (uint16_t)((v >> (32u - 16u * w)) & 0xFFFFu);
}

static uint16_t input_value(ds_core_t *c, uint16_t a, uint64_t now)
{
    if (a >= DS_IR_EVT_WINDOW) {
        uint16_t off = (uint16_t)(a - DS_IR_EVT_WINDOW);
        const ds_event_t *e = ds_fifo_at(c, (uint16_t)(off / DS_EVENT_WORDS));
        if (e == NULL) {
            return 0u;
        }
        switch (off % DS_EVENT_WORDS) {
        case 0: return e->seq;
        case 1: return e->kind_arg;
        case 2: return e->step;
        default: return u48_word(e->ts_us, (uint16_t)(off % DS_EVENT_WORDS - 3u));
        }
    }
    switch (a) {
    case DS_IR_MAGIC: return (uint16_t)DS_MAGIC;
    case DS_IR_PROTO_VERSION: return (uint16_t)(DS_PROTO_VERSION_MAJOR << 8 | DS_PROTO_VERSION_MINOR);
    case DS_IR_FW_VERSION: return (uint16_t)(DS_FW_VERSION_MAJOR << 8 | DS_FW_VERSION_MINOR);
    case DS_IR_FW_PATCH: return (uint16_t)DS_FW_VERSION_PATCH;
    case DS_IR_N_LEDS: return (uint16_t)DS_N_LEDS;
    case DS_IR_N_BACKLIGHTS: return (uint16_t)DS_N_BACKLIGHTS;
    case DS_IR_MAX_STEPS: return (uint16_t)DS_MAX_STEPS;
    case DS_IR_FIFO_DEPTH: return (uint16_t)DS_FIFO_DEPTH;
    case DS_IR_STATE: return c->state;
    case DS_IR_ERROR: return c->error;
    case DS_IR_ERROR_STEP: return c->error_step;
    case DS_IR_CUR_STEP: return c->cur_step;
    case DS_IR_SEQ_CRC: return ds_seq_crc(c);
    case DS_IR_UPTIME_US: case DS_IR_UPTIME_US + 1u: case DS_IR_UPTIME_US + 2u:
        return u48_word(now, (uint16_t)(a - DS_IR_UPTIME_US));
    case DS_IR_POLARIZER_NOW: return c->polarizer_now;
    case DS_IR_EVT_COUNT: return c->fifo_count;
    case DS_IR_EVT_FIRST_SEQ: return ds_fifo_first_seq(c);
    case DS_IR_EVT_DROPPED: return c->dropped;
    case DS_IR_FRAMES_OK: return c->frames_ok;
    case DS_IR_FRAMES_BAD_CRC: return c->frames_bad_crc;
    case DS_IR_FRAMES_BAD: return c->frames_bad;
    case DS_IR_WATCHDOG_TRIPS: return c->watchdog_trips;
    case DS_IR_UART_PARITY_ERRORS: return c->uart_parity_errors;
    case DS_IR_UART_FRAMING_ERRORS: return c->uart_framing_errors;
    case DS_IR_UART_NOISE_ERRORS: return c->uart_noise_errors;
    case DS_IR_UART_OVERRUNS: return c->uart_overruns;
    case DS_IR_SEQ_DURATION_US: case DS_IR_SEQ_DURATION_US + 1u: case DS_IR_SEQ_DURATION_US + 2u:
        return u48_word(c->seq_duration_us, (uint16_t)(a - DS_IR_SEQ_DURATION_US));
    default: return 0u;
    }
}

uint8_t ds_regs_read_input(ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out, uint64_t now)
{
    if (!ds_regs_input_mapped(addr, n)) {
        return DS_EX_ILLEGAL_ADDRESS;
    }
    for (uint16_t i = 0; i < n; i++) {
        put16(&out[2u * i], input_value(c, (uint16_t)(addr + i), now));
    }
    return DS_EX_NONE;
}

uint8_t ds_regs_read_holding(ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out)
{
    if (!ds_regs_holding_mapped(addr, n)) {
        return DS_EX_ILLEGAL_ADDRESS;
    }
    for (uint16_t i = 0; i < n; i++) {
        uint16_t a = (uint16_t)(addr + i), v;
        if (a >= DS_STEP_TABLE_ADDR) {
            v = c->steps[a - DS_STEP_TABLE_ADDR];
        } else if (a == DS_HR_COMMAND) {
            v = 0u; /* write-only */
        } else {
            v = c->hr[a];
        }
        put16(&out[2u * i], v);
    }
    return DS_EX_NONE;
}

int ds_line_format_ok(uint16_t parity, uint16_t stop_bits)
{
    /* Modbus over Serial Line v1.02 §2.5.1: no parity needs 2 stop bits */
    return parity <= DS_HR_SERIAL_PARITY_MAX && stop_bits >= DS_HR_SERIAL_STOP_BITS_MIN &&
           stop_bits <= DS_HR_SERIAL_STOP_BITS_MAX && (parity != DS_PARITY_NONE || stop_bits == 2u);
}

/* Range of one written holding register, checked against the candidate register file. */
static int holding_value_ok(const uint16_t *cand, uint16_t a, uint16_t cmd)
{
    uint16_t v = cand[a];
    switch (a) {
    case DS_HR_COMMAND: return cmd <= DS_HR_COMMAND_MAX;
    case DS_HR_TRIGGER_MODE: return v <= DS_HR_TRIGGER_MODE_MAX;
    case DS_HR_SEQ_LEN: return v <= DS_HR_SEQ_LEN_MAX;
    case DS_HR_EVT_ACK: return 1;
    case DS_HR_WATCHDOG_MS:
        return v == 0u || (v >= DS_WATCHDOG_MS_MIN && v <= DS_HR_WATCHDOG_MS_MAX);
    case DS_HR_POLARIZER_CDEG:
        return v >= cand[DS_HR_SERVO_MIN_CDEG] && v <= cand[DS_HR_SERVO_MAX_CDEG];
    case DS_HR_MANUAL_INTENSITY: return 1;
    case DS_HR_LED_MAX_ON_MS: return v >= DS_HR_LED_MAX_ON_MS_MIN && v <= DS_HR_LED_MAX_ON_MS_MAX;
    case DS_HR_LED_DUTY_PERMILLE:
        return v >= DS_HR_LED_DUTY_PERMILLE_MIN && v <= DS_HR_LED_DUTY_PERMILLE_MAX;
    case DS_HR_SERVO_MIN_CDEG:
    case DS_HR_SERVO_MAX_CDEG:
        return cand[DS_HR_SERVO_MIN_CDEG] <= DS_HR_SERVO_MIN_CDEG_MAX &&
               cand[DS_HR_SERVO_MAX_CDEG] <= DS_HR_SERVO_MAX_CDEG_MAX &&
               cand[DS_HR_SERVO_MIN_CDEG] <= cand[DS_HR_SERVO_MAX_CDEG];
    case DS_HR_CAMERA_TIMEOUT_MS:
        return v >= DS_HR_CAMERA_TIMEOUT_MS_MIN && v <= DS_HR_CAMERA_TIMEOUT_MS_MAX;
    case DS_HR_MASTER_CAMERA: return v <= DS_HR_MASTER_CAMERA_MAX;
    case DS_HR_FRAME_TIMEOUT_US: return v <= DS_HR_FRAME_TIMEOUT_US_MAX;
    case DS_HR_SERIAL_PARITY:
    case DS_HR_SERIAL_STOP_BITS: /* one value, like the servo window */
        return ds_line_format_ok(cand[DS_HR_SERIAL_PARITY], cand[DS_HR_SERIAL_STOP_BITS]);
    case DS_HR_FRAME_GAP_US:
    case DS_HR_FRAME_GAP_US + 1u: {
        uint32_t gap = ((uint32_t)cand[DS_HR_FRAME_GAP_US] << 16) | cand[DS_HR_FRAME_GAP_US + 1u];
        return gap <= DS_HR_FRAME_GAP_US_MAX;
    }
    default: return 0;
    }
}

static uint8_t exec_command(ds_core_t *c, uint16_t cmd, uint64_t now)
{
    switch (cmd) {
    case DS_CMD_START:
        return ds_seq_start(c, now);
    case DS_CMD_ABORT:
        if (ds_seq_active(c)) {
            ds_seq_stop(c, (uint8_t)DS_ABORT_HOST, now); /* state ABORTED */
        }
        ds_all_off(c, now);
        return DS_EX_NONE;
    case DS_CMD_CLEAR_ERROR:
        c->error = DS_ERR_NONE;
        c->error_step = DS_STEP_NONE;
        if (c->state == DS_STATE_FAULT) {
            c->state = DS_STATE_IDLE;
        }
        return DS_EX_NONE;
    case DS_CMD_ALL_OFF:
        ds_all_off(c, now);
        return DS_EX_NONE;
    case DS_CMD_CLEAR_EVENTS:
        ds_fifo_clear(c);
        return DS_EX_NONE;
    default:
        return DS_EX_NONE;
    }
}

uint8_t ds_regs_write_holding(ds_core_t *c, uint16_t addr, uint16_t n, const uint8_t *be, uint64_t now)
{
    if (!ds_regs_holding_mapped(addr, n)) {
        return DS_EX_ILLEGAL_ADDRESS;
    }
    if (addr >= DS_STEP_TABLE_ADDR) { /* raw words; START validates */
        if (ds_seq_active(c)) {
            return DS_EX_BUSY;
        }
        for (uint16_t i = 0; i < n; i++) {
            c->steps[addr - DS_STEP_TABLE_ADDR + i] = get16(&be[2u * i]);
        }
        return DS_EX_NONE;
    }
    uint16_t cand[DS_HR_COUNT];
    uint16_t cmd = DS_CMD_NONE;
    uint32_t written = 0u;
    memcpy(cand, c->hr, sizeof cand);
    for (uint16_t i = 0; i < n; i++) {
        uint16_t a = (uint16_t)(addr + i);
        written |= 1u << a;
        if (a == DS_HR_COMMAND) {
            cmd = get16(&be[2u * i]);
        } else {
            cand[a] = get16(&be[2u * i]);
        }
    }
    for (uint16_t a = 0; a < DS_HR_COUNT; a++) {
        if ((written & (1u << a)) && !holding_value_ok(cand, a, cmd)) {
            return DS_EX_ILLEGAL_VALUE;
        }
    }
    int has_cmd = (written & (1u << DS_HR_COMMAND)) != 0u && cmd != DS_CMD_NONE;
    if (ds_seq_active(c)) {
        if (written & ((1u << DS_HR_TRIGGER_MODE) | (1u << DS_HR_POLARIZER_CDEG))) {
            return DS_EX_BUSY;
        }
        if (has_cmd && cmd != DS_CMD_ABORT) {
            if (cmd == DS_CMD_START) {
                c->error = DS_ERR_BUSY;
                c->error_step = DS_STEP_NONE;
            }
            return DS_EX_BUSY;
        }
    }
    if (has_cmd && cmd == DS_CMD_START && c->state == DS_STATE_FAULT) {
        return DS_EX_BUSY;
    }
    for (uint16_t a = 0; a < DS_HR_COUNT; a++) {
        if (a != DS_HR_COMMAND && (written & (1u << a))) { /* COMMAND is write-only: not stored */
            c->hr[a] = cand[a];
        }
    }
    if (written & ((1u << DS_HR_SERIAL_PARITY) | (1u << DS_HR_SERIAL_STOP_BITS))) {
        c->line_format_pending = 1u; /* applied once the response is on its way */
    }
    if (written & (1u << DS_HR_EVT_ACK)) {
        ds_fifo_ack(c, c->hr[DS_HR_EVT_ACK]);
    }
    if ((written & (1u << DS_HR_POLARIZER_CDEG)) && c->hr[DS_HR_POLARIZER_CDEG] != c->polarizer_now) {
        c->polarizer_now = c->hr[DS_HR_POLARIZER_CDEG];
        ds_hal_polarizer(c, c->polarizer_now);
        ds_evt_push(c, (uint8_t)DS_EVT_POLARIZER, 0u, DS_STEP_NONE, now);
    }
    return has_cmd ? exec_command(c, cmd, now) : DS_EX_NONE;
}

void ds_coils_read(const ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out)
{
    memset(out, 0, (n + 7u) / 8u);
    for (uint16_t i = 0; i < n; i++) {
        uint16_t src = ds_src_from_coil((uint16_t)(addr + i));
        if (src != DS_NO_SOURCE && c->lights[src].intensity) {
            out[i / 8u] = (uint8_t)(out[i / 8u] | (1u << (i % 8u)));
        }
    }
}

uint8_t ds_coils_write(ds_core_t *c, uint16_t addr, uint16_t n, const uint8_t *bits, uint64_t now)
{
    if (!ds_coils_mapped(addr, n)) {
        return DS_EX_ILLEGAL_ADDRESS;
    }
    if (ds_seq_active(c)) {
        return DS_EX_BUSY;
    }
    for (uint16_t i = 0; i < n; i++) {
        int on = (bits[i / 8u] >> (i % 8u)) & 1u;
        uint16_t src = ds_src_from_coil((uint16_t)(addr + i));
        ds_light_set(c, src, on ? c->hr[DS_HR_MANUAL_INTENSITY] : 0u, 1u, now);
    }
    return DS_EX_NONE;
}
