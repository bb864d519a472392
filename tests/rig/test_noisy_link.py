"""Noisy links (issue 13 §2): the 264-step demo upload completes through a line that corrupts
1 byte in 100 or loses 1 byte in 1,000 (both directions, seeded), with the client's defaults.

Each run takes ~20 s at 1e-2 corruption (most of it is timeouts of corrupted requests), ~2 s at
1e-3 loss; the 10-run measurement is bench/bench_link.py (figures in firmware/README.md).
"""
from __future__ import annotations

import pytest

from dualscale.rig.client import RigClient
from dualscale.rig.launcher import SimulatedRig
from dualscale.rig.sequence import CapturePlan, seq_crc

from .linkproxy import LinkProxy

DEMO_STEPS = 264


def upload_through(fault: str, rate: float, seed: int) -> tuple[RigClient, LinkProxy]:
    with SimulatedRig("posix") as sim, LinkProxy(sim.port, **{fault: rate}, seed=seed) as proxy:
        with RigClient(proxy.port) as rig:
            steps = CapturePlan().build(rig.status().polarizer_cdeg)
            assert len(steps) == DEMO_STEPS
            rig.upload(steps)  # verifies SEQ_CRC itself
            # read back through a clean line: the device holds exactly this table
            proxy.corrupt = proxy.drop = 0.0
            assert rig.status().seq_crc == seq_crc(steps)
        return rig, proxy


@pytest.mark.parametrize("fault, rate, seed", [
    ("corrupt", 1e-2, 1), ("drop", 1e-3, 1), ("drop", 1e-3, 2),
    pytest.param("corrupt", 1e-2, 2, marks=pytest.mark.slow),
    pytest.param("corrupt", 1e-2, 3, marks=pytest.mark.slow)])
def test_the_demo_upload_survives_a_noisy_line(fault, rate, seed):
    rig, proxy = upload_through(fault, rate, seed)
    assert (proxy.corrupted if fault == "corrupt" else proxy.dropped) > 0  # the line was noisy
    assert rig.stats.timeouts + rig.stats.bad_frames > 0  # ... and the client saw it
    assert rig.stats.chunk_shrinks > 0
