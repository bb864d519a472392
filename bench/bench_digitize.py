"""`dualscale digitize` benchmark: prints the markdown tables of docs/DIGITIZE.md.

    PYTHONPATH=host python bench/bench_digitize.py [--work /tmp/digitizebench] [--size 48]
        [--qualities draft standard paper] [--threads 1] [--demo]

For each ``--quality`` preset, on one synthetic twill of the virtual rig (micro: ``--size``^2
texels of 9 um, all 127 LEDs x P0/P90, renderer radiance; guidance: the same twill at 6.25 um per
pixel over three times the micro field, so the micro field spans about 70 guidance pixels):
time per stage, and error per stage against the ground truth (fit: map errors and held-out
relative L1; fly-outs: precision/recall against the true fibres; propagation: map errors of the
propagated maps against ``generate(material, mid_size, mid_texel)``), with the ratio of each to
``paper`` from the same run.  ``--demo`` times ``make demo``'s digitize (the run folder of the demo,
its stage records) instead.  Machine, load average and date are printed with the tables.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "host"))

MATERIAL = "twill"
TEXEL_UM = 9.0


def sh(*args: str) -> float:
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    subprocess.run([sys.executable, "-m", "dualscale.cli", *args], check=True, stdout=subprocess.DEVNULL, env=env)
    return time.perf_counter() - t0


def machine() -> str:
    load = open("/proc/loadavg").read().split()[:3]
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"load average {' '.join(load)}, {date.today().isoformat()}")


def prepare(work: Path, size: int) -> Path:
    sample = work / f"sample{size}"
    if not (sample / "mid" / "manifest.json").is_file():
        mid_field = 3 * size * TEXEL_UM / 1000
        mid_size = int(round(mid_field / 0.00625))
        sh("synth", MATERIAL, "-o", str(sample), "--size", str(size), "--texel-um", str(TEXEL_UM), "--dataset",
           "--mid", "--mid-size", str(mid_size), "--mid-field-mm", f"{mid_field:.6f}", "--no-previews",
           "--no-progress")
    return sample


def errors(sample: Path, run: Path) -> dict[str, dict]:
    """Error of each stage against the synthetic ground truth."""
    from dualscale.fit.metrics import map_errors
    from dualscale.fit.flyouts import score
    from dualscale.formats.flyouts import read_flyouts
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.metrics import compare
    from dualscale.sim.materials import generate

    out: dict[str, dict] = {}
    rec = {s: json.loads((run / "stages" / f"{s}.json").read_text()) for s in
           ("calibrate", "fit", "flyouts", "propagate", "export", "report")}
    gt, _ = load_maps(sample / "maps")
    fit, _ = load_maps(run / "fit" / "maps")
    comps = rec["fit"]["summary"]["components"]
    e = map_errors(fit, gt, comps.get("ior", 1.5))
    e["heldout_relative_l1"] = rec["fit"]["summary"]["heldout_relative_l1"]
    out["fit"] = e
    if (run / "flyouts" / "flyouts.json").is_file() and (sample / "maps" / "flyouts.json").is_file():
        _, det = read_flyouts(run / "flyouts")
        _, truth = read_flyouts(sample / "maps")
        out["flyouts"] = score(det, truth)
    if (run / "propagate" / "maps" / "material.json").is_file():
        pm, meta = load_maps(run / "propagate" / "maps")
        h, w = pm.shape
        mid = generate(MATERIAL, h, meta["texel_mm"], 0).maps
        pred = {k: v.numpy() for k, v in pm.items()}
        truth = {k: v.numpy() for k, v in mid.items() if k in pred}
        out["propagate"] = {"per_map": compare(pred, truth)}
    out["seconds"] = {s: r["seconds"] for s, r in rec.items()}
    return out


def table(results: dict[str, dict]) -> str:
    qs = list(results)
    ref = results.get("paper")
    rows = ["| quality | " + " | ".join(f"{s} s" for s in ("calibrate", "fit", "flyouts", "propagate", "export",
                                                                 "report")) + " | total s | ratio to paper |",
            "|---|" + "---:|" * 8]
    for q in qs:
        s = results[q]["seconds"]
        tot = sum(s.values())
        ratio = "" if ref is None else f"{tot / sum(ref['seconds'].values()):.3f}"
        rows.append(f"| {q} | " + " | ".join(f"{s[k]:.1f}" for k in s) + f" | {tot:.1f} | {ratio} |")
    rows += ["", "| quality | normal mean deg | albedo RMSE | roughness MAE | held-out rel. L1 | fly-out P / R "
             "| propagated albedo L1 | propagated roughness L1 |", "|---|" + "---:|" * 7]
    for q in qs:
        f = results[q]["fit"]
        fo = results[q].get("flyouts")
        pm = results[q].get("propagate", {}).get("per_map", {})

        def r(v: float | None, key: str, sub: str | None = None) -> str:
            if v is None:
                return "n/a"
            if ref is None or q == "paper":
                return f"{v:.4g}"
            rv = ref["fit"].get(key) if sub is None else ref.get("propagate", {}).get("per_map", {}).get(key, {}).get(sub)
            return f"{v:.4g} ({v / rv:.2f}x)" if rv else f"{v:.4g}"

        rows.append(f"| {q} | {r(f.get('normal_mean_deg'), 'normal_mean_deg')} | {r(f.get('albedo_rmse'), 'albedo_rmse')}"
                    f" | {r(f.get('roughness_mae'), 'roughness_mae')} | {r(f.get('heldout_relative_l1'), 'heldout_relative_l1')}"
                    f" | {'n/a' if fo is None else '%.2f / %.2f' % (fo['precision'], fo['recall'])}"
                    f" | {r(pm.get('albedo', {}).get('l1'), 'albedo', 'l1')}"
                    f" | {r(pm.get('roughness', {}).get('l1'), 'roughness', 'l1')} |")
    return "\n".join(rows)


def demo_table(run: Path) -> str:
    rows = ["| stage | seconds | note |", "|---|---:|---|"]
    tot = 0.0
    for s in ("calibrate", "fit", "flyouts", "propagate", "export", "report"):
        r = json.loads((run / "stages" / f"{s}.json").read_text())
        tot += r["seconds"]
        note = r["summary"].get("skipped", "") or (f"preset {r['summary'].get('preset')}" if s == "fit" else "")
        rows.append(f"| {s} | {r['seconds']:.1f} | {note} |")
    rows.append(f"| **total** | **{tot:.1f}** | |")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/digitizebench"))
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--qualities", nargs="*", default=["draft", "standard", "paper"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--demo", type=Path, default=None, metavar="RUN", help="tabulate a finished demo run folder")
    a = ap.parse_args()
    print(f"machine: {machine()}\n")
    if a.demo is not None:
        print(demo_table(a.demo))
        return 0
    sample = prepare(a.work, a.size)
    results = {}
    for q in a.qualities:
        run = a.work / f"run{a.size}_{q}"
        sh("digitize", str(sample / "micro"), "-o", str(run), "--guidance", str(sample / "mid"), "--quality", q,
           "--threads", str(a.threads), "--no-progress")
        results[q] = errors(sample, run)
    print(f"twill {a.size}^2 texels of {TEXEL_UM} um, all LEDs, {a.threads} thread(s); ratio = quality / paper\n")
    print(table(results))
    (a.work / f"results{a.size}.json").write_text(json.dumps(results, indent=1, default=str))
    print(f"\nmachine at the end: {machine()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
