"""The simulator's as-fast-as-possible mode (speed 0) with long sequences: the host's replies are
never held back by the FIFO's congestion cap, and the host watchdog keeps its meaning
(firmware/targets/posix/main.c `effective_cap`)."""

from __future__ import annotations

import pytest

from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.launcher import SimulatedRig, sim_binary
from dualscale.rig.sequence import Step, split_words

pytestmark = pytest.mark.skipif(not sim_binary().exists(), reason="POSIX simulator not built (make -C firmware posix)")

# 40 steps of two gate brackets of 0.9 s and 3.6 s: 180 s of device time, events far apart
STEPS = [Step(rm.Source.LED, i, 65535, 0 if i == 0 else None, 2000, 900000, 0, 2, 2, 1) for i in range(40)]


@pytest.mark.parametrize("watchdog_ms", [0, 1000, rm.WATCHDOG_MS_MAX])
def test_a_long_sequence_at_speed_0_runs_to_the_end(watchdog_ms):
    """Before: with the watchdog off the link died (every reply waited for real time to catch
    up with a clock that had jumped past the cap); with it on, jumps tripped it (FAULT)."""
    with SimulatedRig("posix", speed=0.0) as sim:
        rig = RigClient(sim.port)
        rig.open()
        rig.write_registers(rm.HR.FRAME_GAP_US, split_words(1000, 2))
        res = rig.run(STEPS, watchdog_ms=watchdog_ms, timeout_s=60)
        assert res.state == rm.State.DONE and res.error == rm.Error.NONE and res.dropped == 0
        assert sum(e.kind == rm.Event.TRIGGER for e in res.events) == 80
        assert rig.status().watchdog_trips == 0
        rig.close()


def test_a_silent_host_still_trips_the_watchdog_at_speed_0():
    """The rule that keeps a talking host safe must not make a dead one safe: a host that stops
    polling (killed) trips the watchdog after about its period of real time."""
    import time

    with SimulatedRig("posix", speed=0.0) as sim:
        rig = RigClient(sim.port)
        rig.open()
        rig.write_registers(rm.HR.FRAME_GAP_US, split_words(1000, 2))
        rig.upload(STEPS)
        rig.set_watchdog(500)
        rig.start()
        time.sleep(1.5)  # the host goes quiet
        st = rig.status()
        assert st.state == rm.State.FAULT and st.error == rm.Error.WATCHDOG and st.watchdog_trips == 1
        assert st.cur_step < len(STEPS) - 1  # it stopped the sequence, which had 180 s to go
        rig.close()
