"""Bad and display-encoded guidance images: refused with clear errors before anything is written,
or linearised by the stated transfer; maps record the guidance's texel size."""

import json

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.errors import FormatError, InputError, UnitsError
from dualscale.formats.exr import write_exr
from dualscale.propagate.guidance import read_guidance

from .conftest import BED


def _png(path, rgb8):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(rgb8.shape[1], rgb8.shape[0], 3, "uint8"))
    out.write_image(np.ascontiguousarray(rgb8))
    out.close()
    return path


def _exr(tmp_path, name="g.exr", h=48, w=40):
    img = (0.2 + 0.3 * np.random.default_rng(0).random((h, w, 3))).astype(np.float32)
    write_exr(tmp_path / name, img)
    return tmp_path / name, img


def test_nan_pixel_is_refused_with_its_position(tmp_path):
    path, img = _exr(tmp_path)
    img[17, 5, 1] = np.nan
    img[30, 2, 0] = np.inf
    write_exr(path, img)
    with pytest.raises(InputError, match=r"g\.exr: 2 pixel\(s\) are NaN or Inf \(first at row 17, col 5\)"):
        read_guidance(path)


def test_cli_run_refuses_one_nan_pixel_and_writes_nothing(tiny_model, tmp_path, capsys):
    """One NaN pixel used to make every map NaN with exit code 0: now exit 2, a clear message,
    no output folder and no ONNX export."""
    model = tmp_path / "m.dsp"
    model.write_bytes(tiny_model.read_bytes())
    path, img = _exr(tmp_path)
    img[3, 4] = np.nan
    write_exr(path, img)
    out = tmp_path / "maps"
    assert main(["propagate", "run", str(model), str(path), "-o", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "g.exr" in err and "1 pixel(s) are NaN or Inf (first at row 3, col 4)" in err and "--fixnan" in err
    assert not out.exists() and not model.with_suffix(".onnx").exists()


def test_display_encoded_needs_a_stated_transfer(tmp_path):
    code = np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    png = _png(tmp_path / "g.png", code)
    with pytest.raises(UnitsError, match="--transfer srgb"):
        read_guidance(png)
    g = read_guidance(png, "srgb")
    import colour

    assert np.allclose(g.rgb, colour.cctf_decoding(code / 255.0, function="sRGB"), atol=1e-5)
    assert np.allclose(read_guidance(png, "gamma:2.2").rgb, (code / 255.0) ** 2.2, atol=1e-5)
    assert np.allclose(read_guidance(png, "linear").rgb, code / 255.0, atol=1e-6)
    exr, _ = _exr(tmp_path)
    with pytest.raises(UnitsError, match="linear already"):
        read_guidance(exr, "srgb")


def test_clipped_pixels_are_reported(tmp_path):
    code = np.full((20, 20, 3), 120, np.uint8)
    code[:4] = 255
    g = read_guidance(_png(tmp_path / "c.png", code), "srgb")
    assert g.clipped == pytest.approx(0.2) and "20.0 % of the guidance pixels are clipped" in g.warnings[0]


def test_grey_exr_is_refused(tmp_path):
    write_exr(tmp_path / "grey.exr", np.ones((16, 16), np.float32))
    with pytest.raises(FormatError, match="RGB"):
        read_guidance(tmp_path / "grey.exr")


def test_dataset_guidance_knows_its_texel(bed):
    g = read_guidance(bed / "mid")
    assert g.texel_mm == pytest.approx(BED["mid_um"] / 1000) and g.texel_source == "dataset camera"
    assert g.camera.kind == "perspective" and g.shape == (BED["mid"], BED["mid"])
    assert read_guidance(bed / "mid", texel_mm=0.05).texel_mm == 0.05
    with pytest.raises(UnitsError, match="does not apply"):
        read_guidance(bed / "mid", "srgb")
    with pytest.raises(InputError, match="positive"):
        read_guidance(bed / "mid", texel_mm=-1.0)


def test_cli_run_records_texel_mm(tiny_model, bed, tmp_path, capsys):
    """From a dataset: its camera's texel; a plain image: --texel-mm, else null with a warning; a
    PNG with --transfer srgb."""
    def texel(folder):
        return json.loads((folder / "material.json").read_text())["texel_mm"]

    common = ["--tile", "64", "--overlap", "16", "--no-progress"]
    assert main(["propagate", "run", str(tiny_model), str(bed / "mid"), "-o", str(tmp_path / "a"), *common]) == 0
    assert texel(tmp_path / "a") == pytest.approx(BED["mid_um"] / 1000)
    exr, _ = _exr(tmp_path)
    capsys.readouterr()
    assert main(["propagate", "run", str(tiny_model), str(exr), "-o", str(tmp_path / "b"), *common]) == 0
    assert texel(tmp_path / "b") is None and "texel size of g.exr is unknown" in capsys.readouterr().err
    assert main(["propagate", "run", str(tiny_model), str(exr), "-o", str(tmp_path / "c"), "--texel-mm", "0.025",
                 *common]) == 0
    doc = json.loads((tmp_path / "c" / "material.json").read_text())
    assert doc["texel_mm"] == 0.025 and doc["field_mm"] == pytest.approx([40 * 0.025, 48 * 0.025])
    png = _png(tmp_path / "g.png", np.random.default_rng(2).integers(0, 256, (40, 40, 3), dtype=np.uint8))
    assert main(["propagate", "run", str(tiny_model), str(png), "-o", str(tmp_path / "d"), *common]) == 2
    assert "--transfer" in capsys.readouterr().err and not (tmp_path / "d").exists()
    assert main(["propagate", "run", str(tiny_model), str(png), "-o", str(tmp_path / "d"), "--transfer", "srgb",
                 *common]) == 0
    assert json.loads((tmp_path / "d" / "material.json").read_text())["meta"]["propagate"]["transfer"] == "srgb"
