"""Fitted maps on disk: one float32 EXR per map carrying the fit's metadata, plus
``material.json`` in the ``dualscale-maps`` format (so ``dualscale render`` reads them) and
``fit.json`` (the full report).

EXR header attributes (strings): ``dualscale:preset``, ``dualscale:components`` (JSON),
``dualscale:iterations``, ``dualscale:final_losses`` (JSON), ``dualscale:selection`` (JSON:
the component decision and its evidence), ``dualscale:map``.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from dualscale.dome.exr import read_exr_attributes, write_exr, write_png_preview
from dualscale.materials.io import CONVENTIONS

from .core import FitResult

_CHANNELS = {"normal": ("X", "Y", "Z"), 1: ("Y",), 3: ("R", "G", "B")}


def fit_attributes(res: FitResult, selection: dict | None) -> dict[str, str]:
    return {"dualscale:preset": res.preset.name,
            "dualscale:components": json.dumps(asdict(res.comps)),
            "dualscale:iterations": str(res.iterations),
            "dualscale:final_losses": json.dumps(res.losses),
            "dualscale:selection": json.dumps(selection or {})}


def save_fit(root: str | Path, res: FitResult, selection: dict | None = None, extra: dict | None = None,
             previews: bool = True) -> Path:
    """Write the maps of ``res`` under ``root``; returns the path of ``fit.json``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    attrs = fit_attributes(res, selection)
    names = []
    for name, t in res.maps.items():
        arr = t.detach().cpu().numpy()
        ch = _CHANNELS["normal"] if name == "normal" else _CHANNELS[arr.shape[-1]]
        write_exr(root / f"{name}.exr", arr, ch, {**attrs, "dualscale:map": name})
        if previews:
            prev = 0.5 * arr + 0.5 if name == "normal" else arr
            write_png_preview(root / f"{name}.png", prev, srgb=name in ("albedo", "transmittance"))
        names.append(name)
    h, w = res.maps.shape
    report: dict[str, Any] = {
        "preset": asdict(res.preset), "components": asdict(res.comps), "iterations": res.iterations,
        "seconds": res.seconds, "final_losses": res.losses, "selection": selection or {},
        "resumed_from_iteration": res.resumed_from, "loss_history": res.history[-200:], **(extra or {})}
    (root / "material.json").write_text(json.dumps(
        {"format": "dualscale-maps", "version": 1, "maps": names, "height": h, "width": w,
         "conventions": CONVENTIONS, "meta": {"fit": {k: report[k] for k in ("preset", "components", "iterations",
                                                                              "final_losses")},
                                              "ior": res.comps.ior}}, indent=1))
    path = root / "fit.json"
    path.write_text(json.dumps(report, indent=1, default=str))
    return path


def read_fit_attributes(path: str | Path) -> dict[str, Any]:
    """The ``dualscale:*`` attributes of a fitted EXR, JSON values decoded."""
    out: dict[str, Any] = {}
    for key, val in read_exr_attributes(path).items():
        try:
            out[key] = json.loads(val) if key in ("components", "final_losses", "selection") else val
        except (TypeError, json.JSONDecodeError):
            out[key] = val
    return out
