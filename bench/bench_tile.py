"""Seamless tiles (issue 12 Sec. 2; docs/TILE.md): the repeat found against the synthetic
fabrics' known repeat (error in um), and the seam score of each tile (its albedo, and the worst of its
maps) beside the untreated crop's; the twill period on the real photos (../shared/data/fabric-rt)
against the hand measurement.

    PYTHONPATH=host python bench/bench_tile.py [--size 320] [--texel-mm 0.0113] [--seeds 3]

Prints markdown tables with the machine, its load average and the date.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "tile"))
DATA = REPO.parent / "shared" / "data" / "fabric-rt"
HAND_LINE_SPACING_PX = {"twill1_R": 4.13}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=320)
    ap.add_argument("--texel-mm", type=float, default=0.0113)
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from dualscale.bsdf import MaterialMaps
    from dualscale.sim.materials import generate
    from dualscale.tile import NoRepeatError, find_lattice, make_tile
    from dualscale.tile.lattice import dominant_period
    from tile_known import known_lattice_px, lattice_error_px

    print(f"machine: {platform.node()} ({platform.processor() or platform.machine()}, {os.cpu_count()} cpus); "
          f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}; {datetime.datetime.now():%Y-%m-%d %H:%M}")
    print(f"\nsynthetic fabrics, {a.size}^2 texels of {a.texel_mm * 1000:.1f} um (pitch 0.3 mm = "
          f"{0.3 / a.texel_mm:.2f} texels), seeds 0..{a.seeds - 1}\n")
    print("| material | known repeat (mm) | found (mm, seed 0) | max error (um) | tile (mm) | seam tile | "
          "seam all maps (worst) | seam untreated | seam no blend (albedo / worst) | s per tile |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in ("plain", "twill", "satin", "denim", "rib_knit"):
        errs, seams, raw, t_s, worst = [], [], [], [], []
        for seed in range(a.seeds):
            m = generate(name, a.size, a.texel_mm, seed=seed).maps
            t0 = time.perf_counter()
            L = find_lattice(m, a.texel_mm)
            tile = make_tile(m, a.texel_mm, L)
            t_s.append(time.perf_counter() - t0)
            known = known_lattice_px(name, a.texel_mm)
            same = abs(L.cell_area_px / abs(np.linalg.det(known)) - 1) < 0.01
            errs.append(lattice_error_px(L.vectors_px, known) * a.texel_mm * 1000 if same else float("inf"))
            seams.append((tile.seam["tile"], tile.seam["untreated"]))
            worst.append(max(v for v in tile.seam["maps"].values() if np.isfinite(v)))  # every map wraps
            with warnings.catch_warnings():  # the no-blend ablation is expected above the goal
                warnings.simplefilter("ignore", RuntimeWarning)
                nb = make_tile(m, a.texel_mm, L, blend_px=0).seam
            raw.append((nb["tile"], max(v for v in nb["maps"].values() if np.isfinite(v))))
            if seed == 0:
                kmm, fmm, size = known * [1, -1] * a.texel_mm, L.vectors_mm, tile.size_mm
        s = np.array(seams)
        fmt = lambda B: "; ".join(f"({v[0]:.4f}, {v[1]:.4f})" for v in B)  # noqa: E731
        print(f"| {name} | {fmt(kmm)} | {fmt(fmm)} | {max(errs):.3f} | {size[0]:.3f} x {size[1]:.3f} | "
              f"{s[:, 0].mean():.3f} (max {s[:, 0].max():.3f}) | {np.mean(worst):.3f} (max {np.max(worst):.3f}) | "
              f"{s[:, 1].mean():.3f} | {np.mean(raw, 0)[0]:.3f} / {np.mean(raw, 0)[1]:.3f} | "
              f"{np.mean(t_s):.2f} |")
    if not DATA.is_dir():
        print(f"\n(real photos skipped: {DATA} not found)")
        return
    from dualscale.formats.photo import read_photo

    print("\nreal photos (8-bit sRGB, 512^2, no stated scale: texels only)\n")
    print("| photo | dominant period (px) | angle (deg) | hand (px) | lattice (px) | line spacing (px) | strength | "
          "tile (px) | seam tile | seam untreated |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for stem in ("twill1_R", "twill1_T", "twill3_R", "twill3_T", "satin1_R", "satin1_T"):
        rgb = read_photo(DATA / f"{stem}.png", "srgb").rgb
        per, ang = dominant_period(rgb)
        hand = HAND_LINE_SPACING_PX.get(stem)
        try:
            L = find_lattice(rgb)
        except NoRepeatError as e:
            print(f"| {stem} | {per:.3f} | {ang:.1f} | {hand or ''} | refused: {str(e)[:60]}... | | | | | |")
            continue
        maps = MaterialMaps(albedo=torch.from_numpy(rgb), roughness=torch.full((*rgb.shape[:2], 1), 0.5))
        try:
            tile = make_tile(maps, None, L, repeats=(4, 4))
            tcol = (f"{tile.size_px[0]:.2f} x {tile.size_px[1]:.2f} | {tile.seam['tile']:.3f} | "
                    f"{tile.seam['untreated']:.3f}")
        except Exception as e:  # noqa: BLE001 - reported in the table
            tcol = f"failed: {e} | | "
        vec = "; ".join(f"({v[0]:.2f}, {v[1]:.2f})" for v in L.vectors_px)
        print(f"| {stem} | {per:.3f} | {ang:.1f} | {hand or ''} | {vec} | {L.line_spacing_px:.3f} | "
              f"{L.strength:.2f} | {tcol} |")


if __name__ == "__main__":
    main()
