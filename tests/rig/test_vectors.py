"""Replay protocol/vectors.toml (exact bytes) against freshly started simulators.

The C unit tests replay the same file against the core (firmware/tests)."""
from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from dualscale.rig.launcher import SimulatedRig

from .conftest import TARGETS, RawLink

VECTORS = tomllib.loads((Path(__file__).resolve().parents[2] / "protocol/vectors.toml").read_text())["vector"]


def _hex(s: str) -> bytes:
    return bytes.fromhex(s.replace(" ", ""))


@pytest.mark.parametrize("target", TARGETS)
def test_shared_vectors(target):
    assert len(VECTORS) >= 20
    with SimulatedRig(target) as sim:
        link = RawLink(sim.port)
        try:
            for v in VECTORS:
                want = _hex(v["response"])
                got = link.transact(_hex(v["request"]), timeout=1.0 if want else 0.15)
                if target != "posix" and b"posix" in want:
                    # identification names the target: same frame with the other name
                    assert got[:2] == want[:2] and b"stm32f405" in got, v["name"]
                    continue
                assert got.hex(" ") == want.hex(" "), v["name"]
        finally:
            link.close()
