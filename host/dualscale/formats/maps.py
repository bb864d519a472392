"""SVBSDF maps on disk: one float32 EXR per active map, PNG previews, and ``material.json``.
The one reader (:func:`load_maps`) and writer (:func:`save_maps`) of maps, for ground truth
(``synth``), fitted maps (``fit``), propagated maps (``propagate run``) and exports.

``material.json`` (version 2)::

    {"format": "dualscale-maps", "version": 2, "maps": [names], "height": H, "width": W,
     "texel_mm": t | null, "field_mm": [W * t, H * t] | null,
     "conventions": CONVENTIONS, "meta": {...}}

``texel_mm`` is the physical size of one texel (the dataset's pixel pitch, carried through fit
and propagation); version-1 files (no size) are still read, with ``texel_mm`` null.  The value
conventions (:data:`CONVENTIONS`) are the single source of truth for every map on disk; the
canonical in-memory maps are :class:`dualscale.bsdf.MaterialMaps` (seed Sec. 5).

Loading refuses (``FormatError``/``GeometryError``) names it does not know, sizes that disagree
with ``material.json``, non-finite values and normal maps whose vectors are not unit length
(tolerance 1e-2) or point below the sample plane (z <= 0).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from dualscale.bsdf import MAP_CHANNELS, MaterialMaps, validate_maps
from dualscale.errors import FormatError, GeometryError

from .atomic import remove_file, write_json
from .exr import read_exr, write_exr, write_png_preview
from .versioned import read_versioned_json

FORMAT = "dualscale-maps"
VERSION = 2
_CHANNELS = {1: ("Y",), 3: ("R", "G", "B")}
_NORMAL = ("X", "Y", "Z")
NORMAL_TOLERANCE = 1e-2
CONVENTIONS = {
    "albedo": "linear RGB (Rec.709 primaries), [0,1]",
    "normal": "unit vector XYZ in the macro frame, +z = macro normal, +x = image right, +y = image up",
    "tangent": "azimuth = pi * value, CCW from image +x (axial)",
    "ior": "eta = 1 + 2 * value",
    "roughness": "GGX roughness r in [0,1] (alpha = r^2, Burley 2015)",
    "rows": "row 0 is the top of the image (+y)",
    "texel_mm": "physical size of one texel in mm (null when unknown)",
}


def channel_names(name: str) -> tuple[str, ...]:
    """EXR channel names of map ``name``."""
    return _NORMAL if name == "normal" else _CHANNELS[MAP_CHANNELS[name]]


def save_maps(root: str | Path, maps: MaterialMaps, meta: dict | None = None, previews: bool = True,
              texel_mm: float | None = None, attributes: dict[str, str] | None = None) -> Path:
    """Write every active map as ``<name>.exr`` (+ ``.png`` previews) and ``material.json``
    (written last, atomically: a folder with ``material.json`` is complete).  An earlier
    ``material.json`` is removed before the first map is written, so a write that fails half-way
    (a full disk) never leaves new maps under an old, complete-looking record; maps and previews
    of an earlier set that this one lacks (e.g. ``transmittance`` of another material) are
    removed, so no reader picks up a stale map.

    ``texel_mm``: texel size in mm (``None``: taken from ``meta["texel_mm"]`` when present);
    ``attributes``: extra EXR header attributes (``dualscale:*`` strings) for every map, plus
    ``dualscale:map`` = the map's name.  Returns the path of ``material.json``.
    """
    validate_maps(maps)
    root = Path(root)
    if texel_mm is None and meta and meta.get("texel_mm"):
        texel_mm = float(meta["texel_mm"])
    if texel_mm is not None and not (np.isfinite(texel_mm) and texel_mm > 0):
        raise ValueError(f"texel_mm must be a positive number of mm, got {texel_mm!r}")
    remove_file(root / "material.json")
    for name, t in maps.items():
        arr = t.detach().cpu().numpy()
        write_exr(root / f"{name}.exr", arr, channel_names(name), {**(attributes or {}), "dualscale:map": name}
                  if attributes else None)
        if previews:
            if name == "normal":
                write_png_preview(root / f"{name}.png", 0.5 * arr + 0.5, srgb=False)
            else:
                write_png_preview(root / f"{name}.png", arr, srgb=name in ("albedo", "transmittance"))
    written = {n for n, _ in maps.items()}
    for name in MAP_CHANNELS:
        for suffix in (".exr", ".png"):
            if name not in written or (suffix == ".png" and not previews):
                remove_file(root / f"{name}{suffix}")
    h, w = maps.shape
    doc = {"format": FORMAT, "version": VERSION, "maps": [n for n, _ in maps.items()], "height": h, "width": w,
           "texel_mm": texel_mm, "field_mm": None if texel_mm is None else [w * texel_mm, h * texel_mm],
           "conventions": CONVENTIONS, "meta": meta or {}}
    return write_json(root / "material.json", doc)


def read_material_json(root: str | Path) -> dict[str, Any]:
    """The validated ``material.json`` of a maps folder."""
    path = Path(root) / "material.json"
    if not path.is_file():
        raise FileNotFoundError(f"no material.json in {root} (not a maps folder)")
    doc = read_versioned_json(path, FORMAT, (1, VERSION))
    for key in ("maps", "height", "width"):
        if key not in doc:
            raise FormatError(f"{path}: missing {key!r}")
    return doc


def load_maps(root: str | Path, dtype: torch.dtype = torch.float32) -> tuple[MaterialMaps, dict]:
    """Read a maps folder written by :func:`save_maps`; returns ``(maps, meta)`` where ``meta``
    is the file's ``meta`` plus ``texel_mm`` and ``field_mm`` (``None`` when unknown)."""
    root = Path(root)
    doc = read_material_json(root)
    arrays = {}
    for name in doc["maps"]:
        if name not in MAP_CHANNELS:
            raise FormatError(f"{root / 'material.json'}: unknown map {name!r}")
        arr = read_exr(root / f"{name}.exr", channel_names(name))
        if arr.shape[:2] != (doc["height"], doc["width"]):
            raise FormatError(f"{root / name}.exr is {arr.shape[:2]}, material.json says "
                              f"{(doc['height'], doc['width'])}")
        if not np.isfinite(arr).all():
            raise FormatError(f"{root / name}.exr: {int((~np.isfinite(arr)).sum())} non-finite values")
        if name == "normal":
            check_normals(arr, f"{root / name}.exr")
        arrays[name] = torch.from_numpy(np.ascontiguousarray(arr)).to(dtype)
    if "albedo" not in arrays or "roughness" not in arrays:
        raise FormatError(f"{root}: albedo and roughness maps are required")
    maps = MaterialMaps(**arrays)
    validate_maps(maps)
    meta = dict(doc.get("meta", {}))
    meta["texel_mm"] = doc.get("texel_mm", meta.get("texel_mm"))
    t = meta["texel_mm"]
    meta["field_mm"] = doc.get("field_mm") or (None if not t else [doc["width"] * t, doc["height"] * t])
    return maps, meta


def check_normals(normal: np.ndarray, where: str) -> None:
    """Refuse ``(H, W, 3)`` normals that are not unit length or point below the sample plane."""
    n = np.asarray(normal, np.float64)
    length = np.linalg.norm(n, axis=-1)
    bad = np.abs(length - 1) > NORMAL_TOLERANCE
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise GeometryError(f"{where}: {int(bad.sum())} normals are not unit vectors (first at row {r}, col {c}: "
                            f"length {length[r, c]:.4f}; tolerance {NORMAL_TOLERANCE})")
    below = n[..., 2] <= 0
    if below.any():
        r, c = np.argwhere(below)[0]
        raise GeometryError(f"{where}: {int(below.sum())} normals point at or below the sample plane "
                            f"(z <= 0; first at row {r}, col {c})")
