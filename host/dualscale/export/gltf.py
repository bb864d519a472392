"""glTF 2.0 export (issue 12): our maps on a swatch mesh at real-world size, as ``.gltf`` (JSON +
``.bin`` + PNG textures with relative URIs) or as one self-contained ``.glb``.

Written with ``pygltflib``; the tests run the Khronos glTF-Validator on every export.  The
parameters come from :mod:`.exchange` (one conversion for all formats); this module only
encodes them.  docs/EXPORT.md tabulates what is exact, approximated and lost.

Material (glTF 2.0 spec Sec. 3.9 and the Khronos extensions named):

* ``pbrMetallicRoughness``: ``baseColorTexture`` (sRGB 8-bit PNG; alpha = our opacity,
  linear, when the sample has holes), ``metallicRoughnessTexture`` (linear 16-bit: G =
  roughness ``r`` with ``alpha = r^2``, B = metallic = 0, R = 1 unused), ``metallicFactor 0``.
* ``normalTexture``: linear 16-bit, ``0.5 n + 0.5`` of our OpenGL (+Y up) normal.
* ``KHR_materials_ior``: ``ior`` = :attr:`Exchange.ior_scalar` (a scalar in glTF).
* ``KHR_materials_specular`` (when there is a tint or an IOR map): ``specularColorTexture``
  (sRGB 8-bit) and ``specularColorFactor`` from :func:`.exchange.specular_f0_color`; the
  extension's schema bounds ``specularColorFactor`` only below (>= 0), so factors > 1 are legal.
* ``KHR_materials_anisotropy`` (anisotropic maps): ``anisotropyTexture`` (linear 16-bit, RG =
  ``0.5 d + 0.5`` of the direction in tangent/bitangent space, B = strength),
  ``anisotropyStrength 1``; the roughness texture then holds the extension's base roughness
  (:func:`.exchange.gltf_anisotropy`).
* ``KHR_materials_transmission`` (transmitting samples): ``transmissionTexture`` (linear
  16-bit, R = weight) from :func:`.exchange.gltf_transmission`, which also gives the base colour.
  Without ``KHR_materials_volume`` the surface is thin-walled (transmission spec, "Thin-walled
  materials"): right for a fabric sheet.  ``KHR_materials_volume`` is *not* written: it needs a
  closed mesh with a thickness and an attenuation, and our swatch is a single sheet and the rig
  measures neither (docs/EXPORT.md).
* Opacity (coverage of the yarns) is the base colour's alpha with ``alphaMode "BLEND"``: it is
  fractional at the texel scale (gaps between yarns), which ``MASK`` would binarise; maps
  without opacity, or fully opaque, are ``OPAQUE``.
* ``KHR_texture_transform`` (``scale = ctx.repeats()``) on every texture when the swatch holds
  more than one repeat, with ``REPEAT`` samplers (tiles; ``CLAMP_TO_EDGE`` for a single, untiled
  map, so that bilinear filtering does not bleed the opposite border in).
* ``doubleSided: true`` (a fabric is seen from both sides).

The mesh and its tangent frame are :func:`.swatch.swatch_mesh` (image +x = tangent, image +y =
bitangent, so no texture is flipped).  ``asset.generator`` is ``"dualscale <version>"``;
``asset.extras.dualscale`` holds the provenance (``ctx.meta``), the repeat and swatch sizes in
mm, the texel size, and whether the scale is known (an unknown texel size gives a swatch of
:data:`~dualscale.export.DEFAULT_SWATCH_MM` with a note that the scale is unknown; pygltflib
drops null values, so unknown sizes are absent keys).

Errors: :class:`~dualscale.errors.UnitsError` for a repeat or swatch size that is not finite and
positive; :class:`~dualscale.errors.InputError` for an :class:`Exchange` whose maps disagree in
size; ``ValueError`` from :mod:`.textures` for values outside [0, 1].
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib as g

from dualscale import __version__
from dualscale.errors import InputError
from dualscale.formats.atomic import write_bytes, write_text

from .exchange import Exchange, gltf_anisotropy, gltf_transmission, specular_f0_color
from .swatch import SwatchMesh, swatch_mesh
from .textures import encode_normal, write_png

GENERATOR = f"dualscale {__version__}"
DATA_BITS = 16  # linear data textures: 16-bit PNG (accepted by the glTF-Validator; tested)
OPAQUE_TOL = 0.5 / 255  # opacity within half an 8-bit step of 1 everywhere: OPAQUE

_FLOAT, _USHORT = 5126, 5123            # accessor component types
_ARRAY, _ELEMENT = 34962, 34963         # bufferView targets
_LINEAR, _LINEAR_MIPMAP_LINEAR = 9729, 9987
_REPEAT, _CLAMP = 10497, 33071


@dataclass
class _Tex:
    """One texture image: ``key`` (file and image name), values in [0, 1] ``(H, W[, C])``,
    sRGB or linear, 8 or 16 bits."""

    key: str
    image: np.ndarray
    srgb: bool
    bits: int


def _textures(ex: Exchange) -> tuple[list[_Tex], dict]:
    """The texture images and the scalar parameters of the material (module docstring)."""
    h, w = ex.shape
    for name in ("roughness", "anisotropy", "tangent_angle", "normal", "ior", "specular_color",
                 "transmittance", "opacity"):
        a = getattr(ex, name)
        if a is not None and tuple(a.shape[:2]) != (h, w):
            raise InputError(f"glTF export: map {name} is {a.shape[1]}x{a.shape[0]}, "
                             f"base_color is {w}x{h}")
    texs: list[_Tex] = []
    params: dict = {"alpha_mode": "OPAQUE"}
    trans = gltf_transmission(ex)
    base = ex.base_color if trans is None else trans.base_color
    if ex.opacity is not None and float(ex.opacity.min()) < 1.0 - OPAQUE_TOL:
        params["alpha_mode"] = "BLEND"
        rgba = np.concatenate([base, ex.opacity[..., None]], -1)  # alpha linear, unassociated (write_png)
        texs.append(_Tex("base_color", rgba, True, 8))
    else:
        texs.append(_Tex("base_color", base, True, 8))
    rough, strength, direction = gltf_anisotropy(ex)
    mr = np.stack([np.ones_like(rough), rough, np.zeros_like(rough)], -1)
    texs.append(_Tex("metallic_roughness", mr, False, DATA_BITS))
    if ex.normal is not None:
        texs.append(_Tex("normal", encode_normal(ex.normal), False, DATA_BITS))
    if strength is not None:
        aniso = np.concatenate([0.5 * direction + 0.5, strength[..., None]], -1)
        texs.append(_Tex("anisotropy", aniso, False, DATA_BITS))
    if ex.specular_color is not None or ex.ior is not None:
        color, factor = specular_f0_color(ex)
        texs.append(_Tex("specular_color", color, True, 8))
        params["specular_color_factor"] = factor
    if trans is not None and float(trans.weight.max()) > 0.0:
        texs.append(_Tex("transmission", trans.weight, False, DATA_BITS))
    return texs, params


def _check_sizes(ctx) -> tuple[tuple[float, float], tuple[float, float] | None]:
    return ctx.checked_sizes("glTF export")


class _Builder:
    """Accumulates the binary buffer, buffer views and accessors of one glTF document."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[g.BufferView] = []
        self.accessors: list[g.Accessor] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        self.blob += b"\0" * (-len(self.blob) % 4)  # 4-byte alignment of every view
        self.views.append(g.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data),
                                       target=target))
        self.blob += data
        return len(self.views) - 1

    def accessor(self, arr: np.ndarray, kind: str, minmax: bool = False) -> int:
        arr = np.ascontiguousarray(arr)
        index = arr.dtype == np.uint16
        view = self.view(arr.tobytes(), _ELEMENT if index else _ARRAY)
        flat = arr.reshape(len(arr), -1)
        self.accessors.append(g.Accessor(
            bufferView=view, componentType=_USHORT if index else _FLOAT, count=len(arr), type=kind,
            min=[float(x) for x in flat.min(0)] if minmax else None,
            max=[float(x) for x in flat.max(0)] if minmax else None))
        return len(self.accessors) - 1


def _document(ex: Exchange, ctx, params: dict,
              images: list[tuple[_Tex, str | bytes]]) -> tuple[g.GLTF2, bytearray]:
    """The glTF document and its binary buffer; ``images`` pairs each texture with a relative
    URI (``.gltf``) or its PNG bytes (``.glb``, embedded as a buffer view)."""
    sw_mm, repeat_mm = _check_sizes(ctx)
    mesh: SwatchMesh = swatch_mesh(*sw_mm)
    b = _Builder()
    attrs = g.Attributes(POSITION=b.accessor(mesh.positions, "VEC3", minmax=True),
                         NORMAL=b.accessor(mesh.normals, "VEC3"),
                         TANGENT=b.accessor(mesh.tangents, "VEC4"),
                         TEXCOORD_0=b.accessor(mesh.texcoords, "VEC2"))
    indices = b.accessor(mesh.indices, "SCALAR")

    reps = ctx.repeats()
    transformed = any(abs(r - 1.0) > 1e-9 for r in reps)
    wrap = _REPEAT if (ctx.tiled or transformed) else _CLAMP
    used: set[str] = set()

    gl_images, textures, slot = [], [], {}
    for tex, src in images:
        if isinstance(src, str):
            gl_images.append(g.Image(uri=src, name=tex.key))
        else:
            gl_images.append(g.Image(bufferView=b.view(src), mimeType="image/png", name=tex.key))
        textures.append(g.Texture(source=len(gl_images) - 1, sampler=0, name=tex.key))
        slot[tex.key] = len(textures) - 1

    def info(key: str, cls=g.TextureInfo, **kw):
        ext = {}
        if transformed:
            ext = {"KHR_texture_transform": {"scale": [float(reps[0]), float(reps[1])]}}
            used.add("KHR_texture_transform")
        return cls(index=slot[key], extensions=ext, **kw)

    def as_dict(ti) -> dict:
        d = {"index": ti.index}
        if ti.extensions:
            d["extensions"] = ti.extensions
        return d

    exts: dict = {"KHR_materials_ior": {"ior": round(float(ex.ior_scalar), 6)}}
    used.add("KHR_materials_ior")
    if "specular_color" in slot:
        exts["KHR_materials_specular"] = {
            "specularColorTexture": as_dict(info("specular_color")),
            "specularColorFactor": [float(params["specular_color_factor"])] * 3}
        used.add("KHR_materials_specular")
    if "anisotropy" in slot:
        exts["KHR_materials_anisotropy"] = {"anisotropyStrength": 1.0,
                                            "anisotropyTexture": as_dict(info("anisotropy"))}
        used.add("KHR_materials_anisotropy")
    if "transmission" in slot:
        exts["KHR_materials_transmission"] = {"transmissionFactor": 1.0,
                                              "transmissionTexture": as_dict(info("transmission"))}
        used.add("KHR_materials_transmission")

    material = g.Material(
        name=ctx.name, doubleSided=True, alphaMode=params["alpha_mode"], extensions=exts,
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0,
            baseColorTexture=info("base_color"),
            metallicRoughnessTexture=info("metallic_roughness")),
        normalTexture=info("normal", g.NormalMaterialTexture, scale=1.0) if "normal" in slot else None)

    scale_known = repeat_mm is not None
    extras = {"dualscale": {
        "provenance": dict(ctx.meta),
        "repeat_mm": None if repeat_mm is None else [float(repeat_mm[0]), float(repeat_mm[1])],
        "swatch_mm": [sw_mm[0], sw_mm[1]],
        "repeats": [float(reps[0]), float(reps[1])],
        "texel_mm": ex.texel_mm,
        "tiled": bool(ctx.tiled),
        "scale_known": scale_known,
        "units": "mesh in metres (glTF); sizes here in mm",
        "tangent_space": "tangent = +u = image right, bitangent = image up; normals OpenGL (+Y up)",
    }}
    if not scale_known:
        extras["dualscale"]["note"] = (
            f"the texel size is unknown: the swatch is a conventional {sw_mm[0]:g} x {sw_mm[1]:g} mm, "
            "not the sample's physical size")

    doc = g.GLTF2(
        asset=g.Asset(generator=GENERATOR, version="2.0", extras=extras),
        scene=0, scenes=[g.Scene(nodes=[0], name=ctx.name)],
        nodes=[g.Node(mesh=0, name=ctx.name)],
        meshes=[g.Mesh(name=f"{ctx.name}_swatch", primitives=[
            g.Primitive(attributes=attrs, indices=indices, material=0, mode=4)])],
        materials=[material], textures=textures, images=gl_images,
        samplers=[g.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=wrap, wrapT=wrap)],
        accessors=b.accessors, bufferViews=b.views,
        extensionsUsed=sorted(used))
    return doc, b.blob


def _write_pngs(texs: list[_Tex], folder: Path, stem: str) -> list[tuple[_Tex, Path]]:
    out = []
    for t in texs:
        out.append((t, write_png(folder / f"{stem}_{t.key}.png", t.image, srgb=t.srgb, bits=t.bits)))
    return out


def write_gltf(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write ``<name>.gltf`` + ``<name>.bin`` + ``<name>_<map>.png`` into ``out`` (relative
    URIs); returns the files, the ``.gltf`` first.  See the module docstring for the mapping."""
    out = Path(out)
    _check_sizes(ctx)  # refuse a bad size before any file is written
    texs, params = _textures(ex)
    written = _write_pngs(texs, out, ctx.name)
    doc, blob = _document(ex, ctx, params, [(t, p.name) for t, p in written])
    bin_path = write_bytes(out / f"{ctx.name}.bin", bytes(blob))
    doc.buffers = [g.Buffer(uri=bin_path.name, byteLength=len(blob))]
    gltf_path = write_text(out / f"{ctx.name}.gltf", doc.gltf_to_json() + "\n")
    return [gltf_path, bin_path] + [p for _, p in written]


def write_glb(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write one self-contained ``<name>.glb`` into ``out`` (textures embedded as buffer views);
    returns ``[path]``."""
    out = Path(out)
    _check_sizes(ctx)  # refuse a bad size before any file is written
    texs, params = _textures(ex)
    with tempfile.TemporaryDirectory(prefix="dualscale-glb-") as tmp:
        pngs = [(t, p.read_bytes()) for t, p in _write_pngs(texs, Path(tmp), ctx.name)]
    doc, blob = _document(ex, ctx, params, pngs)
    blob += b"\0" * (-len(blob) % 4)
    doc.buffers = [g.Buffer(byteLength=len(blob))]
    doc.set_binary_blob(bytes(blob))
    return [write_bytes(out / f"{ctx.name}.glb", b"".join(doc.save_to_bytes()))]
