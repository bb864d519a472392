#!/usr/bin/env python3
"""Link-fault bench: the 264-step demo upload through a faulty line, 10 seeded runs per fault.

A pty proxy (tests/rig/linkproxy.py) between the POSIX simulator and the client corrupts
(XOR with a random non-zero byte) or drops bytes in both directions. For each fault the client
with its defaults (adaptive request size, RTT-based timeout with backoff) is set against a
baseline measured in the same run: the same client with fixed 120-word (249-byte) requests,
a fixed 0.5 s timeout and 3 retries, which is what the client did before issue 13.
Then the host watchdog: a console running the demo capture at speed 1 is SIGKILLed while a
light is on, and the wall time until the side channel shows every light off is measured
(`--watchdog-runs`, against the period, 1 s).
Prints markdown tables for firmware/README.md ("Link faults").

    .venv/bin/python bench/bench_link.py [--runs 10] [--watchdog-runs 5]
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

import signal  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402

from dualscale.rig.client import DEFAULT_WATCHDOG_MS, RigClient  # noqa: E402
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


def killed_host(run: int) -> float:
    """Seconds from SIGKILL of a capturing console to every light off (side channel)."""
    from tests.rig.test_sidechannel import Side
    from tests.rig.test_watchdog import Lights

    with tempfile.TemporaryDirectory() as d:
        link, hw = Path(d) / "tty", Path(d) / "hw.sock"
        with SimulatedRig("posix", link=link, speed=1, hw_socket=hw):
            side = Side(hw)
            side.read_until(lambda o: o.get("ev") == "hello")
            lights = Lights(side)
            host = subprocess.Popen([sys.executable, "-m", "dualscale.cli", "console", "--port", str(link),
                                     "-c", "upload demo; run"], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
            try:
                lights.until(lambda s: len(s.on) > 0, 30)
                time.sleep(0.3 + 0.37 * run)  # somewhere else in the capture each time
                host.send_signal(signal.SIGKILL)
                t_kill = time.monotonic()
                return lights.until(lambda s: not s.on and s.watchdog_events, 5.0) - t_kill
            finally:
                host.kill()
                host.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--watchdog-runs", type=int, default=5)
    ap.add_argument("--only-watchdog", action="store_true")
    a = ap.parse_args()
    if a.only_watchdog:
        a.runs = 0
    print(f"{datetime.date.today()}, load average {os.getloadavg()[0]:.2f} at start, {a.runs} runs each")
    if a.runs:
        print("| fault (both directions) | client | uploads completed | time per upload, median (min–max) |")
        print("|---|---|---|---|")
    for fault, rate in (FAULTS if a.runs else []):
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
    if a.watchdog_runs:
        t = [killed_host(i) for i in range(a.watchdog_runs)]
        print(f"\n| host watchdog ({DEFAULT_WATCHDOG_MS} ms), host SIGKILLed mid-capture | every light off after |")
        print("|---|---|")
        print(f"| {len(t)} runs | median {statistics.median(t):.3f} s ({min(t):.3f}–{max(t):.3f}) |")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
