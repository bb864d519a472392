/* Replays protocol/vectors.toml (via the generated ds_vectors.h) against one fresh core at
 * address 1, target "posix", in three ways: whole frames through ds_core_rx + ds_core_poll,
 * byte by byte with character gaps shorter than t3.5, and straight into ds_core_handle_frame. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "test_hal.h"

#include "ds_vectors.h"

static size_t parse_hex(const char *s, uint8_t *out, size_t max)
{
    size_t n = 0;
    while (*s) {
        if (*s == ' ') {
            s++;
            continue;
        }
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1 || n >= max) {
            fail_msg("bad hex in vector");
        }
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static void hexdump(const char *label, const uint8_t *b, size_t n)
{
    fprintf(stderr, "%s:", label);
    for (size_t i = 0; i < n; i++) {
        fprintf(stderr, " %02x", b[i]);
    }
    fprintf(stderr, "\n");
}

enum mode { WHOLE_FRAMES, BYTE_BY_BYTE, HANDLE_FRAME };

static void replay(enum mode mode)
{
    static ds_core_t core;
    static test_hal_t th;
    th_init(&th, 1);
    th.now = 1000000u;
    ds_core_init(&core, &th.hal, 1, th.now);
    ds_core_set_target(&core, "posix");
    assert_true(DS_N_VECTORS > 0u);
    unsigned failures = 0;
    for (size_t i = 0; i < DS_N_VECTORS; i++) {
        const ds_vector_t *v = &DS_VECTORS[i];
        uint8_t req[512], want[512], got[512];
        size_t nreq = parse_hex(v->request, req, sizeof req);
        size_t nwant = parse_hex(v->response, want, sizeof want);
        size_t ngot = 0;
        /* well over t3.5 since the previous frame; run whatever falls due in between */
        uint64_t send = th.now + 20000u;
        for (uint64_t d = ds_core_next_deadline(&core); d <= send; d = ds_core_next_deadline(&core)) {
            th.now = d;
            ds_core_poll(&core, d);
        }
        th.now = send;
        if (mode == HANDLE_FRAME) {
            ngot = ds_core_handle_frame(&core, req, nreq, got, th.now);
        } else {
            unsigned before = th.uart_frames;
            if (mode == WHOLE_FRAMES) {
                ds_core_rx(&core, req, nreq, th.now);
            } else {
                for (size_t b = 0; b < nreq; b++) {
                    ds_core_rx(&core, &req[b], 1, th.now);
                    ds_core_poll(&core, th.now);
                    assert_int_equal(th.uart_frames, before); /* no early end of frame */
                    th.now += 87u;                             /* one character at 115200 */
                }
                th.now -= 87u;
            }
            uint64_t end = ds_core_next_deadline(&core);
            if (end != th.now + 1750u) {
                fprintf(stderr, "vector %zu '%s': deadline %llu, frame end %llu\n", i, v->name,
                        (unsigned long long)end, (unsigned long long)(th.now + 1750u));
            }
            assert_int_equal(end, th.now + 1750u); /* t3.5 at 115200 baud */
            ds_core_poll(&core, end - 1u);
            assert_int_equal(th.uart_frames, before);
            th.now = end;
            ds_core_poll(&core, th.now);
            if (th.uart_frames != before) {
                assert_int_equal(th.uart_frames, before + 1u);
                ngot = th.uart_len;
                memcpy(got, th.uart, ngot);
            }
        }
        if (ngot != nwant || memcmp(got, want, ngot) != 0) {
            fprintf(stderr, "vector %zu '%s' (mode %d) mismatch\n", i, v->name, (int)mode);
            hexdump("  request ", req, nreq);
            hexdump("  expected", want, nwant);
            hexdump("  got     ", got, ngot);
            failures++;
        }
    }
    assert_int_equal(failures, 0);
}

static void test_vectors_whole_frames_through_rx(void **state)
{
    (void)state;
    replay(WHOLE_FRAMES);
}

static void test_vectors_byte_by_byte_through_rx(void **state)
{
    (void)state;
    replay(BYTE_BY_BYTE);
}

static void test_vectors_through_handle_frame(void **state)
{
    (void)state;
    replay(HANDLE_FRAME);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_vectors_whole_frames_through_rx),
        cmocka_unit_test(test_vectors_byte_by_byte_through_rx),
        cmocka_unit_test(test_vectors_through_handle_frame),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
