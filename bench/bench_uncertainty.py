"""Calibration and cost of the per-pixel uncertainty (issue 26; docs/FITTING.md, "Per-pixel
uncertainty").

    PYTHONPATH=host python bench/bench_uncertainty.py [--size 32] [--materials twill,leather,satin,denim]
        [--seeds 0,1,2] [--plans full,MOD3,ROW2+4] [--preset standard] [--json out.json]

Each material and seed is rendered by the virtual rig and captured through its sensor model, in
one of two ways (``--source``):

* ``sensor`` (the default): the noise-free dataset captured image by image with the rig's
  per-image metered exposure (peak at 90 % of full well), shot and read noise, saturation and 12
  bit (``bench_fit.add_noise``: :func:`dualscale.sim.sensor.capture`), back to radiance by the
  known exposure: the sensor's noise alone;
* ``calibrated``: ``synth --realistic`` (also LED gains and spectra, dark signal, vignetting)
  made radiance by the product's own calibration (``synth-targets`` -> ``calibrate`` ->
  :func:`dualscale.calib.apply.to_radiance`, one calibration for every sample, as one rig has):
  the sensor's noise plus whatever error the calibration leaves.

Each is fitted on each light plan with the preset, ``uncertainty`` on, with the ground truth's
components.  Per map: the share of determined texel channels, the z-scores' spread and the 95 %
coverage (:func:`dualscale.fit.uncertainty.calibration`), pooled over the seeds; the
misspecified case fits the anisotropic twill with an isotropic lobe.  The cost is the fit's
time with the uncertainty over the same fit's time without it, less 1, the median over the
full-plan fits (and the whole ``dualscale fit`` command's, ``--command-size``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import numpy as np

from dualscale.calib.apply import to_radiance
from dualscale.cli import main as cli_main
from dualscale.fit.core import fit_observations
from dualscale.fit.observations import load_observations
from dualscale.fit.study import builtin_subsets
from dualscale.fit.uncertainty import calibration
from dualscale.formats.maps import load_maps
from dualscale.threads import set_threads

import bench_fit  # (bench/ is on the path when this script runs)


def _cli(*args: str) -> None:
    rc = cli_main([*args, "--threads", "1", "--no-progress"])
    if rc:
        raise SystemExit(f"dualscale {' '.join(args)} failed ({rc})")


def _calibrated(work: Path, cal: Path, material: str, seed: int, size: int):
    raw = work / f"{material}-{seed}-{size}"
    _cli("synth", material, "--size", str(size), "--texel-um", "9", "--seed", str(seed), "--dataset", "--realistic",
         "--no-previews", "-o", str(raw))
    rad = work / f"{material}-{seed}-{size}-radiance"
    to_radiance(raw, rad, cal)
    return load_observations(rad), load_maps(raw / "maps")[0]


def _pool(recs: list[dict]) -> dict:
    """Pooled over fits: n-weighted means of z_sd^2 (as variance), z_mean and coverage."""
    out = {}
    for n in sorted({k for r in recs for k in r}):
        rs = [r[n] for r in recs if n in r and r[n].get("n")]
        if not rs:
            continue
        w = np.array([r["n"] for r in rs], float)
        det = float(np.mean([r["determined"] for r in rs]))
        zsd = float(np.sqrt(np.average([r["z_sd"] ** 2 for r in rs], weights=w)))
        cov = float(np.average([r["coverage_95"] for r in rs], weights=w))
        med = float(np.median([r["median_sigma"] for r in rs]))
        out[n] = {"determined": det, "z_sd": zsd, "coverage_95": cov, "median_sigma": med, "n": int(w.sum())}
    return out


def _command_cost(work: Path, size: int, preset: str, repeats: int) -> dict:
    """The whole ``dualscale fit`` command (selection, cross-validation, the fit, the files)
    with and without its uncertainty, alternating, ``repeats`` each: median wall times."""
    ds = work / f"command-{size}"
    if not (ds / "micro" / "manifest.json").is_file():
        _cli("synth", "twill", "--size", str(size), "--texel-um", "9", "--dataset", "--no-previews", "-o", str(ds))
    times: dict[bool, list[float]] = {True: [], False: []}
    for with_unc in (True, False):  # untimed: the kernels' first calls (numba's on-disk cache, allocators)
        _cli("fit", str(ds), "-o", str(work / f"command-fit-{with_unc}"), "--overwrite", "--preset", preset,
             "--no-previews", *([] if with_unc else ["--no-uncertainty"]))
    for k in range(repeats):
        for with_unc in (True, False) if k % 2 == 0 else (False, True):
            t0 = time.perf_counter()
            _cli("fit", str(ds), "-o", str(work / f"command-fit-{with_unc}"), "--overwrite", "--preset", preset,
                 "--no-previews", *([] if with_unc else ["--no-uncertainty"]))
            times[with_unc].append(time.perf_counter() - t0)
    w, wo = statistics.median(times[True]), statistics.median(times[False])
    return {"with_s": w, "without_s": wo, "cost": w / wo - 1.0, "runs": {str(k): v for k, v in times.items()}}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--materials", default="twill,leather,satin,denim")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--plans", default="full,MOD3,ROW2+4")
    ap.add_argument("--preset", default="standard", help="a preset, or bench_fit's NAME[@LOSS][*FACTOR][~SD][%%RATIO]")
    ap.add_argument("--source", choices=("sensor", "calibrated"), default="sensor")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", default=None, help="keep the datasets here (default: a temporary folder)")
    ap.add_argument("--command-size", type=int, default=64,
                    help="also time the whole dualscale fit command on a twill of this size, with and without its "
                         "uncertainty (0: not)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    set_threads(a.threads)
    preset = bench_fit.preset(a.preset)  # NAME[@LOSS][*FACTOR][~SD][%RATIO], as bench_fit
    wanted = [p for p in a.plans.split(",") if p != "full"]
    subsets = builtin_subsets(names=wanted) if wanted else {}
    work = Path(a.work or tempfile.mkdtemp(prefix="bench-unc-"))
    work.mkdir(parents=True, exist_ok=True)
    cal = work / "rig.calib.json"
    if a.source == "calibrated" and not cal.is_file():
        _cli("synth-targets", "-o", str(work / "targets"), "--led-step", "1")
        _cli("calibrate", str(work / "targets"), "-o", str(cal))
    cases: dict[tuple[str, str], list[dict]] = {}
    costs: list[float] = []
    walls: list[float] = []
    noise = None
    for material in a.materials.split(","):
        for seed in (int(s) for s in a.seeds.split(",")):
            if a.source == "calibrated":
                obs, gt = _calibrated(work, cal, material, seed, a.size)
            else:
                obs, gt = bench_fit.dataset(work / f"{material}-{seed}-{a.size}-sensor", material, a.size, 9.0, seed=seed)
            comps = gt.components()
            plans = {"full": None, **subsets}
            if material == "twill":
                plans["full, isotropic lobe (misspecified)"] = None
            if not costs and not walls:  # untimed: the kernels' first calls
                fit_observations(obs.crop(0, 4, 0, 4), preset.scaled(0.02), comps, seed=seed, uncertainty=True)
            for plan, ids in plans.items():
                o = obs if ids is None else obs.select_leds(ids & set(obs.led_ids.tolist()))
                c = replace(comps, isotropic=True) if "misspecified" in plan else comps
                t0 = time.perf_counter()
                res = fit_observations(o, preset, c, seed=seed, uncertainty=True)
                total = time.perf_counter() - t0
                u = res.uncertainty
                noise = u.noise
                if "misspecified" not in plan:  # its own clock (for the LM presets it includes the last
                    costs.append(u.seconds / max(1e-9, total - u.seconds))  # iteration's kernel pass)
                if plan == "full":  # the same fit without its uncertainty, timed beside it
                    t0 = time.perf_counter()
                    fit_observations(o, preset, c, seed=seed, uncertainty=False)
                    walls.append(total / (time.perf_counter() - t0) - 1.0)
                cases.setdefault((material if "misspecified" not in plan else "twill (isotropic fit)",
                                  plan.split(",")[0]), []).append(calibration(res.maps, u.sigma, u.undetermined, gt))
                print(f"{material} seed {seed} {plan}: {total:.1f} s, uncertainty {u.seconds:.2f} s", flush=True)
    command = _command_cost(work, a.command_size, a.preset, a.repeats) if a.command_size else None
    by_plan: dict[str, list[dict]] = {}
    for (m, plan), recs in cases.items():
        if "isotropic" not in m:
            by_plan.setdefault(plan, []).extend(recs)
    rep = {"date": date.today().isoformat(), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
           "load": os.getloadavg()[0], "threads": a.threads, "size": a.size, "preset": a.preset, "noise": noise,
           "source": a.source,
           "cost_median": statistics.median(costs) if costs else None,
           "wall_cost_median": statistics.median(walls) if walls else None, "command": command,
           "per_plan": {p: _pool(r) for p, r in by_plan.items()},
           "per_case": {f"{m} / {p}": _pool(r) for (m, p), r in cases.items()}}
    print(f"\n{rep['date']}, {rep['machine']}, load {rep['load']:.2f}, {a.threads} thread(s); "
          f"{a.size}^2, source {a.source}; preset {a.preset}; noise scale: {noise}")
    print(f"uncertainty cost: the fit with it took a median {100 * rep['wall_cost_median']:+.1f} % longer than the "
          f"same fit without it (full plan; its own clock, which for the LM presets includes the last iteration's "
          f"kernel pass that the fit makes anyway, a median {100 * rep['cost_median']:.1f} % of the fit's)\n")
    if command:
        print(f"dualscale fit of a {a.command_size}^2 twill (noise-free), {a.repeats} runs each, alternating: median "
              f"{command['with_s']:.1f} s with the uncertainty, {command['without_s']:.1f} s with --no-uncertainty: "
              f"{100 * command['cost']:+.1f} %\n")
    print("| plan / case | map | determined | z sd | 95 % coverage | median σ |\n|---|---|---|---|---|---|")
    for title, group in (("all materials", rep["per_plan"]), ("", rep["per_case"])):
        for plan, maps in group.items():
            for k, (n, r) in enumerate(maps.items()):
                print(f"| {(plan + (' (' + title + ')' if title else '')) if k == 0 else ''} | {n} | "
                      f"{100 * r['determined']:.0f} % | {r['z_sd']:.2f} | {100 * r['coverage_95']:.1f} % | "
                      f"{r['median_sigma']:.3g} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))
    return rep


if __name__ == "__main__":
    main()
