"""Parity and stop bits on the client and the rig commands (issue 13 §1/§2): 8E1 by default as
the firmware's reset format (rig.toml), 2 stop bits without parity, 8N1 refused like the
firmware refuses it; a client whose format differs from the device's is told so."""
from __future__ import annotations

import subprocess
import sys

import pytest

from dualscale.errors import InputError
from dualscale.protocol import regmap as rm
from dualscale.rig.client import DEFAULT_PARITY, RigClient, serial_settings
from dualscale.rig.launcher import SimulatedRig

DUALSCALE = [sys.executable, "-m", "dualscale.cli"]


def test_the_default_is_the_firmware_reset_format_8e1():
    assert rm.Parity(rm.DEFAULT_PARITY) == rm.Parity.EVEN and rm.DEFAULT_STOP_BITS == 1
    c = RigClient("/dev/null-not-opened")
    assert (c.parity, c.stopbits) == ("E", 1) == (DEFAULT_PARITY, 1)
    assert (c._mb.comm_params.parity, c._mb.comm_params.stopbits) == ("E", 1)


@pytest.mark.parametrize("parity, stopbits, want", [
    ("E", None, ("E", 1)), ("o", None, ("O", 1)), ("N", None, ("N", 2)), ("E", 2, ("E", 2))])
def test_stop_bits_follow_the_serial_line_rule(parity, stopbits, want):
    assert serial_settings(parity, stopbits) == want


@pytest.mark.parametrize("parity, stopbits, msg", [("N", 1, "needs 2 stop bits"), ("X", None, "parity must be"),
                                                   ("E", 3, "stop bits must be")])
def test_a_bad_format_is_an_input_error(parity, stopbits, msg):
    with pytest.raises(InputError, match=msg):
        RigClient("/dev/null", parity=parity, stopbits=stopbits)


def test_the_client_opens_the_simulator_and_reports_a_format_mismatch():
    with SimulatedRig("posix") as sim:
        with RigClient(sim.port) as rig:
            assert rig.format_mismatch is None
            assert rig.device_serial_format() == ("E", 1)
        with RigClient(sim.port, parity="N") as rig:  # a pty passes bytes whatever the format
            assert rig.format_mismatch == ("E", 1)


def test_the_console_takes_parity_and_refuses_8n1(tmp_path):
    r = subprocess.run([*DUALSCALE, "console", "--port", str(tmp_path / "x"), "--parity", "N", "--stopbits", "1",
                        "-c", "id"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "parity N needs 2 stop bits" in r.stderr
    r = subprocess.run([*DUALSCALE, "demo", "--help"], capture_output=True, text=True, timeout=60)
    assert "--parity {E,O,N}" in r.stdout and "--stop-bits" in r.stdout
