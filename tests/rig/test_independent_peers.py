"""An independent Modbus implementation (mbpoll/libmodbus, minimalmodbus) talks to both targets."""
from __future__ import annotations

import shutil
import subprocess

import minimalmodbus
import pytest

from dualscale.protocol import regmap as rm


def mbpoll(*args: str) -> str:
    exe = shutil.which("mbpoll")
    assert exe, "mbpoll is not installed (make apt)"
    r = subprocess.run([exe, "-m", "rtu", "-a", "1", "-b", "115200", "-P", "none", "-1", *args],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def test_mbpoll_reads_report_server_id(sim):
    out = mbpoll("-u", sim.port)
    target = "stm32f405" if sim.target == "qemu" else "posix"
    assert "Id    : 0x01" in out and "Status: On" in out
    major, minor = rm.PROTOCOL_VERSION
    assert f"Data  : dualscale fw=0.1.0 proto={major}.{minor} target={target}" in out


def test_mbpoll_reads_input_registers(sim):
    out = mbpoll("-t", "3", "-r", "1", "-c", "8", sim.port)  # mbpoll counts from 1
    values = [int(ln.split(":")[1]) for ln in out.splitlines() if ln.startswith("[")]
    assert values == [rm.MAGIC, (rm.PROTOCOL_VERSION[0] << 8) | rm.PROTOCOL_VERSION[1], 0x0001, 0, rm.N_LEDS, rm.N_BACKLIGHTS, rm.MAX_STEPS, rm.FIFO_DEPTH]


def test_minimalmodbus_reads_and_writes(sim):
    inst = minimalmodbus.Instrument(sim.port, 1)
    inst.serial.baudrate = 115200
    inst.serial.timeout = 1.0
    inst.clear_buffers_before_each_transaction = True
    try:
        assert inst.read_register(rm.IR.MAGIC, functioncode=4) == rm.MAGIC
        inst.write_register(rm.HR.MANUAL_INTENSITY, 4321, functioncode=16)
        assert inst.read_register(rm.HR.MANUAL_INTENSITY, functioncode=3) == 4321
        with pytest.raises(minimalmodbus.IllegalRequestError):
            inst.read_register(0x7F00, functioncode=3)
    finally:
        inst.serial.close()
