"""Fly-out detection on the shadowed synthetic test bed: precision and recall per material.

For each fabric, a map at the paper's pixel pitch (1.8 um) is rendered under what the detector
reads -- the zenith LED and the most grazing ring, analyser at P0 -- with cast shadows, raised
fly-out fibres and HDR-style sensor noise (``bench_fit.add_noise``).  The detector runs with the
ground-truth tangent map (step 6) and without it.  Baselines from the same run: chance (the
share of fibre pixels: the precision of a detector that marks pixels at random) and the same
detector on the same material rendered without shadows.

    PYTHONPATH=host python bench/bench_flyouts.py [--size 384] [--seeds 0,1]

``--fitted PRESET`` instead runs the whole pipeline a user runs: ``dualscale synth --dataset
--shadows`` (127 LEDs x P0/P90 and the back light), the same sensor noise, a ``PRESET`` fit of
the maps, then detection with the *fitted* tangent map, against the ground-truth tangent and none
on the same captures.  It also reports the fitted tangent's error on the yarns (axial, degrees).

``--resolution TEXELS_UM`` measures how the precision falls as the texel grows against the fibre
(12 um across, ``sim.materials.fabrics.add_flyouts``): the same field (``--field-mm``) rendered
at each texel size (comma-separated, micrometres), detected with the true tangent, scored with
the 2-px buffer.  Its table is the source of ``dualscale.fit.flyouts.SIMULATED_PRECISION``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fit import add_noise  # noqa: E402

from dualscale.sim.testbed import flyout_views  # noqa: E402
from dualscale.fit.flyouts import confidence_map, detect, score  # noqa: E402
from dualscale.fit.observations import Observations  # noqa: E402
from dualscale.sim.materials import generate  # noqa: E402

FABRICS = "plain,twill,satin,denim,rib_knit,sheer"


def observations(mat, size: int, texel_um: float, shadows: bool, seed: int) -> Observations:
    obs = Observations.relative_p0(*flyout_views(mat, texel_um, shadows), pixel_mm=texel_um / 1000)
    torch.manual_seed(seed)
    add_noise(obs, size, texel_um)
    return obs


def run(materials: list[str], seeds: list[int], size: int, texel_um: float) -> list[dict]:
    rows = []
    for name in materials:
        for seed in seeds:
            mat = generate(name, size, texel_um / 1000, seed)
            gt = mat.flyout_mask
            tan = mat.maps.tangent[..., 0].double().numpy()
            row = {"material": name, "seed": seed, "fibres": len(mat.flyouts), "chance": float(gt.mean())}
            for shadows in (True, False):
                conf = confidence_map(observations(mat, size, texel_um, shadows, seed))
                for label, t in (("tangent", tan), ("no_tangent", None)):
                    if not shadows and t is None:
                        continue
                    t0 = time.perf_counter()
                    res = detect(conf, texel_um / 1000, tangent=t)
                    s = score(res["mask"], gt)
                    key = label if shadows else "no_shadows"
                    row[key] = {"precision": s["precision"], "recall": s["recall"], "detected": len(res["paths"]),
                                "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def _axial_deg(a, b):
    """Angle between two axial tangent maps in normalised units (period 1 = 180 deg), degrees."""
    d = np.abs(a - b) % 1.0
    return np.minimum(d, 1.0 - d) * 180.0


def run_fitted(materials: list[str], seeds: list[int], size: int, texel_um: float, preset_name: str) -> list[dict]:
    import tempfile

    from bench_fit import preset

    from dualscale.cli import main as cli_main
    from dualscale.fit.core import fit_observations
    from dualscale.fit.observations import load_observations
    from dualscale.fit.params import fit_components

    rows = []
    for name in materials:
        for seed in seeds:
            mat = generate(name, size, texel_um / 1000, seed)
            with tempfile.TemporaryDirectory() as tmp:
                rc = cli_main(["synth", name, "-o", tmp, "--size", str(size), "--texel-um", str(texel_um),
                               "--seed", str(seed), "--dataset", "--shadows", "--no-previews"])
                assert rc == 0
                obs = load_observations(tmp)
            torch.manual_seed(seed)
            add_noise(obs, size, texel_um)
            comps = fit_components(opaque=mat.maps.opacity is None, isotropic=False, tinted=True)
            fit = fit_observations(obs, preset(preset_name), comps)
            gt_tan = mat.maps.tangent[..., 0].double().numpy()
            fit_tan = fit.maps.tangent[..., 0].double().numpy()
            yarn = ~mat.flyout_mask & (mat.maps.anisotropy[..., 0].numpy() > 0.3)
            err = _axial_deg(fit_tan, gt_tan)[yarn]
            conf = confidence_map(obs)
            row = {"material": name, "seed": seed, "fibres": len(mat.flyouts), "chance": float(mat.flyout_mask.mean()),
                   "fit_seconds": fit.seconds, "tangent_err_median_deg": float(np.median(err)),
                   "tangent_err_p90_deg": float(np.percentile(err, 90))}
            for label, t in (("fitted", fit_tan), ("tangent", gt_tan), ("no_tangent", None)):
                res = detect(conf, texel_um / 1000, tangent=t)
                sc = score(res["mask"], mat.flyout_mask)
                row[label] = {"precision": sc["precision"], "recall": sc["recall"], "detected": len(res["paths"])}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def run_resolution(materials: list[str], seeds: list[int], field_mm: float, texels_um: list[float]) -> list[dict]:
    """Precision and recall per texel size on one field (see the module docstring)."""
    from dualscale.fit.flyouts import FIBRE_DIAMETER_MM

    rows = []
    for texel_um in texels_um:
        size = int(round(field_mm * 1000 / texel_um))
        for name in materials:
            for seed in seeds:
                mat = generate(name, size, texel_um / 1000, seed)
                gt = mat.flyout_mask
                tan = mat.maps.tangent[..., 0].double().numpy()
                conf = confidence_map(observations(mat, size, texel_um, True, seed))
                res = detect(conf, texel_um / 1000, tangent=tan)
                s = score(res["mask"], gt)
                row = {"texel_um": texel_um, "size": size, "texels_across": FIBRE_DIAMETER_MM * 1000 / texel_um,
                       "material": name, "seed": seed, "fibres": len(mat.flyouts), "detected": len(res["paths"]),
                       "precision": s["precision"] if res["paths"] else None, "recall": s["recall"],
                       "chance": float(gt.mean())}
                rows.append(row)
                print(json.dumps(row), flush=True)
    return rows


def table_resolution(rows: list[dict], field_mm: float) -> str:
    out = [f"Machine: {platform.machine()}, {torch.get_num_threads()} torch threads; date {datetime.date.today()}; "
           f"a {field_mm} mm field at each texel size; 12 um fibres; zenith + grazing ring at P0, HDR-style sensor "
           "noise; true tangent; tolerance 2 px. Precision: over the rows with a detection.", "",
           "| texel [um] | px | fibre / texel | rows | fibres true / detected | precision median (min-max) | "
           "recall median |", "|---:|---:|---:|---:|---|---|---:|"]
    for t in sorted({r["texel_um"] for r in rows}):
        rs = [r for r in rows if r["texel_um"] == t]
        ps = [r["precision"] for r in rs if r["precision"] is not None]
        p = (f"{statistics.median(ps):.2f} ({min(ps):.2f}-{max(ps):.2f})" if ps else "no detection")
        out.append(f"| {t:g} | {rs[0]['size']} | {rs[0]['texels_across']:.2f} | {len(rs)} | "
                   f"{sum(r['fibres'] for r in rs)} / {sum(r['detected'] for r in rs)} | {p} | "
                   f"{statistics.median(r['recall'] for r in rs):.2f} |")
    return "\n".join(out)


def _machine(size: int, texel_um: float) -> str:
    return (f"Machine: {platform.machine()} {platform.node() or 'vm'}, {torch.get_num_threads()} torch threads; "
            f"date {datetime.date.today()}; {size}x{size} px of {texel_um} um")


def _pr(row: dict, keys: tuple[str, ...]) -> dict[str, str]:
    return {k: f"{row[k]['precision']:.2f} / {row[k]['recall']:.2f}" for k in keys}


def table_fitted(rows: list[dict], size: int, texel_um: float, preset_name: str) -> str:
    out = [f"{_machine(size, texel_um)}; full dataset with shadows and HDR-style sensor noise; `{preset_name}` "
           "fit; tolerance 2 px.", "",
           "| material | seed | fit [s] | tangent err on yarns, median / p90 [deg] | P / R fitted tangent | "
           "P / R true tangent | P / R no tangent |", "|---|---:|---:|---|---|---|---|"]
    for r in rows:
        pr = _pr(r, ("fitted", "tangent", "no_tangent"))
        out.append(f"| {r['material']} | {r['seed']} | {r['fit_seconds']:.0f} | {r['tangent_err_median_deg']:.1f} / "
                   f"{r['tangent_err_p90_deg']:.1f} | {pr['fitted']} | {pr['tangent']} | {pr['no_tangent']} |")
    return "\n".join(out)


def table(rows: list[dict], size: int, texel_um: float) -> str:
    out = [f"{_machine(size, texel_um)}; zenith + grazing ring at P0, HDR-style sensor noise; tolerance 2 px.", "",
           "| material | seed | fibres | chance | P / R with tangent | P / R no tangent | P / R no shadows | "
           "detect [s] |", "|---|---:|---:|---:|---|---|---|---:|"]
    for r in rows:
        pr = _pr(r, ("tangent", "no_tangent", "no_shadows"))
        out.append(f"| {r['material']} | {r['seed']} | {r['fibres']} | {r['chance']:.3f} | {pr['tangent']} | "
                   f"{pr['no_tangent']} | {pr['no_shadows']} | {r['tangent']['seconds']:.1f} |")
    med = {k: (statistics.median(r[k]["precision"] for r in rows), statistics.median(r[k]["recall"] for r in rows))
           for k in ("tangent", "no_tangent", "no_shadows")}
    chance = statistics.median(r["chance"] for r in rows)
    out += ["", "Medians: " + "; ".join(f"{k} P {p:.2f} R {rc:.2f}" for k, (p, rc) in med.items())
            + f"; chance precision {chance:.3f} (ratio {med['tangent'][0] / chance:.0f}x)."]
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--texel-um", type=float, default=1.8)
    ap.add_argument("--materials", default=FABRICS)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    ap.add_argument("--fitted", default=None, metavar="PRESET",
                    help="detect with the tangent map of a PRESET fit of the full dataset (see above)")
    ap.add_argument("--resolution", default=None, metavar="TEXELS_UM",
                    help="precision per texel size, comma-separated micrometres (see above)")
    ap.add_argument("--field-mm", type=float, default=0.6912, help="the field of --resolution, mm")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.resolution:
        rows = run_resolution(a.materials.split(","), [int(s) for s in a.seeds.split(",")], a.field_mm,
                              [float(t) for t in a.resolution.split(",")])
        if a.json:
            Path(a.json).write_text(json.dumps(rows, indent=1))
        print(table_resolution(rows, a.field_mm))
        return
    if a.fitted:
        rows = run_fitted(a.materials.split(","), [int(s) for s in a.seeds.split(",")], a.size, a.texel_um, a.fitted)
        if a.json:
            Path(a.json).write_text(json.dumps(rows, indent=1))
        print(table_fitted(rows, a.size, a.texel_um, a.fitted))
        return
    rows = run(a.materials.split(","), [int(s) for s in a.seeds.split(",")], a.size, a.texel_um)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    print(table(rows, a.size, a.texel_um))


if __name__ == "__main__":
    main()
