"""Bad bytes on the wire: the device answers with the right exception or stays silent, keeps
working, and never leaves a light on."""
from __future__ import annotations

import random

from dualscale.protocol import regmap as rm
from dualscale.protocol.crc import crc16, rtu_frame

READ_STATE = bytes([1, 0x04, 0, rm.IR.STATE, 0, 1])


def _counters(raw):
    r = raw.request(bytes([1, 0x04, 0, rm.IR.FRAMES_OK, 0, 3]))
    assert len(r) == 11, r.hex()
    return [int.from_bytes(r[3 + 2 * i:5 + 2 * i], "big") for i in range(3)]


def assert_valid_response(req: bytes, resp: bytes) -> None:
    assert 5 <= len(resp) <= 256, resp.hex()
    assert crc16(resp[:-2]) == int.from_bytes(resp[-2:], "little"), resp.hex()
    assert resp[0] == req[0]
    assert resp[1] & 0x7F == req[1]
    if resp[1] & 0x80:
        assert len(resp) == 5 and resp[2] in (1, 2, 3, 4, 6)


def test_bad_crc_is_silent_and_counted(raw):
    ok0, crc0, bad0 = _counters(raw)
    frame = bytearray(rtu_frame(READ_STATE))
    frame[-1] ^= 0xFF
    assert raw.transact(bytes(frame)) == b""
    ok1, crc1, bad1 = _counters(raw)
    assert crc1 == (crc0 + 1) & 0xFFFF


def test_wrong_address_is_silent(raw):
    assert raw.request(bytes([7]) + READ_STATE[1:]) == b""
    assert raw.request(READ_STATE) != b""


def test_truncated_and_oversize_frames_are_dropped(raw):
    _, _, bad0 = _counters(raw)
    assert raw.transact(b"\x01\x04\x00") == b""
    assert raw.transact(rtu_frame(bytes([1, 0x10]) + bytes(298))) == b""
    _, _, bad1 = _counters(raw)
    assert bad1 >= bad0 + 2
    assert raw.request(READ_STATE)[:3] == b"\x01\x04\x02"


def test_exceptions_on_the_wire(raw):
    assert raw.request(bytes([1, 0x42])) == rtu_frame(bytes([1, 0xC2, 0x01]))       # unknown FC
    assert raw.request(bytes([1, 0x03, 0x7F, 0x00, 0, 1])) == rtu_frame(bytes([1, 0x83, 0x02]))
    assert raw.request(bytes([1, 0x03, 0, 0, 0, 0])) == rtu_frame(bytes([1, 0x83, 0x03]))  # qty 0
    assert raw.request(bytes([1, 0x04, 0, 0, 0, 126])) == rtu_frame(bytes([1, 0x84, 0x03]))  # qty > 125
    assert raw.request(bytes([1, 0x05, 0, 0, 0x12, 0x34])) == rtu_frame(bytes([1, 0x85, 0x03]))
    # FC 10 whose byte count disagrees with its quantity
    assert raw.request(bytes([1, 0x10, 0, 6, 0, 2, 2, 0, 1])) == rtu_frame(bytes([1, 0x90, 0x03]))


def test_random_garbage_never_breaks_the_device(raw):
    rnd = random.Random(1234)
    for i in range(150):
        kind = i % 3
        if kind == 0:   # noise, mostly bad CRCs
            data = bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 40)))
            raw.transact(data, timeout=0.05)
        else:           # valid CRC, random PDU: must be answered properly or ignored
            body = bytes([1, rnd.choice([1, 3, 4, 5, 6, 15, 16, 17, 0x11, 0x2B, 2, 7, 0x63])]) + \
                bytes(rnd.randrange(256) for _ in range(rnd.randrange(0, 12)))
            if body[1] in (5, 15) or (body[1] in (6, 16) and len(body) > 3 and body[2] == 0 and body[3] == 0):
                continue  # don't switch lights or run commands by chance: covered by the fuzzers
            req = rtu_frame(body)
            resp = raw.transact(req, timeout=0.2)
            if resp:
                assert_valid_response(req, resp)
    # still alive, still dark
    r = raw.request(bytes([1, 0x01, 0, 0, 0, 127]))
    assert r[:3] == bytes([1, 1, 16]) and r[3:19] == bytes(16)


def test_frame_timeout_broadcast_sets_the_register_silently(raw):
    """The launcher's broadcast (QEMU's FRAME_TIMEOUT_US) reaches the register it names, and
    nobody answers a broadcast."""
    from dualscale.rig.launcher import frame_timeout_broadcast

    read = bytes([1, 0x03]) + rm.HR.FRAME_TIMEOUT_US.to_bytes(2, "big") + (1).to_bytes(2, "big")
    try:
        assert raw.transact(frame_timeout_broadcast(1234)) == b""
        r = raw.request(read)
        assert len(r) == 7 and int.from_bytes(r[3:5], "big") == 1234, r.hex()
    finally:
        raw.transact(frame_timeout_broadcast(0))
    assert int.from_bytes(raw.request(read)[3:5], "big") == 0
