"""glTF 2.0 export (dualscale.export.gltf): every export passes the Khronos glTF-Validator with zero
errors and zero warnings, the swatch has the physical size, the tangent frame reads our image
conventions, and the textures decode back to the exchange values within quantisation."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch

from dualscale.bsdf import MaterialMaps
from dualscale.errors import InputError, UnitsError
from dualscale.export import DEFAULT_SWATCH_MM, ExportContext, _registry, exchange
from dualscale.export.exchange import gltf_anisotropy, gltf_transmission, specular_f0_color
from dualscale.export.gltf import GENERATOR, write_glb, write_gltf
from dualscale.export.textures import decode_normal
from dualscale.sim.materials import generate

TEXEL_MM = 0.01
WRITERS = {"gltf": write_gltf, "glb": write_glb}
# No validator warning is tolerated: every export below must come out with none.
ALLOWED_WARNINGS: tuple[str, ...] = ()

_CTYPE = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, np.float32))


def _iso_maps(h: int = 32, w: int = 48) -> MaterialMaps:
    """Isotropic, opaque, untinted: albedo and roughness only (non-square on purpose)."""
    rng = np.random.default_rng(1)
    return MaterialMaps(albedo=_t(rng.uniform(0.05, 0.9, (h, w, 3))),
                        roughness=_t(rng.uniform(0.2, 0.8, (h, w, 1))))


def _case(name: str):
    """(Exchange, ExportContext) of a named test case."""
    if name == "isotropic":
        ex = exchange(_iso_maps(), TEXEL_MM)
        return ex, ExportContext("iso", ex.size_mm, meta={"case": name})
    if name in ("anisotropic", "tiled"):
        ex = exchange(generate("twill", size=32, texel_mm=TEXEL_MM).maps, TEXEL_MM)
        return ex, ExportContext("twill", ex.size_mm, tiled=name == "tiled", meta={"case": name})
    if name == "transmissive":
        ex = exchange(generate("sheer", size=32, texel_mm=TEXEL_MM).maps, TEXEL_MM)
        return ex, ExportContext("sheer", ex.size_mm, meta={"case": name})
    raise KeyError(name)


def _export(tmp_path: Path, case: str, fmt: str):
    ex, ctx = _case(case)
    out = tmp_path / fmt
    out.mkdir()
    files = WRITERS[fmt](ex, ctx, out)
    return ex, ctx, files


class Loaded:
    """A written glTF/GLB read back with pygltflib: JSON, binary buffer, accessors and images."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.doc = pygltflib.GLTF2.load(str(path))
        if path.suffix == ".glb":
            self.blob = self.doc.binary_blob()
        else:
            self.blob = (path.parent / self.doc.buffers[0].uri).read_bytes()
        self.json = json.loads(self.doc.gltf_to_json())

    def view_bytes(self, index: int) -> bytes:
        v = self.doc.bufferViews[index]
        return self.blob[v.byteOffset or 0:(v.byteOffset or 0) + v.byteLength]

    def accessor(self, index: int) -> np.ndarray:
        a = self.doc.accessors[index]
        raw = self.view_bytes(a.bufferView)[a.byteOffset or 0:]
        n = _NCOMP[a.type]
        return np.frombuffer(raw, _CTYPE[a.componentType], count=a.count * n).reshape(a.count, n)

    def image(self, key: str) -> np.ndarray:
        """The stored code values / (2^bits - 1) of the texture named ``key`` (the writer names
        images after their map), ``(H, W, C)`` in RGB(A) order, decoded by OpenCV -- a PNG
        decoder independent of the writer's (OpenImageIO), taking the file as it is."""
        import cv2

        img = next(i for i in self.doc.images if i.name == key)
        if img.uri is not None:
            data = (self.path.parent / img.uri).read_bytes()
        else:
            assert img.mimeType == "image/png"
            data = self.view_bytes(img.bufferView)
        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert a is not None, f"{key}: not a decodable image"
        a = a[..., None] if a.ndim == 2 else a[..., [2, 1, 0, 3][:a.shape[2]]]
        return a.astype(np.float64) / (255.0 if a.dtype == np.uint8 else 65535.0)

    @property
    def material(self) -> dict:
        return self.json["materials"][0]

    def geometry(self) -> dict[str, np.ndarray]:
        prim = self.doc.meshes[0].primitives[0]
        at = prim.attributes
        return {"P": self.accessor(at.POSITION).astype(np.float64),
                "N": self.accessor(at.NORMAL).astype(np.float64),
                "T": self.accessor(at.TANGENT).astype(np.float64),
                "UV": self.accessor(at.TEXCOORD_0).astype(np.float64),
                "I": self.accessor(prim.indices)[:, 0].astype(np.int64)}


CASES = ["isotropic", "anisotropic", "transmissive", "tiled"]


@pytest.mark.parametrize("fmt", ["gltf", "glb"])
@pytest.mark.parametrize("case", CASES)
def test_export_passes_khronos_validator(tmp_path, gltf_validator, case, fmt):
    ex, ctx, files = _export(tmp_path, case, fmt)
    rep = gltf_validator.check(files[0], ALLOWED_WARNINGS)
    # every texture was loaded and decoded by the validator (external URIs or GLB views)
    images = [r for r in rep["info"]["resources"] if r["pointer"].startswith("/images/")]
    ld = Loaded(files[0])
    assert len(images) == len(ld.doc.images) >= 2
    assert all("image" in r and r["image"]["width"] == ex.shape[1] for r in images)
    # colour textures sRGB, data textures linear (what the PNG says, as the validator reads it)
    srgb = {"base_color", "specular_color"}
    for r in images:
        key = ld.doc.images[int(r["pointer"].split("/")[-1])].name
        assert r["image"]["transfer"] == ("srgb" if key in srgb else "linear"), key
        assert r["image"]["bits"] == (8 if key in srgb else 16), key
    if fmt == "glb":
        assert files == [tmp_path / fmt / f"{ctx.name}.glb"]
        assert all(i.uri is None and i.bufferView is not None for i in ld.doc.images)
        assert ld.doc.buffers[0].uri is None
    else:
        names = {p.name for p in files}
        assert files[0].suffix == ".gltf" and f"{ctx.name}.bin" in names
        assert all(i.uri in names and "/" not in i.uri for i in ld.doc.images)
        assert sorted(p.name for p in (tmp_path / fmt).iterdir()) == sorted(names)
    # extensions: all declared, none required
    mat = ld.material
    used = set(ld.json["extensionsUsed"])
    assert "extensionsRequired" not in ld.json
    in_material = set(mat.get("extensions", {}))
    assert in_material <= used and "KHR_materials_ior" in in_material
    assert ("KHR_texture_transform" in used) == (case == "tiled")
    assert ("KHR_materials_anisotropy" in used) == (case != "isotropic")
    assert ("KHR_materials_specular" in used) == (case != "isotropic")
    assert ("KHR_materials_transmission" in used) == (case == "transmissive")
    assert "KHR_materials_volume" not in used  # a single-sided sheet is thin-walled
    assert mat["doubleSided"] is True
    assert mat["alphaMode"] == ("BLEND" if case == "transmissive" else "OPAQUE")
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    assert ld.json["asset"]["generator"] == GENERATOR
    extras = ld.json["asset"]["extras"]["dualscale"]
    assert extras["provenance"] == {"case": case} and extras["scale_known"] is True
    assert extras["repeat_mm"] == pytest.approx(list(ex.size_mm))


def test_validator_reports_a_broken_export(tmp_path, gltf_validator):
    """The harness can fail: a missing texture and a wrong accessor count are errors."""
    _, _, files = _export(tmp_path, "isotropic", "gltf")
    gltf = files[0]
    doc = json.loads(gltf.read_text())
    doc["accessors"][0]["count"] += 1000  # reads past the end of its buffer view
    gltf.write_text(json.dumps(doc))
    next(p for p in files if p.name.endswith("_normal.png") or p.name.endswith("_base_color.png")).unlink()
    with pytest.raises(AssertionError, match="errors"):
        gltf_validator.check(gltf)
    codes = {m["code"] for m in gltf_validator.report(gltf)["issues"]["messages"] if m["severity"] == 0}
    assert codes, "the validator found no error in a broken file"


@pytest.mark.parametrize("fmt", ["gltf", "glb"])
@pytest.mark.parametrize("case", ["isotropic", "tiled"])
def test_swatch_has_physical_size_in_metres(tmp_path, case, fmt):
    ex, ctx, files = _export(tmp_path, case, fmt)
    ld = Loaded(files[0])
    acc = ld.doc.accessors[ld.doc.meshes[0].primitives[0].attributes.POSITION]
    w_mm, h_mm = ctx.swatch()
    k = 2.0 if case == "tiled" else 1.0
    assert (w_mm, h_mm) == pytest.approx((k * ex.shape[1] * TEXEL_MM, k * ex.shape[0] * TEXEL_MM))
    assert acc.max[0] - acc.min[0] == pytest.approx(w_mm * 1e-3, rel=1e-6)   # X: width
    assert acc.max[2] - acc.min[2] == pytest.approx(h_mm * 1e-3, rel=1e-6)   # Z: height
    assert acc.max[1] == acc.min[1] == 0.0                                    # flat in XZ
    geo = ld.geometry()
    assert geo["P"].min(0) == pytest.approx(acc.min) and geo["P"].max(0) == pytest.approx(acc.max)
    extras = ld.json["asset"]["extras"]["dualscale"]
    assert extras["swatch_mm"] == pytest.approx([w_mm, h_mm])
    reps = ctx.repeats()
    if case == "tiled":
        assert reps == (2.0, 2.0)
        for ti in _texture_infos(ld.material):
            assert ti["extensions"]["KHR_texture_transform"] == {"scale": [2.0, 2.0]}
        assert ld.json["samplers"][0]["wrapS"] == ld.json["samplers"][0]["wrapT"] == 10497  # REPEAT
    else:
        assert all("extensions" not in ti for ti in _texture_infos(ld.material))
        assert ld.json["samplers"][0]["wrapS"] == 33071  # CLAMP_TO_EDGE: one untiled map


def _texture_infos(mat: dict) -> list[dict]:
    pbr = mat["pbrMetallicRoughness"]
    out = [pbr["baseColorTexture"], pbr["metallicRoughnessTexture"]]
    if "normalTexture" in mat:
        out.append(mat["normalTexture"])
    for ext in mat.get("extensions", {}).values():
        out += [v for k, v in ext.items() if k.endswith("Texture")]
    return out


def _frame(geo: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """From the emitted geometry: (T, B, N) per glTF's rule and where image right / image up
    lie on the mesh (dP/du and -dP/dv: v runs down the image), from one triangle."""
    N, T4 = geo["N"][0], geo["T"][0]
    T = T4[:3]
    B = np.cross(N, T) * T4[3]          # glTF 2.0 spec 3.7.2.1: bitangent = cross(N, T.xyz) * T.w
    i0, i1, i2 = geo["I"][:3]
    P, UV = geo["P"], geo["UV"]
    dP = np.stack([P[i1] - P[i0], P[i2] - P[i0]], 1)        # (3, 2)
    dUV = np.stack([UV[i1] - UV[i0], UV[i2] - UV[i0]], 1)    # (2, 2)
    J = dP @ np.linalg.inv(dUV)                               # columns dP/du, dP/dv
    right = J[:, 0] / np.linalg.norm(J[:, 0])
    up = -J[:, 1] / np.linalg.norm(J[:, 1])
    return T, B, N, right, up


def test_tangent_frame_reads_image_conventions(tmp_path):
    """Tangent = image right, bitangent = image up, normal = front face; a normal map tilted
    towards image +x and +y and an anisotropy direction decode to where the image says."""
    h = w = 32
    n_img = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])   # tilted right and up
    phi = math.radians(30.0)                                              # CCW from image +x
    maps = MaterialMaps(
        albedo=_t(np.full((h, w, 3), 0.5)), roughness=_t(np.full((h, w, 1), 0.4)),
        anisotropy=_t(np.full((h, w, 1), 0.8)), tangent=_t(np.full((h, w, 1), phi / math.pi)),
        normal=_t(np.broadcast_to(n_img, (h, w, 3))))
    ex = exchange(maps, TEXEL_MM)
    out = tmp_path / "g"
    out.mkdir()
    ld = Loaded(write_gltf(ex, ExportContext("tilt", ex.size_mm), out)[0])
    geo = ld.geometry()
    T, B, N, right, up = _frame(geo)
    assert np.allclose(geo["T"][:, 3], 1.0) and np.allclose(geo["N"], N) and np.allclose(geo["T"][:, :3], T)
    assert T == pytest.approx(right, abs=1e-6)   # tangent = increasing u = image right
    assert B == pytest.approx(up, abs=1e-6)      # bitangent = image up (v decreasing)
    assert N == pytest.approx([0, 1, 0])         # glTF +Y up: the swatch lies flat, facing up
    # every triangle winds counter-clockwise seen from the normal (front face up)
    P, I = geo["P"], geo["I"].reshape(-1, 3)
    face = np.cross(P[I[:, 1]] - P[I[:, 0]], P[I[:, 2]] - P[I[:, 0]])
    assert (face @ N > 0).all()
    # image row 0 (v = 0) is the top of the image: the far edge in the 'up' direction
    top = geo["UV"][:, 1] == 0.0
    assert (P[top] @ up).min() == pytest.approx((P @ up).max())
    # the normal texture, read as glTF does (TBN), points right and up on the mesh
    tex = ld.image("normal")
    n_dec = decode_normal(tex[0, 0])
    world = n_dec[0] * T + n_dec[1] * B + n_dec[2] * N
    expect = n_img[0] * right + n_img[1] * up + n_img[2] * N
    assert world == pytest.approx(expect, abs=1e-4)
    # the anisotropy direction (tangent/bitangent space, KHR_materials_anisotropy)
    an = ld.image("anisotropy")[0, 0]
    d = 2 * an[:2] - 1
    d_world = (d[0] * T + d[1] * B) / np.linalg.norm(d)
    assert d_world == pytest.approx(math.cos(phi) * right + math.sin(phi) * up, abs=1e-4)


@pytest.mark.parametrize("fmt", ["gltf", "glb"])
@pytest.mark.parametrize("case", ["anisotropic", "transmissive"])
def test_textures_decode_to_exchange_values(tmp_path, case, fmt):
    import colour

    ex, _, files = _export(tmp_path, case, fmt)
    ld = Loaded(files[0])
    q8, q16 = 0.5 / 255 + 1e-6, 0.5 / 65535 + 1e-7

    def enc(x):
        return colour.models.eotf_inverse_sRGB(np.clip(x, 0, 1))

    trans = gltf_transmission(ex)
    base = ex.base_color if trans is None else trans.base_color
    bc = ld.image("base_color")          # raw code values
    assert np.abs(bc[..., :3] - enc(base)).max() <= q8              # sRGB 8-bit: half a step
    if ex.opacity is not None:
        assert bc.shape[-1] == 4
        assert np.abs(bc[..., 3] - ex.opacity).max() <= q8          # alpha linear coverage
    rough, strength, direction = gltf_anisotropy(ex)
    mr = ld.image("metallic_roughness")
    assert np.abs(mr[..., 1] - rough).max() <= q16
    assert np.abs(mr[..., 2]).max() == 0.0                           # metallic 0
    n = decode_normal(ld.image("normal"))
    ref = ex.normal.astype(np.float64)
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    angle = np.arctan2(np.linalg.norm(np.cross(n, ref), axis=-1), (n * ref).sum(-1))
    # 16-bit: half a step per component, |dn| <= sqrt(3) / 65535 rad (8-bit would be ~0.45 deg)
    assert np.degrees(angle).max() <= np.degrees(math.sqrt(3) / 65535)
    an = ld.image("anisotropy")
    assert np.abs(an[..., :2] - (0.5 * direction + 0.5)).max() <= q16
    assert np.abs(an[..., 2] - strength).max() <= q16
    color, factor = specular_f0_color(ex)
    sc = ld.image("specular_color")
    assert np.abs(sc - enc(color)).max() <= q8
    ext = ld.material["extensions"]
    assert ext["KHR_materials_specular"]["specularColorFactor"] == pytest.approx([factor] * 3)
    assert ext["KHR_materials_ior"]["ior"] == pytest.approx(ex.ior_scalar, abs=1e-6)
    if trans is not None:
        tw = ld.image("transmission")
        assert np.abs(tw[..., 0] - trans.weight).max() <= q16
        assert ext["KHR_materials_transmission"]["transmissionFactor"] == 1.0


def test_unknown_texel_size_gives_default_swatch_with_note(tmp_path, gltf_validator):
    ex = exchange(_iso_maps(32, 32), None)
    assert ex.size_mm is None
    ctx = ExportContext("noscale", None)
    out = tmp_path / "glb"
    out.mkdir()
    ld = Loaded(write_glb(ex, ctx, out)[0])
    gltf_validator.check(ld.path, ALLOWED_WARNINGS)
    acc = ld.doc.accessors[ld.doc.meshes[0].primitives[0].attributes.POSITION]
    assert acc.max[0] - acc.min[0] == pytest.approx(DEFAULT_SWATCH_MM * 1e-3)
    assert acc.max[2] - acc.min[2] == pytest.approx(DEFAULT_SWATCH_MM * 1e-3)
    extras = ld.json["asset"]["extras"]["dualscale"]
    # pygltflib drops null values: an unknown size is an absent key
    assert extras["scale_known"] is False and "repeat_mm" not in extras and "texel_mm" not in extras
    assert "unknown" in extras["note"]


@pytest.mark.parametrize("bad", [(0.0, 1.0), (float("nan"), 1.0), (-2.0, 3.0), (float("inf"), 1.0)])
@pytest.mark.parametrize("fmt", ["gltf", "glb"])
def test_bad_physical_size_is_refused_before_writing(tmp_path, bad, fmt):
    ex = exchange(_iso_maps(8, 8), TEXEL_MM)
    out = tmp_path / fmt
    out.mkdir()
    with pytest.raises(UnitsError, match="repeat_mm"):
        WRITERS[fmt](ex, ExportContext("bad", bad), out)
    with pytest.raises(UnitsError, match="swatch_mm"):
        WRITERS[fmt](ex, ExportContext("bad", (1.0, 1.0), swatch_mm=bad), out)
    assert list(out.iterdir()) == []


def test_maps_of_different_sizes_are_refused(tmp_path):
    ex = exchange(_iso_maps(8, 8), TEXEL_MM)
    ex.normal = np.tile(np.float32([0, 0, 1]), (8, 9, 1))
    with pytest.raises(InputError, match="normal"):
        write_gltf(ex, ExportContext("bad", ex.size_mm), tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_registry_has_the_gltf_writers():
    reg = _registry()
    assert reg["gltf"] is write_gltf and reg["glb"] is write_glb


def test_gltf_and_glb_carry_the_same_textures(tmp_path):
    _, _, f1 = _export(tmp_path, "transmissive", "gltf")
    _, _, f2 = _export(tmp_path, "transmissive", "glb")
    a, b = Loaded(f1[0]), Loaded(f2[0])
    assert [i.name for i in a.doc.images] == [i.name for i in b.doc.images]
    for img in a.doc.images:
        assert np.array_equal(a.image(img.name), b.image(img.name))
    assert a.material == b.material
    shutil.rmtree(tmp_path / "gltf")
