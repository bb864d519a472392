"""The serial-line format (PROTOCOL.md section 1; Modbus over Serial Line v1.02 section 2.5.1):
8E1 at reset, SERIAL_PARITY / SERIAL_STOP_BITS registers, the simulator's pty termios, its side
channel and the launcher's options. The STM32 USART register values are checked in
firmware/tests/test_uart_cfg.c.

A Linux pty forces CS8 and clears PARENB on every tcsetattr (drivers/tty/pty.c,
pty_set_termios) but keeps PARODD and CSTOPB, so the termios checks compare what the kernel keeps;
the side channel's hello line states the whole format."""
from __future__ import annotations

import json
import os
import pty
import socket
import struct
import subprocess
import termios
import time

import pytest

from dualscale.errors import InputError
from dualscale.protocol import regmap as rm
from dualscale.rig.launcher import SimulatedRig, line_format, sim_binary

from .conftest import RawLink


def _cflag(port: str) -> int:
    """The pty's c_cflag, read without configuring the port (pyserial would set its own)."""
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        return termios.tcgetattr(fd)[2]
    finally:
        os.close(fd)


def _pty_keeps_parenb() -> bool:
    m, s = pty.openpty()
    try:
        a = termios.tcgetattr(s)
        a[2] |= termios.PARENB | termios.CSTOPB
        try:
            termios.tcsetattr(s, termios.TCSANOW, a)
        except termios.error:  # Linux: EINVAL when PARENB was the only change it could not keep
            return False
        return bool(termios.tcgetattr(s)[2] & termios.PARENB)
    finally:
        os.close(m)
        os.close(s)


KEEPS_PARENB = _pty_keeps_parenb()


def _fmt(cflag: int) -> str:
    """'8E1'-style format as far as the pty keeps it: parity E/O/N where PARENB survives, else
    '-' (no parity bit shown) or 'O' (PARODD)."""
    if KEEPS_PARENB:
        parity = "N" if not cflag & termios.PARENB else ("O" if cflag & termios.PARODD else "E")
    else:
        parity = "O" if cflag & termios.PARODD else "-"
    bits = 8 if cflag & termios.CSIZE == termios.CS8 else 0
    return f"{bits}{parity}{2 if cflag & termios.CSTOPB else 1}"


def _shown(fmt: str) -> str:
    """What _fmt reports for the format `fmt` on this kernel."""
    return fmt if KEEPS_PARENB else fmt.replace("E", "-").replace("N", "-")


def _hello(path) -> dict:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(path))
    s.settimeout(5.0)
    buf, t0 = b"", time.monotonic()
    try:
        while time.monotonic() - t0 < 5.0:
            buf += s.recv(4096)
            for line in buf.split(b"\n"):
                if line.strip():
                    o = json.loads(line)
                    if o.get("ev") == "hello":
                        return o
    finally:
        s.close()
    raise AssertionError("no hello line on the side channel")


def _read_format(link: RawLink) -> list[int]:
    resp = link.request(struct.pack(">BBHH", 1, 0x03, rm.HR.SERIAL_PARITY, 2), timeout=1.0)
    assert len(resp) == 9 and resp[1] == 0x03, resp.hex(" ")
    return list(struct.unpack(">HH", resp[3:7]))


def _write_format(link: RawLink, parity: int, stop_bits: int) -> bytes:
    body = struct.pack(">BBHHBHH", 1, 0x10, rm.HR.SERIAL_PARITY, 2, 4, parity, stop_bits)
    return link.request(body, timeout=1.0)


@pytest.mark.parametrize("args, want_fmt, want_regs", [
    ({}, "8E1", [rm.Parity.EVEN, 1]),
    ({"parity": "O"}, "8O1", [rm.Parity.ODD, 1]),
    ({"parity": "N"}, "8N2", [rm.Parity.NONE, 2]),
    ({"parity": "E", "stop_bits": 2}, "8E2", [rm.Parity.EVEN, 2]),
])
def test_simulator_starts_in_the_asked_format(args, want_fmt, want_regs, tmp_path):
    with SimulatedRig("posix", hw_socket=tmp_path / "hw.sock", **args) as sim:
        assert _fmt(_cflag(sim.port)) == _shown(want_fmt)
        hello = _hello(tmp_path / "hw.sock")
        assert f"8{hello['parity']}{hello['stop_bits']}" == want_fmt
        link = RawLink(sim.port)
        try:
            assert _read_format(link) == want_regs
        finally:
            link.close()


def test_default_is_8e1_as_the_serial_line_spec_requires():
    assert (rm.DEFAULT_PARITY, rm.DEFAULT_STOP_BITS) == (rm.Parity.EVEN, 1)
    assert line_format(None, None) == ("E", 1)
    regs = {r.name: r for r in rm.REGISTERS if r.space == "holding"}
    assert regs["SERIAL_PARITY"].default == rm.Parity.EVEN and regs["SERIAL_STOP_BITS"].default == 1


def test_a_register_write_switches_the_pty_after_the_response():
    with SimulatedRig("posix") as sim:
        link = RawLink(sim.port)  # pyserial sets 8N1 on the shared terminal
        try:
            resp = _write_format(link, rm.Parity.NONE, 2)
            assert resp[1] == 0x10, resp.hex(" ")  # answered (in the old format)
            assert _fmt(_cflag(sim.port)) == _shown("8N2")
            assert _write_format(link, rm.Parity.NONE, 1)[1:3] == b"\x90\x03"  # 8N1 refused
            assert _fmt(_cflag(sim.port)) == _shown("8N2")
            assert _write_format(link, rm.Parity.ODD, 1)[1] == 0x10
            assert _fmt(_cflag(sim.port)) == "8O1"
            assert _read_format(link) == [rm.Parity.ODD, 1]
        finally:
            link.close()


def test_8n1_is_refused_by_the_simulator_and_the_launcher():
    exe = sim_binary()
    if not exe.exists():
        pytest.skip("simulator not built")
    r = subprocess.run([str(exe), "--parity", "N", "--stop-bits", "1"], capture_output=True,
                       text=True, timeout=10)
    assert r.returncode == 2 and "stop-bits 2" in r.stderr
    r = subprocess.run([str(exe), "--parity", "X"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2 and "--parity" in r.stderr
    with pytest.raises(InputError, match="2 stop bits"):
        SimulatedRig("posix", parity="N", stop_bits=1)
    with pytest.raises(InputError, match="parity"):
        SimulatedRig("posix", parity="M")


@pytest.mark.qemu
def test_arm_image_boots_8e1_and_takes_the_launchers_format():
    with SimulatedRig("qemu") as sim:
        link = RawLink(sim.port)
        try:
            assert _read_format(link) == [rm.Parity.EVEN, 1]
        finally:
            link.close()
    with SimulatedRig("qemu", parity="N") as sim:  # broadcast by the launcher after boot
        link = RawLink(sim.port)
        try:
            assert _read_format(link) == [rm.Parity.NONE, 2]
        finally:
            link.close()
