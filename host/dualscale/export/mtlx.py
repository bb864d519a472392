"""MaterialX export: one ``<name>.mtlx`` with two shaders, ``standard_surface`` and
``open_pbr_surface``, each with its own ``surfacematerial``, plus their textures (issue 12).

Written with the MaterialX Python API (PyPI ``materialx`` 1.39) and checked with MaterialX's
own ``Document.validate()`` against its standard data libraries before the file is written.
docs/EXPORT.md (MaterialX tables) says, per input, what is exact, approximated and lost.

Textures (rows top first; MaterialX puts texture coordinate (0, 0) at the image's lower-left,
so image +y = +v = the bitangent, which makes our OpenGL-style normals and CCW angles right):

* colour -- ``base_color``, ``specular_color``, ``subsurface_color``: sRGB-encoded 8-bit PNG,
  ``colorspace="srgb_texture"`` (MaterialX's name for the IEC 61966-2-1 texture encoding).
* data -- roughness, anisotropy, IOR, normal, tangent, subsurface weight, opacity:
  linear float32 EXR read by ``float``/``vector3`` image nodes.  MaterialX applies colour
  management only to ``color3``/``color4`` images, so these carry no ``colorspace`` (there is
  no ``raw`` in MaterialX's colour-space list; the document's working space ``lin_rec709`` is
  inherited and is the identity).  EXR keeps them exact: the IOR is stored unnormalised (eta),
  16-bit PNG would quantise it and need a decode node.
* ``normal`` and ``tangent`` hold ``0.5 v + 0.5`` (``vector3``), what the 1.39 ``normalmap``
  node decodes (``2 in - 1`` in the T, B, N frame, then normalised).  The tangent texture is the
  in-plane direction ``(cos phi, sin phi, 0)``, so ``normalmap`` gives
  ``normalize(T cos phi + B sin phi)``: the surface tangent turned by ``phi`` CCW about the
  normal, which is OpenPBR's ``geometry_tangent``.  (This avoids ``rotate3d``, whose GLSL/OSL
  implementation in MaterialX 1.39 turns clockwise about its axis: MaterialX issue #2083.)

Tiling and size: when the repeat size is known every texture is a ``tiledimage`` with
``realworldimagesize`` = the repeat (mm) and ``realworldtilesize`` = the swatch (mm) that one UV
unit spans (``unit="millimeter"``, ``unittype="distance"``), so the texture repeats
:meth:`ExportContext.repeats` times per UV unit; otherwise plain ``image`` nodes.  Provenance
(``ctx.meta``) and the sizes are custom attributes of each ``surfacematerial``, declared with
``attributedef`` elements, and summarised in the document's ``doc`` string.

Element names (``NG_<e>``, ``SR_<e>_<shader>``, ``M_<e>_<shader>``) are built from the
material's name by :func:`element_stem`, which is injective: ``denim-01`` and ``denim_01`` give
different elements, so a library that imports several exports into one document keeps every
material (MaterialX's ``importLibrary`` skips an element whose name is already there).  The
material's name as given is the ``dualscale_name`` attribute of each ``surfacematerial``.

Sources: MaterialX Specification 1.39 (Standard Nodes: ``image``, ``tiledimage``,
``normalmap``; colour spaces); Autodesk Standard Surface v1.0.1 (Georgiev et al. 2019);
OpenPBR Surface v1.1 (Andersson et al.); seed Sec. 5 for our model.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from dualscale.errors import InputError
from dualscale.formats.atomic import write_text

from . import NAME_RE, ExportContext
from .exchange import Exchange, openpbr_anisotropy, standard_surface_anisotropy, thin_walled_translucency
from .textures import encode_normal, write_float, write_png

MTLX_VERSION = "1.39"
WORKING_SPACE = "lin_rec709"
SRGB = "srgb_texture"

# Custom attributes on each surfacematerial: (attribute, MaterialX type, description).
ATTRIBUTES = (
    ("dualscale_repeat_mm", "vector2", "physical (width, height) of one texture repeat in mm"),
    ("dualscale_texel_mm", "float", "physical size of one texel in mm"),
    ("dualscale_tiled", "boolean", "the textures are a seamless tile"),
    ("dualscale_meta", "string", "provenance (JSON): generator, version, source"),
    ("dualscale_name", "string", "the material's name as given (the files' stem), which the element names encode"),
)

_NOT_ELEMENT = re.compile(r"[^A-Za-z0-9_]")  # what MaterialX's createValidName maps to '_' in our names
_HASH_TAIL = re.compile(r"_h[0-9a-f]{8}$")  # the suffix element_stem appends


def element_stem(name: str) -> str:
    """The stem of the element names of material ``name`` (a name of
    :data:`dualscale.export.NAME_RE`): ``name`` itself when it is a valid MaterialX name
    (letters, digits, ``_``), else ``name`` with ``.`` and ``-`` mapped to ``_`` plus
    ``_h`` and the first 8 hex digits of the name's SHA-256 (UTF-8): ``denim-01`` ->
    ``denim_01_h08dfef21``, ``denim_01`` -> ``denim_01``.

    Injective on names (up to a collision of 32-bit hash prefixes): a name that sanitising would
    change, or that already ends like a hash suffix (``_h`` + 8 hex digits), always gets its own
    hash appended; every other name is left as it is and cannot end like one.  Stable: the same
    name gives the same stem in every run and version."""
    valid = _NOT_ELEMENT.sub("_", name)
    if valid == name and not _HASH_TAIL.search(name):
        return name
    return f"{valid}_h{hashlib.sha256(name.encode('utf-8')).hexdigest()[:8]}"


@lru_cache(maxsize=1)
def standard_libraries():
    """MaterialX's standard data libraries (stdlib, pbrlib, bxdf, ...) as one document."""
    import MaterialX as mx

    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def validate(doc) -> tuple[bool, str]:
    """``Document.validate()`` of ``doc`` with the standard libraries attached (as data library,
    so they are not copied into the written file): ``(ok, message)``."""
    doc.setDataLibrary(standard_libraries())
    ok, msg = doc.validate()
    return bool(ok), msg


def read_document(path: str | Path):
    """Read a ``.mtlx`` file into a MaterialX document (libraries not attached)."""
    import MaterialX as mx

    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    return doc


@dataclass
class _Tex:
    """A texture to write: ``kind`` is ``"srgb"`` (colour PNG) or ``"data"`` (float EXR)."""

    stem: str
    image: np.ndarray
    kind: str
    mtype: str  # MaterialX image node type: color3, float, vector3

    def filename(self, name: str) -> str:
        return f"{name}_{self.stem}.{'png' if self.kind == 'srgb' else 'exr'}"


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise InputError(f"MaterialX export: name {name!r} must be 1-64 characters of letters, digits, "
                         "'_', '.' or '-', starting with a letter or digit (it is the files' stem)")
    return name


def _check_inputs(ex: Exchange, ctx: ExportContext) -> None:
    for field in ("base_color", "roughness", "anisotropy", "tangent_angle", "normal", "ior",
                  "specular_color", "transmittance", "opacity"):
        arr = getattr(ex, field)
        if arr is None:
            continue
        bad = int((~np.isfinite(np.asarray(arr, np.float64))).sum())
        if bad:
            raise InputError(f"MaterialX export {ctx.name!r}: exchange field {field!r} has {bad} "
                             "non-finite values")
    if not (math.isfinite(ex.ior_scalar) and ex.ior_scalar > 0):
        raise InputError(f"MaterialX export {ctx.name!r}: ior_scalar must be positive and finite, "
                         f"got {ex.ior_scalar}")
    for label, size in (("repeat_mm", ctx.repeat_mm), ("swatch_mm", ctx.swatch_mm)):
        if size is not None and not (len(size) == 2 and all(math.isfinite(s) and s > 0 for s in size)):
            raise InputError(f"MaterialX export {ctx.name!r}: {label} must be two positive finite "
                             f"lengths in mm, got {size}")


def plan_textures(ex: Exchange) -> dict[str, _Tex]:
    """The textures of ``ex``, keyed by role (see the module docstring), values in exchange
    conventions: what :func:`write` stores and what the tests decode back."""
    trans = thin_walled_translucency(ex)
    ss_rough, ss_aniso, ss_rot = standard_surface_anisotropy(ex)
    op_rough, op_aniso = openpbr_anisotropy(ex)
    tex: dict[str, _Tex] = {
        "base_color": _Tex("base_color", ex.base_color if trans is None else trans.base_color, "srgb", "color3"),
        "specular_roughness": _Tex("specular_roughness", ss_rough, "data", "float"),
    }
    if ex.specular_color is not None:
        tex["specular_color"] = _Tex("specular_color", ex.specular_color, "srgb", "color3")
    if ex.ior is not None:
        tex["specular_ior"] = _Tex("specular_ior", ex.ior, "data", "float")
    if ss_aniso is not None:  # the direction goes through the tangent input (specular_rotation stays 0)
        tex["specular_anisotropy"] = _Tex("specular_anisotropy", ss_aniso, "data", "float")
    if op_aniso is not None:
        if not np.array_equal(op_rough, ss_rough):
            tex["openpbr_specular_roughness"] = _Tex("openpbr_specular_roughness", op_rough, "data", "float")
        tex["openpbr_roughness_anisotropy"] = _Tex("openpbr_roughness_anisotropy", op_aniso, "data", "float")
    if ex.tangent_angle is not None and (op_aniso is not None or ss_aniso is not None):
        phi = ex.tangent_angle.astype(np.float64)
        direction = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
        tex["tangent"] = _Tex("tangent", encode_normal(direction), "data", "vector3")
    if ex.normal is not None:
        tex["normal"] = _Tex("normal", encode_normal(ex.normal), "data", "vector3")
    if trans is not None:
        tex["subsurface"] = _Tex("subsurface", trans.weight, "data", "float")
        tex["subsurface_color"] = _Tex("subsurface_color", trans.color, "srgb", "color3")
    if ex.opacity is not None:
        tex["opacity"] = _Tex("opacity", ex.opacity, "data", "float")
    return tex


def _fmt(v: float) -> str:
    return f"{float(v):.9g}"


def _xml_safe_json(obj) -> str:
    """``obj`` as JSON with ``<``, ``>`` and ``&`` written as JSON escapes (``\\u003c`` ...): the
    same JSON when decoded, and nothing MaterialX's writer would copy unescaped into an XML
    attribute (it leaves ``<`` as is, which strict XML parsers refuse; a source path such as
    ``runs/<sample>&1`` reaches the provenance)."""
    return (json.dumps(obj, sort_keys=True, default=str)
            .replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026"))


def build_document(ex: Exchange, ctx: ExportContext, textures: dict[str, _Tex]):
    """The MaterialX document (not yet validated) referencing ``textures`` by relative file name."""
    import MaterialX as mx

    name = ctx.name                   # file stem
    elem = element_stem(name)         # element names: valid and one per name (see element_stem)
    doc = mx.createDocument()
    doc.setVersionString(MTLX_VERSION)
    doc.setColorSpace(WORKING_SPACE)
    size = "unknown" if ctx.repeat_mm is None else f"{_fmt(ctx.repeat_mm[0])} x {_fmt(ctx.repeat_mm[1])} mm"
    doc.setDocString(f"dualscale SVBSDF export of {name!r}; one texture repeat = {size}"
                     f"{' (seamless tile)' if ctx.tiled else ''}; provenance: {_xml_safe_json(ctx.meta)}")
    for attr, mtype, desc in ATTRIBUTES:
        ad = doc.addAttributeDef(f"AD_{attr}")
        ad.setAttrName(attr)
        ad.setType(mtype)
        ad.setAttribute("elements", "surfacematerial")
        ad.setExportable(True)
        ad.setDocString(desc)

    graph = doc.addNodeGraph(f"NG_{elem}")
    outputs: dict[str, str] = {}  # role -> output name in the graph

    def texture_node(role: str):
        t = textures[role]
        if ctx.repeat_mm is not None:
            node = graph.addNode("tiledimage", f"{role}_image", t.mtype)
            sw = ctx.swatch()
            node.setInputValue("realworldimagesize", mx.Vector2(*map(float, ctx.repeat_mm)), "vector2")
            node.setInputValue("realworldtilesize", mx.Vector2(float(sw[0]), float(sw[1])), "vector2")
            for inp in ("realworldimagesize", "realworldtilesize"):
                node.getInput(inp).setUnitType("distance")
                node.getInput(inp).setUnit("millimeter")
        else:
            node = graph.addNode("image", f"{role}_image", t.mtype)
        f = node.addInput("file", "filename")
        f.setValueString(t.filename(name))
        if t.kind == "srgb":
            f.setColorSpace(SRGB)
        return node

    def expose(role: str, node, mtype: str) -> str:
        out = graph.addOutput(f"{role}_out", mtype)
        out.setConnectedNode(node)
        outputs[role] = out.getName()
        return out.getName()

    for role, t in textures.items():
        node = texture_node(role)
        if role in ("normal", "tangent"):
            nm = graph.addNode("normalmap", f"{role}_world", "vector3")
            nm.addInput("in", "vector3").setConnectedNode(node)
            expose(role, nm, "vector3")
        elif role == "opacity":
            expose("opacity", node, "float")
            conv = graph.addNode("convert", "opacity_color", "color3")
            conv.addInput("in", "float").setConnectedNode(node)
            expose("opacity_color", conv, "color3")
        else:
            expose(role, node, t.mtype)

    def connect(shader, inp: str, role: str, mtype: str) -> None:
        i = shader.addInput(inp, mtype)
        i.setNodeGraphString(graph.getName())
        i.setOutputString(outputs[role])

    transmits = "subsurface" in textures
    # -- Autodesk Standard Surface ------------------------------------------------------------
    ss = doc.addNode("standard_surface", f"SR_{elem}_standard_surface", "surfaceshader")
    ss.setInputValue("base", 1.0, "float")
    connect(ss, "base_color", "base_color", "color3")
    ss.setInputValue("diffuse_roughness", 0.0, "float")
    ss.setInputValue("metalness", 0.0, "float")
    ss.setInputValue("specular", 1.0, "float")
    if "specular_color" in textures:
        connect(ss, "specular_color", "specular_color", "color3")
    else:
        ss.setInputValue("specular_color", mx.Color3(1.0, 1.0, 1.0), "color3")
    connect(ss, "specular_roughness", "specular_roughness", "float")
    if "specular_ior" in textures:
        connect(ss, "specular_IOR", "specular_ior", "float")
    else:
        ss.setInputValue("specular_IOR", float(ex.ior_scalar), "float")
    if "specular_anisotropy" in textures:
        connect(ss, "specular_anisotropy", "specular_anisotropy", "float")
        ss.setInputValue("specular_rotation", 0.0, "float")  # see exchange.standard_surface_anisotropy
        connect(ss, "tangent", "tangent", "vector3")
    if "normal" in textures:
        connect(ss, "normal", "normal", "vector3")
    if transmits:
        ss.setInputValue("thin_walled", True, "boolean")  # subsurface -> Lambertian translucent_bsdf
        connect(ss, "subsurface", "subsurface", "float")
        connect(ss, "subsurface_color", "subsurface_color", "color3")
    if "opacity" in textures:
        connect(ss, "opacity", "opacity_color", "color3")

    # -- OpenPBR Surface ----------------------------------------------------------------------
    op = doc.addNode("open_pbr_surface", f"SR_{elem}_open_pbr_surface", "surfaceshader")
    op.setInputValue("base_weight", 1.0, "float")
    connect(op, "base_color", "base_color", "color3")
    op.setInputValue("base_diffuse_roughness", 0.0, "float")
    op.setInputValue("base_metalness", 0.0, "float")
    op.setInputValue("specular_weight", 1.0, "float")
    if "specular_color" in textures:
        connect(op, "specular_color", "specular_color", "color3")
    else:
        op.setInputValue("specular_color", mx.Color3(1.0, 1.0, 1.0), "color3")
    op_rough = "openpbr_specular_roughness" if "openpbr_specular_roughness" in textures else "specular_roughness"
    connect(op, "specular_roughness", op_rough, "float")
    if "specular_ior" in textures:
        connect(op, "specular_ior", "specular_ior", "float")
    else:
        op.setInputValue("specular_ior", float(ex.ior_scalar), "float")
    if "openpbr_roughness_anisotropy" in textures:
        connect(op, "specular_roughness_anisotropy", "openpbr_roughness_anisotropy", "float")
    if "tangent" in textures:
        connect(op, "geometry_tangent", "tangent", "vector3")
    if "normal" in textures:
        connect(op, "geometry_normal", "normal", "vector3")
    if transmits:
        op.setInputValue("geometry_thin_walled", True, "boolean")  # thin-walled subsurface: diffuse transmission
        # OpenPBR's thin-walled subsurface mixes a diffuse reflection weighted (1 - g)/2 and a
        # translucent transmission weighted (1 + g)/2 of subsurface_color; g = 1 transmits all of it,
        # Standard Surface's thin-walled split (our reflectance stays in base_color)
        op.setInputValue("subsurface_scatter_anisotropy", 1.0, "float")
        connect(op, "subsurface_weight", "subsurface", "float")
        connect(op, "subsurface_color", "subsurface_color", "color3")
    if "opacity" in textures:
        connect(op, "geometry_opacity", "opacity", "float")

    meta = _xml_safe_json(ctx.meta)
    for shader, label in ((ss, "standard_surface"), (op, "open_pbr_surface")):
        mat = doc.addMaterialNode(f"M_{elem}_{label}", shader)
        if ctx.repeat_mm is not None:
            mat.setAttribute("dualscale_repeat_mm", f"{_fmt(ctx.repeat_mm[0])}, {_fmt(ctx.repeat_mm[1])}")
        if ex.texel_mm:
            mat.setAttribute("dualscale_texel_mm", _fmt(ex.texel_mm))
        mat.setAttribute("dualscale_tiled", "true" if ctx.tiled else "false")
        mat.setAttribute("dualscale_meta", meta)
        mat.setAttribute("dualscale_name", name)
    return doc


def write(ex: Exchange, ctx: ExportContext, out: Path) -> list[Path]:
    """Write ``<ctx.name>.mtlx`` and its textures into ``out`` (see the module docstring).

    Returns the files written, the ``.mtlx`` first.  Raises
    :class:`~dualscale.errors.InputError` for an unusable name, non-finite inputs or sizes, and
    ``RuntimeError`` if MaterialX's ``validate()`` rejects the document (a bug here).
    """
    import MaterialX as mx

    name = _check_name(ctx.name)
    _check_inputs(ex, ctx)
    out = Path(out)
    textures = plan_textures(ex)
    doc = build_document(ex, ctx, textures)
    ok, msg = validate(doc)
    if not ok:
        raise RuntimeError(f"MaterialX export {name!r}: MaterialX validate() refused the document:\n{msg}")
    files: list[Path] = []
    for t in textures.values():
        path = out / t.filename(name)
        if t.kind == "srgb":
            write_png(path, t.image, srgb=True, bits=8)
        else:
            chans = ("R", "G", "B") if t.image.ndim == 3 else ("Y",)
            write_float(path, t.image, chans)
        files.append(path)
    opts = mx.XmlWriteOptions()
    opts.writeXIncludeEnable = False
    mtlx = out / f"{name}.mtlx"
    write_text(mtlx, mx.writeToXmlString(doc, opts))
    return [mtlx, *files]


__all__ = ["build_document", "element_stem", "plan_textures", "read_document", "standard_libraries", "validate", "write"]
