"""Cast shadows of the relief and of raised fly-out fibres (dualscale.sim.shadow)."""

import math

import numpy as np
import pytest
import torch

from dualscale.geometry.cameras import micro_camera
from dualscale.geometry.dome import DomeGeometry
from dualscale.sim.render import Analyzer, LightRealism, LightState, render
from dualscale.sim.shadow import SurfaceGeometry, visibility
from dualscale.sim.materials import generate

TEXEL = 0.01  # mm


def _dir(elev_deg: float, az_deg: float) -> torch.Tensor:
    e, a = math.radians(elev_deg), math.radians(az_deg)
    return torch.tensor([[math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]], dtype=torch.float64)


def _wall(h: int = 64, w: int = 64, col: int = 40, height: float = 0.1) -> np.ndarray:
    z = np.zeros((h, w))
    z[:, col] = height  # a 1-texel wall along the rows, facing +x and -x
    return z


def test_flat_sample_is_lit_and_horizon_is_dark():
    g = SurfaceGeometry(np.zeros((16, 16)), TEXEL)
    assert torch.all(visibility(g, _dir(5.0, 30.0)) == 1)
    assert torch.all(visibility(g, _dir(-1.0, 30.0)) == 0)


def test_wall_shadow_has_the_length_the_elevation_gives():
    g = SurfaceGeometry(_wall(), TEXEL)
    for elev in (18.0, 30.0, 45.0):
        vis = visibility(g, _dir(elev, 0.0))[0, 32]  # light from +x: the shadow falls to -x of the wall
        length = 0.1 / math.tan(math.radians(elev)) / TEXEL  # texels
        dark = np.nonzero(vis.numpy() == 0)[0]
        assert dark.max() == 39 and abs((40 - dark.min()) - length) <= 1.01, (elev, dark)
        assert vis[41:].min() == 1  # the lit side of the wall
    assert torch.all(visibility(g, _dir(90.0, 0.0)) == 1)  # the zenith casts none
    side = visibility(g, _dir(18.0, 90.0))[0]  # light along the wall: no shadow beside it
    assert side[:, :39].min() == 1


def test_raised_fibre_shades_a_thin_line_where_its_shadow_lands():
    h = w = 64
    mask = np.zeros((h, w), bool)
    mask[:, 40] = True  # a fibre along the rows, axis 0.1 mm up
    g = SurfaceGeometry(np.zeros((h, w)), TEXEL, mask, np.where(mask, 0.1, 0.0), np.where(mask, 0.103, 0.0), 0.003)
    vis = visibility(g, _dir(30.0, 0.0))[0, 32].numpy()
    land = 40 - 0.1 / math.tan(math.radians(30.0)) / TEXEL
    dark = np.nonzero(vis == 0)[0]
    assert len(dark) == 1 and abs(dark[0] - land) <= 1.0  # light passes under it elsewhere
    assert vis[40] == 1


def test_geometry_is_validated():
    with pytest.raises(ValueError):
        SurfaceGeometry(np.full((4, 4), np.nan), TEXEL)
    with pytest.raises(ValueError):
        SurfaceGeometry(np.zeros((4, 4)), TEXEL, np.zeros((3, 4), bool))
    mat = generate("twill", 32, 0.009)
    cam = micro_camera(32, 9.0)
    with pytest.raises(ValueError, match="geometry"):
        render(mat.maps, cam, LightState.led(100), realism=LightRealism(shadows=True))
    small = SurfaceGeometry(np.zeros((16, 16)), 0.009)
    with pytest.raises(ValueError, match="map grid"):
        render(mat.maps, cam, LightState.led(100), realism=LightRealism(shadows=True), geometry=small)


def test_shadows_darken_grazing_light_only_and_keep_fibres_lit():
    mat = generate("twill", 96, 0.0045, seed=0)
    cam, dome = micro_camera(96, 4.5), DomeGeometry.from_regmap()
    on = LightRealism(shadows=True)
    ortho = [render(mat.maps, cam, LightState.led(0), dome, Analyzer(0, True), realism=r, geometry=mat.geometry)
             for r in (LightRealism(), on)]
    assert torch.equal(ortho[0], ortho[1])
    vis = visibility(mat.geometry, dome.led_dirs[120:121])[0].numpy()
    assert 0.05 < 1 - vis.mean() < 0.6  # a grazing LED shades part of the weave
    img = render(mat.maps, cam, LightState.led(120), dome, Analyzer(0, True), realism=on, geometry=mat.geometry)
    assert torch.all(img[torch.from_numpy(vis == 0)] == 0)
    raised = mat.flyout_mask & (mat.geometry.fibre_axis_mm > mat.geometry.height_mm.max())
    assert raised.any() and vis[raised].mean() == 1.0  # above every yarn, nothing shades them


def test_flyout_geometry():
    mat = generate("twill", 200, 0.0018, seed=3)
    g, m = mat.geometry, mat.flyout_mask
    assert len(mat.flyouts) == max(2, round(10.0 * (200 * 0.0018) ** 2)) and m.any()
    for pl in mat.flyouts:  # whole fibres in view
        p = np.asarray(pl)
        assert p.min() >= 2 and p.max() < 198
    n = mat.maps.normal.numpy()[m]
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5) and n[:, 2].min() > 0
    assert n[:, 2].min() < 0.6  # cylinder normals turn towards the horizon at the fibre's sides
    assert (g.fibre_top_mm[m] >= g.fibre_axis_mm[m]).all()
    assert np.median(g.fibre_axis_mm[m] - g.height_mm[m]) > 0.03  # they stand out of the fabric
    sheer = generate("sheer", 64, 0.009)
    assert sheer.geometry is not None and sheer.flyout_mask.any()
    assert generate("leather", 32, 0.009).geometry.fibre_mask is None


def test_geometry_roundtrips_through_exr(tmp_path):
    from dualscale.formats.relief import load_geometry, save_geometry

    g = generate("twill", 48, 0.0045, seed=0).geometry
    assert g.fibre_mask is not None and g.fibre_mask.any()
    save_geometry(tmp_path / "g.exr", g)
    back = load_geometry(tmp_path / "g.exr")
    assert back.texel_mm == g.texel_mm and back.fibre_radius_mm == g.fibre_radius_mm
    assert np.array_equal(back.fibre_mask, g.fibre_mask)
    for a, b in ((back.height_mm, g.height_mm), (back.fibre_axis_mm[g.fibre_mask], g.fibre_axis_mm[g.fibre_mask]),
                 (back.fibre_top_mm[g.fibre_mask], g.fibre_top_mm[g.fibre_mask])):
        assert np.allclose(a, b, rtol=1e-6, atol=1e-9)  # float32 on disk
    d = _dir(10.0, 30.0)
    assert torch.equal(visibility(back, d), visibility(g, d))
    from dualscale.formats.exr import write_exr

    write_exr(tmp_path / "bad.exr", np.zeros((4, 4, 4)), ("height", "fibre_mask", "fibre_axis", "fibre_top"))
    with pytest.raises(ValueError, match="not a dualscale geometry file"):
        load_geometry(tmp_path / "bad.exr")
    with pytest.raises(FileNotFoundError):
        load_geometry(tmp_path / "missing.exr")


def test_render_cli_casts_the_saved_shadows(tmp_path, capsys):
    from dualscale.cli import main
    from dualscale.formats.exr import read_exr

    maps = tmp_path / "t" / "maps"
    assert main(["synth", "twill", "-o", str(tmp_path / "t"), "--size", "48", "--texel-um", "4.5",
                 "--no-previews"]) == 0
    assert (maps / "geometry.exr").is_file()
    dome = DomeGeometry.from_regmap()
    grazing = int(torch.argmin(dome.led_dirs[:, 2]))
    args = ["render", str(maps), "--led", str(grazing), "--texel-um", "4.5", "--analyzer", "90", "--relative"]
    assert main(args + ["-o", str(tmp_path / "lit")]) == 0
    assert main(args + ["-o", str(tmp_path / "shade"), "--shadows"]) == 0
    lit = read_exr(next((tmp_path / "lit").rglob("*.exr")))
    shade = read_exr(next((tmp_path / "shade").rglob("*.exr")))
    assert shade.mean() < 0.9 * lit.mean() and np.all(shade <= lit + 1e-6)
    for argv, needle in [(args + ["-o", str(tmp_path / "x"), "--shadows", "--texel-um", "9"], "does not match"),
                         (["render", str(maps), "--led", "0", "--camera", "mid", "--shadows", "-o", str(tmp_path / "y")],
                          "micro")]:
        assert main(argv) == 2
        assert needle in capsys.readouterr().err
    (maps / "geometry.exr").unlink()
    assert main(args + ["-o", str(tmp_path / "z"), "--shadows"]) == 2
    assert "needs the relief" in capsys.readouterr().err
    assert not any((tmp_path / d).exists() for d in "xyz")  # nothing written
