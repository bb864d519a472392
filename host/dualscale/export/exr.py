"""The exchange EXR set: full-precision float maps named after Autodesk Standard Surface inputs.

One float32 EXR per input, linear, rows top first, written beside our own maps (which keep
the model's own conventions, :mod:`dualscale.formats.maps`).  Standard Surface (v1.0.1) is the
convention of Substance, Arnold, MaterialX and close to Blender's Principled BSDF, and it holds
every one of our parameters exactly (see :mod:`.exchange` and docs/EXPORT.md):

==================== ======= ============================================================
file                 chans   value
==================== ======= ============================================================
base_color.exr       RGB     diffuse reflectance (``b / (1 - subsurface)`` when transmitting)
specular_roughness   Y       ``r``, GGX ``alpha = r^2``
specular_anisotropy  Y       Standard Surface anisotropy ``0.9 a`` (``aspect = sqrt(1 - s)``)
specular_rotation    Y       0..1 = 0..180 deg CCW from texture +u (the spec's unit; axial)
specular_IOR         Y       ``eta`` per pixel (not normalised)
specular_color       RGB     F0 tint ``chr(b) rho_s + 1 - rho_s``
normal               XYZ     unit tangent-space normal, OpenGL (+Y = image up), in [-1, 1]
subsurface           Y       thin-walled subsurface weight (Lambertian transmission)
subsurface_color     RGB     its tint
opacity              Y       coverage
==================== ======= ============================================================

``exchange.json`` lists the files, the repeat size in mm and the conventions.  Source: seed
Sec. 5 (our model); Autodesk Standard Surface v1.0.1 (Georgiev et al. 2019), Sec. 3.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualscale.formats.atomic import write_json

from .exchange import Exchange, standard_surface_anisotropy, thin_walled_translucency
from .textures import write_float

CONVENTIONS = {
    "model": "Autodesk Standard Surface v1.0.1 inputs (thin_walled with subsurface when transmitting)",
    "base_color": "linear Rec.709 RGB",
    "specular_roughness": "r, GGX alpha = r^2",
    "specular_anisotropy": "Standard Surface: aspect = sqrt(1 - value), alpha_x = r^2 / aspect",
    "specular_rotation": "0..1 = 0..180 degrees CCW about the normal from texture +u (Standard Surface spec)",
    "subsurface": "thin-walled subsurface weight: Lambertian diffuse transmission",
    "specular_IOR": "index of refraction eta",
    "specular_color": "linear RGB F0 tint",
    "normal": "unit tangent-space XYZ, +X = texture right (+u), +Y = texture up, +Z out (OpenGL)",
    "rows": "row 0 is the top of the texture",
}


def write(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write the exchange EXR set of ``ex`` into ``out`` (see the module table); returns the files."""
    out = Path(out)
    files: list[Path] = []
    trans = thin_walled_translucency(ex)
    rough, aniso, rot = standard_surface_anisotropy(ex)
    maps: dict[str, tuple[np.ndarray, tuple[str, ...]]] = {
        "base_color": (ex.base_color if trans is None else trans.base_color, ("R", "G", "B")),
        "specular_roughness": (rough, ("Y",)),
    }
    if aniso is not None:
        maps["specular_anisotropy"] = (aniso, ("Y",))
        maps["specular_rotation"] = (rot, ("Y",))
    if ex.ior is not None:
        maps["specular_IOR"] = (ex.ior, ("Y",))
    if ex.specular_color is not None:
        maps["specular_color"] = (ex.specular_color, ("R", "G", "B"))
    if ex.normal is not None:
        maps["normal"] = (ex.normal, ("X", "Y", "Z"))
    if trans is not None:
        maps["subsurface"] = (trans.weight, ("Y",))
        maps["subsurface_color"] = (trans.color, ("R", "G", "B"))
    if ex.opacity is not None:
        maps["opacity"] = (ex.opacity, ("Y",))
    for name, (arr, chans) in maps.items():
        files.append(write_float(out / f"{name}.exr", arr, chans))
    doc = {"format": "dualscale-exchange-exr", "version": 1, "name": ctx.name,
           "maps": sorted(maps), "height": ex.shape[0], "width": ex.shape[1],
           "repeat_mm": list(ctx.repeat_mm) if ctx.repeat_mm else None, "tiled": ctx.tiled,
           "specular_IOR": None if ex.ior is not None else ex.ior_scalar,
           "thin_walled": trans is not None, "conventions": CONVENTIONS, "meta": ctx.meta}
    files.append(write_json(out / "exchange.json", doc))
    return files
