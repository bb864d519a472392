"""The simulator's hardware side channel: what a simulated camera sees (light, polarizer,
trigger edges) lands exactly on schedule in virtual time, and the simulator cleans up on exit."""
from __future__ import annotations

import json
import select
import socket
import time

import pytest

from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.sequence import Step
from dualscale.rig.launcher import SimulatedRig


class Side:
    """Newline-delimited JSON from the side channel."""

    def __init__(self, path):
        self.s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.s.connect(str(path))
        self.buf = b""

    def read_until(self, pred, timeout=10.0) -> list[dict]:
        out, deadline = [], time.monotonic() + timeout
        while time.monotonic() < deadline:
            while b"\n" in self.buf:
                line, self.buf = self.buf.split(b"\n", 1)
                out.append(json.loads(line))
                if pred(out[-1]):
                    return out
            if select.select([self.s], [], [], 0.1)[0]:
                chunk = self.s.recv(65536)
                if not chunk:
                    break
                self.buf += chunk
        raise TimeoutError(f"side channel: condition not met; last {out[-5:]}")


STEPS = [Step(rm.Source.LED, 5, 1000, None, 10_000, 20_000, 100, 1, 0, 0b0001),
         Step(rm.Source.BACKLIGHT, 2, 2000, 9000, 250_000, 5000, 0, 2, 1, 0b0011)]


@pytest.mark.parametrize("speed", [0, 10, 100])
def test_lights_triggers_and_events_exactly_on_schedule(tmp_path, speed):
    link, hw = tmp_path / "tty", tmp_path / "hw.sock"
    with SimulatedRig("posix", link=link, speed=speed, hw_socket=hw) as sim:
        side = Side(hw)
        hello = side.read_until(lambda o: o.get("ev") == "hello")[-1]
        assert hello["target"] == "posix"
        with RigClient(str(link)) as rig:
            rig.set_polarizer(0)
            rig.write_registers(rm.HR.FRAME_GAP_US, [0, 100])  # gate mode needs the line low between brackets
            rig.upload(STEPS)
            rig.start()
            got = side.read_until(lambda o: o.get("ev") == "event" and o["kind"] == rm.Event.SEQ_DONE)
        t0 = next(o["t_us"] for o in got if o.get("ev") == "event" and o["kind"] == rm.Event.SEQ_START)
        after = [o for o in got if o.get("t_us", -1) >= t0]
        evs = [(o["t_us"] - t0, rm.Event(o["kind"]).name, o["arg"], o["step"]) for o in after if o["ev"] == "event"]
        # step 0: settle 10 ms, one 20 ms bracket + 100 us gap; step 1: settle 250 ms, brackets of
        # 5 ms and 10 ms, each followed by the 100 us gap
        assert evs == [(0, "SEQ_START", 0, 0xFFFF), (0, "STEP_START", 0, 0), (10000, "TRIGGER", 0, 0),
                       (30100, "STEP_END", 0, 0), (30100, "POLARIZER", 0, 1), (30100, "STEP_START", 0, 1),
                       (280100, "TRIGGER", 0, 1), (285200, "TRIGGER", 1, 1), (295300, "STEP_END", 0, 1),
                       (295300, "SEQ_DONE", 0, 0xFFFF)]
        trig = [(o["t_us"] - t0, o["mask"]) for o in after if o["ev"] == "triggers"]
        # pulse mode: 100 us; gate mode (PULSE_US = 0): the whole bracket exposure
        assert trig == [(10000, 1), (10100, 0), (280100, 3), (285100, 0), (285200, 3), (295200, 0)]
        lights = [(o["t_us"] - t0, o["kind"], o["index"], o["intensity"]) for o in after if o["ev"] == "light"]
        assert lights == [(0, 1, 5, 1000), (30100, 1, 5, 0), (30100, 2, 2, 2000), (295300, 2, 2, 0)]
        pol = [(o["t_us"] - t0, o["cdeg"]) for o in after if o["ev"] == "polarizer"]
        assert pol == [(30100, 9000)]


def test_exit_switches_lights_off_and_removes_link_and_socket(tmp_path):
    link, hw = tmp_path / "tty", tmp_path / "hw.sock"
    sim = SimulatedRig("posix", link=link, hw_socket=hw).start()
    side = Side(hw)
    with RigClient(str(link)) as rig:
        rig.set_light(rm.Source.LED, 3, True)
    side.read_until(lambda o: o.get("ev") == "light" and o["index"] == 3 and o["intensity"] > 0)
    assert sim.stop() == 0
    side.read_until(lambda o: o.get("ev") == "light" and o["index"] == 3 and o["intensity"] == 0, 2)
    assert not link.exists() and not hw.exists()
