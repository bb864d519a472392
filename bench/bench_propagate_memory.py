"""Peak memory and time per step of ``dualscale propagate train`` against the micro size
(issue 25 Sec. 4; docs/PROPAGATION.md, "Memory at the micro size").

For each size it synthesises ``twill --size N --dataset`` once (kept in ``--work``), then trains
a few steps in a child process under ``/usr/bin/time -v`` three ways: ``before`` (the whole
source in memory, forced with ``DUALSCALE_PROPAGATE_IN_MEMORY_MB=1e12``: the loader of before
this change), ``after`` (the default threshold) and ``disk`` (always from disk, ``=0``).
Prints a markdown table.

    PYTHONPATH=host python bench/bench_propagate_memory.py --sizes 256,512,1024 --iterations 5
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = {"before": "1e12", "after": None, "disk": "0"}


def dualscale() -> list[str]:
    exe = ROOT / ".venv" / "bin" / "dualscale"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "dualscale.cli"]


def run(size: int, mode: str, work: Path, iterations: int, batch: int) -> dict:
    src = work / f"s{size}"
    if not (src / "maps" / "material.json").is_file():
        subprocess.run(dualscale() + ["synth", "twill", "--size", str(size), "-o", str(src), "--dataset",
                                      "--no-previews", "--threads", "1", "--no-progress"], check=True)
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    env.pop("DUALSCALE_PROPAGATE_IN_MEMORY_MB", None)
    if MODES[mode] is not None:
        env["DUALSCALE_PROPAGATE_IN_MEMORY_MB"] = MODES[mode]
    out = work / "runs" / f"m{size}_{mode}" / "m.dsp"  # a folder of its own (no --overwrite near the data)
    out.parent.mkdir(parents=True, exist_ok=True)
    for p in (out, Path(str(out) + ".ckpt")):
        p.unlink(missing_ok=True)
    cmd = ["/usr/bin/time", "-v"] + dualscale() + [
        "propagate", "train", str(src), "-o", str(out), "--iterations", str(iterations), "--batch", str(batch),
        "--threads", "1", "--no-amp", "--checkpoint-every", "1000000", "--no-progress"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr).group(1)) / 1024
    secs = float(re.search(r"([\d.]+) s this run", r.stdout).group(1))
    return {"size": size, "mode": mode, "peak_mib": rss, "wall_s": wall, "train_s": secs,
            "s_per_step": secs / iterations}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="256,512,1024")
    ap.add_argument("--modes", default="before,after,disk")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--work", default="/tmp/bench_propagate_memory")
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for n in (int(v) for v in a.sizes.split(",")):
        for m in a.modes.split(","):
            rows.append(run(n, m, work, a.iterations, a.batch))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(f"load: {os.getloadavg()[0]:.2f}")
    print("| micro size | mode | peak RSS [MiB] | / before | train [s/step] | wall [s] |")
    print("|---|---|---:|---:|---:|---:|")
    before = {r["size"]: r["peak_mib"] for r in rows if r["mode"] == "before"}
    for r in rows:
        ratio = f"{r['peak_mib'] / before[r['size']]:.2f}" if r["size"] in before else "-"
        print(f"| {r['size']}² | {r['mode']} | {r['peak_mib']:.0f} | {ratio} | {r['s_per_step']:.2f} | "
              f"{r['wall_s']:.1f} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
