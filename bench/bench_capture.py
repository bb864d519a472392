"""`dualscale capture` on the simulated rig: time against the physical floor, link faults, and
kill -9 resumes (issue 14 "Measure"; docs/CAPTURE.md).

The virtual rig: the POSIX firmware simulator (the real C core) behind its pty, its hardware
side channel driving a simulated micro camera (``sim:micro``, leather, 12 px so that rendering
never limits the rate), the micro plan (LEDs at P0 and P90, back light).

1. **Floor** -- the simulator at real time (speed 1): the wall time of the capture sequences
   (upload, start, every exposure, collecting and writing the frames) against the physical floor
   of the same plan, Σ (settle + servo + exposure + readout gap) over its steps as the
   device-master schedule (PROTOCOL.md §3.1) gives it.  Metering is reported beside it.
2. **Link faults** -- a corrupting pty proxy between host and simulator (tests/rig/linkproxy.py,
   each byte XORed with a random byte with probability p, both ways), speed 10, noise off: every
   run's dataset is compared with a clean run's, file by file and pixel by pixel; a frame lost
   or doubled shows as a missing, extra or different image, and the journal is checked for
   duplicate shots.
3. **Resume** -- ``dualscale capture`` killed with SIGKILL (its whole process group: host,
   simulator) at a random moment, then rerun with ``--resume``; the dataset is compared with an
   uninterrupted one.

Prints markdown tables with the machine, its load (``uptime``) and the date.  Usage:
``.venv/bin/python bench/bench_capture.py [--floor-lights MOD16] [--fault-runs 10] [--kills 10]``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dualscale.sim.camera  # noqa: E402,F401  registers sim:
from dualscale.capture.camera import open_camera  # noqa: E402
from dualscale.capture.plan import make_plan  # noqa: E402
from dualscale.capture.session import CaptureOptions, CaptureSession  # noqa: E402
from dualscale.formats.dataset import read_dataset  # noqa: E402
from dualscale.rig.client import RigClient  # noqa: E402
from dualscale.rig.demo import demo_watchdog_ms  # noqa: E402
from dualscale.rig.launcher import SimulatedRig  # noqa: E402
from tests.rig.linkproxy import LinkProxy  # noqa: E402

CAM = "sim:micro?material=leather&size=12&texel_um=9&readout_ms=1&noise=0"


def capture(out: Path, lights: str, speed: float, corrupt: float = 0.0, seed: int = 0) -> dict:
    with tempfile.TemporaryDirectory() as td, SimulatedRig("posix", speed=speed, hw_socket=Path(td) / "hw") as sim:
        cam = open_camera(f"{CAM}&hw={Path(td) / 'hw'}")
        try:
            if corrupt:
                proxy = LinkProxy(sim.port, corrupt=corrupt, seed=seed)
                port = proxy.port
            else:
                proxy, port = None, sim.port
            rig = RigClient(port)
            rig.open()
            opts = CaptureOptions(rig_id="virtual-dome-0", watchdog_ms=demo_watchdog_ms(speed))
            s = CaptureSession(rig, {"micro": cam}, make_plan("micro", lights), out, opts).run()
            rig.close()
            corrupted = 0
            if proxy:
                corrupted = proxy.corrupted
                proxy.close()
            return {"summary": s, "reconnects": s.link_reconnects, "corrupted": corrupted}
        finally:
            cam.close()


def compare(a: Path, b: Path) -> tuple[int, int, int]:
    """(images missing from b, extra in b, images that differ)."""
    da, db = read_dataset(a), read_dataset(b)
    fa, fb = {r.file: i for i, r in enumerate(da.records)}, {r.file: i for i, r in enumerate(db.records)}
    diff = sum(1 for f in set(fa) & set(fb) if not np.array_equal(da.load(fa[f]), db.load(fb[f])))
    return len(set(fa) - set(fb)), len(set(fb) - set(fa)), diff


def journal_duplicates(out: Path) -> int:
    keys = [json.loads(ln)["key"] for ln in (out / "journal.jsonl").read_text().splitlines()
            if ln.strip() and json.loads(ln)["kind"] == "shot"]
    return len(keys) - len(set(keys))


def header() -> str:
    load = os.getloadavg()
    return (f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, load "
            f"{load[0]:.2f}/{load[1]:.2f}/{load[2]:.2f}, {datetime.date.today().isoformat()}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--floor-lights", default="MOD16")
    ap.add_argument("--fault-lights", default="MOD32")
    ap.add_argument("--fault-runs", type=int, default=10)
    ap.add_argument("--heavy-runs", type=int, default=3)
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--kill-lights", default="MOD16")
    ap.add_argument("--parts", default="floor,faults,kills")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-capture-"))
    print(f"### capture on the simulated rig ({header()})\n")

    parts = a.parts.split(",")
    ref = tmp / "ref"
    if "floor" in parts:
        floor(tmp, a.floor_lights)
    if "faults" in parts:
        capture(ref, a.fault_lights, 10.0)
        faults(tmp, ref, a)
    if "kills" in parts:
        kills(tmp, a)


def floor(tmp: Path, lights: str) -> None:
    r = capture(tmp / "floor", lights, 1.0)["summary"]
    over = r.capture_wall_s / r.floor_s - 1
    print(f"| plan (speed 1) | shots | frames | physical floor | capture | over the floor | device time "
          f"of the capture sequences | metering |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| micro {lights} | {r.shots} | {r.frames} | {r.floor_s:.2f} s | {r.capture_wall_s:.2f} s | "
          f"{100 * over:+.1f} % | {r.capture_device_s:.2f} s | {r.meter_wall_s:.2f} s |\n")


def faults(tmp: Path, ref: Path, a: argparse.Namespace) -> None:
    print("| corruption per byte | runs completed | bytes corrupted (median) | frames lost | frames doubled | "
          "images differing | shots taken again (median) | reconnects (median) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for p, runs in ((1e-3, a.fault_runs), (1e-2, a.heavy_runs)):
        done = lost = extra = differ = 0
        retakes, recon, bad = [], [], []
        for k in range(runs):
            out = tmp / f"fault-{p:g}-{k}"
            try:
                res = capture(out, a.fault_lights, 10.0, corrupt=p, seed=k)
            except Exception as e:  # noqa: BLE001 - a failed run is a result of the benchmark
                print(f"<!-- p={p:g} run {k}: {type(e).__name__}: {e} -->")
                continue
            done += 1
            m, x, d = compare(ref, out)
            lost += m
            extra += x + journal_duplicates(out)
            differ += d
            retakes.append(res["summary"].retakes)
            recon.append(res["reconnects"])
            bad.append(res["corrupted"])
        print(f"| {p:g} | {done}/{runs} | {statistics.median(bad) if bad else '-'} | {lost} | {extra} | {differ} | "
              f"{statistics.median(retakes) if retakes else '-'} | {statistics.median(recon) if recon else '-'} |")
    print()


def kills(tmp: Path, a: argparse.Namespace) -> None:
    ref = tmp / "ref-kills"
    capture(ref, a.kill_lights, 10.0)
    cmd = [sys.executable, "-m", "dualscale.cli", "capture", "micro", "-o", "", "--port", "sim", "--camera", CAM,
           "--lights", a.kill_lights, "--rig-id", "virtual-dome-0", "--sim-speed", "10", "--no-progress"]
    rng = np.random.default_rng(1)
    same = killed = 0
    delays = []
    for k in range(a.kills):
        out = tmp / f"kill-{k}"
        c = list(cmd)
        c[c.index("-o") + 1] = str(out)
        t0 = time.monotonic()
        p = subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                             cwd=ROOT)
        delay = float(rng.uniform(0.5, 8.0))
        delays.append(delay)
        try:
            p.wait(delay)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            killed += 1
        done = subprocess.run(c + ["--resume"], capture_output=True, text=True, cwd=ROOT)
        rc = done.returncode
        if rc == 0 and compare(ref, out) == (0, 0, 0) and journal_duplicates(out) == 0:
            same += 1
        else:
            why = compare(ref, out) if rc == 0 else (done.stderr.strip().splitlines() or ["?"])[-1]
            print(f"<!-- kill {k} after {delay:.1f} s: rc {rc}: {why} -->")
        _ = time.monotonic() - t0
    print(f"| kill -9 at a random moment 0.5-8 s after the start of a {a.kill_lights} capture (speed 10), then "
          f"--resume | killed before the end | resumed datasets identical to an uninterrupted one |")
    print("|---|---:|---:|")
    print(f"| {a.kills} runs | {killed} | {same}/{a.kills} |")


if __name__ == "__main__":
    main()
