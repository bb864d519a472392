"""Timing: exact in the simulator's virtual time; order and durations under QEMU."""
from __future__ import annotations

import json
import socket
import time

import pytest

from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.demo import run_demo
from dualscale.rig.sequence import Step, schedule
from dualscale.rig.launcher import SimulatedRig


def test_full_micro_capture_lands_exactly_on_schedule_in_virtual_time():
    rep = run_demo("posix", speed=0, out=lambda s: None)
    assert rep.state == "DONE" and rep.dropped == 0
    assert rep.steps == 2 * (127 + 1 + rm.N_BACKLIGHTS)
    assert rep.max_step_dev_us == 0          # every event exactly on schedule
    assert rep.measured_us == rep.scheduled_us
    assert rep.overhead_pct < 1.0


def _steps():
    out = []
    for i in range(12):
        gate = i % 2 == 0  # gate mode (PULSE_US = 0) needs one bracket: no frame gap here
        out.append(Step(rm.Source.LED, i, 2000, 0 if i == 0 else None, settle_us=3000 + 500 * i,
                        exposure_us=4000, pulse_us=0 if gate else 200, brackets=1 if gate else 1 + i % 3,
                        ev_step=1, triggers=1))
    return out


@pytest.mark.qemu
def test_qemu_event_order_and_step_durations_match_the_schedule():
    steps = _steps()
    sched = schedule(steps, frame_gap_us=0)
    # -icount: guest time follows instructions, so host scheduling hiccups don't show as lateness
    with SimulatedRig("qemu", icount="shift=2") as sim, RigClient(sim.port, timeout=2.0) as rig:
        res = rig.run(steps, timeout_s=60)
    assert res.state == rm.State.DONE
    per = [e for e in res.events if e.kind in (rm.Event.STEP_START, rm.Event.TRIGGER, rm.Event.STEP_END)]
    expect = []
    for k, s in enumerate(steps):
        expect += [(rm.Event.STEP_START, k)] + [(rm.Event.TRIGGER, k)] * s.brackets + [(rm.Event.STEP_END, k)]
    assert [(e.kind, e.step) for e in per] == expect
    starts = {e.step: e.ts_us for e in per if e.kind == rm.Event.STEP_START}
    ends = {e.step: e.ts_us for e in per if e.kind == rm.Event.STEP_END}
    for k, t in enumerate(sched):
        got = ends[k] - starts[k]
        want = t.end - t.start
        # the guest busy-polls its SysTick microsecond clock: allow a few µs of polling latency
        assert abs(got - want) <= 20, (k, got, want)


def test_camera_master_latches_steps_on_camera_edges(tmp_path):
    hw = tmp_path / "hw.sock"
    steps = [Step(rm.Source.LED, i, 3000, None, settle_us=0, exposure_us=1000, brackets=2 if i == 1 else 1,
                  triggers=0) for i in range(3)]
    with SimulatedRig("posix", hw_socket=hw) as sim, RigClient(sim.port, timeout=1.0) as rig:
        side = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        side.connect(str(hw))
        rig.upload(steps)
        rig.sync_events()
        rig.start(rm.TriggerMode.CAMERA_MASTER)
        assert rig.status().state == rm.State.ARMED
        assert rig.lights_on() == []
        lights = []
        for _ in range(5):  # 1 + 2 + 1 frames, then the edge that ends the sequence
            side.sendall(json.dumps({"ev": "edge", "camera": 0}).encode() + b"\n")
            time.sleep(0.05)
            lights.append(rig.lights_on())
        side.close()
        evs = rig.poll_events() + rig.poll_events()
        assert lights[:4] == [[(rm.Source.LED, 0)], [(rm.Source.LED, 1)], [(rm.Source.LED, 1)],
                              [(rm.Source.LED, 2)]]
        assert lights[4] == [] and rig.status().state == rm.State.DONE
        starts = [e for e in evs if e.kind == rm.Event.STEP_START]
        edges = [e for e in evs if e.kind == rm.Event.CAMERA_EDGE]
        assert [e.step for e in starts] == [0, 1, 2]
        # each step latched exactly at the edge that caused it
        assert starts[0].ts_us == edges[0].ts_us and starts[1].ts_us == edges[1].ts_us
        assert starts[2].ts_us == edges[3].ts_us


def test_camera_master_times_out_without_edges():
    steps = [Step(rm.Source.LED, 0, 3000, None, 0, 1000, 0, 1, 0, 0)]
    with SimulatedRig("posix") as sim, RigClient(sim.port, timeout=1.0) as rig:
        rig.write_register(rm.HR.CAMERA_TIMEOUT_MS, 200)
        rig.upload(steps)
        rig.start(rm.TriggerMode.CAMERA_MASTER)
        time.sleep(0.5)
        st = rig.status()
        assert st.state == rm.State.FAULT and st.error == rm.Error.CAMERA_TIMEOUT
        assert rig.lights_on() == []
