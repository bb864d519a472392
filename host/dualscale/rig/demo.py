"""The micro-capture run on the simulated rig, with its timing report (`dualscale demo`)."""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

from dualscale.errors import RigError

from ..protocol import regmap as rm
from .client import DEFAULT_PARITY, DEFAULT_WATCHDOG_MS, RigClient, RunResult
from .sequence import CapturePlan, Step, schedule
from .launcher import SimulatedRig


@dataclass
class TimingReport:
    steps: int
    events: int
    scheduled_us: int  # Σ settle + exposures (+ frame gaps): the schedule
    measured_us: int  # device time from the first STEP_START to the last STEP_END
    max_step_dev_us: int  # worst |event time − schedule| over STEP_START/TRIGGER/STEP_END
    upload_s: float
    rtt_ms_median: float
    rtt_ms_p95: float
    wall_s: float
    dropped: int
    state: str

    @property
    def overhead_pct(self) -> float:
        return 100.0 * (self.measured_us - self.scheduled_us) / self.scheduled_us

    def format(self) -> str:
        rows = [
            ("steps", f"{self.steps}"),
            ("events", f"{self.events} (dropped {self.dropped})"),
            ("final state", self.state),
            ("scheduled (settle+exposure)", f"{self.scheduled_us / 1e6:.6f} s"),
            ("measured on the device clock", f"{self.measured_us / 1e6:.6f} s"),
            ("sequencer overhead", f"{self.overhead_pct:.4f} %"),
            ("worst event deviation", f"{self.max_step_dev_us} us"),
            ("upload", f"{self.upload_s * 1e3:.1f} ms"),
            ("register round trip", f"median {self.rtt_ms_median:.2f} ms, p95 {self.rtt_ms_p95:.2f} ms"),
            ("wall time of the run", f"{self.wall_s:.2f} s"),
        ]
        w = max(len(k) for k, _ in rows)
        return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)


def measure_rtt(rig: RigClient, n: int = 50) -> list[float]:
    """Round-trip times (ms) of single-register reads."""
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        rig.read_input(rm.IR.STATE, 1)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def timing_report(steps: list[Step], res: RunResult, upload_s: float, rtt: list[float],
                  frame_gap_us: int = 0, dropped: int = 0) -> TimingReport:
    sched = schedule(steps, frame_gap_us)
    starts = [e for e in res.events if e.kind == rm.Event.STEP_START]
    ends = [e for e in res.events if e.kind == rm.Event.STEP_END]
    trig = [e for e in res.events if e.kind == rm.Event.TRIGGER]
    if not starts or not ends:
        raise RigError("the run produced no step events")
    t0 = starts[0].ts_us
    dev = 0
    for e in starts:
        dev = max(dev, abs(e.ts_us - t0 - sched[e.step].start))
    for e in ends:
        dev = max(dev, abs(e.ts_us - t0 - sched[e.step].end))
    for e in trig:
        dev = max(dev, abs(e.ts_us - t0 - sched[e.step].brackets[e.arg]))
    q = statistics.quantiles(rtt, n=20)
    return TimingReport(len(steps), len(res.events), sched[-1].end, ends[-1].ts_us - t0, dev,
                        upload_s, statistics.median(rtt), q[18], res.wall_s, dropped, res.state.name)


def demo_watchdog_ms(speed: float) -> int:
    """The host watchdog for a demo run, in device milliseconds: DEFAULT_WATCHDOG_MS of real
    time (the simulator's device clock runs `speed` times faster than real time; speed 0 jumps
    from deadline to deadline, so it gets the longest period the register takes)."""
    if speed <= 0:
        return rm.WATCHDOG_MS_MAX
    return int(min(rm.WATCHDOG_MS_MAX, max(rm.WATCHDOG_MS_MIN, DEFAULT_WATCHDOG_MS * max(1.0, speed))))


def run_demo(target: str = "posix", speed: float = 10.0, out=print,
             on_event=None, parity: str = DEFAULT_PARITY, stopbits: int | None = None) -> TimingReport:
    """Start the simulated rig, upload the full micro-capture sequence, run it under the host
    watchdog (`demo_watchdog_ms`), report. `parity`/`stopbits`: the serial format of the
    simulated rig and of the client (PROTOCOL.md §1)."""
    with SimulatedRig(target, speed=speed, parity=parity, stop_bits=stopbits) as sim:
        out(f"simulated rig ({target}, speed {speed:g}x) on {sim.port}")
        with RigClient(sim.port, parity=parity, stopbits=stopbits) as rig:
            ident = rig.identity
            out(f"connected: {ident.text}")
            rtt = measure_rtt(rig)
            plan = CapturePlan()
            steps = plan.build(rig.status().polarizer_cdeg)
            n_led = sum(1 for s in steps if s.source == rm.Source.LED)
            out(f"plan: {n_led} LED steps ({len(plan.leds)} LEDs x {len(plan.modes_cdeg)} analyzer modes), "
                f"+ diffuse and {len(plan.backlights)} back lights per mode = {len(steps)} steps, "
                f"{plan.brackets} HDR brackets each")
            upload_s = rig.upload(steps)
            wd = demo_watchdog_ms(speed)
            out(f"host watchdog: {wd} ms of device time (every light off that long after this host stops)")
            res = rig.run(on_event=on_event, watchdog_ms=wd)
            st = rig.status()
            rep = timing_report(steps, res, upload_s, rtt, dropped=st.evt_dropped)
    out("timing report")
    out(rep.format())
    return rep
