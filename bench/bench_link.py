#!/usr/bin/env python3
"""Link-fault bench: the 264-step demo upload through a faulty line, 10 seeded runs per fault.

A pty proxy (tests/rig/linkproxy.py) between the POSIX simulator and the client corrupts
(XOR with a random non-zero byte) or drops bytes in both directions. For each fault the client
with its defaults (adaptive request size, RTT-based timeout with backoff) is set against a
baseline measured in the same run: the same client with fixed 120-word (249-byte) requests,
a fixed 0.5 s timeout and 3 retries, which is what the client did before issue 13.
Prints a markdown table for firmware/README.md ("Link faults").

    .venv/bin/python bench/bench_link.py [--runs 10]
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dualscale.rig.client import RigClient  # noqa: E402
from dualscale.rig.launcher import SimulatedRig  # noqa: E402
from dualscale.rig.sequence import CapturePlan  # noqa: E402
from tests.rig.linkproxy import LinkProxy  # noqa: E402

FAULTS = [("corrupt", 1e-2), ("drop", 1e-3)]


class FixedClient(RigClient):
    """The baseline: no adaptation (fixed request size, fixed timeout), 3 retries."""

    def __init__(self, port: str):
        super().__init__(port, timeout=0.5, min_timeout=0.5, retries=3, bulk_retries=3)

    def _shrink(self) -> None:
        pass

    def _grow(self) -> None:
        pass

    def rto(self) -> float:
        return self.timeout


def one(make, fault: str, rate: float, seed: int) -> tuple[bool, float, str]:
    with SimulatedRig("posix") as sim, LinkProxy(sim.port, **{fault: rate}, seed=seed) as proxy:
        rig = make(proxy.port)
        t0 = time.monotonic()
        try:
            rig.open()
            steps = CapturePlan().build(rig.status().polarizer_cdeg)
            rig.upload(steps)
            ok, why = True, ""
        except Exception as e:  # noqa: BLE001 - a failed run is a data point
            ok, why = False, str(e)[:80]
        finally:
            rig.close()
        return ok, time.monotonic() - t0, why


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    a = ap.parse_args()
    print(f"{datetime.date.today()}, load average {os.getloadavg()[0]:.2f} at start, {a.runs} runs each")
    print("| fault (both directions) | client | uploads completed | time per upload, median (min–max) |")
    print("|---|---|---|---|")
    for fault, rate in FAULTS:
        for name, make in (("fixed 249-byte requests, 3 retries (before)", FixedClient),
                           ("adaptive (defaults)", RigClient)):
            res = [one(make, fault, rate, seed) for seed in range(1, a.runs + 1)]
            ok = [t for good, t, _ in res if good]
            times = (f"{statistics.median(ok):.1f} s ({min(ok):.1f}–{max(ok):.1f})" if ok else "–")
            print(f"| {fault} {rate:g} per byte | {name} | {len(ok)}/{len(res)} | {times} |", flush=True)
            for good, _, why in res:
                if not good:
                    print(f"<!-- failed: {why} -->")
                    break
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
