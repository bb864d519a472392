"""Preset trade table: map errors, held-out re-render SSIM and wall time per preset, with the
paper preset in the same run on the same machine.

    PYTHONPATH=host python bench/bench_fit.py [--size 48] [--materials twill,leather,...]
        [--presets draft,standard,adam-fast,coarse-to-fine,paper] [--json out.json]

A preset may name its loss, scale its iterations and set its IOR prior,
``NAME[@l1|@l2][*FACTOR][~SD][%RATIO]``: ``standard@l2`` is the least-squares variant of
``standard``, ``standard*0.5`` runs half its iterations, ``standard~0`` drops its IOR prior,
``standard%0`` fits every capture (no cast-shadow rejection).

Each material is generated at ``size`` x ``size`` texels of ``texel_um`` (9 um by default so a
small map still covers yarn structure), rendered by the virtual dome (127 LEDs x P0/P90, plus
the back light, as the rig captures it), every 8th LED held out.  Components are chosen once per
material (timed separately) and shared by all presets.  Prints markdown tables.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch

from dualscale.cli import main as cli_main
from dualscale.geometry.cameras import micro_camera
from dualscale.sim.render import Analyzer, LightState, render
from dualscale.fit.core import fit_observations, split_holdout
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.presets import PRESETS, Preset
from dualscale.fit.select import select_components
from dualscale.fit.uncertainty import calibration, median_sigmas
from dualscale.formats.maps import load_maps
from dualscale.threads import set_threads

CLASSES = {"plain": "woven", "twill": "woven", "satin": "woven", "denim": "woven (dark warp)", "rib_knit": "knit",
           "leather": "leather", "sheer": "sheer (extreme)", "brick": "photo surface", "grass": "photo surface",
           "gravel": "photo surface"}
EXTREME = {"sheer"}  # open gaps (opacity 0): albedo and normal are undefined over a third of the pixels
BOUNDS = {"normal_mean_deg": 3.0, "albedo_rmse": 0.02, "heldout_ssim": 0.95}


def preset(spec: str) -> Preset:
    """``NAME[@LOSS][*FACTOR][~SD][%RATIO]`` (see the module docstring)."""
    spec, _, ratio = spec.partition("%")
    spec, _, sd = spec.partition("~")
    head, _, factor = spec.partition("*")
    name, _, loss = head.partition("@")
    p = replace(PRESETS[name], loss=loss) if loss else PRESETS[name]
    p = replace(p, ior_prior_sd=float(sd)) if sd else p
    p = replace(p, shadow_ratio=float(ratio)) if ratio else p
    return p.scaled(float(factor)) if factor else p


def add_noise(obs, size: int, texel_um: float, headroom: float = 0.9, seed: int = 0):
    """Sensor capture in place, HDR-style as on the rig ("dynamically computed exposure"):
    each image gets the exposure that puts its brightest pixel at ``headroom`` of full well,
    then shot and read noise, saturation and 12-bit quantisation (no spectral response or
    vignetting, so the ground truth stays in the same colour space); back to relative radiance.
    ``seed``: offsets the noise's seeds (image ``i`` draws with ``seed * 100003 + i``)."""
    from dualscale.sim.sensor import SensorModel, capture, radiance_per_dn

    base = SensorModel(shot_noise=True, read_noise=True, saturate=True, quantize=True)
    cam = micro_camera(size, texel_um)

    def shoot(img, seed):
        peak = max(float(img.max()), 1e-6)
        s = replace(base, exposure_s=min(1.0, headroom * base.full_well_e / (peak * base.gain_e)))
        scale = radiance_per_dn(s)
        return capture(img, cam, s, seed=seed) * scale, scale

    shots = [shoot(img, seed * 100003 + i) for i, img in enumerate(obs.images)]
    obs.images = torch.stack([img for img, _ in shots])
    # what a dataset records as each image's signal_scale (the exposure metered per image)
    obs.signal_scale = torch.tensor([[float(k)] * 3 for _, k in shots], dtype=torch.float64)
    if obs.backlight is not None:
        obs.backlight, k = shoot(obs.backlight, seed * 100003 + 99999)
        obs.back_signal_scale = torch.full((3,), float(k), dtype=torch.float64)


def dataset(root: Path, material: str, size: int, texel_um: float, noise: bool = True, shadows: bool = False,
            seed: int = 0):
    threads = torch.get_num_threads()
    rc = cli_main(["synth", material, "-o", str(root), "--size", str(size), "--texel-um", str(texel_um),
                   "--dataset", "--no-previews", "--seed", str(seed), *(["--shadows"] if shadows else [])])
    assert rc == 0
    set_threads(threads)  # the in-process command applied its own count (--threads auto)
    obs = load_observations(root)
    gt, _ = load_maps(root / "maps")
    if obs.backlight is None:  # the rig always captures the back light; the renderer gives black when opaque
        obs.backlight = render(gt, micro_camera(size, texel_um), LightState.backlight(0), analyzer=Analyzer(0.0, True))
        obs.back_wd = 0.5
    if noise:
        add_noise(obs, size, texel_um, seed=seed)
    return obs, gt


def run(materials: list[str], presets: list[str], size: int, texel_um: float, noise: bool,
        shadows: bool = False) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm_obs, _ = dataset(Path(tmp) / "warm", "leather", 8, texel_um)
        for p in presets:  # warm-up (allocator, thread pools, the kernels' compilation or cache loading)
            fit_observations(warm_obs, preset(p).scaled(0.01), select_components(warm_obs)[0], uncertainty=True)
        for m in materials:
            obs, gt = dataset(Path(tmp) / m, m, size, texel_um, noise, shadows)
            train, held = split_holdout(obs, 8)
            t0 = time.perf_counter()
            comps, sel = select_components(train)
            t_sel = time.perf_counter() - t0
            for p in presets:
                # the same fit without its uncertainty beside it: the cost is the difference (the LM
                # presets build the covariance inside their last iteration, so its own clock
                # includes a kernel pass the fit makes anyway)
                plain = fit_observations(train, preset(p), comps, held_out=held, uncertainty=False)
                res = fit_observations(train, preset(p), comps, held_out=held, uncertainty=True)
                err = map_errors(res.maps, gt, comps.ior)
                u = res.uncertainty
                cal = calibration(res.maps, u.sigma, u.undetermined, gt)
                rows.append({"material": m, "class": CLASSES[m], "preset": p, "seconds": plain.seconds,
                             "uncertainty_seconds": res.seconds - plain.seconds, "median_sigma": median_sigmas(u),
                             "sigma_calibration": cal,
                             "selection_seconds": t_sel, "heldout_ssim": res.losses["heldout_ssim"],
                             "heldout_rmse": res.losses["heldout_rmse"], **err,
                             "components": {"opaque": comps.opaque, "isotropic": comps.isotropic,
                                            "tinted": comps.tinted}})
                print(f"  {m:9s} {p:14s} {res.seconds:7.1f} s  ssim {res.losses['heldout_ssim']:.4f}  "
                      f"normal {err['normal_mean_deg']:.2f} deg  albedo {err['albedo_rmse']:.4f}", flush=True)
    return {"machine": f"{platform.node()} {platform.machine()} {torch.get_num_threads()} torch threads",
            "date": date.today().isoformat(), "size": size, "texel_um": texel_um, "lights": "127 LEDs x P0/P90 "
            "+ back light, every 8th LED held out" + (", cast shadows in the captures (not in the fit's model)"
                                                      if shadows else ""), "noise": ("HDR-style per-image exposure (peak at 90 % of full well), shot + read "
            "noise, 12 bit" if noise else "none"), "rows": rows}


def tables(rep: dict) -> str:
    rows = rep["rows"]
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    keys = ["albedo_rmse", "normal_mean_deg", "normal_p95_deg", "roughness_mae", "anisotropy_mae", "ior_mae",
            "heldout_ssim", "seconds"]
    out = [f"Machine: {rep['machine']}; date {rep['date']}; maps {rep['size']}x{rep['size']} texels of "
           f"{rep['texel_um']} um; {rep['lights']}; sensor noise: {rep['noise']}.", "",
           "| material (class) | preset | " + " | ".join(keys) + " |", "|---|---|" + "---:|" * len(keys)]
    for r in rows:
        out.append(f"| {r['material']} ({r['class']}) | {r['preset']} | " + " | ".join(
            f"{r[k]:.1f}" if k == "seconds" else f"{r[k]:.4f}" for k in keys) + " |")
    out += ["", "Medians over materials, and ratios against `paper` in this run (time: the fit without its "
            "uncertainty; median σ: of the determined texels, per material, then the median over materials):", "",
            "| preset | median time [s] | time / paper | median albedo RMSE | median normal err [deg] | "
            "median held-out SSIM | SSIM / paper | median σ albedo | median σ normal [deg] | median σ roughness | "
            "fit time with σ / without |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    med = {p: {k: statistics.median(r[k] for r in rows if r["preset"] == p) for k in keys} for p in presets}
    ref = med.get("paper")

    def msig(p, n):
        v = [r["median_sigma"].get(n) for r in rows if r["preset"] == p and r.get("median_sigma")]
        v = [x for x in v if x is not None]
        return f"{statistics.median(v):.3g}" if v else "-"

    for p in presets:
        m = med[p]
        tr = f"{m['seconds'] / ref['seconds']:.3f}" if ref else "-"
        sr = f"{m['heldout_ssim'] / ref['heldout_ssim']:.4f}" if ref else "-"
        cost = statistics.median(r["uncertainty_seconds"] / r["seconds"] for r in rows if r["preset"] == p)
        out.append(f"| {p} | {m['seconds']:.1f} | {tr} | {m['albedo_rmse']:.4f} | {m['normal_mean_deg']:.2f} | "
                   f"{m['heldout_ssim']:.4f} | {sr} | {msig(p, 'albedo')} | {msig(p, 'normal')} | "
                   f"{msig(p, 'roughness')} | {100 * cost:+.1f} % |")
    out += ["", "Calibration of σ per preset (all materials pooled; z sd 0.8-1.25 and 95 % coverage 90-98 % "
            "asked; the normal's z is its angle over its RMS-angle σ):", "",
            "| preset | map | z sd | 95 % coverage | determined |", "|---|---|---:|---:|---:|"]
    for p in presets:
        recs = [r["sigma_calibration"] for r in rows if r["preset"] == p]
        for k, n in enumerate(("albedo", "normal", "roughness", "anisotropy", "ior")):
            rs = [c[n] for c in recs if n in c and c[n].get("n")]
            if not rs:
                continue
            w = [c["n"] for c in rs]
            zsd = (sum(c["z_sd"] ** 2 * x for c, x in zip(rs, w)) / sum(w)) ** 0.5
            cov = sum(c["coverage_95"] * x for c, x in zip(rs, w)) / sum(w)
            det = statistics.mean(c["determined"] for c in rs)
            out.append(f"| {p if k == 0 else ''} | {n} | {zsd:.2f} | {100 * cov:.1f} % | {100 * det:.0f} % |")
    if ref:
        out += ["", "Ratios to `paper` per material (preset / paper, same run; < 1 is better, SSIM: > 1):", "",
                "| material | preset | " + " | ".join(keys) + " |", "|---|---|" + "---:|" * len(keys)]
        paper = {r["material"]: r for r in rows if r["preset"] == "paper"}
        for r in (r for r in rows if r["preset"] != "paper" and r["material"] in paper):
            q = paper[r["material"]]
            out.append(f"| {r['material']} | {r['preset']} | " + " | ".join(
                (f"{r[k] / q[k]:.4f}" if k == "heldout_ssim" else f"{r[k] / q[k]:.2f}") if q[k] > 0 else "-"
                for k in keys) + " |")
    if ref:
        out += ["", "Paper preset against the acceptance bounds (mean normal < 3 deg, albedo RMSE < 0.02, "
                "held-out SSIM > 0.95):", "", "| material | normal [deg] | albedo RMSE | SSIM | verdict |",
                "|---|---:|---:|---:|---|"]
        for r in (r for r in rows if r["preset"] == "paper"):
            miss = [k for k, b in BOUNDS.items() if (r[k] > b if k != "heldout_ssim" else r[k] < b)]
            tag = "extreme" if r["material"] in EXTREME else ""
            verdict = ("pass" if not miss else "misses " + ", ".join(miss)) + (f" ({tag})" if tag else "")
            out.append(f"| {r['material']} | {r['normal_mean_deg']:.3f} | {r['albedo_rmse']:.4f} | "
                       f"{r['heldout_ssim']:.4f} | {verdict} |")
    return "\n".join(out)


def study(materials: list[str], size: int, texel_um: float, noise: bool, preset: str) -> str:
    """The light-subset study (``dualscale.fit.study``) on each material; markdown per material
    plus the recommendation per class."""
    from dualscale.fit.study import builtin_subsets, study_observations

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in materials:
            obs, gt = dataset(Path(tmp) / m, m, size, texel_um, noise)
            rep = study_observations(obs, builtin_subsets(), preset, gt, m)
            out += [f"### {m} ({rep['material_class']})", "", rep["table_markdown"], "",
                    f"Recommendation: **{rep['recommendation']['subset']}** ({rep['recommendation']['reason']}).", ""]
            print("\n".join(out[-6:]), flush=True)
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--texel-um", type=float, default=9.0)
    ap.add_argument("--materials", default="twill,denim,rib_knit,leather,sheer,brick")
    ap.add_argument("--presets", default="draft,standard,adam-fast,coarse-to-fine,paper")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--clean", action="store_true", help="no sensor noise")
    ap.add_argument("--shadows", action="store_true",
                    help="render the captures with cast shadows (dualscale synth --shadows); the fit does not model them")
    ap.add_argument("--json", default=None)
    ap.add_argument("--study", action="store_true", help="run the light-subset study instead of the trade table")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.study:
        print(study(a.materials.split(","), a.size, a.texel_um, not a.clean, "standard"))
        return
    rep = run(a.materials.split(","), a.presets.split(","), a.size, a.texel_um, not a.clean, a.shadows)
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))
    print(tables(rep))


if __name__ == "__main__":
    main()
