"""Ground-truth maps on disk: one float32 EXR per active map plus ``material.json``.

``material.json``: ``{"format": "dualscale-maps", "version": 1, "maps": [names], "height": H,
"width": W, "conventions": {...}, "meta": {...}}``.  Fly-outs (when present):
``flyouts.json`` (polylines in pixel coordinates ``[col, row]`` and in mm) and
``flyout_mask.exr`` (1 on fibre pixels).  Relief (when present): ``geometry.exr``
(:func:`dualscale.dome.shadow.save_geometry`), which ``dualscale render --shadows`` reads.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from dualscale.bsdf import MAP_CHANNELS, MaterialMaps, validate_maps
from dualscale.dome.exr import read_exr, write_exr, write_png_preview

from .common import SyntheticMaterial

_CHANNELS = {1: ("Y",), 3: ("R", "G", "B")}
_NORMAL = ("X", "Y", "Z")
CONVENTIONS = {
    "albedo": "linear RGB (Rec.709 primaries), [0,1]",
    "normal": "unit vector XYZ in the macro frame, +z = macro normal, +x = image right, +y = image up",
    "tangent": "azimuth = pi * value, CCW from image +x (axial)",
    "ior": "eta = 1 + 2 * value",
    "rows": "row 0 is the top of the image (+y)",
}


def _names(name: str) -> tuple[str, ...]:
    return _NORMAL if name == "normal" else _CHANNELS[MAP_CHANNELS[name]]


def save_maps(root: str | Path, maps: MaterialMaps, meta: dict | None = None, previews: bool = True) -> Path:
    """Write every active map as ``<name>.exr`` (+ ``.png`` previews) and ``material.json``."""
    validate_maps(maps)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for name, t in maps.items():
        arr = t.detach().cpu().numpy()
        write_exr(root / f"{name}.exr", arr, _names(name))
        if previews:
            if name == "normal":
                write_png_preview(root / f"{name}.png", 0.5 * arr + 0.5, srgb=False)
            else:
                write_png_preview(root / f"{name}.png", arr, srgb=name in ("albedo", "transmittance"))
    h, w = maps.shape
    doc = {"format": "dualscale-maps", "version": 1, "maps": [n for n, _ in maps.items()], "height": h, "width": w,
           "conventions": CONVENTIONS, "meta": meta or {}}
    path = root / "material.json"
    path.write_text(json.dumps(doc, indent=1))
    return path


def load_maps(root: str | Path, dtype: torch.dtype = torch.float32) -> tuple[MaterialMaps, dict]:
    """Read a directory written by :func:`save_maps`; checks names, sizes and finiteness."""
    root = Path(root)
    path = root / "material.json"
    if not path.is_file():
        raise FileNotFoundError(f"no material.json in {root}")
    doc = json.loads(path.read_text())
    if doc.get("format") != "dualscale-maps":
        raise ValueError(f"{path}: not a dualscale-maps file")
    arrays = {}
    for name in doc["maps"]:
        if name not in MAP_CHANNELS:
            raise ValueError(f"{path}: unknown map {name!r}")
        arr = read_exr(root / f"{name}.exr", _names(name))
        if arr.shape[:2] != (doc["height"], doc["width"]):
            raise ValueError(f"{name}.exr is {arr.shape[:2]}, material.json says {(doc['height'], doc['width'])}")
        arrays[name] = torch.from_numpy(np.ascontiguousarray(arr)).to(dtype)
    if "albedo" not in arrays or "roughness" not in arrays:
        raise ValueError(f"{root}: albedo and roughness maps are required")
    maps = MaterialMaps(**arrays)
    validate_maps(maps)
    return maps, doc.get("meta", {})


def save_material(root: str | Path, mat: SyntheticMaterial, previews: bool = True) -> None:
    """Maps plus fly-out ground truth (polylines JSON and mask EXR/PNG) and the relief
    (``geometry.exr``) when present."""
    root = Path(root)
    save_maps(root, mat.maps, mat.meta, previews)
    if mat.geometry is not None:
        from dualscale.dome.shadow import save_geometry

        save_geometry(root / "geometry.exr", mat.geometry)
    if mat.flyout_mask is not None:
        h, w = mat.maps.shape
        t = float(mat.meta.get("texel_mm", 0.0))

        def mm(c, r):
            return [(c + 0.5 - w / 2) * t, (h / 2 - r - 0.5) * t]

        (root / "flyouts.json").write_text(json.dumps({
            "count": len(mat.flyouts), "coordinates": "pixel [col, row] (row 0 at top); mm [x, y] macro frame",
            "polylines_px": [[[c, r] for c, r in pl] for pl in mat.flyouts],
            "polylines_mm": [[mm(c, r) for c, r in pl] for pl in mat.flyouts]}, indent=1))
        write_exr(root / "flyout_mask.exr", mat.flyout_mask.astype(np.float32), ("Y",))
        if previews:
            write_png_preview(root / "flyout_mask.png", mat.flyout_mask.astype(np.float32), srgb=False)
