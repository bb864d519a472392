"""CRC-16/MODBUS and RTU framing helpers (for tests and raw-frame tools)."""

from __future__ import annotations


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS: reflected polynomial 0xA001, initial value 0xFFFF."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def rtu_frame(body: bytes) -> bytes:
    """Append the CRC, low byte first, to address + PDU."""
    c = crc16(body)
    return body + bytes((c & 0xFF, c >> 8))
