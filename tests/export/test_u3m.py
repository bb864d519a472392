"""U3M export (issue 12 Sec. 1 "U3M"): the .u3ma against the U3M 1.1 specification.

The specification (../shared/data/u3m: u3m_schema.json, u3m_additional_spec*.txt) is read from
the shared data; tests that need it skip when it is absent.  Each mechanical rule of
u3m_additional_spec_u3ma.txt is one assertion, quoted beside it.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.bsdf import MaterialMaps
from dualscale.errors import UnitsError
from dualscale.export import ExportContext, exchange
from dualscale.export.exchange import f0_from_ior, gltf_transmission, luminance
from dualscale.export.textures import decode_normal, read_png
from dualscale.export.u3m import _principled_tint, write
from dualscale.sim.materials import generate

ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / ".." / "shared" / "data" / "u3m"
needs_spec = pytest.mark.skipif(not (SPEC / "u3m_schema.json").is_file(),
                                reason="../shared/data/u3m (the U3M 1.1 specification) absent")

TEXEL = 0.01


# -- fixtures -------------------------------------------------------------------------------------

def _export(tmp_path: Path, ex, name: str, repeat=None):
    out = tmp_path / name
    out.mkdir()
    ctx = ExportContext(name=name, repeat_mm=repeat if repeat is not None else ex.size_mm)
    files = write(ex, ctx, out)
    return ctx, files


@pytest.fixture(scope="module")
def twill():
    return exchange(generate("twill", size=48, texel_mm=TEXEL).maps, TEXEL)


@pytest.fixture(scope="module")
def sheer():
    return exchange(generate("sheer", size=48, texel_mm=TEXEL).maps, TEXEL)


def _plain_maps(h: int = 32, w: int = 48) -> MaterialMaps:
    """Isotropic, opaque, no optional maps; rectangular so that width/height cannot swap."""
    g = torch.Generator().manual_seed(3)
    return MaterialMaps(albedo=0.1 + 0.7 * torch.rand(h, w, 3, generator=g),
                        roughness=0.2 + 0.6 * torch.rand(h, w, 1, generator=g))


class U3ma:
    """An exported .u3ma: raw bytes, its entries' bytes, and the U3M document."""

    def __init__(self, path: Path):
        import zipfile

        self.path, self.raw = path, path.read_bytes()
        with zipfile.ZipFile(path) as zf:
            assert zf.testzip() is None
            self.infos = zf.infolist()
            self.data = {i.filename: zf.read(i) for i in self.infos}
        u3m = [n for n in self.data if n.endswith(".u3m")]
        assert len(u3m) == 1, f"one .u3m expected in {path.name}, got {u3m}"
        self.u3m_name = u3m[0]
        self.doc = json.loads(self.data[self.u3m_name].decode("utf-8"))

    @property
    def front(self) -> dict:
        return self.doc["material"]["front"]

    def image(self, rel: str, srgb: bool, tmp: Path) -> np.ndarray:
        p = tmp / Path(rel).name
        p.write_bytes(self.data[rel])
        return read_png(p, srgb=srgb)


def _scalar(u: U3ma, key: str, tmp: Path) -> np.ndarray | None:
    """``finalNumericPixel = offset + average(imagePixel) * factor`` (u3m_additional_spec_u3m.txt)."""
    tex = u.front[key]["texture"]
    if tex is None:
        return None
    img = u.image(tex["image"]["path"], srgb=False, tmp=tmp)
    return tex["offset"] + img.mean(-1) * tex["factor"]


def _images(doc) -> list[dict]:
    """Every ``image`` object of the document."""
    found = []

    def walk(o):
        if isinstance(o, dict):
            if {"path", "dpi", "width", "height", "repeat"} <= o.keys():
                found.append(o)
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(doc)
    return found


# -- the JSON: schema and required fields -----------------------------------------------------------

@needs_spec
@pytest.mark.parametrize("which", ["twill", "sheer", "plain"])
def test_u3m_json_validates_against_the_schema(which, twill, sheer, tmp_path):
    import jsonschema

    ex = {"twill": twill, "sheer": sheer, "plain": exchange(_plain_maps(), TEXEL)}[which]
    _, files = _export(tmp_path, ex, which)
    assert [f.name for f in files] == [f"{which}.u3ma"] and files[0].is_file()
    u = U3ma(files[0])
    schema = json.loads((SPEC / "u3m_schema.json").read_text())
    jsonschema.Draft7Validator.check_schema(schema)
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in
              jsonschema.Draft7Validator(schema, format_checker=jsonschema.FormatChecker()).iter_errors(u.doc)]
    assert errors == []
    # required fields, independently of the validator (schema "required" lists)
    assert set(schema["required"]) <= u.doc.keys() and u.doc["schema"] == "1.1"
    mat = u.doc["material"]
    assert set(schema["properties"]["material"]["required"]) <= mat.keys()
    assert set(schema["definitions"]["visualisation"]["required"]) <= mat["front"].keys()
    # "format": "date-time" (jsonschema checks it only with rfc3339-validator installed): RFC 3339 UTC
    for key in ("created", "modified"):
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", mat[key])
        assert datetime.fromisoformat(mat[key]).tzinfo is not None
    # "A valid U3M must contain at least one visual ("front", "back" or "side") or physics"
    assert mat["front"] is not None
    # back/side null: "if null, the values from front are used instead" (we capture the front only)
    assert mat["back"] is None and mat["side"] is None


# -- the zip container: u3m_additional_spec_u3ma.txt, byte by byte --------------------------------

LOCAL = struct.Struct("<IHHHHHIIIHH")
CENTRAL = struct.Struct("<IHHHHHHIIIHHHHHII")
EOCD = struct.Struct("<IHHHHIIH")


@needs_spec
@pytest.mark.parametrize("which", ["twill", "sheer"])
def test_u3ma_zip_follows_the_byte_level_rules(which, twill, sheer, tmp_path):
    ex = {"twill": twill, "sheer": sheer}[which]
    _, files = _export(tmp_path, ex, which)
    u = U3ma(files[0])
    raw = u.raw
    schema = json.loads((SPEC / "u3m_schema.json").read_text())
    path_re = re.compile(schema["definitions"]["relative_file_path"]["pattern"])

    # end of central directory record: "no data may come ... after <end of central directory record>"
    # and "zipFileCommentLength //must be 0" -> the record is the last 22 bytes
    eocd = EOCD.unpack_from(raw, len(raw) - EOCD.size)
    sig, disk, disk_cd, n_disk, n_total, cd_size, cd_off, comment_len = eocd
    assert sig == 0x06054B50                      # "endOfCentralDirSignature //must have the value 0x06054b50"
    assert disk == 0                              # "numberOfThisDisk //must be 0"
    assert disk_cd == 0                           # "numberOfTheDiskWithTheStartOfTheCentralDirectory //must be 0"
    assert comment_len == 0                       # "zipFileCommentLength //must be 0"
    assert n_disk == n_total == len(u.infos)      # "number of <file entries> in this u3ma"
    assert cd_off + cd_size == len(raw) - EOCD.size  # "offsetOfTheCentralDirectory", "sizeOfTheCentralDirectory"
    # "explicitly disabled zip64": no zip64 end record/locator, no 0xFFFFFFFF sizes
    assert b"PK\x06\x06" not in raw[cd_off:] and b"PK\x06\x07" not in raw[cd_off:]

    # central directory headers
    central, pos = [], cd_off
    for _ in range(n_total):
        c = CENTRAL.unpack_from(raw, pos)
        (sig, made_by, needed, flags, method, mtime, mdate, crc, csize, usize,
         nlen, xlen, clen, disk_start, int_attr, ext_attr, offset) = c
        name_b = raw[pos + CENTRAL.size: pos + CENTRAL.size + nlen]
        assert sig == 0x02014B50                  # "centralFileHeaderSignature //must have the value 0x02014b50"
        assert made_by == 0x003F                  # "you should read 0x00?? and write 0x003F"
        assert needed == 0x14                     # "versionNeededToExtract //must be 0x14"
        assert flags & 0x800                      # "bit 11 (EFS) must be always set"
        assert flags & ~0x806 == 0                # "other bits MUST BE ZERO" (so no data descriptor, no encryption)
        assert method in (0, 8)                   # "must be either 0 (no compression) or 8 (compressed with DELFATE)"
        if method == 0:
            assert flags & 0x6 == 0               # "only bits 1 & 2 may be set for compressed files"
            assert csize == usize                 # "must equal uncompressedSize if data is not compressed"
        assert xlen == 0                          # "extraFieldLength //must be 0"
        assert clen == 0                          # "fileCommentLength //must be 0"
        assert disk_start == 0                    # "diskNumberStart //must be 0"
        assert int_attr == 0                      # "internalFileAttributes //must be 0"
        assert ext_attr == 0                      # "externalFileAttributes //must be 0"
        assert 0xFFFFFFFF not in (csize, usize, offset)  # "explicitly disabled zip64"
        name = name_b.decode("utf-8")             # "UTF8 encoded filename (NO TERMINAL ZERO)"
        assert "\0" not in name and name           # "non-empty & utf-8 encoded and must not contain \0 chars"
        assert not name.startswith("/") and not name.endswith("/")  # "must not start with a slash ...
        assert path_re.match(name), name          # "must be a relative path as defined for the rest of u3m"
        # "lastModFileTime //time part of a MS-DOS time (in UTC!)": the document's creation time
        created = datetime.fromisoformat(u.doc["material"]["created"]).astimezone(timezone.utc)
        dos = datetime(1980 + (mdate >> 9), (mdate >> 5) & 15, mdate & 31,
                       mtime >> 11, (mtime >> 5) & 63, 2 * (mtime & 31), tzinfo=timezone.utc)
        assert abs((dos - created).total_seconds()) <= 2
        central.append((c, name_b))
        pos += CENTRAL.size + nlen + xlen + clen
    assert pos == cd_off + cd_size
    names = [n for _, n in central]
    assert len(set(names)) == len(names)          # "unique within the archive"

    # file entries: contiguous from byte 0 ("no data may come before <file entry 1>")
    pos = 0
    for c, name_b in central:
        (_, _, _, flags, method, mtime, mdate, crc, csize, usize, nlen, *_rest) = c
        offset = c[-1]
        assert offset == pos                      # "relativeOffsetOfLocalHeader", entries back to back
        sig, needed, lflags, lmethod, lt, ld, lcrc, lcs, lus, lnlen, lxlen = LOCAL.unpack_from(raw, pos)
        assert sig == 0x04034B50                  # "localFileHeaderSignature //must have the value 0x04034b50"
        assert needed == 0x14                     # "versionNeededToExtract //must be 0x14"
        assert (lflags, lmethod, lt, ld) == (flags, method, mtime, mdate)  # "must have the same value as ..."
        assert (lcrc, lcs, lus, lnlen) == (crc, csize, usize, nlen)        # ... the central directory header"
        assert lxlen == 0                         # "extraFieldLength //must be 0"
        assert raw[pos + LOCAL.size: pos + LOCAL.size + lnlen] == name_b   # "fileName //must have the same value"
        start = pos + LOCAL.size + lnlen
        payload = raw[start: start + csize]
        data = payload if method == 0 else zlib.decompress(payload, -15)
        assert len(data) == usize
        assert zlib.crc32(data) == crc            # "crc32 //with reversed polynomial 0xedb88320 ... (same as used by ZIP)"
        pos = start + csize                       # "explicitly disallowed data description header"
    assert pos == cd_off                          # the central directory follows the last file entry

    # every file is the .u3m or an image it references (no stray files), the .u3m first
    referenced = {img["path"] for img in _images(u.doc)}
    assert names[0].decode() == u.u3m_name
    assert {n.decode() for n in names[1:]} == referenced


# -- the textures ----------------------------------------------------------------------------------

@needs_spec
@pytest.mark.parametrize("which", ["twill", "plain"])
def test_every_texture_exists_is_baseline_png_and_matches_the_size(which, twill, tmp_path):
    import OpenImageIO as oiio

    ex = twill if which == "twill" else exchange(_plain_maps(32, 48), TEXEL)  # plain: W != H
    repeat = (0.7, 0.35)  # a tile's repeat, not the maps' own size: the writer must use ctx's
    ctx, files = _export(tmp_path, ex, which, repeat=repeat)
    u = U3ma(files[0])
    images = _images(u.doc)
    assert len(images) >= (8 if which == "twill" else 2)
    h, w = ex.shape
    for img in images:
        assert img["path"] in u.data, img["path"]
        p = tmp_path / Path(img["path"]).name
        p.write_bytes(u.data[img["path"]])
        inp = oiio.ImageInput.open(str(p))
        assert inp is not None, oiio.geterror()
        spec = inp.spec()
        inp.close()
        # baseline formats: "png: - 8/16bit rgb/rgba"
        assert inp.format_name() == "png"
        assert spec.nchannels in (3, 4) and spec.format in (oiio.UINT8, oiio.UINT16)
        assert (spec.width, spec.height) == (w, h)
        # physical size = one repeat; "the dpi that can be calculated from width & height and the
        # image size" must match the stated dpi
        assert (img["width"], img["height"]) == pytest.approx(repeat, rel=1e-12)
        assert img["dpi"]["x"] == pytest.approx(spec.width * 25.4 / img["width"], rel=1e-9)
        assert img["dpi"]["y"] == pytest.approx(spec.height * 25.4 / img["height"], rel=1e-9)
        assert img["repeat"] == {"rotation": 0.0, "mode": "normal"}
    assert u.doc["custom"]["dualscale"]["repeat_mm"] == list(repeat)


@needs_spec
def test_textures_decode_to_the_exchange_values(twill, tmp_path):
    _, files = _export(tmp_path, twill, "twill")
    u = U3ma(files[0])
    f = u.front
    half16 = 0.5 / 65535
    # base colour: 8-bit sRGB ("Standard colorspace is sRGB"); decode slope <= 2.3 -> 0.5 LSB
    base = u.image(f["basecolor"]["texture"]["image"]["path"], srgb=True, tmp=tmp_path)
    assert np.abs(base - twill.base_color).max() <= 2.3 * 0.5 / 255 + 1e-6
    assert f["basecolor"]["texture"]["mode"] == "multiply"
    # roughness r: principled alpha = r^2, ours too -> copied
    assert np.abs(_scalar(u, "roughness", tmp_path) - twill.roughness).max() <= half16 + 1e-6
    # anisotropy: principled (Burley) aspect sqrt(1 - 0.9 a) = ours -> copied; rotation CCW turns
    assert np.abs(_scalar(u, "anisotropy_value", tmp_path) - twill.anisotropy).max() <= half16 + 1e-6
    rot = _scalar(u, "anisotropy_rotation", tmp_path)
    assert np.abs(rot * 2 * np.pi - twill.tangent_angle).max() <= 2 * np.pi * half16 + 1e-5
    # normals: "All normals are in OpenGL convention" (ours: +Y = image up) -> no flip; (n + 1) / 2
    tex = f["normal"]["texture"]
    n = decode_normal(u.image(tex["image"]["path"], srgb=False, tmp=tmp_path))
    assert tex["scale"] == 1.0
    assert np.abs(n - twill.normal).max() <= 2e-4
    tilt_y = twill.normal[..., 1]
    assert np.corrcoef(n[..., 1].ravel(), tilt_y.ravel())[0, 1] > 0.99  # same sign of Y: not DirectX
    # IOR with factor/offset (16 bit over its range), specular_value = F0 / 8 %
    ior = _scalar(u, "ior", tmp_path)
    span = f["ior"]["texture"]["factor"]
    assert np.abs(ior - twill.ior).max() <= span * half16 + 1e-6
    spec = _scalar(u, "specular_value", tmp_path)
    assert np.abs(spec - f0_from_ior(twill.ior) / 0.08).max() <= 1e-4
    # specular tint: principled scalar fitted to our F0 tint (against the written base colour)
    tint = _scalar(u, "specular_tint", tmp_path)
    assert np.abs(tint - _principled_tint(twill.specular_color, twill.base_color)).max() <= half16 + 1e-6
    # opaque: transmission 0, alpha 1, no texture
    assert f["transmission"] == {"constant": 0.0, "texture": None}
    assert f["alpha"] == {"constant": 1.0, "texture": None}
    # constants: "the average of the final texture value after factors are applied"
    assert f["roughness"]["constant"] == pytest.approx(float(twill.roughness.mean()), abs=1e-4)
    assert f["ior"]["constant"] == pytest.approx(float(twill.ior.mean()), abs=1e-4)
    assert f["sheen_value"] == {"constant": 0.0, "texture": None}


@needs_spec
def test_transmissive_sample_carries_transmission_and_alpha(sheer, tmp_path):
    _, files = _export(tmp_path, sheer, "sheer")
    u = U3ma(files[0])
    f = u.front
    split = gltf_transmission(sheer)
    assert split is not None
    weight = _scalar(u, "transmission", tmp_path)
    assert weight is not None and float(weight.max()) > 0.2
    assert np.abs(weight - split.weight).max() <= 0.5 / 65535 + 1e-6
    assert np.abs(_scalar(u, "alpha", tmp_path) - sheer.opacity).max() <= 0.5 / 65535 + 1e-6
    base = u.image(f["basecolor"]["texture"]["image"]["path"], srgb=True, tmp=tmp_path)
    assert np.abs(base - split.base_color).max() <= 2.3 * 0.5 / 255 + 1e-6
    # what the principled split scatters, (1 - T) base, is our reflectance b (the split keeps the
    # reflection exact and lowers T where base would clip)
    reflected = base * (1 - weight[..., None])
    assert np.abs(reflected - sheer.base_color).max() <= 0.01


@needs_spec
def test_isotropic_maps_write_constants_only_where_they_have_no_map(tmp_path):
    ex = exchange(_plain_maps(), TEXEL)
    _, files = _export(tmp_path, ex, "plain")
    f = U3ma(files[0]).front
    for key in ("anisotropy_value", "anisotropy_rotation", "specular_tint", "transmission", "ior",
                "specular_value"):
        assert f[key]["texture"] is None, key
    assert f["normal"] == {"constant": {"x": 0.0, "y": 0.0, "z": 1.0}, "texture": None}
    assert f["ior"]["constant"] == pytest.approx(ex.ior_scalar)
    assert f["specular_value"]["constant"] == pytest.approx(float(f0_from_ior(ex.ior_scalar)) / 0.08)
    assert f["roughness"]["texture"] is not None


def test_unknown_size_is_refused_and_nothing_written(twill, tmp_path):
    from dataclasses import replace

    ex = replace(twill, texel_mm=None)
    out = tmp_path / "u3m"
    out.mkdir()
    with pytest.raises(UnitsError, match="--texel-mm") as err:
        write(ex, ExportContext(name="twill", repeat_mm=None), out)
    assert "width/height" in str(err.value) and "'twill'" in str(err.value)
    assert list(out.iterdir()) == []


def test_principled_tint_inverts_the_principled_formula():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.05, 0.9, (16, 16, 3))
    s = rng.uniform(0, 1, (16, 16))
    c = base / luminance(base)[..., None]
    tint = (1 - s)[..., None] + s[..., None] * c  # principled: mix(1, base / lum(base), s)
    assert np.abs(_principled_tint(tint, base) - s).max() < 1e-9
    grey = np.full((2, 2, 3), 0.4)
    assert np.all(_principled_tint(np.ones((2, 2, 3)), grey) == 0.0)
    assert _principled_tint(None, grey) is None


def test_rotation_is_a_fraction_of_a_full_turn(twill, tmp_path):
    # U3M "anisotropy_rotation ... value is in percent, to get to degree, multiply by 360"
    ctx = ExportContext("twill", (1.0, 1.0))
    path = write(twill, ctx, tmp_path)[0]
    rot = _scalar(U3ma(path), "anisotropy_rotation", tmp_path)
    assert np.allclose(rot * 360.0, np.degrees(twill.tangent_angle), atol=0.01)
