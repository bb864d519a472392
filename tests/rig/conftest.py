"""Fixtures: the simulated rig on both targets, a typed client, and a raw RTU link."""
from __future__ import annotations

import time

import pytest
import serial

from dualscale.protocol import regmap as rm
from dualscale.protocol.crc import rtu_frame
from dualscale.rig.client import RigClient, _crc_ok
from dualscale.rig.launcher import SimulatedRig

TARGETS = ["posix", pytest.param("qemu", marks=pytest.mark.qemu)]


class RawLink:
    """Raw bytes over the serial device, for framing and bad-input tests."""

    def __init__(self, port: str):
        self.ser = serial.Serial(port, 115200, timeout=0)

    def send(self, data: bytes) -> None:
        self.ser.reset_input_buffer()
        self.ser.write(data)
        self.ser.flush()

    def recv(self, timeout: float = 0.5, quiet: float = 0.03) -> bytes:
        """Bytes until `quiet` s of silence after the first byte, or nothing within `timeout`.
        A silence inside a frame whose CRC does not check yet (QEMU's USART model stalls mid-frame
        on a loaded host) waits on, up to `timeout` more, so a slow frame is not cut short."""
        buf, t0, last = b"", time.monotonic(), None
        while True:
            chunk = self.ser.read(512)
            now = time.monotonic()
            if chunk:
                buf, last = buf + chunk, now
            elif last is not None and now - last > quiet and (_crc_ok(buf) or now - last > timeout):
                return buf
            elif last is None and now - t0 > timeout:
                return b""
            time.sleep(0.002)

    def transact(self, frame: bytes, timeout: float = 0.5) -> bytes:
        self.send(frame)
        return self.recv(timeout)

    def request(self, body: bytes, timeout: float = 0.5) -> bytes:
        """Send address+PDU with a correct CRC; return the raw response."""
        return self.transact(rtu_frame(body), timeout)

    def close(self) -> None:
        self.ser.close()


@pytest.fixture(scope="module", params=TARGETS)
def sim(request):
    with SimulatedRig(request.param) as s:
        yield s


@pytest.fixture
def rig(sim):
    c = RigClient(sim.port, timeout=2.0)
    c.open()
    yield c
    # leave the device as the next test expects it: idle, dark, default settings
    c.abort()
    c.clear_error()
    c.all_off()
    c.set_watchdog(0)
    c.write_register(rm.HR.TRIGGER_MODE, 0)
    c.write_register(rm.HR.LED_MAX_ON_MS, rm.LED_MAX_ON_MS_DEFAULT)
    c.write_register(rm.HR.LED_DUTY_PERMILLE, rm.LED_DUTY_PERMILLE_DEFAULT)
    c.write_registers(rm.HR.FRAME_GAP_US, [0, 0])
    c.sync_events()
    assert c.lights_on() == []
    c.close()


@pytest.fixture
def raw(sim):
    link = RawLink(sim.port)
    yield link
    link.close()
