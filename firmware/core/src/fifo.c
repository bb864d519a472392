/* The event FIFO (PROTOCOL.md §4): a ring of DS_FIFO_DEPTH events, freed by EVT_ACK. */
#include "ds_priv.h"

void ds_fifo_reset(ds_core_t *c)
{
    c->fifo_head = 0u;
    c->fifo_count = 0u;
    c->next_seq = 0u;
    c->dropped = 0u;
}

void ds_evt_push(ds_core_t *c, uint8_t kind, uint8_t arg, uint16_t step, uint64_t ts_us)
{
    if (c->fifo_count >= DS_FIFO_DEPTH) {
        if (c->dropped != 0xFFFFu) {
            c->dropped++;
        }
        return;
    }
    ds_event_t *e = &c->fifo[(c->fifo_head + c->fifo_count) % DS_FIFO_DEPTH];
    e->seq = c->next_seq++;
    e->kind_arg = (uint16_t)(kind | (uint16_t)(arg << 8));
    e->step = step;
    e->ts_us = ts_us & 0xFFFFFFFFFFFFull;
    c->fifo_count++;
    if (c->hal && c->hal->on_event) {
        c->hal->on_event(c->hal->ctx, e);
    }
}

uint16_t ds_fifo_first_seq(const ds_core_t *c)
{
    /* with nothing pending: the SEQ the next event will get */
    return (uint16_t)(c->next_seq - c->fifo_count);
}

void ds_fifo_ack(ds_core_t *c, uint16_t seq)
{
    uint16_t off = (uint16_t)(seq - ds_fifo_first_seq(c));
    if (off >= c->fifo_count) {
        return; /* outside the pending range: a repeated or bogus ack */
    }
    uint16_t n = (uint16_t)(off + 1u);
    c->fifo_head = (uint16_t)((c->fifo_head + n) % DS_FIFO_DEPTH);
    c->fifo_count = (uint16_t)(c->fifo_count - n);
}

uint16_t ds_core_events_pending(const ds_core_t *c)
{
    return c->fifo_count;
}

void ds_fifo_clear(ds_core_t *c)
{
    c->fifo_head = (uint16_t)((c->fifo_head + c->fifo_count) % DS_FIFO_DEPTH);
    c->fifo_count = 0u;
}

const ds_event_t *ds_fifo_at(const ds_core_t *c, uint16_t i)
{
    if (i >= c->fifo_count) {
        return NULL;
    }
    return &c->fifo[(c->fifo_head + i) % DS_FIFO_DEPTH];
}
