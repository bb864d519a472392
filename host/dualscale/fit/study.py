"""Light-subset study (supplementary Sec. 6): fit with each subset of LEDs, evaluate each.

Subsets on our dome (rings ``r = 0..6`` from the zenith, 1/6/12/18/24/30/36 LEDs at
0/12/24/36/48/60/72 deg; ids ring by ring):

* ``ALL``      -- all 127 LEDs;
* ``MOD2``     -- ids divisible by 2 (64 LEDs); ``MOD3`` -- by 3 (43);
* ``ROW2+4``   -- the zenith plus every other LED of rings 2 and 4 (1 + 6 + 12 = 19);
* ``ROW2+5``   -- the zenith plus every other LED of rings 2 and 5 (1 + 6 + 15 = 22);
* ``MINIMAL``  -- 8 LEDs of ring 4 (48 deg), 45 deg apart in azimuth;
* any user subset ``NAME=ids`` (``0,3,10-20``).

Every 8th LED is held out of every subset and used for the re-render SSIM, so all subsets are
scored on the same unseen lights.  Components are chosen once (on the ALL training set) and
shared.  With both analyser modes captured, a subset uses both images of each of its LEDs.

Every subset's fit also gives its per-pixel uncertainty (:mod:`.uncertainty`, issue 26): the
table has the median sigma of each map, so a subset can be chosen by the uncertainty a user
accepts on their own sample, without ground truth (``max_sigma``, ``--max-sigma MAP=SIGMA``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from dualscale.bsdf import MaterialMaps
from dualscale.formats.atomic import atomic_path, write_json, write_text
from dualscale.geometry.dome import ring_layout

from .core import fit_observations, split_holdout
from .metrics import map_errors
from .observations import Observations, load_observations
from .params import param_names
from .presets import get_preset
from .select import select_components
from .uncertainty import median_sigmas

MATERIAL_CLASSES = {"plain": "woven", "twill": "woven", "satin": "woven", "denim": "woven", "rib_knit": "knit",
                    "leather": "leather", "sheer": "sheer", "brick": "rough surface", "grass": "rough surface",
                    "gravel": "rough surface"}
SSIM_TOLERANCE = 0.005


def _rings() -> list[list[int]]:
    rings: dict[int, list[int]] = {}
    for i, (row, _, _) in enumerate(ring_layout()):
        rings.setdefault(row, []).append(i)
    return [rings[r] for r in sorted(rings)]


def _every_other(ids: list[int]) -> list[int]:
    return ids[::2]


SUBSETS: dict[str, Callable[[], set[int]]] = {
    "ALL": lambda: set(range(sum(len(r) for r in _rings()))),
    "MOD2": lambda: {i for i in range(sum(len(r) for r in _rings())) if i % 2 == 0},
    "MOD3": lambda: {i for i in range(sum(len(r) for r in _rings())) if i % 3 == 0},
    "ROW2+4": lambda: {*_rings()[0], *_every_other(_rings()[2]), *_every_other(_rings()[4])},
    "ROW2+5": lambda: {*_rings()[0], *_every_other(_rings()[2]), *_every_other(_rings()[5])},
    "MINIMAL": lambda: set(_rings()[4][::3]),
}


def parse_subset(text: str) -> tuple[str, set[int]]:
    """``'NAME=0,3,10-20'`` -> ``('NAME', {0, 3, 10, ..., 20})``."""
    if "=" not in text:
        raise ValueError(f"subset {text!r} must look like NAME=0,3,10-20")
    name, spec = text.split("=", 1)
    ids: set[int] = set()
    try:
        for part in filter(None, spec.split(",")):
            if "-" in part:
                a, b = part.split("-", 1)
                ids.update(range(int(a), int(b) + 1))
            else:
                ids.add(int(part))
    except ValueError as e:
        raise ValueError(f"subset {text!r}: bad LED list ({e})") from e
    if not name or not ids:
        raise ValueError(f"subset {text!r} needs a name and at least one LED")
    return name, ids


#: the maps whose median sigma the study's table shows, in this order
SIGMA_MAPS = ("albedo", "normal", "roughness", "anisotropy", "tangent", "ior", "specular_tint")
#: a subset meets ``max_sigma`` only where at most this share of the named map is undetermined
#: (the median is over the determined texels alone)
MAX_UNDETERMINED = 0.5


def recommend(rows: list[dict[str, Any]], max_sigma: dict[str, float] | None = None) -> dict[str, str]:
    """The fewest lights whose held-out SSIM is within ``SSIM_TOLERANCE`` of the best subset's;
    with ``max_sigma`` (``{map: sigma}`` in the map's sigma units, :data:`dualscale.formats.maps.
    SIGMA_UNITS`), the fewest lights whose median sigma of every named map is at most its limit
    and whose undetermined share of it at most :data:`MAX_UNDETERMINED` (no ground truth
    needed).  Raises ``ValueError`` for a map no row has a sigma of."""
    if max_sigma:
        for n in max_sigma:
            if not any(n in (r.get("median_sigma") or {}) for r in rows):
                raise ValueError(f"--max-sigma {n}: no subset has a sigma of {n!r}; "
                                 f"known: {sorted({k for r in rows for k in (r.get('median_sigma') or {})})}")

        def meets(r):
            ms, un = r.get("median_sigma") or {}, r.get("undetermined") or {}
            return all(ms.get(n) is not None and ms[n] <= v and un.get(n, 0.0) <= MAX_UNDETERMINED
                       for n, v in max_sigma.items())

        ok = [r for r in rows if meets(r)]
        limits = ", ".join(f"{n} {v:g}" for n, v in max_sigma.items())
        if not ok:
            return {"subset": None, "reason": f"no subset reaches the median sigma asked ({limits}); "
                    "capture more lights or a slower preset"}
        pick = min(ok, key=lambda r: (r["leds"], -r["heldout_ssim"]))
        return {"subset": pick["subset"], "reason": f"fewest LEDs ({pick['leds']}) whose median sigma is within "
                f"{limits}"}
    best = max(r["heldout_ssim"] for r in rows)
    ok = [r for r in rows if r["heldout_ssim"] >= best - SSIM_TOLERANCE]
    pick = min(ok, key=lambda r: (r["leds"], -r["heldout_ssim"]))
    return {"subset": pick["subset"], "reason": f"fewest LEDs ({pick['leds']}) with held-out SSIM "
            f"{pick['heldout_ssim']:.4f} within {SSIM_TOLERANCE} of the best ({best:.4f})"}


def _table(rows: list[dict[str, Any]]) -> str:
    keys = [k for k in ("albedo_rmse", "normal_mean_deg", "roughness_mae", "anisotropy_mae", "ior_mae")
            if k in rows[0]]
    sig = [n for n in SIGMA_MAPS if any((r.get("median_sigma") or {}).get(n) is not None for r in rows)]
    units = {n: {"normal": " [°]", "tangent": " [°]", "ior": " [η]"}.get(n, "") for n in sig}
    sig_title = {"specular_tint": "tint"}
    head = ("| subset | LEDs | images | held-out SSIM | " + " | ".join(keys + [f"median σ {sig_title.get(n, n)}{units[n]}" for n in sig])
            + " | time [s] |")
    lines = [head, "|---|---:|---:|---:|" + "---:|" * (len(keys) + len(sig)) + "---:|"]
    for r in rows:
        ms = r.get("median_sigma") or {}
        cells = [f"{r[k]:.4f}" for k in keys] + [f"{ms[n]:.3g}" if ms.get(n) is not None else "undetermined"
                                                 for n in sig]
        lines.append(f"| {r['subset']} | {r['leds']} | {r['images']} | {r['heldout_ssim']:.4f} | "
                     + " | ".join(cells) + f" | {r['seconds']:.1f} |")
    return "\n".join(lines)


def _plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = [r["subset"] for r in rows]
    ax.bar(names, [r["heldout_ssim"] for r in rows], color="tab:blue")
    lo = min(r["heldout_ssim"] for r in rows)
    ax.set_ylim(max(0.0, lo - 0.02), 1.0)
    ax.set_ylabel("held-out re-render SSIM")
    for i, r in enumerate(rows):
        ax.text(i, r["heldout_ssim"], f"{r['leds']}", ha="center", va="bottom", fontsize=8)
    ax.set_title(title + " (bar labels: LEDs)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def builtin_subsets(custom: dict[str, set[int]] | None = None, names: list[str] | None = None) -> dict[str, set[int]]:
    """The built-in subsets plus ``custom``, optionally restricted to ``names`` (in that order)."""
    subsets = {k: f() for k, f in SUBSETS.items()}
    subsets.update(custom or {})
    if names:
        missing = set(names) - set(subsets)
        if missing:
            raise ValueError(f"unknown subsets {sorted(missing)}; known: {sorted(subsets)}")
        subsets = {k: subsets[k] for k in names}
    return subsets


def study_observations(obs: Observations, subsets: dict[str, set[int]], preset: str = "standard",
                       gt: MaterialMaps | None = None, material: str | None = None, progress: bool = False,
                       holdout_every: int = 8, max_sigma: dict[str, float] | None = None) -> dict[str, Any]:
    """Fit and score every subset of ``obs`` (see the module docstring); returns the report.
    Every row has the fit's ``median_sigma`` per map (:func:`.uncertainty.median_sigmas`) and
    ``undetermined`` share; ``max_sigma``: recommend by them (:func:`recommend`)."""
    p = get_preset(preset)
    train_all, held = split_holdout(obs, holdout_every)
    if held is None:
        raise ValueError("the study needs held-out LEDs; the dataset has too few")
    comps, sel = select_components(train_all)
    if max_sigma:  # before any subset's fit: a map this fit has no sigma of
        fitted = set(param_names(comps))
        unknown = sorted(set(max_sigma) - fitted)
        if unknown:
            raise ValueError(f"--max-sigma {', '.join(unknown)}: the chosen components fit no {' or '.join(unknown)} "
                             f"(they fit {sorted(fitted)})")
    rows, noise = [], None
    for name, leds in subsets.items():
        sub = train_all.select_leds(leds)
        if sub.n == 0:
            raise ValueError(f"subset {name}: none of its LEDs is in the dataset (outside the held-out set)")
        t0 = time.perf_counter()
        res = fit_observations(sub, p, comps, held_out=held, progress=progress, uncertainty=True)
        row: dict[str, Any] = {"subset": name, "leds": len(set(sub.led_ids.tolist())), "images": sub.n,
                               "heldout_ssim": res.losses["heldout_ssim"], "heldout_rmse": res.losses["heldout_rmse"],
                               "seconds": time.perf_counter() - t0, "median_sigma": median_sigmas(res.uncertainty),
                               "undetermined": {n: float(u.double().mean()) for n, u in
                                                res.uncertainty.undetermined.items()}}
        noise = res.uncertainty.noise
        if gt is not None and gt.shape == res.maps.shape:
            row.update(map_errors(res.maps, gt, comps.ior))
        rows.append(row)
    return {"material": material, "material_class": MATERIAL_CLASSES.get(material or "", "unknown"),
            "preset": preset, "components": sel, "heldout_leds": sorted(set(held.led_ids.tolist())),
            "subsets": {k: sorted(v) for k, v in subsets.items()}, "rows": rows,
            "recommendation": recommend(rows, max_sigma), "noise": noise,
            "table_markdown": _table(rows)}


def write_study(rep: dict[str, Any], out: str | Path) -> None:
    """``study.json``, ``study.md`` (table) and ``study.png`` (SSIM per subset) in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "study.json", rep)
    write_text(out / "study.md", rep["table_markdown"] + "\n\nRecommendation: "
               + (rep["recommendation"]["subset"] or "none") + " (" + rep["recommendation"]["reason"] + ")\n")
    _plot(rep["rows"], out / "study.png", f"{rep.get('material') or 'dataset'} ({rep['preset']})")


def run_study(dataset: str | Path, out: str | Path, preset: str = "standard", custom: dict[str, set[int]] | None = None,
              names: list[str] | None = None, gt_dir: str | Path | None = None, progress: bool = False,
              holdout_every: int = 8, max_sigma: dict[str, float] | None = None) -> dict[str, Any]:
    """Load ``dataset`` (and its ground truth when found), run the study, write it to ``out``."""
    subsets = builtin_subsets(custom, names)
    obs = load_observations(dataset)
    gt, material = None, None
    gdir = Path(gt_dir) if gt_dir else None
    if gdir is not None:
        from dualscale.formats.maps import load_maps

        gt, meta = load_maps(gdir)
        material = meta.get("material")
    rep = study_observations(obs, subsets, preset, gt, material, progress, holdout_every, max_sigma)
    rep["dataset"] = str(dataset)
    write_study(rep, out)
    return rep
