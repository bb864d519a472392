"""GenICam backend throughput against Aravis's GigE Vision emulator (issue 14, docs/CAPTURE.md).

Starts ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (none may be running already: every emulator
binds 127.0.0.1:3956), opens it through ``genicam:127.0.0.1`` and measures, for each configured
``AcquisitionFrameRate``, ``--repeats`` free-running acquisitions of ``--seconds`` each into a
pool of as many buffers as frames (512x512, ``--format``):

* delivered fps: (frames - 1) / (last - first device timestamp);
* sent: the frames the camera numbered over that span (GVSP block ids, last - first + 1);
* dropped: sent - delivered (frames damaged in transfer or that never arrived: block-id gaps,
  plus Aravis's failures);

then one row of software-triggered acquisitions (``trigger()`` after each frame: the emulator
looks at its trigger register on a fixed 25 Hz tick).  Each cell is the median of the repeats
(min-max in brackets where they differ).  Prints a markdown table with the machine, its load
(``uptime``) and the date.  Usage: ``.venv/bin/python bench/bench_genicam.py [--seconds 1]
[--repeats 5] [--rates 25,100,250,500,1000] [--format Mono8]``.
"""

from __future__ import annotations

import argparse
import ctypes
import datetime
import os
import platform
import shutil
import signal
import statistics
import subprocess
import time

from dualscale.capture.camera import TriggerInfo, TriggerMode, open_camera
from dualscale.errors import CameraTimeout


def _die_with_parent() -> None:
    """In the emulator's process: SIGKILL when the bench dies (PR_SET_PDEATHSIG)."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)


def _gvcp_bound() -> bool:
    with open("/proc/net/udp") as f:
        return any(line.split()[1] == "0100007F:0F74" for line in list(f)[1:])


def _cell(values: list[float], fmt: str) -> str:
    med = statistics.median(values)
    lo, hi = min(values), max(values)
    return fmt.format(med) + ("" if lo == hi else f" [{fmt.format(lo)}-{fmt.format(hi)}]")


def _free_run(cam, rate: float, seconds: float) -> tuple[float, int, int]:
    """One free-running acquisition: (delivered fps, frames delivered, frames dropped)."""
    cam.set_frame_rate(rate)
    n = min(1000, max(5, int(rate * seconds)))
    cam.prepare_free_run(n, 0.0005, timeout_s=seconds * 3 + 2)
    cam.arm()
    try:
        frames = cam.collect()
    except CameraTimeout as e:  # report what came
        frames = e.frames
    st = cam.stats()
    cam.disarm()
    if len(frames) < 2:
        return 0.0, len(frames), st["dropped"]
    ids = [f.metadata["frame_id"] for f in frames]
    sent = (ids[-1] - ids[0]) % 65535 + 1  # GVSP block ids run 1..65535
    fps = (len(frames) - 1) / (frames[-1].timestamp_s - frames[0].timestamp_s)
    return fps, len(frames), sent - len(frames)


def _triggered(cam, n: int) -> tuple[float, int, int]:
    """One software-triggered acquisition of ``n`` frames: (fps, delivered, dropped)."""
    cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=n, exposure_s=0.0005, timeout_s=n * 0.2 + 5))
    cam.arm()
    try:
        for _ in range(n):
            cam.trigger()
        frames = cam.collect()
    except CameraTimeout as e:
        frames = e.frames
    cam.disarm()
    fps = (len(frames) - 1) / (frames[-1].timestamp_s - frames[0].timestamp_s) if len(frames) > 1 else 0.0
    return fps, len(frames), n - len(frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rates", default="25,100,250,500,1000")
    ap.add_argument("--triggers", type=int, default=20, help="frames per software-triggered acquisition")
    ap.add_argument("--format", default="Mono8")
    a = ap.parse_args()
    fake = shutil.which("arv-fake-gv-camera-0.8")
    if fake is None:  # `make bench` runs every bench: say why this one has no table, and go on
        print("bench_genicam: skipped: arv-fake-gv-camera-0.8 not installed (Debian aravis-tools)")
        return
    if _gvcp_bound():
        print("bench_genicam: skipped: another GigE Vision emulator holds 127.0.0.1:3956")
        return
    serial = f"BENCH{os.getpid()}"
    proc = subprocess.Popen([fake, "-i", "127.0.0.1", "-s", serial], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, preexec_fn=_die_with_parent)
    try:
        end = time.monotonic() + 5
        while not _gvcp_bound() and time.monotonic() < end:
            time.sleep(0.01)
        cam = open_camera(f"genicam:127.0.0.1?pixel_format={a.format}")
        s = cam.sensor()
        up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
        print(f"# GenICam bench: {platform.node()} {platform.machine()} {os.cpu_count()} cores, "
              f"{datetime.datetime.now().isoformat(timespec='minutes')}, uptime: {up}; "
              f"{s.width}x{s.height} {s.pixel_format}, {a.seconds:g} s per run, median of {a.repeats} runs "
              "[min-max]")
        print("| configured fps | delivered fps | frames delivered | dropped frames |")
        print("|---:|---:|---:|---:|")
        for rate in (float(r) for r in a.rates.split(",")):
            runs = [_free_run(cam, rate, a.seconds) for _ in range(a.repeats)]
            print(f"| {rate:g} | {_cell([r[0] for r in runs], '{:.1f}')} | "
                  f"{_cell([r[1] for r in runs], '{:.0f}')} | {_cell([r[2] for r in runs], '{:.0f}')} |")
        runs = [_triggered(cam, a.triggers) for _ in range(a.repeats)]
        print(f"| software trigger, {a.triggers} frames | {_cell([r[0] for r in runs], '{:.1f}')} | "
              f"{_cell([r[1] for r in runs], '{:.0f}')} | {_cell([r[2] for r in runs], '{:.0f}')} |")
        print(f"# end: uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
        cam.close()
    finally:
        proc.kill()
        proc.wait()


if __name__ == "__main__":
    main()
