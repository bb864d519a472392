"""A serial drop in the middle of a run: the client reopens the port and loses no event."""
from __future__ import annotations

from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.sequence import Step
from dualscale.rig.launcher import SimulatedRig


def test_serial_drop_mid_sequence_loses_no_event():
    steps = [Step(rm.Source.LED, i, 1000, None, 1000, 20_000, 100, 2, 0, 1) for i in range(40)]
    with SimulatedRig("posix", speed=1) as sim, RigClient(sim.port, timeout=0.5) as rig:
        drops = []

        def yank(e):
            # pull the cable twice: once at step 5, once at step 25
            if e.kind == rm.Event.STEP_START and e.step in (5, 25):
                rig._mb.close()
                drops.append(e.step)

        res = rig.run(steps, on_event=yank, timeout_s=30)
    assert drops == [5, 25] and res.reconnects >= 2
    assert res.state == rm.State.DONE
    seqs = [e.seq for e in res.events]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # contiguous: none lost, none twice
    assert [e.step for e in res.events if e.kind == rm.Event.STEP_END] == list(range(40))
