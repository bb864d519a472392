/* libFuzzer harness: whole frames through ds_core_handle_frame.
 * Input: records of [flags][gap_lo][gap_hi][len][len bytes]. flags bit 0: replace the last two
 * bytes by a valid CRC (so most frames get past the CRC check); bits 1-2: address 1, 0, or as is;
 * bit 3: a camera edge before the frame. The gap (x 64 us) passes before the frame. */
#include "fuzz_common.h"

static ds_core_t core;
static fz_t fz;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fz_init(&fz, &core);
    size_t i = 0;
    while (i + 4 <= size) {
        uint8_t flags = data[i];
        uint64_t gap = (uint64_t)(data[i + 1] | data[i + 2] << 8) * 64u;
        size_t len = data[i + 3];
        i += 4;
        if (len > size - i) {
            len = size - i;
        }
        uint8_t req[300], resp[DS_RTU_MAX_ADU + 8];
        memcpy(req, &data[i], len);
        i += len;
        if (len >= 1 && ((flags >> 1) & 3) == 0) {
            req[0] = 1;
        } else if (len >= 1 && ((flags >> 1) & 3) == 1) {
            req[0] = 0;
        }
        if ((flags & 1) && len >= 3) {
            uint16_t crc = ds_crc16(req, len - 2);
            req[len - 2] = (uint8_t)crc;
            req[len - 1] = (uint8_t)(crc >> 8);
        }
        fz_advance(&fz, &core, fz.now + gap);
        if (flags & 8) {
            ds_core_camera_edge(&core, (uint8_t)(flags >> 4), fz.now);
            fz_touched(&fz);
            fz_check_state(&fz);
        }
        memset(resp, 0xAA, sizeof resp);
        size_t rn = ds_core_handle_frame(&core, req, len, resp, fz.now);
        fz_touched(&fz);
        FZ_CHECK(rn <= DS_RTU_MAX_ADU);
        FZ_CHECK(resp[DS_RTU_MAX_ADU] == 0xAA); /* nothing written past 256 bytes */
        fz_check_response(resp, rn);
        if (len >= 4 && req[0] == 0) {
            FZ_CHECK(rn == 0); /* broadcast: never answered */
        }
        fz_check_command(&fz, req, len, resp, rn);
        fz_check_state(&fz);
    }
    /* let whatever is running play out (bounded), checking on the way */
    fz_advance(&fz, &core, fz.now + 120000000u);
    return 0;
}
