"""GenICam backend throughput against Aravis's GigE Vision emulator (issue 14, docs/CAPTURE.md).

Starts ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (none may be running already), opens it through
``genicam:SERIAL``, and for each configured ``AcquisitionFrameRate`` free-runs ``frames`` frames
of 512x512 into a pool of as many buffers, then prints delivered frames per second (from the
device timestamps), dropped frames (gaps in the frame ids: incomplete frames or no free buffer) and the
machine/load/date.  Usage: ``.venv/bin/python bench/bench_genicam.py [--seconds 1.0]``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import time

from dualscale.capture.camera import open_camera
from dualscale.capture.genicam import list_devices


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--rates", default="25,100,250,500,1000")
    ap.add_argument("--format", default="Mono8")
    a = ap.parse_args()
    fake = shutil.which("arv-fake-gv-camera-0.8")
    if fake is None:  # `make bench` runs every bench: say why this one has no table, and go on
        print("bench_genicam: skipped: arv-fake-gv-camera-0.8 not installed (Debian aravis-tools)")
        return
    serial = f"BENCH{os.getpid()}"
    proc = subprocess.Popen([fake, "-i", "127.0.0.1", "-s", serial], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        time.sleep(0.5)
        list_devices()
        cam = open_camera(f"genicam:{serial}?pixel_format={a.format}")
        s = cam.sensor()
        print(f"# GenICam bench: {platform.node()} {platform.machine()} {os.cpu_count()} cores, "
              f"load {os.getloadavg()[0]:.2f}, {datetime.datetime.now().isoformat(timespec='seconds')}, "
              f"{s.width}x{s.height} {s.pixel_format}, {a.seconds:g} s per rate")
        print("| configured fps | frames | delivered fps | dropped (frame-id gaps) | incomplete frames | no-buffer packets |")
        print("|---:|---:|---:|---:|---:|---:|")
        for rate in (float(r) for r in a.rates.split(",")):
            cam.set_frame_rate(rate)
            n = min(1000, max(5, int(rate * a.seconds)))  # pool of n 512x512 buffers
            cam.prepare_free_run(n, 0.0005, timeout_s=a.seconds * 3 + 2)
            cam.arm()
            try:
                frames = cam.collect()
            except Exception as e:  # CameraTimeout: report what came
                frames = getattr(e, "frames", [])
            st = cam.stats()
            cam.disarm()
            ids = [f.metadata["frame_id"] for f in frames]
            gaps = sum((b - a_ - 1) % 65535 for a_, b in zip(ids, ids[1:]))  # GVSP block ids run 1..65535
            fps = (len(frames) - 1) / (frames[-1].timestamp_s - frames[0].timestamp_s) if len(frames) > 1 else 0.0
            print(f"| {rate:g} | {len(frames)}/{n} | {fps:.1f} | {gaps} | {st['failures']} | "
                  f"{st['underrun_packets']} |")
        cam.close()
    finally:
        proc.kill()
        proc.wait()


if __name__ == "__main__":
    main()
