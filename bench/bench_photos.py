"""Real photographs from another rig: leave-one-light-out re-render error of our fit against the
classic Lambertian photometric-stereo baseline, per object (docs/PHOTOS.md).

    PYTHONPATH=host python bench/bench_photos.py [--data ../shared/data/psm-12lights]
        [--objects cat,buddha,owl] [--pixels 4000] [--preset standard] [--out out/bench_photos]
        [--no-ablation] [--ablation-pixels 1500] [--json results.json]

Runs the user's workflow through the command line: ``dualscale lights sphere chrome/`` and
``dualscale import OBJ/ --transfer srgb`` (mask from the folder), then, per object:

* leave-one-light-out on a random subset of ``--pixels`` mask pixels (the same pixels for both
  methods; :mod:`dualscale.fit.holdout`): our fit with the preset and the component choice
  ``dualscale fit`` makes (made again in every fold, on its 11 lights), and the Lambertian
  baseline; relative L1 per held-out light over the valid (masked, unclipped) pixels;
* the baseline's leave-one-light-out over the *whole* mask too (it is cheap), to show the
  subset's sampling error;
* one fit of the whole mask on all lights (only the mask's pixels are fitted), the baseline on
  all lights, and the mean angle between the two normal maps; both written as PNG
  (``OUT/<object>/normals_ours.png``, ``normals_baseline.png``: RGB = (n + 1) / 2, background
  black) and the maps as EXR (``OUT/<object>/maps/``);
* with the ablation (default on): the same leave-one-light-out, on its own ``--ablation-pixels``
  subset, as fitted and for what the fit did before
  (light scale 1, i.e. the 8-bit values read as radiance; a specular lobe forced; the draft
  preset as it was, 6 of the 11 lights), to show what each fix is worth.

Prints markdown tables; skips cleanly (exit 0) when the shared data is absent.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "psm-12lights"
OBJECTS = ("cat", "buddha", "owl")


def cli(*args: str) -> str:
    """Run ``dualscale ARGS`` in this process; returns what it printed; raises on failure."""
    import contextlib
    import io

    from dualscale.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(list(args))
    if code != 0:
        raise RuntimeError(f"dualscale {' '.join(args)} exited {code}:\n{buf.getvalue()}")
    return buf.getvalue()


def normal_png(path: Path, normal: np.ndarray, mask: np.ndarray) -> None:
    from dualscale.formats.exr import write_png_preview

    rgb = np.where(mask[..., None], 0.5 * (normal + 1.0), 0.0).astype(np.float32)
    write_png_preview(path, rgb, srgb=False)


def run_object(name: str, data: Path, lights: Path, out: Path, args: argparse.Namespace) -> dict:
    from dualscale.calib.photo_import import import_photos
    from dualscale.fit.holdout import fit_sample, lambertian_prediction, leave_one_light_out, relative_l1
    from dualscale.fit.io import save_fit
    from dualscale.fit.lambertian import fit_lambertian
    from dualscale.fit.metrics import normal_angle_deg
    from dualscale.fit.observations import load_observations
    from dualscale.fit.params import fit_components
    from dualscale.fit.presets import get_preset
    from dualscale.fit.select import select_components
    from dualscale.fit.core import FitResult

    ds = out / name / "dataset"
    cli("import", str(data / name), "--lights", str(lights), "-o", str(ds), "--transfer", "srgb")
    obs = load_observations(ds, camera="photo")
    preset = get_preset(args.preset)

    def choose(o):
        return select_components(o, seed=args.seed)[0]

    row: dict = {"object": name}
    rep = leave_one_light_out(obs, preset, choose, pixels=args.pixels, seed=args.seed)
    row["loo"] = rep.as_json()
    # the baseline over the whole mask (cheap): the subset's sampling error
    full = []
    for lid in rep.light_ids:
        tr, he = obs.select_leds({lid}, keep=False), obs.select_leds({lid}, keep=True)
        m = obs.fitted_pixels
        pred = lambertian_prediction(tr.pixels(torch.nonzero(m.reshape(-1)).flatten()),
                                     he.pixels(torch.nonzero(m.reshape(-1)).flatten()))[0]
        cap = he.images[0][m]
        full.append(relative_l1(pred, cap, he.valid[0][m]))
    row["baseline_full_mask"] = {"per_light": full, "mean": float(np.mean(full))}
    # the whole mask, all lights: maps and normals
    t0 = time.perf_counter()
    comps, sel = select_components(obs, seed=args.seed)
    maps = fit_sample(obs, preset, comps, seed=args.seed)
    secs = time.perf_counter() - t0
    mask = obs.fitted_pixels.numpy()
    k = obs.n
    lam = fit_lambertian(obs.images.reshape(k, -1, 3).double().numpy(), obs.dirs.double().numpy(),
                         obs.valid.reshape(k, -1).numpy())
    nb = lam.normal.reshape(*obs.shape, 3)
    no = maps.normal.double().numpy()
    ang = normal_angle_deg(torch.from_numpy(no), torch.from_numpy(nb)).numpy()[mask]
    for what, t in (("maps", maps.normal), ("albedo", maps.albedo)):
        if not bool(torch.isfinite(t).all()):
            raise RuntimeError(f"{name}: non-finite {what}")
    row["full_fit"] = {"seconds": secs, "pixels": int(mask.sum()), "components": sel.get("components"),
                       "specular": sel.get("specular"), "normal_angle_mean_deg": float(ang.mean()),
                       "normal_angle_median_deg": float(np.median(ang)),
                       "tilt_median_deg": {"ours": float(np.degrees(np.median(np.arccos(no[mask][:, 2])))),
                                           "baseline": float(np.degrees(np.median(np.arccos(nb[mask][:, 2]))))}}
    normal_png(out / name / "normals_ours.png", no, mask)
    normal_png(out / name / "normals_baseline.png", nb, mask)
    res = FitResult(maps, comps, preset, preset.total, secs, {})
    save_fit(out / name / "maps", res, sel, {"dataset": str(ds)}, previews=True, texel_mm=obs.pixel_mm)
    if args.ablation:
        ab = {}
        ds1 = out / name / "dataset_scale1"
        import_photos(data / name, lights, ds1, "srgb", scale=1.0)
        obs1 = load_observations(ds1, camera="photo")
        spec = fit_components(True, True, False)
        draft_as_was = replace(get_preset("draft"), name="draft (6 of 11 lights)")
        for label, o, p, c in (("as fitted (all fixes)", obs, preset, choose),
                               ("light scale 1 (8-bit values as radiance)", obs1, preset, choose),
                               ("light scale 1, specular forced", obs1, preset, spec),
                               ("specular forced", obs, preset, spec),
                               ("draft preset, specular forced", obs, draft_as_was, spec)):
            if o is obs1:  # the fit warns that these albedos leave their box: that is the point here
                import warnings

                warnings.filterwarnings("ignore", message=".*Lambertian albedo >= 1", category=RuntimeWarning)
            if p.name.startswith("draft"):
                from dualscale.fit import core

                saved, core.MIN_STRIDED_LEDS = core.MIN_STRIDED_LEDS, 1  # the stride as it was
                try:
                    r = leave_one_light_out(o, p, c, pixels=args.ablation_pixels, seed=args.seed)
                finally:
                    core.MIN_STRIDED_LEDS = saved
            else:
                r = leave_one_light_out(o, p, c, pixels=args.ablation_pixels, seed=args.seed)
            ab[label] = r.summary()
        row["ablation"] = ab
    return row


def machine() -> str:
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"{platform.machine()} {platform.node() or 'vm'}, {os.cpu_count()} cores, {torch.get_num_threads()} torch "
            f"thread(s), load average {load}; {datetime.date.today()}")


def tables(rows: list[dict], lights_table: str, args: argparse.Namespace, seconds: float) -> str:
    out = [f"Machine: {machine()}; `{args.preset}` preset, components chosen per fold; leave-one-light-out on "
           f"{args.pixels} random mask pixels per object (seed {args.seed}); total {seconds:.0f} s.", "",
           "| object | ours, LOO rel. L1 | baseline (same pixels) | ratio | lights won | baseline, whole mask | "
           "normal angle ours vs baseline, mean / median [deg] | components (whole mask) | LOO time ours / "
           "baseline [s] |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s, f = r["loo"], r["full_fit"]
        comps = "specular" if (f["specular"] or {}).get("chosen") else "diffuse only"
        out.append(f"| {r['object']} | {s['ours_mean']:.4f} | {s['baseline_mean']:.4f} | {s['ratio']:.3f} | "
                   f"{s['wins']}/{s['lights']} | {r['baseline_full_mask']['mean']:.4f} | "
                   f"{f['normal_angle_mean_deg']:.1f} / {f['normal_angle_median_deg']:.1f} | {comps} | "
                   f"{s['seconds_ours']:.0f} / {s['seconds_baseline']:.1f} |")
    out += ["", "Per held-out light, relative L1 (ours / baseline):", "",
            "| object | " + " | ".join(str(i) for i in rows[0]["loo"]["light_ids"]) + " |",
            "|---|" + "---|" * len(rows[0]["loo"]["light_ids"])]
    for r in rows:
        out.append(f"| {r['object']} | " + " | ".join(f"{a:.3f} / {b:.3f}" for a, b in
                                                      zip(r["loo"]["ours"], r["loo"]["baseline"])) + " |")
    if any("ablation" in r for r in rows):
        out += ["", f"Ablation ({args.ablation_pixels} random mask pixels, the same for every column; "
                "leave-one-light-out mean relative L1, the baseline on the same pixels in brackets):", "",
                "| object | " + " | ".join(rows[0]["ablation"]) + " |", "|---|" + "---|" * len(rows[0]["ablation"])]
        for r in rows:
            out.append(f"| {r['object']} | " + " | ".join(f"{v['ours_mean']:.4f} ({v['baseline_mean']:.4f})"
                                                          for v in r["ablation"].values()) + " |")
    out += ["", "Light directions recovered from chrome/ (`dualscale lights sphere`):", "", lights_table]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--objects", default=",".join(OBJECTS))
    ap.add_argument("--pixels", type=int, default=4000)
    ap.add_argument("--preset", default="standard")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "out" / "bench_photos")
    ap.add_argument("--no-ablation", dest="ablation", action="store_false")
    ap.add_argument("--ablation-pixels", type=int, default=1500)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if not (args.data / "chrome").is_dir():
        print(f"bench_photos: skipped: {args.data} is absent (the shared real photographs; a fresh clone has none)")
        return 0
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    printed = cli("lights", "sphere", str(args.data / "chrome"), "-o", str(args.out / "lights"))
    table = [ln for ln in printed.splitlines() if not ln.startswith("wrote")]
    lights_table = "```\n" + "\n".join(table) + "\n```"
    rows = [run_object(o, args.data, args.out / "lights.lp", args.out, args) for o in args.objects.split(",")]
    text = tables(rows, lights_table, args, time.perf_counter() - t0)
    print(text)
    from dualscale.formats.atomic import write_json, write_text

    write_text(args.out / "table.md", text + "\n")
    write_json(args.json or args.out / "results.json", {"machine": machine(), "rows": rows})
    print(f"\nwrote {args.out / 'table.md'}, {args.json or args.out / 'results.json'} and the normal maps "
          f"{args.out}/<object>/normals_ours.png, normals_baseline.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
