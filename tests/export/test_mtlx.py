"""MaterialX export (issue 12 Sec. 1): MaterialX's own validate(), the textures decode back to the
exchange values, the node graph connects each shader input to the right texture, tiling and
physical size, the tangent direction, and refusals.  Small maps (32-64 px): a few seconds."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

mx = pytest.importorskip("MaterialX")

from dualscale.errors import InputError  # noqa: E402
from dualscale.export import ExportContext, exchange  # noqa: E402
from dualscale.export import mtlx  # noqa: E402
from dualscale.export.exchange import (  # noqa: E402
    openpbr_anisotropy, standard_surface_anisotropy, thin_walled_translucency)
from dualscale.export.textures import read_png  # noqa: E402
from dualscale.formats.exr import read_exr  # noqa: E402
from dualscale.sim.materials import generate  # noqa: E402
from dualscale.sim.materials.common import to_maps  # noqa: E402

TEXEL_MM = 0.01
SRGB_8BIT_TOL = 0.005  # 8-bit sRGB: half a code value times the EOTF's max slope (2.27) ~ 0.0045


def _isotropic(size: int = 32):
    rng = np.random.default_rng(3)
    albedo = rng.uniform(0.05, 0.9, (size, size, 3))
    rough = rng.uniform(0.1, 0.9, (size, size))
    return exchange(to_maps(albedo=albedo, roughness=rough), TEXEL_MM)


def _case(kind: str):
    """(Exchange, ExportContext) for the four cases of the issue."""
    if kind == "isotropic":
        ex = _isotropic()
    elif kind == "anisotropic":
        ex = exchange(generate("twill", size=64, texel_mm=TEXEL_MM).maps, TEXEL_MM)
    elif kind == "transmissive":
        ex = exchange(generate("sheer", size=32, texel_mm=TEXEL_MM).maps, TEXEL_MM)
    elif kind == "tiled":
        ex = exchange(generate("plain", size=32, texel_mm=TEXEL_MM).maps, TEXEL_MM)
    else:  # pragma: no cover
        raise AssertionError(kind)
    tiled = kind == "tiled"
    ctx = ExportContext(name=f"swatch_{kind}", repeat_mm=ex.size_mm, tiled=tiled,
                        meta={"generator": "dualscale", "source": f"test {kind}"})
    return ex, ctx


CASES = ["isotropic", "anisotropic", "transmissive", "tiled"]


@pytest.fixture(scope="module", params=CASES)
def exported(request, tmp_path_factory):
    ex, ctx = _case(request.param)
    out = tmp_path_factory.mktemp(request.param)
    files = mtlx.write(ex, ctx, out)
    return request.param, ex, ctx, out, files


def _shader(doc, category: str):
    nodes = [n for n in doc.getNodes() if n.getCategory() == category]
    assert len(nodes) == 1, f"expected one {category} node, got {[n.getName() for n in nodes]}"
    return nodes[0]


def _source(inp) -> tuple[str, list[str], object]:
    """Follow a shader input through the node graph: (file name, categories passed, image node)."""
    out = inp.getConnectedOutput()
    assert out is not None, f"input {inp.getName()} is not connected"
    node = out.getConnectedNode()
    chain = []
    while node.getCategory() not in ("image", "tiledimage"):
        chain.append(node.getCategory())
        node = node.getInput("in").getConnectedNode()
        assert node is not None, f"{inp.getName()}: {chain[-1]} has no upstream image"
    return node.getInputValue("file"), chain, node


def _read(path: Path, srgb: bool) -> np.ndarray:
    img = read_png(path, srgb=True) if srgb else np.asarray(read_exr(path), np.float64)
    return img[..., 0] if img.shape[-1] == 1 else img


def _expected(ex) -> dict[tuple[str, str], tuple[np.ndarray, bool, str]]:
    """(shader, input) -> (exchange value the texture must hold, sRGB?, nodes between), computed
    here from the exchange functions rather than from the writer's plan."""
    trans = thin_walled_translucency(ex)
    ss_r, ss_a, ss_rot = standard_surface_anisotropy(ex)
    op_r, op_a = openpbr_anisotropy(ex)
    base = ex.base_color if trans is None else trans.base_color
    exp = {("standard_surface", "base_color"): (base, True, ""),
           ("open_pbr_surface", "base_color"): (base, True, ""),
           ("standard_surface", "specular_roughness"): (ss_r, False, ""),
           ("open_pbr_surface", "specular_roughness"): (op_r, False, "")}
    if ex.specular_color is not None:
        for s in ("standard_surface", "open_pbr_surface"):
            exp[(s, "specular_color")] = (ex.specular_color, True, "")
    if ex.ior is not None:
        exp[("standard_surface", "specular_IOR")] = (ex.ior, False, "")
        exp[("open_pbr_surface", "specular_ior")] = (ex.ior, False, "")
    if ss_a is not None:
        exp[("standard_surface", "specular_anisotropy")] = (ss_a, False, "")
    if op_a is not None:
        exp[("open_pbr_surface", "specular_roughness_anisotropy")] = (op_a, False, "")
        phi = ex.tangent_angle.astype(np.float64)
        enc = 0.5 * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1) + 0.5
        exp[("open_pbr_surface", "geometry_tangent")] = (enc, False, "normalmap")
        exp[("standard_surface", "tangent")] = (enc, False, "normalmap")
    if ex.normal is not None:
        enc = 0.5 * ex.normal.astype(np.float64) + 0.5
        exp[("standard_surface", "normal")] = (enc, False, "normalmap")
        exp[("open_pbr_surface", "geometry_normal")] = (enc, False, "normalmap")
    if trans is not None:
        exp[("standard_surface", "subsurface")] = (trans.weight, False, "")
        exp[("open_pbr_surface", "subsurface_weight")] = (trans.weight, False, "")
        exp[("standard_surface", "subsurface_color")] = (trans.color, True, "")
        exp[("open_pbr_surface", "subsurface_color")] = (trans.color, True, "")
    if ex.opacity is not None:
        exp[("standard_surface", "opacity")] = (ex.opacity, False, "convert")
        exp[("open_pbr_surface", "geometry_opacity")] = (ex.opacity, False, "")
    return exp


def test_passes_materialx_validate(exported):
    kind, ex, ctx, out, files = exported
    assert files[0] == out / f"{ctx.name}.mtlx"
    doc = mtlx.read_document(files[0])
    ok, msg = mtlx.validate(doc)
    assert ok, f"MaterialX validate() refused {files[0]}:\n{msg}"
    # the written file does not carry copies of the standard libraries
    assert "ND_standard_surface" not in files[0].read_text()
    mats = {m.getName(): m for m in doc.getMaterialNodes()}
    assert set(mats) == {f"M_{ctx.name}_standard_surface", f"M_{ctx.name}_open_pbr_surface"}
    for label, m in (("standard_surface", mats[f"M_{ctx.name}_standard_surface"]),
                     ("open_pbr_surface", mats[f"M_{ctx.name}_open_pbr_surface"])):
        shaders = mx.getShaderNodes(m)
        assert [s.getCategory() for s in shaders] == [label]


def test_every_texture_exists_and_decodes(exported):
    kind, ex, ctx, out, files = exported
    doc = mtlx.read_document(files[0])
    referenced = set()
    for elem in doc.traverseTree():
        if elem.isA(mx.Input) and elem.getType() == "filename":
            path = out / elem.getValueString()
            assert path.is_file(), f"{elem.getNamePath()} refers to missing {path.name}"
            referenced.add(path)
    assert referenced == set(files[1:]), "files written and files referenced differ"
    for (shader, inp), (value, srgb, _) in _expected(ex).items():
        fname, _, _ = _source(_shader(doc, shader).getInput(inp))
        got = _read(out / fname, srgb)
        assert got.shape == np.shape(value), f"{shader}.{inp}: {fname} has shape {got.shape}"
        err = float(np.abs(got - np.asarray(value, np.float64)).max())
        tol = SRGB_8BIT_TOL if srgb else 1e-6 * max(1.0, float(np.abs(value).max()))
        assert err <= tol, f"{shader}.{inp}: {fname} decodes {err:.2e} away from the exchange value"


def test_graph_connects_each_claimed_input(exported):
    kind, ex, ctx, out, files = exported
    doc = mtlx.read_document(files[0])
    expected = _expected(ex)
    for shader_cat in ("standard_surface", "open_pbr_surface"):
        shader = _shader(doc, shader_cat)
        connected = {i.getName() for i in shader.getInputs() if i.getConnectedOutput() is not None}
        claimed = {inp for (s, inp) in expected if s == shader_cat}
        assert connected == claimed, f"{shader_cat}: connected {sorted(connected)}, expected {sorted(claimed)}"
        for inp in claimed:
            value, srgb, via = expected[(shader_cat, inp)]
            fname, chain, image = _source(shader.getInput(inp))
            assert chain == ([via] if via else []), f"{shader_cat}.{inp} goes through {chain}"
            assert fname.endswith(".png" if srgb else ".exr"), f"{shader_cat}.{inp}: {fname}"
            cs = image.getInput("file").getColorSpace()
            assert cs == ("srgb_texture" if srgb else ""), f"{shader_cat}.{inp}: colorspace {cs!r}"
            want = "color3" if srgb else ("vector3" if via == "normalmap" else "float")
            assert image.getType() == want, f"{shader_cat}.{inp}: image of type {image.getType()}"
    ss, op = _shader(doc, "standard_surface"), _shader(doc, "open_pbr_surface")
    for node, name, value in ((ss, "base", 1.0), (ss, "specular", 1.0), (ss, "diffuse_roughness", 0.0),
                              (op, "base_weight", 1.0), (op, "specular_weight", 1.0)):
        assert node.getInputValue(name) == value, f"{node.getCategory()}.{name}"
    transmits = ex.transmittance is not None
    assert bool(ss.getInputValue("thin_walled")) == transmits
    assert bool(op.getInputValue("geometry_thin_walled")) == transmits
    if transmits:  # OpenPBR thin-walled subsurface: (1 + g) / 2 transmits; g = 1 is Standard Surface's split
        assert op.getInputValue("subsurface_scatter_anisotropy") == 1.0
    if ex.ior is None:  # one IOR for the whole sample
        assert ss.getInputValue("specular_IOR") == pytest.approx(ex.ior_scalar)
        assert op.getInputValue("specular_ior") == pytest.approx(ex.ior_scalar)


def test_size_tiling_and_provenance(exported):
    kind, ex, ctx, out, files = exported
    doc = mtlx.read_document(files[0])
    images = [n for n in doc.traverseTree() if n.isA(mx.Node) and n.getCategory() in ("image", "tiledimage")]
    assert images and all(n.getCategory() == "tiledimage" for n in images)
    for n in images:
        img = np.array(n.getInputValue("realworldimagesize").asTuple())
        tile = np.array(n.getInputValue("realworldtilesize").asTuple())
        np.testing.assert_allclose(img, ctx.repeat_mm, rtol=1e-6)
        np.testing.assert_allclose(tile / img, ctx.repeats(), rtol=1e-6)
        for name in ("realworldimagesize", "realworldtilesize"):
            assert n.getInput(name).getUnit() == "millimeter"
            assert n.getInput(name).getUnitType() == "distance"
    if kind == "tiled":
        assert ctx.repeats() == (2.0, 2.0)
    for m in doc.getMaterialNodes():
        rep = [float(v) for v in m.getAttribute("dualscale_repeat_mm").split(",")]
        np.testing.assert_allclose(rep, ctx.repeat_mm, rtol=1e-6)
        assert float(m.getAttribute("dualscale_texel_mm")) == pytest.approx(TEXEL_MM)
        assert m.getAttribute("dualscale_tiled") == ("true" if ctx.tiled else "false")
        assert json.loads(m.getAttribute("dualscale_meta")) == ctx.meta
    assert "dualscale" in doc.getDocString() and "mm" in doc.getDocString()


def test_names_the_exporter_accepts(tmp_path):
    """Names that dualscale.export.material accepts (digits first, '.', '-') give valid elements."""
    files = mtlx.write(_isotropic(8), ExportContext("2024.twill-v2", (0.08, 0.08)), tmp_path)
    assert files[0].name == "2024.twill-v2.mtlx"
    doc = mtlx.read_document(files[0])
    ok, msg = mtlx.validate(doc)
    assert ok, msg
    stem = mtlx.element_stem("2024.twill-v2")
    assert stem.startswith("2024_twill_v2_h") and mx.createValidName(stem) == stem
    assert {m.getName() for m in doc.getMaterialNodes()} == {
        f"M_{stem}_standard_surface", f"M_{stem}_open_pbr_surface"}
    assert {m.getAttribute("dualscale_name") for m in doc.getMaterialNodes()} == {"2024.twill-v2"}
    assert all(p.name.startswith("2024.twill-v2_") for p in files[1:])


def test_element_names_are_one_per_material_name():
    """issue 24 §7: names that the MaterialX sanitiser maps alike ('.', '-' -> '_') keep apart,
    valid names stay as they are, and a name that looks like a hashed stem does not collide."""
    names = ["denim-01", "denim_01", "denim.01", "denim-01-", "denim--01", "denim_-01", "Denim_01", "d",
             "swatch_isotropic", "2024.twill-v2", "2024_twill_v2", "2024-twill.v2"]
    names.append(mtlx.element_stem("denim-01"))  # a user's name equal to another's hashed stem
    stems = [mtlx.element_stem(n) for n in names]
    assert len(set(stems)) == len(names), dict(zip(names, stems))
    assert all(mx.createValidName(s) == s for s in stems)
    assert mtlx.element_stem("denim_01") == "denim_01" and mtlx.element_stem("swatch_isotropic") == "swatch_isotropic"
    assert mtlx.element_stem("denim-01") == mtlx.element_stem("denim-01")  # stable


def test_a_library_of_names_that_sanitise_alike_keeps_every_material(tmp_path):
    """issue 24 §7: 'denim-01' and 'denim_01' exported side by side and imported into one
    document (as a user's library does, ``importLibrary``): four materials, not two, each
    reaching its own textures, its name recoverable, and the library passes ``validate()``."""
    rng = np.random.default_rng(5)
    docs = {}
    for name in ("denim-01", "denim_01"):
        albedo = rng.uniform(0.05, 0.9, (8, 8, 3))
        ex = exchange(to_maps(albedo=albedo, roughness=rng.uniform(0.1, 0.9, (8, 8))), TEXEL_MM)
        files = mtlx.write(ex, ExportContext(name, (0.08, 0.08)), tmp_path)
        docs[name] = (files[0], albedo)
    lib = mx.createDocument()
    for path, _ in docs.values():
        lib.importLibrary(mtlx.read_document(path))
    ok, msg = mtlx.validate(lib)
    assert ok, msg
    mats = lib.getMaterialNodes()
    assert len(mats) == 4, [m.getName() for m in mats]
    assert sorted(m.getAttribute("dualscale_name") for m in mats) == ["denim-01", "denim-01", "denim_01", "denim_01"]
    for m in mats:
        name = m.getAttribute("dualscale_name")
        (shader,) = mx.getShaderNodes(m)
        fname, _, _ = _source(shader.getInput("base_color"))
        assert fname == f"{name}_base_color.png", (m.getName(), fname)
        got = _read(tmp_path / fname, srgb=True)
        assert np.abs(got - docs[name][1]).max() < SRGB_8BIT_TOL


def test_unknown_size_uses_plain_images(tmp_path):
    ex = _isotropic(16)
    ex.texel_mm = None
    files = mtlx.write(ex, ExportContext("nosize", None), tmp_path)
    doc = mtlx.read_document(files[0])
    ok, msg = mtlx.validate(doc)
    assert ok, msg
    cats = {n.getCategory() for n in doc.traverseTree() if n.isA(mx.Node)}
    assert "image" in cats and "tiledimage" not in cats
    assert all(not m.hasAttribute("dualscale_repeat_mm") for m in doc.getMaterialNodes())


def _normalmap_decode(texel: np.ndarray) -> np.ndarray:
    """MaterialX 1.39 ``normalmap`` in the frame T = +x, B = +y, N = +z (image right, up, out)."""
    v = 2.0 * texel - 1.0
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _library_source(rel: str) -> str:
    return (Path(mx.__file__).parent / "libraries" / rel).read_text()


def test_openpbr_tangent_is_our_direction(exported):
    """geometry_tangent = normalmap(tangent texture) = T cos phi + B sin phi: the tangent turned
    by phi CCW from +u, i.e. our tangent azimuth (image +x towards image up)."""
    kind, ex, ctx, out, files = exported
    if ex.tangent_angle is None:
        pytest.skip("isotropic sample: no tangent")
    assert "value * 2.0 - 1.0" in _library_source("stdlib/genglsl/mx_normalmap.glsl"), \
        "MaterialX's normalmap decoding changed: revisit the tangent/normal encoding"
    doc = mtlx.read_document(files[0])
    fname, chain, _ = _source(_shader(doc, "open_pbr_surface").getInput("geometry_tangent"))
    t = _normalmap_decode(_read(out / fname, srgb=False))
    angle = np.remainder(np.arctan2(t[..., 1], t[..., 0]), math.pi)
    diff = np.abs(np.remainder(angle - ex.tangent_angle + math.pi / 2, math.pi) - math.pi / 2)
    assert float(diff.max()) < 1e-5


def test_standard_surface_direction_goes_through_the_tangent_not_the_rotation(tmp_path):
    """MaterialX 1.39's standard_surface turns its tangent by 360 * specular_rotation degrees with
    rotate3d, clockwise in its GLSL/OSL (MaterialX issue #2083), while the Standard Surface spec
    says 1 = 180 degrees: no rotation value is right in both, so the writer leaves it at 0 and
    connects the rotated tangent (the same network as OpenPBR's geometry_tangent)."""
    ex, ctx = _case("anisotropic")
    files = mtlx.write(ex, ctx, tmp_path)
    doc = mtlx.read_document(files[0])
    ss = _shader(doc, "standard_surface")
    assert ss.getInput("specular_rotation").getValue() == 0.0
    fname, chain, _ = _source(ss.getInput("tangent"))
    t = _normalmap_decode(_read(tmp_path / fname, srgb=False))
    angle = np.remainder(np.arctan2(t[..., 1], t[..., 0]), math.pi)
    diff = np.abs(np.remainder(angle - ex.tangent_angle + math.pi / 2, math.pi) - math.pi / 2)
    assert float(diff.max()) < 1e-5


def test_shader_code_generates(exported):
    """MaterialX's GLSL and OSL generators accept both shaders (the graph is complete and typed)."""
    import MaterialX.PyMaterialXGenGlsl as mx_glsl
    import MaterialX.PyMaterialXGenOsl as mx_osl
    import MaterialX.PyMaterialXGenShader as mx_gen

    kind, ex, ctx, out, files = exported
    doc = mtlx.read_document(files[0])
    doc.setDataLibrary(mtlx.standard_libraries())
    for gen in (mx_glsl.GlslShaderGenerator.create(), mx_osl.OslShaderGenerator.create()):
        gctx = mx_gen.GenContext(gen)
        gctx.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
        for cat in ("standard_surface", "open_pbr_surface"):
            node = _shader(doc, cat)
            src = gen.generate(node.getName(), node, gctx).getSourceCode(mx_gen.PIXEL_STAGE)
            assert len(src) > 1000, f"{gen.getTarget()} {cat}: empty shader"


@pytest.mark.parametrize("name", ["", "a b", "../up", ".hidden", "-x", "x/y", "é", "a" * 65])
def test_bad_name_is_refused(tmp_path, name):
    ex = _isotropic(8)
    with pytest.raises(InputError, match="name"):
        mtlx.write(ex, ExportContext(name, (1.0, 1.0)), tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("field", ["roughness", "base_color", "ior"])
def test_non_finite_input_is_refused(tmp_path, field):
    ex = exchange(generate("twill", size=16, texel_mm=TEXEL_MM).maps, TEXEL_MM)
    arr = getattr(ex, field).copy()
    arr.reshape(-1)[5] = np.nan if field != "ior" else np.inf
    setattr(ex, field, arr)
    with pytest.raises(InputError, match=f"{field}.*non-finite"):
        mtlx.write(ex, ExportContext("twill", (0.16, 0.16)), tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("repeat", [(0.0, 1.0), (float("nan"), 1.0), (-1.0, 2.0)])
def test_bad_repeat_size_is_refused(tmp_path, repeat):
    with pytest.raises(InputError, match="repeat_mm"):
        mtlx.write(_isotropic(8), ExportContext("iso", repeat), tmp_path)


def test_xml_special_characters_in_the_provenance_give_a_strictly_parsable_document(tmp_path):
    """A source path with '<' and '&' (issue 24 §7): MaterialX's writer copies '<' into the
    attribute unescaped, which strict XML parsers refuse; the provenance is written with JSON
    escapes and decodes to the same path."""
    import xml.etree.ElementTree as ET

    from dualscale.cli import main

    src = tmp_path / "runs<1>&b"
    assert main(["synth", "leather", "-o", str(src), "--size", "8", "--no-previews"]) == 0
    out = tmp_path / "exp"
    assert main(["export", str(src / "maps"), "-o", str(out), "--format", "mtlx", "--name", "m"]) == 0
    f = next(out.rglob("*.mtlx"))
    root = ET.parse(f).getroot()  # strict: fails on a raw '<' inside an attribute
    metas = [e.get("dualscale_meta") for e in root.iter() if e.get("dualscale_meta")]
    assert metas and json.loads(metas[0])["source"].endswith("runs<1>&b/maps")
