/* Private interfaces between the files of the portable core. Not for targets. */
#ifndef DS_PRIV_H
#define DS_PRIV_H

#include "ds_core.h"

/* Modbus exception codes */
#define DS_EX_NONE 0u
#define DS_EX_ILLEGAL_FUNCTION 1u
#define DS_EX_ILLEGAL_ADDRESS 2u
#define DS_EX_ILLEGAL_VALUE 3u
#define DS_EX_DEVICE_FAILURE 4u
#define DS_EX_BUSY 6u

/* Register-map numbers (DS_HR_COUNT, DS_IR_COUNT, DS_HR_DEFAULTS, DS_STEP_NONE, DS_POL_KEEP, ...)
 * come from ds_regmap.h, generated from protocol/registers.toml: never define them here. */
#define DS_STEP_TABLE_WORDS (DS_MAX_STEPS * DS_STEP_WORDS)

/* HAL calls, NULL-safe */
static inline void ds_hal_light(const ds_core_t *c, uint8_t kind, uint8_t index, uint16_t intensity)
{
    if (c->hal && c->hal->light_set) {
        c->hal->light_set(c->hal->ctx, kind, index, intensity);
    }
}
static inline void ds_hal_triggers(const ds_core_t *c, uint8_t mask)
{
    if (c->hal && c->hal->triggers_write) {
        c->hal->triggers_write(c->hal->ctx, mask);
    }
}
static inline void ds_hal_polarizer(const ds_core_t *c, uint16_t cdeg)
{
    if (c->hal && c->hal->polarizer_set) {
        c->hal->polarizer_set(c->hal->ctx, cdeg);
    }
}
static inline int ds_hal_has_preload(const ds_core_t *c)
{
    return c->hal && c->hal->light_preload && c->hal->light_latch;
}

/* crc.c */
uint16_t ds_crc16_update(uint16_t crc, const uint8_t *buf, size_t n);

/* rtu.c */
uint64_t ds_rtu_deadline(const ds_core_t *c);
void ds_rtu_check_end(ds_core_t *c, uint64_t now);
void ds_line_format_apply(ds_core_t *c); /* hands a written SERIAL_* format to the HAL */

/* modbus.c: one complete ADU, no timers run. */
size_t ds_modbus_process(ds_core_t *c, const uint8_t *req, size_t n, uint8_t *resp, uint64_t now);

/* regs.c: register and coil access. Each returns a Modbus exception code (0 = success).
 * The caller has already checked quantities; these check mapping, values, busy. */
uint8_t ds_regs_read_input(ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out, uint64_t now);
uint8_t ds_regs_read_holding(ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out);
int ds_regs_holding_mapped(uint16_t addr, uint16_t n);
int ds_regs_input_mapped(uint16_t addr, uint16_t n);
int ds_coils_mapped(uint16_t addr, uint16_t n);
uint8_t ds_regs_write_holding(ds_core_t *c, uint16_t addr, uint16_t n, const uint8_t *be, uint64_t now);
void ds_coils_read(const ds_core_t *c, uint16_t addr, uint16_t n, uint8_t *out);
uint8_t ds_coils_write(ds_core_t *c, uint16_t addr, uint16_t n, const uint8_t *bits, uint64_t now);
uint16_t ds_seq_crc(const ds_core_t *c);
int ds_line_format_ok(uint16_t parity, uint16_t stop_bits); /* SERIAL_PARITY/STOP_BITS pair */

/* fifo.c */
void ds_fifo_reset(ds_core_t *c);
void ds_evt_push(ds_core_t *c, uint8_t kind, uint8_t arg, uint16_t step, uint64_t ts_us);
void ds_fifo_ack(ds_core_t *c, uint16_t seq);
void ds_fifo_clear(ds_core_t *c);
uint16_t ds_fifo_first_seq(const ds_core_t *c);
const ds_event_t *ds_fifo_at(const ds_core_t *c, uint16_t i); /* i-th oldest pending, or NULL */

/* safety.c */
int ds_src_from_word(uint16_t source_word, uint16_t *src);   /* 1 if a real light; src out */
int ds_src_word_valid(uint16_t source_word);                 /* kind/index exist (OFF: index 0) */
void ds_src_split(uint16_t src, uint8_t *kind, uint8_t *index);
uint16_t ds_src_from_coil(uint16_t coil);                    /* DS_NO_SOURCE if unmapped */
uint64_t ds_bucket_drain(uint64_t level, uint64_t dt, uint16_t permille);
uint64_t ds_bucket_cap_us(const ds_core_t *c);
void ds_light_set(ds_core_t *c, uint16_t src, uint16_t intensity, uint8_t manual, uint64_t now);
void ds_light_track(ds_core_t *c, uint16_t src, uint16_t intensity, uint8_t manual, uint64_t now);
void ds_all_off(ds_core_t *c, uint64_t now);
void ds_safety_run(ds_core_t *c, uint64_t now);
uint64_t ds_safety_deadline(const ds_core_t *c);
void ds_fault(ds_core_t *c, uint16_t error, uint64_t now);

/* seq.c */
uint16_t ds_seq_validate(ds_core_t *c, uint16_t len, uint8_t mode, uint32_t gap_us,
                         uint16_t *err_step, uint64_t *duration_us);
uint8_t ds_seq_start(ds_core_t *c, uint64_t now);           /* exception code */
void ds_seq_stop(ds_core_t *c, uint8_t abort_reason, uint64_t now); /* lights off, SEQ_ABORT */
void ds_seq_run(ds_core_t *c, uint64_t now);
uint64_t ds_seq_deadline(const ds_core_t *c);
void ds_seq_edge(ds_core_t *c, uint8_t camera, uint64_t now);
int ds_seq_active(const ds_core_t *c);                      /* ARMED or RUNNING */

/* core.c */
void ds_run_timers(ds_core_t *c, uint64_t now);

#endif /* DS_PRIV_H */
