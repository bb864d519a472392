/* libFuzzer harness: the RTU byte stream through ds_core_rx / ds_core_poll with fuzzer-chosen
 * time gaps and camera edges. Input: ops of [op][arg] then op-specific bytes:
 *   op % 4 == 0: feed arg % 64 bytes that follow, all at `now`
 *   op % 4 == 1: time passes: arg * 16 us, or arg * 8 ms when op bit 2 is set; with op bit 3
 *                set, a poll at the new time whether anything is due or not
 *   op % 4 == 2: camera edge on input arg % 5 (4 = no such camera); with op bit 2 set, a
 *                character received with the UART errors arg & 0x0F (DS_UART_ERR_*) instead
 *   op % 4 == 3: feed the arg % 64 bytes that follow as one frame with a valid CRC appended,
 *                address 1 (so requests get past the CRC check), one byte every 87 us */
#include "fuzz_common.h"

static ds_core_t core;
static fz_t fz;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fz_init(&fz, &core);
    size_t i = 0;
    while (i + 2 <= size) {
        uint8_t op = data[i], arg = data[i + 1];
        i += 2;
        switch (op % 4) {
        case 0: {
            size_t n = arg % 64u;
            if (n > size - i) {
                n = size - i;
            }
            fz.uart_len = 0;
            fz_rx(&fz, &core, &data[i], n);
            fz_check_response(fz.uart, fz.uart_len);
            i += n;
            break;
        }
        case 1:
            fz_advance(&fz, &core, fz.now + ((op & 4) ? (uint64_t)arg * 8000u : (uint64_t)arg * 16u));
            if (op & 8) {
                fz_poll_now(&fz, &core); /* a target's idle poll, due or not */
            }
            fz_check_response(fz.uart, fz.uart_len);
            break;
        case 2:
            if (op & 4) {
                fz.uart_len = 0;
                fz_rx_error(&fz, &core, (uint8_t)(arg & 0x0Fu));
                FZ_CHECK(fz.uart_len == 0); /* a bad character is never answered at once */
            } else {
                ds_core_camera_edge(&core, (uint8_t)(arg % 5u), fz.now);
                fz_touched(&fz);
            }
            break;
        default: {
            size_t n = arg % 64u;
            if (n > size - i) {
                n = size - i;
            }
            uint8_t frame[80];
            frame[0] = 1;
            memcpy(&frame[1], &data[i], n);
            uint16_t crc = ds_crc16(frame, n + 1);
            frame[n + 1] = (uint8_t)crc;
            frame[n + 2] = (uint8_t)(crc >> 8);
            i += n;
            fz_advance(&fz, &core, fz.now + 2000u); /* t3.5 since anything before */
            for (size_t b = 0; b < n + 3; b++) {
                fz.uart_len = 0;
                fz_rx(&fz, &core, &frame[b], 1);
                FZ_CHECK(fz.uart_len == 0); /* the frame is not over yet */
                fz_advance(&fz, &core, fz.now + 87u);
            }
            fz.uart_len = 0;
            fz_advance(&fz, &core, fz.now + 1750u);
            fz_check_response(fz.uart, fz.uart_len);
            fz_check_command(&fz, frame, n + 3, fz.uart, fz.uart_len);
            break;
        }
        }
        fz_check_state(&fz);
    }
    fz_advance(&fz, &core, fz.now + 120000000u);
    return 0;
}
