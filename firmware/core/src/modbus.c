/* Modbus RTU server: ADU checks, silence rules, function-code dispatch, exceptions.
 *
 * Every function code checks in the order of the Modbus Application Protocol v1.1b3 state
 * diagrams (§6), PROTOCOL.md §2: function (01), then the request's own fields - quantity, byte
 * count, a coil's output value, a device-id read code (03) - then the address range (02), then
 * the execution: a register's range (03), busy (06), failure (04). */
#include "ds_priv.h"

#define PDU_MAX 253u

static uint16_t get16(const uint8_t *p)
{
    return (uint16_t)((uint16_t)(p[0] << 8) | p[1]);
}

static int is_write_fc(uint8_t fc)
{
    return fc == 0x05u || fc == 0x06u || fc == 0x0Fu || fc == 0x10u;
}

/* Appends a NUL-terminated string; returns its length. */
static uint8_t put_str(uint8_t *out, const char *s)
{
    uint8_t n = 0;
    while (s[n] != '\0' && n < 64u) {
        out[n] = (uint8_t)s[n];
        n++;
    }
    return n;
}

static uint8_t put_uint(uint8_t *out, unsigned v)
{
    char tmp[10];
    uint8_t n = 0, k = 0;
    do {
        tmp[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v != 0u && n < sizeof tmp);
    while (n) {
        out[k++] = (uint8_t)tmp[--n];
    }
    return k;
}

static uint8_t put_fw_version(uint8_t *out)
{
    uint8_t n = put_uint(out, DS_FW_VERSION_MAJOR);
    out[n++] = '.';
    n = (uint8_t)(n + put_uint(&out[n], DS_FW_VERSION_MINOR));
    out[n++] = '.';
    return (uint8_t)(n + put_uint(&out[n], DS_FW_VERSION_PATCH));
}

static uint8_t put_proto(uint8_t *out) /* "proto=MAJ.MIN" */
{
    uint8_t n = put_str(out, "proto=");
    n = (uint8_t)(n + put_uint(&out[n], DS_PROTO_VERSION_MAJOR));
    out[n++] = '.';
    return (uint8_t)(n + put_uint(&out[n], DS_PROTO_VERSION_MINOR));
}

#define OBJ_VENDOR "dualscale"
#define OBJ_PRODUCT_CODE "DS-RIG"
#define OBJ_VENDOR_URL "https://github.com/dualscale/dualscale"
#define OBJ_PRODUCT_NAME "dualscale rig controller"
#define N_OBJECTS 7u    /* 0x00..0x06: basic 0x00..0x02 and regular 0x03..0x06; no extended */
#define LAST_BASIC 2u
#define VERSION_MAX 13u /* longest "255.255.65535" (MAJ.MIN.PATCH) and "proto=255.255" */

/* Every object of the regular category fits one response, so "more follows" is always 00 and a
 * client never needs a second transaction: header 7 bytes, then id + length + value each. */
_Static_assert(7u + 2u * N_OBJECTS + sizeof OBJ_VENDOR - 1u + sizeof OBJ_PRODUCT_CODE - 1u +
                   VERSION_MAX + sizeof OBJ_VENDOR_URL - 1u + sizeof OBJ_PRODUCT_NAME - 1u +
                   DS_TARGET_NAME_MAX + VERSION_MAX <= PDU_MAX,
               "device identification objects do not fit one response");

static uint8_t device_object(const ds_core_t *c, uint8_t id, uint8_t *out)
{
    switch (id) {
    case 0x00: return put_str(out, OBJ_VENDOR);
    case 0x01: return put_str(out, OBJ_PRODUCT_CODE);
    case 0x02: return put_fw_version(out);
    case 0x03: return put_str(out, OBJ_VENDOR_URL);
    case 0x04: return put_str(out, OBJ_PRODUCT_NAME);
    case 0x05: return put_str(out, c->target);
    default: return put_proto(out);
    }
}

/* FC 2B / MEI 0E, Read Device Identification (Modbus Application Protocol v1.1b3 §6.21).
 * Checks: MEI type (01), read code (03), then, for individual access only, the object (02).
 * Stream access - read codes 01 (basic: 0x00..0x02), 02 (regular: 0x00..0x06) and 03 (extended:
 * the regular objects, as there are no private ones) - answers the category's objects from the
 * requested id on; an id that is not an object of the category restarts at 0x00. Individual
 * access (04) answers the one object, or 02 when it does not exist. out starts with the FC. */
static uint8_t read_device_id(const ds_core_t *c, const uint8_t *pdu, size_t plen, uint8_t *out,
                              size_t *rlen)
{
    if (plen < 2u) {
        return DS_EX_ILLEGAL_VALUE;
    }
    if (pdu[1] != 0x0Eu) {
        return DS_EX_ILLEGAL_FUNCTION;
    }
    if (plen != 4u || pdu[2] < 1u || pdu[2] > 4u) {
        return DS_EX_ILLEGAL_VALUE;
    }
    uint8_t code = pdu[2], first = pdu[3], last;
    if (code == 4u) { /* individual access */
        if (first >= N_OBJECTS) {
            return DS_EX_ILLEGAL_ADDRESS;
        }
        last = first;
    } else { /* stream access */
        last = code == 1u ? LAST_BASIC : (uint8_t)(N_OBJECTS - 1u);
        if (first > last) {
            first = 0u;
        }
    }
    size_t n = 0;
    out[n++] = 0x2Bu;
    out[n++] = 0x0Eu;
    out[n++] = code;
    out[n++] = 0x82u; /* conformity: regular identification, stream and individual access */
    out[n++] = 0x00u; /* more follows: no (everything fits, see the assertion above) */
    out[n++] = 0x00u; /* next object id: 0 when nothing follows */
    out[n++] = (uint8_t)(last - first + 1u);
    for (uint8_t id = first; id <= last; id++) {
        out[n] = id;
        uint8_t len = device_object(c, id, &out[n + 2u]);
        out[n + 1u] = len;
        n += 2u + len;
    }
    *rlen = n;
    return DS_EX_NONE;
}

static uint8_t report_server_id(const ds_core_t *c, size_t plen, uint8_t *out, size_t *rlen)
{
    if (plen != 1u) {
        return DS_EX_ILLEGAL_VALUE;
    }
    uint8_t n = 2u;
    out[0] = 0x11u;
    out[n++] = c->address;
    out[n++] = c->state == DS_STATE_FAULT ? 0x00u : 0xFFu;
    n = (uint8_t)(n + put_str(&out[n], "dualscale fw="));
    n = (uint8_t)(n + put_fw_version(&out[n]));
    out[n++] = ' ';
    n = (uint8_t)(n + put_proto(&out[n]));
    n = (uint8_t)(n + put_str(&out[n], " target="));
    n = (uint8_t)(n + put_str(&out[n], c->target));
    out[1] = (uint8_t)(n - 2u);
    *rlen = n;
    return DS_EX_NONE;
}

static uint8_t dispatch(ds_core_t *c, const uint8_t *pdu, size_t plen, uint8_t *out, size_t *rlen,
                        uint64_t now)
{
    uint8_t fc = pdu[0];
    uint8_t ex;
    out[0] = fc;
    switch (fc) {
    case 0x01: { /* read coils */
        if (plen != 5u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        uint16_t addr = get16(&pdu[1]), qty = get16(&pdu[3]);
        if (qty < 1u || qty > 2000u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        if (!ds_coils_mapped(addr, qty)) {
            return DS_EX_ILLEGAL_ADDRESS;
        }
        out[1] = (uint8_t)((qty + 7u) / 8u);
        ds_coils_read(c, addr, qty, &out[2]);
        *rlen = 2u + out[1];
        return DS_EX_NONE;
    }
    case 0x03:
    case 0x04: { /* read holding / input registers */
        if (plen != 5u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        uint16_t addr = get16(&pdu[1]), qty = get16(&pdu[3]);
        if (qty < 1u || qty > 125u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        ex = fc == 0x03u ? ds_regs_read_holding(c, addr, qty, &out[2])
                         : ds_regs_read_input(c, addr, qty, &out[2], now);
        if (ex) {
            return ex;
        }
        out[1] = (uint8_t)(2u * qty);
        *rlen = 2u + out[1];
        return DS_EX_NONE;
    }
    case 0x05: { /* write single coil: the value is a field of the request, checked first */
        if (plen != 5u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        uint16_t addr = get16(&pdu[1]), v = get16(&pdu[3]);
        if (v != 0xFF00u && v != 0x0000u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        if (!ds_coils_mapped(addr, 1u)) {
            return DS_EX_ILLEGAL_ADDRESS;
        }
        uint8_t bit = v ? 1u : 0u;
        ex = ds_coils_write(c, addr, 1u, &bit, now);
        if (ex) {
            return ex;
        }
        for (size_t i = 1; i < 5u; i++) {
            out[i] = pdu[i];
        }
        *rlen = 5u;
        return DS_EX_NONE;
    }
    case 0x06: { /* write single register */
        if (plen != 5u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        ex = ds_regs_write_holding(c, get16(&pdu[1]), 1u, &pdu[3], now);
        if (ex) {
            return ex;
        }
        for (size_t i = 1; i < 5u; i++) {
            out[i] = pdu[i];
        }
        *rlen = 5u;
        return DS_EX_NONE;
    }
    case 0x0F:
    case 0x10: { /* write multiple coils / registers */
        if (plen < 6u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        uint16_t addr = get16(&pdu[1]), qty = get16(&pdu[3]);
        uint8_t bc = pdu[5];
        if (fc == 0x0Fu) {
            if (qty < 1u || qty > 1968u || bc != (qty + 7u) / 8u || plen != 6u + bc) {
                return DS_EX_ILLEGAL_VALUE;
            }
            if (!ds_coils_mapped(addr, qty)) {
                return DS_EX_ILLEGAL_ADDRESS;
            }
            ex = ds_coils_write(c, addr, qty, &pdu[6], now);
        } else {
            if (qty < 1u || qty > 123u || bc != 2u * qty || plen != 6u + bc) {
                return DS_EX_ILLEGAL_VALUE;
            }
            ex = ds_regs_write_holding(c, addr, qty, &pdu[6], now);
        }
        if (ex) {
            return ex;
        }
        for (size_t i = 1; i < 5u; i++) {
            out[i] = pdu[i];
        }
        *rlen = 5u;
        return DS_EX_NONE;
    }
    case 0x11:
        return report_server_id(c, plen, out, rlen);
    case 0x17: { /* read/write multiple registers: the write is done first */
        if (plen < 10u) {
            return DS_EX_ILLEGAL_VALUE;
        }
        uint16_t raddr = get16(&pdu[1]), rqty = get16(&pdu[3]);
        uint16_t waddr = get16(&pdu[5]), wqty = get16(&pdu[7]);
        uint8_t bc = pdu[9];
        if (rqty < 1u || rqty > 125u || wqty < 1u || wqty > 121u || bc != 2u * wqty ||
            plen != 10u + bc) {
            return DS_EX_ILLEGAL_VALUE;
        }
        if (!ds_regs_holding_mapped(raddr, rqty) || !ds_regs_holding_mapped(waddr, wqty)) {
            return DS_EX_ILLEGAL_ADDRESS;
        }
        ex = ds_regs_write_holding(c, waddr, wqty, &pdu[10], now);
        if (ex) {
            return ex;
        }
        ex = ds_regs_read_holding(c, raddr, rqty, &out[2]);
        if (ex) {
            return ex;
        }
        out[1] = (uint8_t)(2u * rqty);
        *rlen = 2u + out[1];
        return DS_EX_NONE;
    }
    case 0x2B:
        return read_device_id(c, pdu, plen, out, rlen);
    default:
        return DS_EX_ILLEGAL_FUNCTION;
    }
}

size_t ds_modbus_process(ds_core_t *c, const uint8_t *req, size_t n, uint8_t *resp, uint64_t now)
{
    if (n < 4u || n > DS_RTU_MAX_ADU) {
        c->frames_bad++;
        return 0u;
    }
    uint16_t crc = ds_crc16(req, n - 2u);
    if (req[n - 2u] != (uint8_t)(crc & 0xFFu) || req[n - 1u] != (uint8_t)(crc >> 8)) {
        c->frames_bad_crc++;
        return 0u;
    }
    uint8_t addr = req[0];
    if (addr != c->address && addr != 0u) {
        return 0u; /* another server's frame */
    }
    if (now > c->last_host_us) {
        c->last_host_us = now; /* feeds the host watchdog */
    }
    const uint8_t *pdu = &req[1];
    size_t plen = n - 3u;
    uint8_t fc = pdu[0];
    if (addr == 0u) { /* broadcast: writes are executed, nothing is answered */
        if (is_write_fc(fc)) {
            uint8_t scratch[16]; /* write FCs answer at most 5 PDU bytes */
            size_t rlen = 0;
            (void)dispatch(c, pdu, plen, scratch, &rlen, now);
        }
        return 0u;
    }
    c->frames_ok++;
    size_t rlen = 0;
    uint8_t ex = dispatch(c, pdu, plen, &resp[1], &rlen, now);
    if (ex == DS_EX_NONE && (rlen == 0u || rlen > PDU_MAX)) {
        ex = DS_EX_DEVICE_FAILURE; /* an internal invariant failed */
    }
    resp[0] = c->address;
    if (ex != DS_EX_NONE) {
        resp[1] = (uint8_t)(fc | 0x80u);
        resp[2] = ex;
        rlen = 2u;
    }
    size_t len = 1u + rlen;
    crc = ds_crc16(resp, len);
    resp[len++] = (uint8_t)(crc & 0xFFu);
    resp[len++] = (uint8_t)(crc >> 8);
    return len;
}
