"""Photographs with an alpha channel (issue 24 §7): the colour is imported as stored, not
premultiplied by alpha (OpenImageIO associates alpha on read by default)."""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.formats.photo import read_codes


def _pil(path, mode, arr, **kw):
    from PIL import Image

    Image.fromarray(arr, mode).save(path, **kw)


@pytest.mark.parametrize("mode", ["RGBA", "LA", "P"])
def test_pil_written_alpha_pngs_read_as_stored(tmp_path, mode):
    """PNGs written by another library (Pillow), alpha 0.5: the colour comes back as stored."""
    p = tmp_path / f"x_{mode}.png"
    if mode == "RGBA":
        a = np.zeros((4, 5, 4), np.uint8)
        a[..., :3] = (153, 100, 50)
        a[..., 3] = 128
        _pil(p, mode, a)
        want = np.array([153, 100, 50]) / 255
    elif mode == "LA":
        a = np.zeros((4, 5, 2), np.uint8)
        a[..., 0], a[..., 1] = 153, 128
        _pil(p, mode, a)
        want = np.array([153, 153, 153]) / 255
    else:  # a palette image whose entry 1 is half transparent
        from PIL import Image

        img = Image.new("P", (5, 4), 1)
        img.putpalette([0, 0, 0, 153, 100, 50] + [0] * (256 * 3 - 6))
        img.info["transparency"] = bytes([255, 128] + [255] * 254)
        img.save(p, transparency=bytes([255, 128] + [255] * 254))
        want = np.array([153, 100, 50]) / 255
    c = read_codes(p)
    assert c.bits == 8
    assert np.allclose(c.code[0, 0], want, atol=0.5 / 255), (c.code[0, 0], want)


@pytest.mark.parametrize("ext,bits", [("png", 16), ("tif", 8), ("tif", 16)])
def test_oiio_written_unassociated_rgba_read_as_stored(tmp_path, ext, bits):
    import OpenImageIO as oiio

    top = 2 ** bits - 1
    a = np.zeros((4, 5, 4), np.uint8 if bits == 8 else np.uint16)
    a[..., :3] = round(0.6 * top)
    a[..., 3] = top // 2
    p = tmp_path / f"x.{ext}"
    spec = oiio.ImageSpec(5, 4, 4, oiio.UINT8 if bits == 8 else oiio.UINT16)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store the colour as given
    out = oiio.ImageOutput.create(str(p))
    out.open(str(p), spec)
    out.write_image(a)
    out.close()
    c = read_codes(p)
    assert np.allclose(c.code[0, 0], round(0.6 * top) / top, atol=0.5 / top), c.code[0, 0]


@pytest.mark.parametrize("what", ["garbage", "truncated"])
def test_corrupt_photographs_are_bad_input_naming_the_file(tmp_path, what, capsys):
    """A corrupt or truncated photograph is bad input (exit 2), named (issue 24 §2)."""
    from dualscale.cli import main
    from dualscale.errors import FormatError
    from dualscale.sim.photos import PSM_LIGHTS, render_photos, write_photos

    folder, lp = write_photos(tmp_path / "obj", render_photos("sphere", size=(24, 32)))
    bad = folder / "obj.3.png"
    data = bad.read_bytes()
    bad.write_bytes(b"not an image at all" * 10 if what == "garbage" else data[: len(data) // 2])
    with pytest.raises(FormatError, match="obj.3.png"):
        read_codes(bad)
    assert main(["import", str(folder), "--lights", str(lp), "-o", str(tmp_path / "ds"), "--transfer", "auto"]) == 2
    err = capsys.readouterr().err
    assert "obj.3.png" in err
    assert not (tmp_path / "ds" / "manifest.json").exists()
    assert len(PSM_LIGHTS) == 12
