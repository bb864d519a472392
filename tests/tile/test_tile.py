"""Cutting the tile: periodic, seamless, its size in material.json; the CLI end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dualscale.bsdf import MaterialMaps
from dualscale.errors import InputError
from dualscale.formats.maps import load_maps, save_maps
from dualscale.tile import make_tile, save_tile, seam_score
from test_lattice import lattice_image


@pytest.fixture(scope="module")
def twill():
    from dualscale.sim.materials import generate

    return generate("twill", 320, 0.0113, seed=2).maps


def test_twill_tile_is_seamless_and_sized(twill):
    t = make_tile(twill, 0.0113)
    assert t.axis_aligned  # the diagonal twill's (4p, 0), (0, 4p) cell
    np.testing.assert_allclose(t.size_mm, (1.2, 1.2), atol=0.002)
    assert t.seam["tile"] <= 1.1 and t.seam["tile"] < t.seam["untreated"]
    assert all(v <= 1.1 for v in t.seam["maps"].values()), t.seam["maps"]
    n = t.maps.normal.numpy()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    assert (t.maps.tangent.numpy() >= 0).all() and (t.maps.tangent.numpy() < 1).all()


def test_oblique_lattice_is_sheared_onto_the_axes():
    B = np.array([[21.37, 7.12], [-5.8, 23.9]])
    img = lattice_image(B, 256, noise=0.0)
    img = (img - img.min()) / (img.max() - img.min())
    maps = MaterialMaps(albedo=torch.from_numpy(np.repeat(img[..., None], 3, -1).astype(np.float32)),
                        roughness=torch.full((256, 256, 1), 0.5))
    t = make_tile(maps, 0.01, repeats=(2, 1), blend_px=0)
    assert not t.axis_aligned and abs(t.shear_deg) > 3  # the cell's sides meet at 85 deg
    assert t.seam["tile"] <= 1.1, t.seam  # periodic from the warp alone, no blending
    np.testing.assert_allclose(t.size_mm[0], 2 * np.linalg.norm(t.lattice.vectors_px[0]) * 0.01, rtol=1e-6)


def test_tile_folder_carries_its_size(twill, tmp_path):
    t = make_tile(twill, 0.0113, repeats=(2, 1))
    save_tile(t, tmp_path / "tile")
    doc = json.loads((tmp_path / "tile" / "material.json").read_text())
    tile = doc["meta"]["tile"]
    assert tile["repeats"] == [2, 1]
    np.testing.assert_allclose(tile["size_mm"], (2.4, 1.2), atol=0.004)
    np.testing.assert_allclose(np.abs(tile["lattice_mm"]), 0.3 * np.array([[1, 1], [2, 2]]), atol=0.002)
    maps, meta = load_maps(tmp_path / "tile")
    assert maps.shape == (t.maps.shape) and meta["texel_mm"] == pytest.approx(0.0113, rel=0.01)


def test_unknown_texel_size_gives_texels_and_no_mm():
    from dualscale.sim.materials import generate

    t = make_tile(generate("plain", 256, 0.01, seed=0).maps, None)
    assert t.size_mm is None and t.texel_mm is None and t.meta()["lattice_mm"] is None
    np.testing.assert_allclose(t.size_px, (60, 60), atol=0.05)


def test_seam_score():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.standard_normal(64))[None, :] + np.zeros((64, 1))  # a random walk along x: a jump at the wrap
    assert seam_score(x) > 5
    from scipy import ndimage

    per = ndimage.gaussian_filter(rng.standard_normal((128, 128)), 2.0, mode="wrap")  # periodic: no seam
    assert seam_score(per) == pytest.approx(1.0, abs=0.25)


def test_too_many_repeats_refused(twill):
    with pytest.raises(InputError, match="needs .* texels of the field"):
        make_tile(twill, 0.0113, repeats=(3, 3))


def _cli(*args):
    from dualscale.cli import _Parser, exit_code
    from dualscale.cli.tile import register

    p = _Parser(prog="dualscale")
    register(p.add_subparsers(dest="cmd"))
    try:
        a = p.parse_args(list(args))
        return a.fn(a)
    except SystemExit as e:
        return e.code
    except Exception as e:  # noqa: BLE001 - mapped like dualscale.cli.main does
        return exit_code(e)


def test_cli_end_to_end(tmp_path, capsys):
    from dualscale.sim.materials import generate

    save_maps(tmp_path / "maps", generate("satin", 256, 0.01, seed=0).maps, texel_mm=0.01)
    assert _cli("tile", str(tmp_path / "maps"), "-o", str(tmp_path / "tile"), "--repeats", "1x1") == 0
    out = capsys.readouterr().out
    assert "1.500 x 1.500 mm" in out
    meta = json.loads((tmp_path / "tile" / "material.json").read_text())["meta"]["tile"]
    assert meta["size_mm"]
    worst = meta["seam"]["worst"]  # the score the origin is chosen on is the one printed beside the albedo's
    assert worst["map"] == "albedo" or f"its worst map, {worst['map']}, {worst['score']:.3f}" in out, out


def test_cli_refuses_a_map_without_repeat(tmp_path, capsys):
    from scipy import ndimage

    rng = np.random.default_rng(0)
    a = ndimage.gaussian_filter(rng.random((128, 128, 3)), (2, 2, 0))
    save_maps(tmp_path / "maps", MaterialMaps(albedo=torch.from_numpy(a.astype(np.float32)),
                                              roughness=torch.full((128, 128, 1), 0.5)), texel_mm=0.01)
    assert _cli("tile", str(tmp_path / "maps"), "-o", str(tmp_path / "tile")) == 2
    assert _cli("tile", str(tmp_path / "maps"), "-o", str(tmp_path / "tile"), "--repeats", "0x2") == 2
    assert not (tmp_path / "tile").exists()
