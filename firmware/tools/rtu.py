"""Minimal Modbus RTU master over a serial device or pty, standard library only.

Used by the boot checks in this folder (qemu_check.py, sim_check.py). It is deliberately tiny
and independent of the host package, so a firmware check never depends on the code it checks.

    python3 rtu.py /dev/pts/7            # FC 11 + the first input registers
"""
import os
import select
import sys
import termios
import time


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS: reflected polynomial 0xA001, initial value 0xFFFF."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def frame(address: int, pdu: bytes) -> bytes:
    body = bytes([address]) + pdu
    c = crc16(body)
    return body + bytes([c & 0xFF, c >> 8])


class Port:
    """A raw 8N1 serial port (or pty slave)."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        attrs = termios.tcgetattr(self.fd)
        # cfmakeraw equivalent
        attrs[0] &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP
                      | termios.INLCR | termios.IGNCR | termios.ICRNL | termios.IXON)
        attrs[1] &= ~termios.OPOST
        attrs[3] &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
        attrs[2] &= ~(termios.CSIZE | termios.PARENB)
        attrs[2] |= termios.CS8 | termios.CREAD | termios.CLOCAL
        attrs[4] = attrs[5] = termios.B115200
        termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        termios.tcflush(self.fd, termios.TCIOFLUSH)

    def close(self):
        os.close(self.fd)

    def transact(self, address: int, pdu: bytes, timeout: float = 1.0, silence: float = 0.02) -> bytes:
        """Send one request; return the response PDU (CRC checked), or raise TimeoutError.
        The response ends after `silence` seconds without bytes (generous: ptys and QEMU
        deliver in bursts)."""
        os.write(self.fd, frame(address, pdu))
        buf = b""
        deadline = time.monotonic() + timeout
        while True:
            wait = (deadline - time.monotonic()) if not buf else silence
            if wait <= 0:
                break
            r, _, _ = select.select([self.fd], [], [], wait)
            if not r:
                if buf:
                    break
                continue
            buf += os.read(self.fd, 512)
        if not buf:
            raise TimeoutError("no response")
        if len(buf) < 4 or crc16(buf) != 0:
            raise ValueError(f"bad response frame: {buf.hex(' ')}")
        if buf[0] != address:
            raise ValueError(f"response from address {buf[0]}, expected {address}")
        return buf[1:-2]

    def report_server_id(self, address: int = 1) -> tuple:
        """FC 11: returns (server id, run indicator, ascii text)."""
        pdu = self.transact(address, b"\x11")
        if pdu[0] != 0x11:
            raise ValueError(f"exception {pdu.hex(' ')}")
        n = pdu[1]
        data = pdu[2:2 + n]
        return data[0], data[1], data[2:].decode("ascii", "replace")

    def read_input(self, start: int, count: int, address: int = 1) -> list:
        pdu = self.transact(address, bytes([0x04, start >> 8, start & 0xFF, count >> 8, count & 0xFF]))
        if pdu[0] != 0x04:
            raise ValueError(f"exception {pdu.hex(' ')}")
        return [int.from_bytes(pdu[2 + 2 * i:4 + 2 * i], "big") for i in range(count)]

    def read_holding(self, start: int, count: int, address: int = 1) -> list:
        pdu = self.transact(address, bytes([0x03, start >> 8, start & 0xFF, count >> 8, count & 0xFF]))
        if pdu[0] != 0x03:
            raise ValueError(f"exception {pdu.hex(' ')}")
        return [int.from_bytes(pdu[2 + 2 * i:4 + 2 * i], "big") for i in range(count)]

    def write_register(self, reg: int, value: int, address: int = 1) -> bytes:
        return self.transact(address, bytes([0x06, reg >> 8, reg & 0xFF, value >> 8, value & 0xFF]))

    def write_registers(self, start: int, values: list, address: int = 1) -> bytes:
        body = b"".join(v.to_bytes(2, "big") for v in values)
        return self.transact(address, bytes([0x10, start >> 8, start & 0xFF, 0, len(values), 2 * len(values)]) + body)

    def write_coil(self, coil: int, on: bool, address: int = 1) -> bytes:
        return self.transact(address, bytes([0x05, coil >> 8, coil & 0xFF, 0xFF if on else 0, 0]))


def main(argv):
    if len(argv) != 2:
        print(__doc__)
        return 2
    p = Port(argv[1])
    sid, run, text = p.report_server_id()
    print(f"FC11: id={sid} run=0x{run:02X} '{text}'")
    print("IR0..8:", p.read_input(0, 9))
    p.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
