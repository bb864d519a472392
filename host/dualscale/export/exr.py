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

``exchange.json`` lists the files, the repeat size in mm and the conventions.

**Uncertainty** (issue 26): when the maps folder has ``uncertainty/``
(:func:`dualscale.formats.maps.load_uncertainty`, passed in ``ctx.uncertainty``), the set also
holds ``<input>_sigma.exr`` (float32, the 1-sigma standard deviation, NaN where undetermined)
and ``sigma_undetermined.exr`` (one channel ``<input>_sigma.<chan>`` per sigma channel, 1 =
undetermined).  The sigma is in the exchange input's units where that input is a linear
function of our map (:data:`SIGMA_MAPPING`: ``specular_anisotropy = 0.9 a`` -> ``0.9 sigma_a``,
``specular_rotation = phi / pi`` -> ``sigma_deg / 180``, roughness, IOR, opacity, an opaque
``base_color`` as they are, the normal as an angle in degrees), and in our map's own units,
so stated, where it is not (``base_color = b / (1 - S)`` of a transmitting sample, the
``specular_color`` tint, the transmittance split into ``subsurface`` and ``subsurface_color``,
written as ``transmittance_sigma.exr``).  ``exchange.json`` ``"uncertainty"`` records, per file,
our map, the unit, the mapping and whether it is the exchange input's unit, plus the mask, the
noise source and what was left out (``null`` without an uncertainty).

Source: seed Sec. 5 (our model); Autodesk Standard Surface v1.0.1 (Georgiev et al. 2019),
Sec. 3; issue 26 (the uncertainty).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualscale.formats.atomic import write_json
from dualscale.formats.exr import write_exr, write_pixels

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


#: our map -> (exchange input or file stem, scale to the exchange unit or None (our unit kept),
#: the unit, the mapping), for the 1-sigma maps of the set (issue 26); ``base_color`` is in the
#: exchange unit only when the sample does not transmit (see :func:`_sigma_plan`)
SIGMA_MAPPING: dict[str, tuple[str, float | None, str, str]] = {
    "albedo": ("base_color", 1.0, "linear reflectance (base_color's unit)",
               "base_color = b: sigma(base_color) = sigma(b)"),
    "roughness": ("specular_roughness", 1.0, "specular_roughness r (GGX alpha = r^2)",
                  "specular_roughness = r: sigma = sigma_r"),
    "anisotropy": ("specular_anisotropy", 0.9, "specular_anisotropy (Standard Surface's value)",
                   "specular_anisotropy = 0.9 a: sigma = 0.9 sigma_a"),
    "tangent": ("specular_rotation", 1.0 / 180.0, "specular_rotation (1 = 180 degrees)",
                "specular_rotation = phi / pi: sigma = sigma_phi[deg] / 180"),
    "ior": ("specular_IOR", 1.0, "eta (index of refraction)", "specular_IOR = eta: sigma = sigma_eta"),
    "normal": ("normal", 1.0, "degrees (RMS angle to the true normal)",
               "the same unit vector: the angle is the same, in degrees (one channel)"),
    "opacity": ("opacity", 1.0, "coverage (opacity's unit)", "opacity = our opacity: sigma unchanged"),
    "specular_tint": ("specular_color", None, "our specular_tint rho_s (the map's value), not specular_color",
                      "specular_color = chr(b) rho_s + 1 - rho_s: not a function of rho_s alone; the sigma "
                      "of rho_s"),
    "transmittance": ("transmittance", None, "our diffuse transmittance t (linear), per channel",
                      "t = subsurface * subsurface_color (thin-walled split, S = Y(t) / Y(b + t)): no one "
                      "input holds t; the sigma of t"),
}


def _sigma_plan(maps: dict, trans) -> tuple[dict, dict]:
    """``(plan, left_out)``: ``{our map: (stem, scale, unit, mapping, exchange_unit)}`` for the
    sigma maps this set can carry, ``{our map: why}`` for the others."""
    plan, left_out = {}, {}
    needs = {"anisotropy": "specular_anisotropy", "tangent": "specular_rotation", "ior": "specular_IOR",
             "normal": "normal", "opacity": "opacity", "specular_tint": "specular_color",
             "transmittance": "subsurface_color"}
    for name, (stem, scale, unit, mapping) in SIGMA_MAPPING.items():
        if name in needs and needs[name] not in maps:
            left_out[name] = f"the set has no {needs[name]} map"
            continue
        if name == "albedo" and trans is not None:
            scale, unit = None, "our albedo b (linear reflectance), not base_color"
            mapping = ("base_color = b / (1 - subsurface) of a transmitting sample: not a function of b "
                       "alone; the sigma of b")
        plan[name] = (stem, 1.0 if scale is None else scale, unit, mapping, scale is not None)
    return plan, left_out


def _write_uncertainty(ex: Exchange, ctx, out: Path, maps: dict, trans) -> tuple[list[Path], dict | None]:
    """The sigma files and the mask of ``ctx.uncertainty`` (see the module docstring); returns
    ``(files, the exchange.json record)``.  ``ValueError`` when its size is not the maps'."""
    import OpenImageIO as oiio

    if ctx.uncertainty is None:
        return [], None if ctx.uncertainty_note is None else {"files": {}, "left_out": {"*": ctx.uncertainty_note}}
    sigma, und, doc = ctx.uncertainty
    plan, left_all = _sigma_plan(maps, trans)
    files: list[Path] = []
    record: dict[str, dict] = {}
    mask_names, masks = [], []
    for name in sigma:
        if name not in plan:
            continue
        stem, scale, unit, mapping, exchange_unit = plan[name]
        s, u = sigma[name], und[name]
        if s.shape[:2] != ex.shape:
            raise ValueError(f"the uncertainty of {name!r} is {s.shape[:2]}, the maps {ex.shape}")
        chans = ("Y",) if s.shape[2] == 1 else ("R", "G", "B")
        value = np.where(u, np.nan, np.asarray(s, np.float64) * scale).astype(np.float32)
        path = out / f"{stem}_sigma.exr"
        write_exr(path, value, chans, {"dualscale:sigma_of": name, "dualscale:unit": unit})
        files.append(path)
        record[stem] = {"file": path.name, "channels": list(chans), "of": name, "unit": unit,
                        "mapping": mapping, "exchange_unit": exchange_unit}
        mask_names += [f"{stem}_sigma.{c}" for c in chans]
        masks.append(u)
    left_out = {n: why for n, why in left_all.items() if n in sigma}
    mask_file = None
    if masks:
        mask = np.ascontiguousarray(np.concatenate(masks, -1).astype(np.float16))
        spec = oiio.ImageSpec(ex.shape[1], ex.shape[0], mask.shape[2], "half")
        spec.channelnames = tuple(mask_names)
        spec.attribute("compression", "zip")
        spec.attribute("DateTime", "")
        files.append(write_pixels(out / "sigma_undetermined.exr", mask, spec))
        mask_file = "sigma_undetermined.exr"
    meta = doc.get("meta") or {}
    return files, {"level": "1 sigma (standard deviation), NaN where undetermined", "files": record,
                   "mask": None if mask_file is None else {
                       "file": mask_file, "channels": mask_names,
                       "value": "1 = undetermined (the sigma there is NaN), 0 = determined",
                       "read": "by channel name (OpenEXR stores channels in its own order)"},
                   "noise": meta.get("noise"), "source_meta": meta,
                   "source": "maps/uncertainty (dualscale-uncertainty version "
                             f"{doc.get('version')})", "left_out": left_out}


def write(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write the exchange EXR set of ``ex`` into ``out`` (see the module table), with the 1-sigma
    maps of ``ctx.uncertainty`` when given (module docstring); returns the files."""
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
    sigma_files, uncertainty = _write_uncertainty(ex, ctx, out, maps, trans)
    files += sigma_files
    doc = {"format": "dualscale-exchange-exr", "version": 1, "name": ctx.name,
           "maps": sorted(maps), "height": ex.shape[0], "width": ex.shape[1],
           "repeat_mm": list(ctx.repeat_mm) if ctx.repeat_mm else None, "tiled": ctx.tiled,
           "specular_IOR": None if ex.ior is not None else ex.ior_scalar,
           "thin_walled": trans is not None, "conventions": CONVENTIONS, "meta": ctx.meta,
           "uncertainty": uncertainty}
    files.append(write_json(out / "exchange.json", doc))
    return files
