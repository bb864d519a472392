"""Fit speed: the fused kernel against the eager reference (today's `standard`) and `paper`,
side by side in one run, at several map sizes; prints markdown tables for docs/FITTING.md.

    PYTHONPATH=host python bench/bench_fit_speed.py [--sizes 16,64,128,256] [--eager-max 128]
        [--paper-max 32] [--compiled-max 0] [--threads 1] [--material twill] [--json out.json]

`paper` runs through both kernels (Adam's gradient by autograd, or by the fused kernel's
vector-Jacobian product).  Every size is its own synthetic capture (``bench_fit.dataset``: the material at ``size`` x
``size`` texels of 9 um, 127 LEDs x P0/P90 plus the back light, HDR-style sensor noise, every
8th LED held out).  Components are chosen once per size with the fused kernel (timed apart, and
with the eager kernel up to ``--eager-max``).  Per size and kernel: the fit's wall time, its
map errors against the ground truth and the held-out SSIM.  The marginal cost per pixel is the
slope between consecutive sizes (what a bigger map adds); the fixed cost is the time of the
smallest size.  A size above ``--eager-max`` (``--paper-max``) is fitted by the fused kernel
only (paper: not at all): the eager `standard` costs about 5 ms per pixel on this machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch

from bench_fit import dataset
from dualscale.fit import select as select_module
from dualscale.fit.core import fit_observations, split_holdout
from dualscale.fit.metrics import map_errors
from dualscale.fit.presets import PRESETS
from dualscale.threads import set_threads

ERRORS = ("albedo_rmse", "normal_mean_deg", "roughness_mae", "anisotropy_mae", "ior_mae")


def load() -> str:
    return open("/proc/loadavg").read().split()[0]


def select(train, kernel: str):
    """Component selection with ``kernel`` (it fits short `standard` runs per hypothesis)."""
    saved = select_module.PRESETS
    select_module.PRESETS = {**saved, "standard": replace(saved["standard"], kernel=kernel)}
    try:
        t0 = time.perf_counter()
        comps, _ = select_module.select_components(train)
        return comps, time.perf_counter() - t0
    finally:
        select_module.PRESETS = saved


def run(sizes: list[int], material: str, eager_max: int, paper_max: int, compiled_max: int = 0,
        threads: int = 1) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm, _ = dataset(Path(tmp) / "warm", "leather", 8, 9.0)  # numba cache, thread pools, allocator
        set_threads(threads)
        for k in ("fused", "eager"):
            fit_observations(warm, replace(PRESETS["standard"], kernel=k).scaled(0.05),
                             select(warm, "fused")[0])
        for size in sizes:
            obs, gt = dataset(Path(tmp) / f"{material}{size}", material, size, 9.0)
            set_threads(threads)  # the in-process `synth` command applied its own (--threads auto)
            train, held = split_holdout(obs, 8)
            comps, t_sel = select(train, "fused")
            t_sel_eager = select(train, "eager")[1] if size <= eager_max else None
            runs = [("standard", "fused")] + ([("standard", "eager")] if size <= eager_max else []) + \
                   ([("standard", "compiled")] if size <= compiled_max else []) + \
                   ([("paper", "eager"), ("paper", "fused")] if size <= paper_max else [])
            for preset, kernel in runs:
                p = replace(PRESETS[preset], kernel=kernel)
                res = fit_observations(train, p, comps, held_out=held)
                err = map_errors(res.maps, gt, comps.ior)
                rows.append({"size": size, "preset": preset, "kernel": kernel, "seconds": res.seconds,
                             "selection_seconds": t_sel if kernel == "fused" else t_sel_eager,
                             "heldout_ssim": res.losses["heldout_ssim"], "load": load(),
                             **{k: err[k] for k in ERRORS}})
                print(f"  {size:4d}^2 {preset:8s} {kernel:6s} {res.seconds:8.1f} s  load {load()}  "
                      + "  ".join(f"{k} {err[k]:.4f}" for k in ERRORS), flush=True)
    return {"machine": f"{platform.node()} {platform.machine()} {platform.processor() or ''}".strip(),
            "threads": torch.get_num_threads(), "date": date.today().isoformat(), "material": material, "rows": rows}


def tables(rep: dict) -> str:
    rows = rep["rows"]
    out = [f"Machine: {rep['machine']}, {rep['threads']} thread(s); date {rep['date']}; material "
           f"{rep['material']}, 9 um texels, 127 LEDs x P0/P90 + back light, every 8th LED held out, sensor noise; "
           "load average (1 min) per row.", "",
           "| size | preset | kernel | fit [s] | per pixel [ms] | selection [s] | " + " | ".join(ERRORS)
           + " | held-out SSIM | load |", "|---:|---|---|---:|---:|---:|" + "---:|" * (len(ERRORS) + 2)]
    for r in rows:
        sel = f"{r['selection_seconds']:.1f}" if r["selection_seconds"] is not None else "-"
        out.append(f"| {r['size']}² | {r['preset']} | {r['kernel']} | {r['seconds']:.1f} | "
                   f"{1e3 * r['seconds'] / r['size'] ** 2:.3f} | {sel} | "
                   + " | ".join(f"{r[k]:.4f}" for k in ERRORS) + f" | {r['heldout_ssim']:.4f} | {r['load']} |")
    by = {(r["size"], r["preset"], r["kernel"]): r for r in rows}
    sizes = sorted({r["size"] for r in rows})
    out += ["", "Ratios in this run (eager `standard` / fused `standard`; `standard` / `paper`), and the map errors "
            "of the fused fit relative to the eager one (1.00 = equal, < 1 = better):", "",
            "| size | eager / fused time | fused / paper time | eager / paper time | paper: eager / fused time | "
            + " | ".join(f"{k} fused/eager" for k in ERRORS) + " |", "|---:|---:|---:|---:|---:|" + "---:|" * len(ERRORS)]
    for s in sizes:
        f, e, p = by.get((s, "standard", "fused")), by.get((s, "standard", "eager")), by.get((s, "paper", "eager"))
        pf = by.get((s, "paper", "fused"))
        cells = [f"{e['seconds'] / f['seconds']:.1f}" if e else "-", f"1/{p['seconds'] / f['seconds']:.0f}" if p else "-",
                 f"1/{p['seconds'] / e['seconds']:.0f}" if (p and e) else "-",
                 f"{p['seconds'] / pf['seconds']:.1f}" if (p and pf) else "-"]
        cells += [f"{f[k] / e[k]:.2f}" if (e and e[k] > 0) else "-" for k in ERRORS]
        out.append(f"| {s}² | " + " | ".join(cells) + " |")
    out += ["", "Marginal cost per pixel (slope between consecutive sizes) and fixed cost (the smallest size):", "",
            "| sizes | fused [ms/pixel] | eager [ms/pixel] | eager / fused |", "|---|---:|---:|---:|"]
    for a, b in zip(sizes, sizes[1:]):
        def slope(kernel: str) -> float | None:
            ra, rb = by.get((a, "standard", kernel)), by.get((b, "standard", kernel))
            return None if not (ra and rb) else 1e3 * (rb["seconds"] - ra["seconds"]) / (b * b - a * a)
        sf, se = slope("fused"), slope("eager")
        out.append(f"| {a}² → {b}² | {sf:.3f} | " + (f"{se:.3f} | {se / sf:.1f} |" if se else "- | - |"))
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="16,64,128,256")
    ap.add_argument("--eager-max", type=int, default=128)
    ap.add_argument("--paper-max", type=int, default=32)
    ap.add_argument("--compiled-max", type=int, default=0,
                    help="also fit `standard` through the torch.compile'd eager reference up to this size")
    ap.add_argument("--material", default="twill")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    set_threads(a.threads)
    rep = run([int(s) for s in a.sizes.split(",")], a.material, a.eager_max, a.paper_max, a.compiled_max, a.threads)
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))
    print(tables(rep))


if __name__ == "__main__":
    main()
