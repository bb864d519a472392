"""U3M 1.1 export: the front side of our maps as a Vizoo/Browzwear ``.u3ma`` (U3M JSON + textures, zipped).

Source: the U3M 1.1 specification (Vizoo GmbH, BSD-3): ``u3m_schema.json`` (JSON Schema draft-07),
``u3m_additional_spec.txt`` (colour spaces, paths), ``u3m_additional_spec_u3m.txt`` (baseline image
formats, "All normals are in OpenGL convention", normal encoding ``(n + 1) / 2``, factor/offset:
``final = offset + average(pixel) * factor``) and ``u3m_additional_spec_u3ma.txt`` (the zip subset).
docs/EXPORT.md tabulates what is exact, approximated and lost.

What is written (``material.front``, ``shader: "principled"`` -- the Disney 2012 / Blender
Principled parameters; the spec gives names and ranges, not formulas, so we read each parameter
with the principled model's definition):

* ``basecolor``: 8-bit sRGB PNG (U3M standard colour space sRGB; constant sRGB-encoded);
  with transmission the glTF-style split of :func:`.exchange.gltf_transmission` (``b + t``).
* ``roughness``: ``r`` (principled ``alpha = r^2``, our ``sigma_r``) -- copied.
* ``anisotropy_value``: our ``a`` (principled ``aspect = sqrt(1 - 0.9 a)``, Burley's, ours) and
  ``anisotropy_rotation``: a fraction of a full turn CCW from texture +u, ``phi / (2 pi)`` (the
  schema: "value is in percent, to get to degree, multiply by 360"; axial, so in [0, 0.5)).
* ``normal``: OpenGL (+Y = image up), the exchange convention -- no flip -- encoded ``(n + 1) / 2``.
* ``ior``: ``eta`` per pixel; ``specular_value``: principled ``F0 / 0.08`` of that ``eta``
  (the schema: "[0%, 8%] -> 0.0 equals 0%, and 1.0 equals 8%").
* ``specular_tint``: the principled scalar tint, fitted per pixel to our F0 tint
  (:func:`_principled_tint`, least squares; U3M-specific because principled tints towards
  ``base / luminance(base)`` where ours tints towards ``base / max(base)``).
* ``transmission``: the thin-walled weight of :func:`.exchange.gltf_transmission` (transmissive
  samples only); ``alpha``: our opacity.
* ``back`` and ``side`` are ``null``: the schema's "if null, the values from front are used
  instead" (we capture only the front).  No sheen, clearcoat, subsurface, displacement or metal.

Scalar textures are 16-bit linear RGB PNGs with three equal channels (the baseline PNG formats
are "8/16bit rgb/rgba"; readers average the channels), normalised with ``factor``/``offset``
when the values leave [0, 1].  Every image carries ``width``/``height`` = ``ctx.repeat_mm`` and
the matching ``dpi`` (pixels per 25.4 mm), repeat mode ``"normal"`` (wrap).

Errors: :class:`~dualscale.errors.UnitsError` when ``ctx.repeat_mm`` is ``None`` (U3M requires
the physical size); nothing is written then.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
import tempfile
import uuid
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import UnitsError
from dualscale.formats.atomic import atomic_path

from .exchange import Exchange, f0_from_ior, gltf_transmission, luminance
from .textures import encode_normal, write_png

SCHEMA_VERSION = "1.1"
PRINCIPLED_F0_MAX = 0.08  # schema specular_value: "1.0 equals 8%"
_EFS = 0x800              # zip general purpose bit 11: UTF-8 names (.u3ma: "must be always set")
_MADE_BY_VERSION = 63     # .u3ma versionMadeBy: "you should read 0x00?? and write 0x003F"


class _U3maInfo(zipfile.ZipInfo):
    """A zip entry as ``u3m_additional_spec_u3ma.txt`` requires, from :mod:`zipfile`.

    Two of zipfile's defaults break the .u3ma rules and are overridden here: it gives every
    written entry external attributes ``0o600 << 16`` (.u3ma: ``externalFileAttributes`` "must be
    0") and sets the EFS flag only for non-ASCII names (.u3ma: "bit 11 (EFS) must be always set").
    tests/export/test_u3m.py checks the bytes, so a change in zipfile shows there.
    """

    __slots__ = ()
    external_attr = property(lambda self: 0, lambda self, value: None)

    def __init__(self, name: str, when: _dt.datetime, compress: int):
        super().__init__(name, date_time=when.timetuple()[:6])  # "MS-DOS time (in UTC!)"
        self.create_system = 0                  # upper byte of versionMadeBy: 0 (FAT)
        self.create_version = _MADE_BY_VERSION  # lower byte 63
        self.compress_type = compress           # 0 (stored) or 8 (deflate) only

    def _encodeFilenameFlags(self):  # noqa: N802 - zipfile's name
        return self.filename.encode("utf-8"), self.flag_bits | _EFS


def _stem(name: str) -> str:
    """A portable file stem (``[0-9a-zA-Z._-]``, the spec's "portable posix" names)."""
    s = re.sub(r"[^0-9A-Za-z_.-]", "_", name).strip(". ")
    return s or "material"


def _image(path: str, shape: tuple[int, int], size_mm: tuple[float, float]) -> dict[str, Any]:
    h, w = shape
    return {"width": float(size_mm[0]), "height": float(size_mm[1]),
            "dpi": {"x": w * 25.4 / size_mm[0], "y": h * 25.4 / size_mm[1]},
            "path": path, "repeat": {"rotation": 0.0, "mode": "normal"}}


class _Textures:
    """Collects the PNGs of one material (written to a scratch folder, then zipped)."""

    def __init__(self, scratch: Path, stem: str, shape: tuple[int, int], size_mm: tuple[float, float]):
        self.scratch, self.stem, self.shape, self.size_mm = scratch, stem, shape, size_mm
        self.files: list[str] = []

    def png(self, key: str, img: np.ndarray, srgb: bool, bits: int) -> dict[str, Any]:
        name = f"{self.stem}_{key}.png"
        write_png(self.scratch / name, img, srgb=srgb, bits=bits)
        self.files.append(name)
        return _image(name, self.shape, self.size_mm)

    def scalar(self, key: str, values: np.ndarray | None, constant: float) -> dict[str, Any]:
        """``texture_and_number``: a 16-bit grey-as-RGB texture (``None``: constant only)."""
        if values is None:
            return {"constant": float(constant), "texture": None}
        v = np.asarray(values, np.float64)
        lo, hi = float(v.min()), float(v.max())
        if hi - lo < 1e-7:
            return {"constant": float(lo), "texture": None}
        offset, factor = (0.0, 1.0) if lo >= 0.0 and hi <= 1.0 else (lo, hi - lo)
        img = np.repeat(((v - offset) / factor)[..., None], 3, axis=-1)
        tex = {"factor": factor, "offset": offset, "image": self.png(key, img, srgb=False, bits=16)}
        return {"constant": float(v.mean()), "texture": tex}


def _srgb(rgb) -> dict[str, float]:
    """A linear colour as the schema's ``color_rgb`` ("in u3m standard colorspace": sRGB)."""
    import colour

    s = np.clip(colour.models.eotf_inverse_sRGB(np.clip(np.asarray(rgb, np.float64), 0, 1)), 0, 1)
    return {"r": float(s[0]), "g": float(s[1]), "b": float(s[2])}


def _principled_tint(tint: np.ndarray | None, base: np.ndarray) -> np.ndarray | None:
    """Principled ``specular_tint`` ``s`` (H, W) best matching our F0 tint (H, W, 3).

    Principled's tint is ``mix(1, c, s)`` with ``c = base / luminance(base)`` (Burley 2012,
    Blender's ``m_ctint``); ours is ``chr(b) rho_s + 1 - rho_s`` with ``chr(b) = b / max(b)``
    (seed Sec. 5).  Per pixel ``s = <T - 1, c - 1> / |c - 1|^2`` (least squares), clipped to
    [0, 1]; grey bases (``c = 1``) give 0.  Approximate: the two chromaticities differ in scale.
    """
    if tint is None:
        return None
    b = np.asarray(base, np.float64)
    y = luminance(b)
    c = np.where(y[..., None] > 1e-6, b / np.maximum(y, 1e-6)[..., None], 1.0)
    d = c - 1.0
    num = ((np.asarray(tint, np.float64) - 1.0) * d).sum(-1)
    den = (d * d).sum(-1)
    return np.clip(np.where(den > 1e-9, num / np.maximum(den, 1e-9), 0.0), 0.0, 1.0)


def _axial_mean_rotation(rot: np.ndarray) -> float:
    """Mean of an axial rotation field (fractions of a turn, modulo 0.5) in [0, 0.5)."""
    ang = 4.0 * math.pi * np.asarray(rot, np.float64)  # doubled angle: axial -> circular
    m = math.atan2(float(np.sin(ang).mean()), float(np.cos(ang).mean()))
    return (m / (4.0 * math.pi)) % 0.5


def _visualisation(ex: Exchange, tx: _Textures) -> dict[str, Any]:
    trans = gltf_transmission(ex)
    base = ex.base_color if trans is None else trans.base_color
    vis: dict[str, Any] = {"shader": "principled", "preview": None}
    vis["basecolor"] = {"constant": _srgb(base.reshape(-1, 3).mean(0)), "texture": {
        "mode": "multiply", "factor": {"r": 1.0, "g": 1.0, "b": 1.0},
        "image": tx.png("basecolor", base, srgb=True, bits=8)}}
    vis["roughness"] = tx.scalar("roughness", ex.roughness, 0.7)
    # "value is in percent, to get to degree, multiply by 360": a fraction of a full turn
    rotation = None if ex.tangent_angle is None else (ex.tangent_angle.astype(np.float64) / (2 * math.pi))
    if ex.anisotropy is not None and rotation is not None:
        vis["anisotropy_value"] = tx.scalar("anisotropy", ex.anisotropy, 0.0)
        vis["anisotropy_rotation"] = tx.scalar("anisotropy_rotation", rotation, 0.0)
        if vis["anisotropy_rotation"]["texture"] is not None:
            vis["anisotropy_rotation"]["constant"] = _axial_mean_rotation(rotation)
    else:
        vis["anisotropy_value"] = tx.scalar("anisotropy", None, 0.0)
        vis["anisotropy_rotation"] = tx.scalar("anisotropy_rotation", None, 0.0)
    if ex.normal is not None:
        mean = ex.normal.reshape(-1, 3).astype(np.float64).mean(0)
        mean = mean / max(float(np.linalg.norm(mean)), 1e-12)
        vis["normal"] = {"constant": dict(zip("xyz", map(float, mean))), "texture": {
            "scale": 1.0, "image": tx.png("normal", encode_normal(ex.normal), srgb=False, bits=16)}}
    else:
        vis["normal"] = {"constant": {"x": 0.0, "y": 0.0, "z": 1.0}, "texture": None}
    vis["ior"] = tx.scalar("ior", ex.ior, ex.ior_scalar)
    spec = None if ex.ior is None else f0_from_ior(ex.ior) / PRINCIPLED_F0_MAX
    vis["specular_value"] = tx.scalar("specular", spec, float(f0_from_ior(ex.ior_scalar)) / PRINCIPLED_F0_MAX)
    tint = _principled_tint(ex.specular_color, base)
    vis["specular_tint"] = tx.scalar("specular_tint", tint, 0.0)
    vis["transmission"] = tx.scalar("transmission", None if trans is None else trans.weight, 0.0)
    vis["alpha"] = tx.scalar("alpha", ex.opacity, 1.0)
    zero = {"constant": 0.0, "texture": None}
    for key in ("clearcoat_value", "clearcoat_roughness", "metalness", "displacement", "sheen_value",
                "sheen_tint", "subsurface_radius", "subsurface_value"):
        vis[key] = dict(zero)
    vis["clearcoat_normal"] = {"constant": {"x": 0.0, "y": 0.0, "z": 1.0}, "texture": None}
    vis["subsurface_color"] = {"constant": {"r": 1.0, "g": 1.0, "b": 1.0}, "texture": None}
    return vis


def u3m_document(ex: Exchange, ctx, tx: _Textures, when: _dt.datetime) -> dict[str, Any]:
    """The U3M 1.1 JSON object (writes the textures through ``tx``)."""
    stamp = when.strftime("%Y-%m-%dT%H:%M:%SZ")
    h, w = ex.shape
    size = tx.size_mm
    desc = (f"Digitized SVBSDF ({w} x {h} texels, one repeat {size[0]:.4g} x {size[1]:.4g} mm"
            f"{', seamless tile' if ctx.tiled else ''}); front side measured, back and side null "
            f"(= front). Written by dualscale (Garces et al. 2023 dual-scale rig).")
    custom_meta = {k: (v if isinstance(v, (str, int, float, bool)) or v is None else str(v))
                   for k, v in dict(ctx.meta).items()}
    return {
        "schema": SCHEMA_VERSION,
        "material": {
            "id": str(uuid.uuid4()), "name": ctx.name, "description": desc,
            "created": stamp, "modified": stamp,
            "front": _visualisation(ex, tx), "back": None, "side": None,
            "physics": None, "metadata": None,
        },
        "custom": {"dualscale": {**custom_meta, "repeat_mm": list(size), "tiled": bool(ctx.tiled),
                                 "texel_mm": ex.texel_mm}},
    }


def write(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write ``out/<name>.u3ma`` (U3M 1.1 JSON + PNG textures, zipped per the .u3ma rules).

    ``ctx.repeat_mm`` ``(width, height)`` mm becomes every image's ``width``/``height`` (and
    ``dpi``).  Raises :class:`UnitsError` when it is ``None``.  Returns ``[path]``.
    """
    if ctx.repeat_mm is None:
        raise UnitsError(
            f"U3M export of {ctx.name!r}: U3M requires the physical size of the texture "
            "(u3m_schema.json image.width/height in mm, required), but the texel size of these maps "
            "is unknown. Re-import the photographs with `dualscale import ... --texel-mm MM` (the "
            "pixel pitch on the sample), or export another format (exr, mtlx, gltf, glb).")
    size = (float(ctx.repeat_mm[0]), float(ctx.repeat_mm[1]))
    if not all(math.isfinite(s) and s > 0 for s in size):
        raise UnitsError(f"U3M export of {ctx.name!r}: repeat_mm {ctx.repeat_mm} must be positive (mm)")
    out = Path(out)
    stem = _stem(ctx.name)
    when = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)
    when = when.replace(second=when.second - when.second % 2)  # MS-DOS time has 2 s steps
    path = out / f"{stem}.u3ma"
    with tempfile.TemporaryDirectory(prefix="dualscale-u3m-") as scratch:
        tx = _Textures(Path(scratch), stem, ex.shape, size)
        doc = u3m_document(ex, ctx, tx, when)
        body = json.dumps(doc, indent=2, allow_nan=False).encode("utf-8")
        with atomic_path(path) as tmp:
            with zipfile.ZipFile(tmp, "w", allowZip64=False) as zf:
                zf.writestr(_U3maInfo(f"{stem}.u3m", when, zipfile.ZIP_DEFLATED), body)
                for name in tx.files:  # PNG data is already deflated: stored
                    zf.writestr(_U3maInfo(name, when, zipfile.ZIP_STORED), (Path(scratch) / name).read_bytes())
    return [path]
