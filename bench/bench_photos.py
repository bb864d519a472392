"""Real photographs from another rig, under several decodings: the camera response and the
lights' intensities the importer estimates, and the leave-one-light-out re-render error of our
fit against the classic Lambertian photometric-stereo baseline, per object and per decoding
(docs/PHOTOS.md, "Measured: psm-12lights"; issue 23, "Measure").

    PYTHONPATH=host python bench/bench_photos.py [--data ../shared/data/psm-12lights]
        [--objects cat,buddha,owl] [--decodings srgb,auto,gamma:1.2] [--matte MATTE_DIR]
        [--pixels 4000] [--preset standard] [--out out/bench_photos] [--no-full-fit]
        [--full-fit-decoding auto] [--no-ablation] [--ablation-decoding auto] [--ablation-pixels 1500]
        [--json results.json] [--threads 1]
    PYTHONPATH=host python bench/bench_photos.py --tables-from out/bench_photos/results.json

Runs the user's workflow through the command line: ``dualscale lights sphere chrome/`` (with
``--matte MATTE_DIR`` also ``dualscale lights sphere chrome/ --matte MATTE_DIR``), then per
object and per **decoding** (a row):

* ``srgb``: ``dualscale import OBJ --transfer srgb`` (what the docs used to say);
* ``auto``: ``--transfer auto``, the response and the lights' intensities estimated from the
  photographs (:mod:`dualscale.calib.response`);
* ``gamma:1.2``: ``--transfer gamma:1.2``, a *stated reference*: the power issue 23 measured on
  a matte sphere photographed by the same camera (not in the shared data);
* ``matte`` (only with ``--matte``): the light file of ``lights sphere --matte`` and
  ``--transfer lights``, the response and intensities from the matte reference sphere.

Every import keeps the default intensities (``--intensities auto``: the light file's when it has
them, else estimated), so the chrome rows differ only by the decoding.  The import's wall time
and the estimation's (``extra.import.radiometry.seconds``) are recorded.

Then, on ``--pixels`` random mask pixels (the **same pixels in every row**), leave-one-light-out:
for each of the 12 lights, fit on the other 11 and predict it, with

* **ours**: the component choice ``dualscale fit`` makes (:func:`dualscale.fit.select.
  select_components`) and the loss it picks (:func:`~dualscale.fit.select.preset_for`), both
  made again **in every fold** on its 11 lights, the preset without its coarse level
  (:func:`~dualscale.fit.holdout.pixel_preset`), as :func:`~dualscale.fit.holdout.
  cross_validate` does with a chooser (which cannot vary the loss per fold, hence this loop);
* the **Lambertian baseline** (:func:`~dualscale.fit.holdout.lambertian_prediction`) on the
  same training images and valid samples;

scored two ways over the held-out image's valid (masked, unclipped) samples and 3 channels:

* **linear**: relative L1 ``sum |p - x| / sum x`` in the row's decoded linear values
  (:func:`~dualscale.fit.holdout.relative_l1`, as ``fit`` reports); rows with different
  decodings are *not* comparable in it;
* **codes**: the prediction re-encoded through the row's response (``Response.forward`` of the
  prediction times the image's light intensity ``E rel_k``: the dataset's pixels are linear
  values divided by it) against the captured 8-bit codes, ``sum |f(p E_k) - c| / sum c``:
  decoding-independent, the one score that compares rows.

Also per object: the whole-mask fit on all lights under ``--full-fit-decoding`` (default auto;
``--no-full-fit`` skips it) with its normal maps (``OUT/<object>/normals_ours.png``,
``normals_baseline.png``) and maps (``OUT/<object>/maps/``), the mean angle between our normals
and the baseline's, and the baseline's normals under each decoding against that decoding's;
whether the three objects' ``auto`` estimates agree (issue 23 asks a gamma spread <= 0.05 or
the same curve within 1 % of full scale).  The ablation (``--no-ablation`` skips it: five more
leave-one-light-out passes per object, on ``--ablation-pixels``, under ``--ablation-decoding``,
default auto) takes the old fixes back one at a time: light scale 1 (the decoded values read as
radiance), a specular lobe forced, the draft preset as it was (6 of the 11 lights); it uses
:func:`~dualscale.fit.holdout.leave_one_light_out` with a component chooser, so the loss there is
the preset's (L1), not chosen per fold.

Prints markdown tables, writes ``OUT/table.md`` and ``--json`` (default ``OUT/results.json``;
``--tables-from`` prints an earlier run's tables again); skips cleanly (exit 0) when the shared
data is absent.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import platform
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "psm-12lights"
OBJECTS = ("cat", "buddha", "owl")
DECODINGS = ("srgb", "auto", "gamma:1.2")
#: what each row's decoding is, for the tables
LABELS = {"srgb": "srgb (stated, IEC 61966-2-1)",
          "auto": "auto (estimated from the photographs)",
          "gamma:1.2": "gamma:1.2 (stated reference: the matte-sphere power of issue 23)",
          "matte": "matte target (--transfer lights)"}
FAMILIES = ("linear", "srgb", "gamma", "curve")


def cli(*args: str) -> str:
    """Run ``dualscale ARGS`` in this process; returns what it printed (stdout and stderr);
    raises on failure."""
    from dualscale.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        code = main(list(args))
    if code != 0:
        raise RuntimeError(f"dualscale {' '.join(args)} exited {code}:\n{buf.getvalue()}")
    return buf.getvalue()


def normal_png(path: Path, normal: np.ndarray, mask: np.ndarray) -> None:
    from dualscale.formats.exr import write_png_preview

    rgb = np.where(mask[..., None], 0.5 * (normal + 1.0), 0.0).astype(np.float32)
    write_png_preview(path, rgb, srgb=False)


def slug(key: str) -> str:
    return key.replace(":", "")


# -- one decoding: import, response, intensities ----------------------------------------------

def import_row(name: str, key: str, data: Path, lights: dict[str, Path], out: Path, args) -> dict:
    """Import ``name`` under decoding ``key`` through the CLI; the dataset, its observations,
    the response and the per-light intensities ``E rel_k`` (by light id)."""
    from dualscale.fit.observations import load_observations
    from dualscale.formats.dataset import read_dataset
    from dualscale.formats.response import response_from_json

    transfer = "lights" if key == "matte" else key
    light_file = lights["matte"] if key == "matte" else lights["chrome"]
    ds = out / name / f"dataset_{slug(key)}"
    t0 = time.perf_counter()
    printed = cli("import", str(data / name), "--lights", str(light_file), "-o", str(ds), "--transfer", transfer,
                  "--threads", str(args.threads), "--no-progress")
    t_import = time.perf_counter() - t0
    dset = read_dataset(ds)
    imp = dset.manifest["extra"]["import"]
    rad = imp["radiometry"]
    resp = response_from_json(rad["response"], f"{ds}: extra.import.radiometry.response")
    inten = {rec.light_id: float(rec.intensity * rec.exposure_s) for rec in dset.records if rec.light_kind == "led"}
    obs = load_observations(ds, camera="photo")
    return {"key": key, "transfer": transfer, "dataset": ds, "obs": obs, "response": resp, "radiometry": rad,
            "intensity": inten, "import": imp, "seconds_import": t_import, "printed": printed}


def captured_codes(imp: dict) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """The captured normalised code values ``(H*W, 3)`` and clipped flags per light id, read
    from the photographs the import names (``extra.import.sources``)."""
    from dualscale.formats.photo import read_codes

    folder = Path(imp["images"])
    codes, clipped = {}, {}
    for s in imp["sources"]:
        c = read_codes(folder / s["file"])
        codes[int(s["id"])] = c.code.reshape(-1, 3).astype(np.float64)
        clipped[int(s["id"])] = c.clipped.reshape(-1)
    return codes, clipped


def radiometry_summary(row: dict) -> dict:
    """What the table shows of a row's radiometry record."""
    rad, resp = row["radiometry"], row["response"]
    est = rad["response"] if row["key"] == "auto" else rad.get("estimate")
    ev = (est or {}).get("evidence") or {}
    fits = ev.get("fits") or {}
    ints = rad.get("intensities") or {}
    out = {"used": rad.get("used"), "family": resp.family, "params": list(resp.params), "source": resp.source,
           "gamma_std": resp.uncertainty.get("gamma_std"), "curve_std_max": resp.uncertainty.get("curve_std_max"),
           "scores": {f: fits[f]["score"] for f in FAMILIES if f in fits},
           "gamma_fit": (fits.get("gamma") or {}).get("params", [None])[0],
           "estimate": None if est is None else {"family": est.get("family"), "params": est.get("params"),
                                                 "chosen": ev.get("chosen")},
           "check": rad.get("check"), "warnings": rad.get("warnings") or [],
           "intensities": ints.get("values"), "intensities_std": ints.get("std"),
           "intensities_source": rad.get("intensities_source") or ints.get("source"),
           "seconds_estimation": rad.get("seconds"), "seconds_import": row["seconds_import"],
           "light_scale": row["import"].get("light_scale"),
           "equal_intensities_response": ((rad.get("equal_intensities") or {}).get("gamma") or {}).get("transfer"),
           "equal_intensities_curve_distance": (rad.get("equal_intensities") or {}).get("curve_distance"),
           "code_range_used": ev.get("code_range_used"), "notes": rad.get("notes") or []}
    return out


# -- leave-one-light-out, both scores -----------------------------------------------------------

def loo(row: dict, flat: torch.Tensor, codes: dict[int, np.ndarray], args) -> dict:
    """Leave-one-light-out of ours (choice and loss per fold) and the baseline on the pixels
    ``flat``; relative L1 in linear values and in code values per held-out light."""
    from dualscale.fit.core import fit_observations
    from dualscale.fit.holdout import lambertian_prediction, light_folds, pixel_preset, relative_l1
    from dualscale.fit.presets import get_preset
    from dualscale.fit.render import clamp_images, render_leds
    from dualscale.fit.select import preset_for, select_components

    obs, resp, inten = row["obs"], row["response"], row["intensity"]
    preset = get_preset(args.preset)
    sub = obs.pixels(flat)
    fl = flat.numpy()
    res_ = {"light_ids": [], "ours": [], "baseline": [], "ours_codes": [], "baseline_codes": [], "choices": []}
    t_ours = t_base = 0.0
    for fold in light_folds(sub.led_ids, "loo"):
        train, held = sub.select_leds(set(fold), keep=False), sub.select_leds(set(fold), keep=True)
        t0 = time.perf_counter()
        comps, sel = select_components(train, seed=args.seed)
        p = pixel_preset(preset_for(preset, sel))
        fit = fit_observations(train, p, comps, seed=args.seed)
        with torch.no_grad():
            pred = render_leds(fit.maps.to(held.images.dtype), comps, held)
        t_ours += time.perf_counter() - t0
        t0 = time.perf_counter()
        pb = lambertian_prediction(train, held)
        t_base += time.perf_counter() - t0
        if not (bool(torch.isfinite(pred).all()) and np.isfinite(pb).all()):
            raise RuntimeError(f"{row['dataset']}: non-finite prediction of light(s) {fold}")
        cap = clamp_images(held.images)
        ids = held.led_ids.tolist()
        for k, lid in enumerate(ids):
            v = held.valid[k].reshape(-1).numpy() if held.valid is not None else np.ones(fl.size, bool)
            po = pred[k].reshape(-1, 3).double().numpy()
            pbk = pb[k].reshape(-1, 3)
            c = codes[lid][fl]
            res_["light_ids"].append(int(lid))
            res_["ours"].append(relative_l1(po, cap[k].reshape(-1, 3), v))
            res_["baseline"].append(relative_l1(pbk, cap[k].reshape(-1, 3), v))
            res_["ours_codes"].append(relative_l1(resp.forward(po * inten[lid]), c, v))
            res_["baseline_codes"].append(relative_l1(resp.forward(pbk * inten[lid]), c, v))
        res_["choices"].append({"lights": list(fold), "specular": bool(sel["specular"]["chosen"]),
                                "diffuse": sel["diffuse"]["chosen"], "loss": p.loss})
    order = np.argsort(res_["light_ids"])
    for k in ("light_ids", "ours", "baseline", "ours_codes", "baseline_codes"):
        res_[k] = [res_[k][i] for i in order]
    o, b = np.array(res_["ours"]), np.array(res_["baseline"])
    oc, bc = np.array(res_["ours_codes"]), np.array(res_["baseline_codes"])
    res_.update({"ours_mean": float(o.mean()), "baseline_mean": float(b.mean()), "ratio": float(o.mean() / b.mean()),
                 "wins": int((o < b).sum()), "ours_codes_mean": float(oc.mean()),
                 "baseline_codes_mean": float(bc.mean()), "ratio_codes": float(oc.mean() / bc.mean()),
                 "wins_codes": int((oc < bc).sum()), "lights": len(o), "pixels": int(fl.size),
                 "seconds_ours": t_ours, "seconds_baseline": t_base})
    for k in ("ours", "baseline", "ours_codes", "baseline_codes", "ours_mean", "baseline_mean",
              "ours_codes_mean", "baseline_codes_mean"):
        if not np.isfinite(res_[k]).all():
            raise RuntimeError(f"{row['dataset']}: non-finite {k}")
    return res_


def check_codes(row: dict, codes: dict[int, np.ndarray], clipped: dict[int, np.ndarray]) -> float:
    """Largest |forward(stored linear) - captured code| over the mask's unclipped pixels, in
    code values: the re-encoding of the code score inverts the import (should be < 0.5)."""
    obs, resp, inten = row["obs"], row["response"], row["intensity"]
    m = obs.fitted_pixels.reshape(-1).numpy()
    worst = 0.0
    for k, lid in enumerate(obs.led_ids.tolist()):
        x = obs.images[k].reshape(-1, 3).double().numpy()[m] * inten[lid]
        ok = ~clipped[lid][m]
        worst = max(worst, float(np.abs(resp.forward(x[ok]) - codes[lid][m][ok]).max()) * 255.0)
    return worst


def lambert_normals(obs) -> np.ndarray:
    from dualscale.fit.lambertian import fit_lambertian

    k = obs.n
    lam = fit_lambertian(obs.images.reshape(k, -1, 3).double().numpy(), obs.dirs.double().numpy(),
                         obs.valid.reshape(k, -1).numpy())
    return lam.normal.reshape(*obs.shape, 3)


def angle(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    from dualscale.fit.metrics import normal_angle_deg

    x = normal_angle_deg(torch.from_numpy(np.ascontiguousarray(a)), torch.from_numpy(np.ascontiguousarray(b)))
    x = x.numpy()[mask]
    return float(x.mean()), float(np.median(x))


def full_fit(name: str, row: dict, out: Path, args) -> dict:
    """The whole mask on all lights (choice and loss as ``dualscale fit``), its normals against
    the baseline's, and the maps."""
    from dualscale.fit.core import FitResult
    from dualscale.fit.holdout import fit_sample
    from dualscale.fit.io import save_fit
    from dualscale.fit.presets import get_preset
    from dualscale.fit.select import preset_for, select_components

    obs = row["obs"]
    t0 = time.perf_counter()
    comps, sel = select_components(obs, seed=args.seed)
    preset = preset_for(get_preset(args.preset), sel)
    maps = fit_sample(obs, preset, comps, seed=args.seed)
    secs = time.perf_counter() - t0
    for what, t in (("normal", maps.normal), ("albedo", maps.albedo)):
        if not bool(torch.isfinite(t).all()):
            raise RuntimeError(f"{name}: non-finite {what}")
    mask = obs.fitted_pixels.numpy()
    nb = lambert_normals(obs)
    no = maps.normal.double().numpy()
    mean, med = angle(no, nb, mask)
    normal_png(out / name / "normals_ours.png", no, mask)
    normal_png(out / name / "normals_baseline.png", nb, mask)
    save_fit(out / name / "maps", FitResult(maps, comps, preset, preset.total, secs, {}), sel,
             {"dataset": str(row["dataset"])}, previews=True, texel_mm=obs.pixel_mm)
    return {"decoding": row["key"], "seconds": secs, "pixels": int(mask.sum()), "components": sel.get("components"),
            "specular": bool(sel["specular"]["chosen"]), "diffuse": sel["diffuse"]["chosen"], "loss": preset.loss,
            "normal_angle_mean_deg": mean, "normal_angle_median_deg": med}


def ablation(name: str, row: dict, data: Path, lights: Path, out: Path, args) -> dict:
    """The ablation (docs/PHOTOS.md, "Why the fit failed") under ``row``'s decoding: what each
    fix is worth."""
    from dualscale.calib.photo_import import import_photos
    from dualscale.fit import observations
    from dualscale.fit.holdout import leave_one_light_out
    from dualscale.fit.observations import load_observations
    from dualscale.fit.params import fit_components
    from dualscale.fit.presets import get_preset
    from dualscale.fit.select import select_components

    obs, preset = row["obs"], get_preset(args.preset)
    ds1 = out / name / f"dataset_{slug(row['key'])}_scale1"
    import_photos(data / name, lights, ds1, row["transfer"], scale=1.0)
    obs1 = load_observations(ds1, camera="photo")
    spec = fit_components(True, True, False)
    draft_as_was = replace(get_preset("draft"), name="draft (6 of 11 lights)")

    def choose(o):
        return select_components(o, seed=args.seed)[0]

    ab = {}
    for label, o, p, c in (("as fitted", obs, preset, choose),
                           ("light scale 1 (decoded values as radiance)", obs1, preset, choose),
                           ("light scale 1, specular forced", obs1, preset, spec),
                           ("specular forced", obs, preset, spec),
                           ("draft preset, specular forced", obs, draft_as_was, spec)):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*Lambertian albedo >= 1", category=RuntimeWarning)
            saved = observations.MIN_STRIDED_LEDS
            if p.name.startswith("draft"):
                observations.MIN_STRIDED_LEDS = 1  # the stride as it was
            try:
                ab[label] = leave_one_light_out(o, p, c, pixels=args.ablation_pixels, seed=args.seed).summary()
            finally:
                observations.MIN_STRIDED_LEDS = saved
    return ab


# -- per object --------------------------------------------------------------------------------

def run_object(name: str, data: Path, lights: dict[str, Path], out: Path, args) -> dict:
    from dualscale.fit.holdout import sample_pixels

    obj: dict = {"object": name, "rows": {}}
    flat = fitted = codes = clipped = None
    rows = {}
    for key in args.decoding_list:
        row = import_row(name, key, data, lights, out, args)
        rows[key] = row
        obs = row["obs"]
        if flat is None:
            fitted = obs.fitted_pixels.clone()
            flat = sample_pixels(obs, args.pixels, args.seed)
            codes, clipped = captured_codes(row["import"])
        elif not torch.equal(obs.fitted_pixels, fitted):
            raise RuntimeError(f"{name}: decoding {key} has other sample pixels than {args.decoding_list[0]}")
        rec = radiometry_summary(row)
        rec["reencode_max_codes"] = check_codes(row, codes, clipped)
        print(f"[{name} {key}] import {row['seconds_import']:.1f} s: {rec['used']}", file=sys.stderr, flush=True)
        rec["loo"] = loo(row, flat, codes, args)
        s = rec["loo"]
        print(f"[{name} {key}] LOO codes {s['ours_codes_mean']:.4f} / {s['baseline_codes_mean']:.4f}, linear "
              f"{s['ours_mean']:.4f} / {s['baseline_mean']:.4f} ({s['seconds_ours']:.0f} s)", file=sys.stderr,
              flush=True)
        obj["rows"][key] = rec
    # the baseline's normals under each decoding against the full-fit decoding's
    mask = fitted.numpy()
    ref_key = args.full_fit_decoding if args.full_fit_decoding in rows else args.decoding_list[0]
    nref = lambert_normals(rows[ref_key]["obs"])
    obj["baseline_normals_vs"] = {"reference": ref_key, **{k: angle(lambert_normals(r["obs"]), nref, mask)
                                                           for k, r in rows.items() if k != ref_key}}
    if args.full_fit:
        obj["full_fit"] = full_fit(name, rows[ref_key], out, args)
    if args.ablation:
        if args.ablation_decoding not in rows or args.ablation_decoding == "matte":
            raise RuntimeError(f"--ablation-decoding {args.ablation_decoding}: not one of the chrome rows")
        t0 = time.perf_counter()
        obj["ablation"] = ablation(name, rows[args.ablation_decoding], data, lights["chrome"], out, args)
        obj["ablation_seconds"] = time.perf_counter() - t0
    return obj


def agreement(objs: list[dict], key: str = "auto") -> dict | None:
    """Do the objects' ``key`` estimates agree (issue 23: gamma spread <= 0.05, or the same curve
    within 1 % of full scale)?"""
    from dualscale.calib.response import curve_distance, code_window
    from dualscale.formats.response import Response

    recs = [(o["object"], o["rows"][key]) for o in objs if key in o["rows"]]
    if len(recs) < 2:
        return None
    resp = {n: Response(r["family"], tuple(r["params"])) for n, r in recs}
    lo, hi = code_window(8)
    pairs = {}
    names = [n for n, _ in recs]
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            a, b = resp[names[i]], resp[names[j]]
            pairs[f"{names[i]}-{names[j]}"] = {"full": curve_distance(a, b), "window": curve_distance(a, b, (lo, hi))}
    gam = [r["gamma_fit"] for _, r in recs if r["gamma_fit"] is not None]
    eq = [r["equal_intensities_response"] for _, r in recs]
    curve_max = max(p["window"] for p in pairs.values())
    spread = float(max(gam) - min(gam)) if gam else None
    return {"families": {n: r["family"] for n, r in recs}, "gamma_fit": {n: r["gamma_fit"] for n, r in recs},
            "gamma_fit_spread": spread, "curve_distance": pairs, "curve_distance_max_window": curve_max,
            "equal_intensities": dict(zip(names, eq)),
            "agree": bool((spread is not None and spread <= 0.05) or curve_max <= 0.01)}


# -- tables -----------------------------------------------------------------------------------

def machine() -> str:
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"{platform.machine()} {platform.node() or 'vm'}, {os.cpu_count()} cores, {torch.get_num_threads()} torch "
            f"thread(s), load average {load}; {datetime.date.today()}")


def revision() -> str:
    """The revision of the ``dualscale`` package this run imported: the checkout's commit (and
    whether its host/ has uncommitted edits), or, for a package imported from elsewhere (a
    ``git archive`` snapshot on ``PYTHONPATH``), that folder and its ``REVISION`` file."""
    import dualscale

    root = Path(dualscale.__file__).resolve().parents[1]
    if root != REPO / "host":
        note = (root.parent / "REVISION").read_text().strip() if (root.parent / "REVISION").is_file() else "?"
        return f"{note} (dualscale imported from {root})"
    try:
        head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--", "host"], capture_output=True,
                               text=True, check=True).stdout.strip()
        return head + (" + uncommitted host/ edits" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _resp_cell(r: dict) -> str:
    fam, p = r["family"], r["params"]
    if fam == "gamma":
        s = f"gamma {p[0]:.3f}" + (f" ± {r['gamma_std']:.3f}" if r.get("gamma_std") is not None else "")
    elif fam == "curve":
        s = f"curve (power {p[0]:.3f}" + (f" ± {r['gamma_std']:.3f}" if r.get("gamma_std") is not None else "") + ")"
        if r.get("curve_std_max") is not None:
            s += f", ±{100 * r['curve_std_max']:.2f} % FS"
    else:
        s = fam
    return s


def tables(objs: list[dict], lights_table: str, args, seconds: float, meta: dict) -> str:
    keys = args.decoding_list
    out = [f"Machine: {meta['machine']}; revision {meta['revision']}; `{args.preset}` preset; leave-one-light-out on "
           f"{args.pixels} random mask pixels per object (seed {args.seed}, the same pixels in every row), component "
           f"choice and loss made again in every fold; total {seconds:.0f} s.", ""]
    if "matte" not in keys:
        out += ["No matte reference sphere was given (`--matte DIR`): the matte-target row is absent.", ""]
    # radiometry: the estimate (every import of a chrome row runs it: auto to use it, a stated one to check it)
    ref = "auto" if "auto" in keys else next((k for k in keys if k != "matte"), None)
    if ref is not None:
        out += [f"The camera response estimated from the photographs (the `{ref}` import's estimate; consistency: the "
                "mean Cauchy loss of the code residuals, lower = more consistent; the simplest family within the "
                "margin of the best is chosen):", "",
                "| object | chosen | consistency linear / srgb / gamma (its power) / curve | estimate with equal "
                "intensities (curve distance) | codes used | estimation [s] | import [s] |",
                "|---|---|---|---|---|---|---|"]
        for o in objs:
            r = o["rows"][ref]
            sc, g = r["scores"], r["gamma_fit"]
            cons = " / ".join((f"{sc[f]:.4f}" + (f" ({g:.3f})" if f == "gamma" and g is not None else ""))
                              if f in sc else "–" for f in FAMILIES)
            eq, eqd = r.get("equal_intensities_response"), r.get("equal_intensities_curve_distance")
            eqs = "–" if eq is None else f"{eq}" + ("" if eqd is None else f" ({100 * eqd:.1f} % FS)")
            rng = r.get("code_range_used")
            es = r["seconds_estimation"]
            out.append(f"| {o['object']} | {_resp_cell(r) if ref == 'auto' else (r['estimate'] or {}).get('chosen')} | "
                       f"{cons} | {eqs} | {'–' if not rng else f'{rng[0]:.3f}–{rng[1]:.3f}'} | "
                       f"{'–' if es is None else f'{es:.1f}'} | {r['seconds_import']:.1f} |")
    stated = [k for k in keys if k != "auto"]
    if stated:
        from dualscale.calib.response import CONTRADICTION_CURVE, CONTRADICTION_LOSS

        out += ["", "The other decodings, as the import checked them against that estimate (a contradiction warns: "
                f"consistency loss >= {CONTRADICTION_LOSS:.2f} x the estimate's and curves >= "
                f"{100 * CONTRADICTION_CURVE:.0f} % of full scale apart at their best common scale):", "",
                "| object | decoding | response used | its consistency vs the estimate's | curves apart (codes used) | "
                "import warns | import [s] |", "|---|---|---|---|---|---|---|"]
        for o in objs:
            for k in stated:
                r = o["rows"][k]
                ck = r.get("check") or {}
                cons = (f"{ck['stated_score']:.4f} vs {ck['estimate_score']:.4f} "
                        f"(x {ck['stated_score'] / ck['estimate_score']:.2f})") if ck else "–"
                dist = f"{100 * ck['curve_distance']:.1f} %" if ck else "–"
                out.append(f"| {o['object']} | {k} | {_resp_cell(r)} | {cons} | {dist} | "
                           f"{'yes' if r['warnings'] else 'no'} | {r['seconds_import']:.1f} |")
    out += ["", "Lights' relative intensities (geometric mean 1; estimated under each row's response unless the light "
            "file gives them; max std: the bootstrap's, auto only), and the light scale E:", "",
            "| object | decoding | " + " | ".join(str(i) for i in range(12)) + " | max std | E |",
            "|---|---|" + "---|" * 14]
    for o in objs:
        for k in keys:
            r = o["rows"][k]
            v = r["intensities"] or []
            sd = r["intensities_std"]
            out.append(f"| {o['object']} | {k} ({r['intensities_source']}) | " + " | ".join(f"{x:.3f}" for x in v)
                       + f" | {'–' if not sd else f'{max(sd):.4f}'} | {r['light_scale']:.3f} |")
    ag = agreement(objs)
    if ag:
        pd = ", ".join(f"{p} {100 * d['window']:.1f} %" for p, d in ag["curve_distance"].items())
        same = "the same curve" if ag["curve_distance_max_window"] <= 0.01 else "not the same curve"
        spread = ag["gamma_fit_spread"]
        within = "n/a" if spread is None else f"{spread:.3f}: **{'within' if spread <= 0.05 else 'not within'} 0.05**"
        out += ["", f"Agreement of the `auto` estimates across objects (issue 23 asks a gamma spread <= 0.05 or the "
                f"same curve within 1 %): chosen families {ag['families']}, their curves apart by at most {pd} (codes "
                f"0.03–0.98): **{same}**; the best gamma's power "
                + ", ".join(f"{n} {g:.3f}" for n, g in ag["gamma_fit"].items() if g is not None)
                + f", spread {within}; the estimate with equal intensities: "
                + ", ".join(f"{n} {t}" for n, t in ag["equal_intensities"].items()) + "."]
    # LOO
    out += ["", "Leave-one-light-out, mean relative L1 over the 12 held-out lights (codes: the prediction re-encoded "
            "through the row's response against the captured 8-bit codes, comparable across rows; linear: in the "
            "row's decoded values, comparable only within a row):", "",
            "| object | decoding | ours, codes | baseline, codes | ratio | lights won | ours, linear | baseline, "
            "linear | ratio | fold choices (specular / diffuse / loss) | LOO time ours / baseline [s] |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for o in objs:
        for k in keys:
            s = o["rows"][k]["loo"]
            ch = s["choices"]
            nspec = sum(c["specular"] for c in ch)
            dif = ", ".join(f"{d} {sum(c['diffuse'] == d for c in ch)}" for d in sorted({c["diffuse"] for c in ch}))
            los = ", ".join(f"{d} {sum(c['loss'] == d for c in ch)}" for d in sorted({c["loss"] for c in ch}))
            out.append(f"| {o['object']} | {k} | {s['ours_codes_mean']:.4f} | {s['baseline_codes_mean']:.4f} | "
                       f"{s['ratio_codes']:.3f} | {s['wins_codes']}/{s['lights']} | {s['ours_mean']:.4f} | "
                       f"{s['baseline_mean']:.4f} | {s['ratio']:.3f} | specular {nspec}/{len(ch)}; {dif}; {los} | "
                       f"{s['seconds_ours']:.0f} / {s['seconds_baseline']:.1f} |")
    ids = objs[0]["rows"][keys[0]]["loo"]["light_ids"]
    out += ["", "Per held-out light, relative L1 in code values (ours / baseline):", "",
            "| object | decoding | " + " | ".join(str(i) for i in ids) + " |", "|---|---|" + "---|" * len(ids)]
    for o in objs:
        for k in keys:
            s = o["rows"][k]["loo"]
            out.append(f"| {o['object']} | {k} | " + " | ".join(f"{a:.3f} / {b:.3f}" for a, b in
                                                             zip(s["ours_codes"], s["baseline_codes"])) + " |")
    # normals
    ref = objs[0]["baseline_normals_vs"]["reference"]
    others = [k for k in keys if k != ref]
    head = "| object | " + " | ".join(f"baseline normals {k} vs {ref}, mean / median [deg]" for k in others)
    if args.full_fit:
        head += f" | ours vs baseline ({ref}), mean / median [deg] | whole-mask fit ({ref}): pixels, choice, time |"
    else:
        head += " |"
    out += ["", "Normals (whole mask, all 12 lights):", "", head,
            "|---|" + "---|" * (len(others) + (2 if args.full_fit else 0))]
    for o in objs:
        cells = [f"{o['baseline_normals_vs'][k][0]:.1f} / {o['baseline_normals_vs'][k][1]:.1f}" for k in others]
        if args.full_fit:
            f = o["full_fit"]
            cells += [f"{f['normal_angle_mean_deg']:.1f} / {f['normal_angle_median_deg']:.1f}",
                      f"{f['pixels']}, {'specular' if f['specular'] else 'diffuse only'} {f['diffuse']} {f['loss']}, "
                      f"{f['seconds']:.0f} s"]
        out.append(f"| {o['object']} | " + " | ".join(cells) + " |")
    if any("ablation" in o for o in objs):
        first = next(o for o in objs if "ablation" in o)["ablation"]
        secs = ", ".join(f"{o['object']} {o['ablation_seconds']:.0f} s" for o in objs if "ablation" in o)
        out += ["", f"Ablation under {args.ablation_decoding} ({args.ablation_pixels} random mask pixels, the same "
                "for every column; components chosen per fold, the preset's own loss; leave-one-light-out mean "
                f"relative L1 in that decoding's linear values, the baseline in brackets; {secs}):", "",
                "| object | " + " | ".join(first) + " |", "|---|" + "---|" * len(first)]
        for o in objs:
            out.append(f"| {o['object']} | " + " | ".join(f"{v['ours_mean']:.4f} ({v['baseline_mean']:.4f})"
                                                          for v in o["ablation"].values()) + " |")
    out += ["", "Light directions recovered from chrome/ (`dualscale lights sphere`):", "", lights_table]
    return "\n".join(out)


def _json(x):
    if isinstance(x, dict):
        return {str(k): _json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--objects", default=",".join(OBJECTS))
    ap.add_argument("--decodings", default=",".join(DECODINGS),
                    help="comma-separated rows: srgb, auto, gamma:G, linear (matte is added by --matte)")
    ap.add_argument("--matte", type=Path, default=None,
                    help="photographs of a matte reference sphere under the same lights: adds the matte-target row")
    ap.add_argument("--pixels", type=int, default=4000)
    ap.add_argument("--preset", default="standard")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "out" / "bench_photos")
    ap.add_argument("--no-full-fit", dest="full_fit", action="store_false")
    ap.add_argument("--full-fit-decoding", default="auto")
    ap.add_argument("--no-ablation", dest="ablation", action="store_false")
    ap.add_argument("--ablation-decoding", default="auto")
    ap.add_argument("--ablation-pixels", type=int, default=1500)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tables-from", type=Path, default=None,
                    help="print the tables of an earlier run's --json instead of measuring")
    args = ap.parse_args(argv)
    if args.tables_from is not None:
        doc = json.loads(args.tables_from.read_text())
        print(tables(doc["objects"], doc["lights_table"], argparse.Namespace(**doc["args"]), doc["seconds"], doc))
        return 0
    if not (args.data / "chrome").is_dir():
        print(f"bench_photos: skipped: {args.data} is absent (the shared real photographs; a fresh clone has none)")
        return 0
    if args.matte is not None and not args.matte.is_dir():
        print(f"bench_photos: --matte {args.matte}: not a folder", file=sys.stderr)
        return 2
    args.decoding_list = [k.strip() for k in args.decodings.split(",") if k.strip()] + (["matte"] if args.matte else [])
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    printed = cli("lights", "sphere", str(args.data / "chrome"), "-o", str(args.out / "lights"))
    table = [ln for ln in printed.splitlines() if not ln.startswith("wrote")]
    lights_table = "```\n" + "\n".join(table) + "\n```"
    lights = {"chrome": args.out / "lights.lp"}
    if args.matte is not None:
        t1 = time.perf_counter()
        cli("lights", "sphere", str(args.data / "chrome"), "--matte", str(args.matte), "-o",
            str(args.out / "lights_matte"))
        lights["matte"] = args.out / "lights_matte.json"
        print(f"matte target: {time.perf_counter() - t1:.1f} s", file=sys.stderr)
    objs = [run_object(o, args.data, lights, args.out, args) for o in args.objects.split(",")]
    seconds = time.perf_counter() - t0
    meta = {"machine": machine(), "revision": revision()}
    text = tables(objs, lights_table, args, seconds, meta)
    print(text)
    from dualscale.formats.atomic import write_json, write_text

    write_text(args.out / "table.md", text + "\n")
    keep = ("decoding_list", "preset", "pixels", "seed", "full_fit", "full_fit_decoding", "ablation",
            "ablation_decoding", "ablation_pixels", "matte")
    write_json(args.json or args.out / "results.json",
               _json({**meta, "args": {k: getattr(args, k) for k in keep}, "seconds": seconds,
                      "lights_table": lights_table, "agreement_auto": agreement(objs), "objects": objs}))
    print(f"\nwrote {args.out / 'table.md'}, {args.json or args.out / 'results.json'} and the normal maps "
          f"{args.out}/<object>/normals_ours.png, normals_baseline.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
