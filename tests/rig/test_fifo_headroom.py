"""The simulator's event-FIFO headroom in virtual time (firmware/README.md, "The simulator").

A real-time rig produces events at 1x, so a host that stops reading for P seconds finds the
events of P device-seconds waiting. An accelerated simulator must not make that worse: at speed
10 the same pause must lose no event when a real-time rig would lose none, and it must still
count lost events (EVT_DROPPED) when a real-time rig would lose them too.
"""
from __future__ import annotations

import time

from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.launcher import SimulatedRig
from dualscale.rig.sequence import Step

STEP_US = 10_000          # one step every 10 ms of device time ...
EVENTS_PER_STEP = 3       # ... STEP_START, TRIGGER, STEP_END: 300 events per device second
N_STEPS = 600             # 6 s of device time, 0.6 s of real time at speed 10


def _steps(n: int = N_STEPS) -> list[Step]:
    # a settle lets the trigger line fall between steps (TRIGGER_GAP)
    return [Step(rm.Source.LED, i % rm.N_LEDS, 1000, None, settle_us=500, exposure_us=STEP_US - 500,
                 pulse_us=0, brackets=1, triggers=1) for i in range(n)]


def _run_with_pause(speed: float, pause_s: float, read_first_s: float = 0.2):
    """Run the sequence, reading the FIFO except for one `pause_s` pause after `read_first_s`.
    Returns (events kept, EVT_DROPPED, steps, the pause as measured)."""
    steps = _steps()
    with SimulatedRig("posix", speed=speed) as sim, RigClient(sim.port, timeout=1.0) as rig:
        rig.upload(steps)
        rig.sync_events()
        rig.start()
        events, t0, paused, pause = [], time.monotonic(), False, 0.0
        deadline = t0 + 60.0
        while time.monotonic() < deadline:
            batch = rig.poll_events()
            events += batch
            if any(e.kind == rm.Event.SEQ_DONE for e in batch):
                break
            if not paused and time.monotonic() - t0 > read_first_s:
                st = rig.status()
                assert st.state == rm.State.RUNNING, "the pause must fall mid-sequence"
                p0 = time.monotonic()
                time.sleep(pause_s)  # the host stops reading: a GC pause, a slow disk, a debugger
                pause, paused = time.monotonic() - p0, True
            if not batch:
                time.sleep(0.005)
        st = rig.status()
        return events, st.evt_dropped, steps, pause


def test_speed_10_host_pause_of_one_second_loses_no_event():
    # A real-time rig produces 300 events in the 1 s pause: far below FIFO_DEPTH (512).
    assert 1.0 * 1e6 / STEP_US * EVENTS_PER_STEP < rm.FIFO_DEPTH - 100
    events, dropped, steps, _ = _run_with_pause(speed=10, pause_s=1.0)
    assert dropped == 0
    assert len(events) == 2 + EVENTS_PER_STEP * len(steps)   # SEQ_START/DONE + 3 per step
    assert [e.seq for e in events] == [(events[0].seq + k) & 0xFFFF for k in range(len(events))]
    # the events still carry the exact schedule: step k starts at k x 10 ms of device time
    starts = [e for e in events if e.kind == rm.Event.STEP_START]
    assert [s.ts_us - starts[0].ts_us for s in starts] == [k * STEP_US for k in range(len(steps))]


def test_speed_10_pause_longer_than_the_fifo_holds_still_counts_lost_events():
    # 3 s without reading: a real-time rig makes 900 events and must drop ~400 of them. The
    # simulator must not hide that by stopping its clock: the loss is counted, and matches.
    events, dropped, steps, pause = _run_with_pause(speed=10, pause_s=3.0)
    rate = 1e6 / STEP_US * EVENTS_PER_STEP                     # events per second at 1x
    assert dropped > 0
    assert len(events) + dropped == 2 + EVENTS_PER_STEP * len(steps)
    # A real-time rig loses at least what the pause makes beyond the FIFO. The simulator may
    # lose a little more: it holds up to SIM_FIFO_HIGH (64) events before it throttles, plus
    # the 20-event window the host read but had not acked, plus the host's own request times.
    least = pause * rate - rm.FIFO_DEPTH - EVENTS_PER_STEP
    assert least <= dropped <= least + 64 + rm.EVT_WINDOW_COUNT + 0.1 * rate
