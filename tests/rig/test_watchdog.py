"""The host watchdog guards every capture (issue 13 §2): a host killed mid-sequence leaves every
light off within the watchdog period (seen on the simulator's side channel), the console feeds
the watchdog while its user is idle, and a run that loses the link aborts the sequence or leaves
it to the watchdog, and says which."""
from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from dualscale.protocol import regmap as rm
from dualscale.rig.client import DEFAULT_WATCHDOG_MS, LinkError, RigClient
from dualscale.rig.launcher import SimulatedRig
from dualscale.rig.sequence import Step

from .linkproxy import LinkProxy
from .test_sidechannel import Side

DUALSCALE = [sys.executable, "-m", "dualscale.cli"]
SLACK_S = 0.3  # the test's own latency: reading the side channel on a loaded machine
PERIOD_S = DEFAULT_WATCHDOG_MS / 1e3


class Lights:
    """The lights' state from the side channel, and the wall time of each change."""

    def __init__(self, side: Side):
        self.side, self.on, self.watchdog_events = side, {}, 0

    def _take(self, o: dict) -> bool:
        if o.get("ev") == "light":
            key = (o["kind"], o["index"])
            if o["intensity"]:
                self.on[key] = o["intensity"]
            else:
                self.on.pop(key, None)
        elif o.get("ev") == "event" and o["kind"] == rm.Event.WATCHDOG:
            self.watchdog_events += 1
        return False

    def until(self, pred, timeout: float) -> float:
        """Follow the channel until `pred(self)`; the wall time then."""
        def check(o):
            self._take(o)
            return pred(self)
        if pred(self):
            return time.monotonic()
        self.side.read_until(check, timeout)
        return time.monotonic()

    def still(self, pred, seconds: float) -> bool:
        """Whether `pred(self)` holds for `seconds` (following the channel)."""
        try:
            self.until(lambda s: not pred(s), seconds)
            return False
        except TimeoutError:
            return pred(self)


def _nonblocking_text(stream) -> str:
    fcntl.fcntl(stream, fcntl.F_SETFL, fcntl.fcntl(stream, fcntl.F_GETFL) | os.O_NONBLOCK)
    try:
        return (stream.read() or b"").decode()
    except (BlockingIOError, TypeError):
        return ""


@pytest.fixture
def rig_with_side(tmp_path):
    link, hw = tmp_path / "tty", tmp_path / "hw.sock"
    with SimulatedRig("posix", link=link, speed=1, hw_socket=hw) as sim:
        side = Side(hw)
        side.read_until(lambda o: o.get("ev") == "hello")
        yield sim, link, Lights(side)


def test_a_killed_capture_leaves_every_light_off_within_the_watchdog_period(rig_with_side):
    sim, link, lights = rig_with_side
    host = subprocess.Popen([*DUALSCALE, "console", "--port", str(link), "-c", "upload demo; run"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        lights.until(lambda s: len(s.on) > 0, 30)  # the capture runs (15.6 s at speed 1) ...
        time.sleep(0.5)
        assert lights.on and host.poll() is None
        host.send_signal(signal.SIGKILL)  # ... and its host dies
        t_kill = time.monotonic()
        t_off = lights.until(lambda s: not s.on and s.watchdog_events, PERIOD_S + 2.0)
    finally:
        host.kill()
        host.wait()
    assert t_off - t_kill <= PERIOD_S + SLACK_S, f"lights off {t_off - t_kill:.3f} s after the kill"
    assert lights.still(lambda s: not s.on, 1.0)  # and they stay off
    with RigClient(str(link)) as rig:
        st = rig.status()
        assert (st.state, st.error) == (rm.State.FAULT, rm.Error.WATCHDOG)
        rig.clear_error()
        rig.set_watchdog(0)


def test_the_console_feeds_the_watchdog_while_idle_and_says_so(rig_with_side):
    sim, link, lights = rig_with_side
    host = subprocess.Popen([*DUALSCALE, "console", "--port", str(link)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        host.stdin.write(b"led 3 on\n")
        host.stdin.flush()
        lights.until(lambda s: (rm.Source.LED, 3) in s.on, 10)
        # the user is idle for three watchdog periods: the light stays on
        assert lights.still(lambda s: (rm.Source.LED, 3) in s.on and not s.watchdog_events, 3 * PERIOD_S)
        said = _nonblocking_text(host.stdout)
        assert f"host watchdog: {DEFAULT_WATCHDOG_MS} ms" in said and "keeps it fed while you are idle" in said
        host.send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        t_off = lights.until(lambda s: not s.on, PERIOD_S + 2.0)
    finally:
        host.kill()
        host.wait()
    assert t_off - t_kill <= PERIOD_S + SLACK_S, f"light off {t_off - t_kill:.3f} s after the kill"
    with RigClient(str(link)) as rig:
        rig.clear_error()
        rig.set_watchdog(0)


STEPS = [Step(rm.Source.LED, i % rm.N_LEDS, 1000, None, 1000, 20_000, 100, 1, 0, 1) for i in range(200)]


def _cut_at_step(proxy: LinkProxy, step: int, for_s: float | None):
    def on_event(e):
        if e.kind == rm.Event.STEP_START and e.step == step:
            proxy.cut(True)
            if for_s is not None:
                threading.Timer(for_s, proxy.cut, (False,)).start()
    return on_event


def test_a_run_that_loses_the_link_aborts_the_sequence(tmp_path):
    with SimulatedRig("posix") as sim, LinkProxy(sim.port) as proxy:
        with RigClient(proxy.port, timeout=0.2, retries=1) as rig:
            rig.upload(STEPS)
            with pytest.raises(LinkError, match="the sequence was aborted"):
                rig.run(on_event=_cut_at_step(proxy, 3, 1.0), watchdog_ms=5000, timeout_s=30)
            st = rig.status()
            assert st.state == rm.State.ABORTED and st.cur_step < len(STEPS) - 1
            assert rig.lights_on() == []


def test_a_run_that_cannot_reach_the_rig_leaves_it_to_the_watchdog(tmp_path):
    with SimulatedRig("posix") as sim, LinkProxy(sim.port) as proxy:
        with RigClient(proxy.port, timeout=0.2, retries=1) as rig:
            rig.upload(STEPS)
            with pytest.raises(LinkError, match=r"host watchdog \(500 ms\) has switched every light off"):
                rig.run(on_event=_cut_at_step(proxy, 3, None), watchdog_ms=500, timeout_s=30)
            proxy.cut(False)
            st = rig.status()
            assert (st.state, st.error) == (rm.State.FAULT, rm.Error.WATCHDOG)
            assert st.cur_step < len(STEPS) - 1
            assert rig.lights_on() == []
