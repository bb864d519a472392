#!/usr/bin/env python3
"""Rig benchmarks: register round trip, 1,000-step upload, sequencer overhead, image size.

Prints a markdown table for firmware/README.md. Every figure is a median over repeats, and each
is set against a baseline measured in the same run:
- round trip: our pymodbus client vs a bare pyserial request/response loop (no library);
- upload: measured time vs the time the same bytes take on a real 115200-baud line;
- overhead: device-clock duration vs the schedule (Σ settle + exposure).
"""
from __future__ import annotations

import datetime
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import serial

from dualscale.protocol import regmap as rm
from dualscale.protocol.crc import rtu_frame
from dualscale.rig.client import STEPS_PER_WRITE, RigClient
from dualscale.rig.demo import measure_rtt as client_rtt, run_demo
from dualscale.rig.sequence import Step, schedule
from dualscale.rig.launcher import SimulatedRig, firmware_elf

REPEATS = 5
N_RTT = 300


def raw_rtt(port: str, n: int) -> list[float]:
    """Baseline: hand-framed FC 04 over pyserial, reading exactly the expected 7 bytes."""
    s = serial.Serial(port, 115200, timeout=1)
    req = rtu_frame(bytes([1, 4, 0, rm.IR.STATE, 0, 1]))
    out = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            s.write(req)
            if len(s.read(7)) != 7:
                raise RuntimeError("no answer")
            out.append((time.perf_counter() - t0) * 1e3)
    finally:
        s.close()
    return out


def wire_time_s(n_steps: int, baud: int = 115200) -> float:
    """Time the upload's bytes would take on a real line: 10 bits a character plus t3.5 per frame."""
    frames = 0
    chars = 0
    for off in range(0, n_steps, STEPS_PER_WRITE):
        k = min(STEPS_PER_WRITE, n_steps - off)
        chars += 9 + 2 * rm.STEP_WORDS * k + 8  # FC 10 request + its 8-byte response
        frames += 2
    chars += 8 + 8 + 8 + 7  # SEQ_LEN write + answer, SEQ_CRC read + answer
    frames += 4
    return chars * 10 / baud + frames * 1750e-6


def main() -> int:
    rows = []
    with SimulatedRig("posix", speed=1) as sim:
        rig = RigClient(sim.port, timeout=1.0)
        rig.open()
        c = client_rtt(rig, N_RTT)
        rig.close()
        r = raw_rtt(sim.port, N_RTT)
        rows.append(("register round trip, posix sim (dualscale client)", f"{statistics.median(c):.3f} ms",
                     f"raw pyserial {statistics.median(r):.3f} ms",
                     f"{statistics.median(c) / statistics.median(r):.2f}x"))
        rig.open()
        steps = [Step(rm.Source.LED, i % rm.N_LEDS, 1000, None, 1000, 5000, 100, 1, 0, 1) for i in range(1000)]
        ups = [rig.upload(steps) for _ in range(REPEATS)]
        rig.close()
        wire = wire_time_s(1000)
        rows.append(("upload of 1,000 steps, posix sim", f"{statistics.median(ups) * 1e3:.1f} ms",
                     f"115200-baud wire time {wire * 1e3:.0f} ms", f"{statistics.median(ups) / wire:.2f}x"))
    with SimulatedRig("qemu") as sim:
        rig = RigClient(sim.port, timeout=1.0)
        rig.open()
        c = client_rtt(rig, 100)
        ups = [rig.upload(steps) for _ in range(3)]
        short = [Step(rm.Source.LED, i, 1000, 0 if i == 0 else None, 2000, 8000, 100, 3, 1, 1) for i in range(40)]
        res = rig.run(short, timeout_s=60)
        rig.close()
    st = [e for e in res.events if e.kind == rm.Event.STEP_START]
    en = [e for e in res.events if e.kind == rm.Event.STEP_END]
    q_meas = en[-1].ts_us - st[0].ts_us
    q_sched = schedule(short)[-1].end
    rows.append(("register round trip, QEMU (dualscale client)", f"{statistics.median(c):.3f} ms", "", ""))
    rows.append(("upload of 1,000 steps, QEMU", f"{statistics.median(ups) * 1e3:.1f} ms",
                 f"115200-baud wire time {wire * 1e3:.0f} ms", f"{statistics.median(ups) / wire:.2f}x"))
    rows.append(("sequencer overhead, 40 steps x 3 brackets, QEMU guest clock",
                 f"{100 * (q_meas - q_sched) / q_sched:.4f} %", f"schedule {q_sched / 1e3:.1f} ms", ""))
    reps = [run_demo("posix", speed=0, out=lambda s: None) for _ in range(3)]
    rep = reps[0]
    rows.append(("sequencer overhead, full demo (264 steps), virtual time",
                 f"{statistics.median(x.overhead_pct for x in reps):.4f} %",
                 f"schedule {rep.scheduled_us / 1e6:.3f} s", f"worst event deviation {rep.max_step_dev_us} us"))
    size = subprocess.run(["arm-none-eabi-size", "-A", str(firmware_elf())], capture_output=True, text=True)
    sec = {ln.split()[0]: int(ln.split()[1]) for ln in size.stdout.splitlines()
           if ln.startswith(".") and len(ln.split()) >= 2}
    flash = sec.get(".isr_vector", 0) + sec.get(".text", 0) + sec.get(".rodata", 0) + sec.get(".data", 0)
    ram = sec.get(".data", 0) + sec.get(".bss", 0)
    rows.append(("STM32F405 image: flash / RAM", f"{flash} B / {ram} B",
                 "of 1024 KiB / 128 KiB", f"{100 * flash / 1048576:.1f} % / {100 * ram / 131072:.1f} %"))

    print(f"\nMachine: {platform.node()} {platform.machine()}, {platform.processor() or 'cpu'}, "
          f"Python {sys.version.split()[0]}; date {datetime.date.today()}; medians of "
          f"{N_RTT} round trips / {REPEATS} uploads.\n")
    print("| measurement | value | baseline (same run) | ratio / note |")
    print("|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
