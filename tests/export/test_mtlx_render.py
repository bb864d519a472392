"""Our MaterialX export rendered by MaterialX's own GLSL renderer (issue 28 Sec. 1), against our
renderer (:func:`dualscale.bsdf.model.evaluate` of the source maps), both shaders, sun at
90/60/35/20 degrees elevation (azimuth 0, from image right), zenith view; and four orientation
checks: the export as written must score better than the same document with its normal map's
green negated, its textures' rows flipped, its tangent mirrored (-phi) or its sRGB colour read
as linear.  The renderer runs under Xvfb with Mesa (tests/export/mtlx_render.py says what it
takes); the tests skip, with the reason, only when no GL context can be made.  A 64 px twill,
one pixel per texel: about 5 s for the first shader compile, 0.05 s a render after that."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

mx = pytest.importorskip("MaterialX")

from dualscale.bsdf.model import evaluate  # noqa: E402
from dualscale.export import ExportContext, exchange, mtlx  # noqa: E402
from dualscale.export.shading import relative_error  # noqa: E402
from dualscale.export.textures import write_float  # noqa: E402
from dualscale.formats.exr import read_exr  # noqa: E402
from dualscale.sim.materials import generate  # noqa: E402

from tests.export import mtlx_render  # noqa: E402

SIZE = 64
TEXEL_MM = 0.01
VIEW = np.array([0.0, 0.0, 1.0])
ELEVATIONS = (90, 60, 35, 20)
# Measured here (2026-12-03, x86_64 2 cores, Mesa 22.3.6 llvmpipe with its anisotropic filter
# hidden, materialx 1.39.5) on generate("twill", 64, 10 um, seed=2): both shaders 7.58 / 9.75 /
# 10.79 / 12.83 %.  Issue 28 measured 5.6 / 5.0 / 6.4 / 7.2 % on a fitted twill (setup not
# recorded); our own Standard Surface scores 3.2-4.2 % on this twill.  Tolerance: the measured
# value plus 1.5 points.
TOLERANCE = {90: 0.091, 60: 0.113, 35: 0.123, 20: 0.143}
# each wrong alternative scores at least this factor worse than the export as written (mean over
# the elevations at ORIENT_AZIMUTH).  Measured (same run as above): normal green negated 7.1x,
# rows flipped 7.7x, sRGB read as linear 9.2x, tangent mirrored 1.33x (the zenith view sees
# little of the anisotropy's direction on this twill: 8.0 / 9.0 / 12.2 / 15.1 % against ours
# 7.6 / 7.4 / 9.0 / 9.2 %)
WORSE_BY = {"normal_green_negated": 1.5, "rows_flipped": 1.5, "srgb_read_as_linear": 1.5,
            "tangent_mirrored": 1.2}
# the orientation checks light from 120 degrees CCW of image right: a light in the xz plane
# cannot see a negated normal y (or a mirrored tangent on a symmetric weave)
ORIENT_AZIMUTH = 120


@pytest.fixture(scope="module")
def gl():
    why = mtlx_render.available()
    if why:
        pytest.skip(why)


@pytest.fixture(scope="module")
def twill(tmp_path_factory):
    """(export folder, .mtlx path, {elevation: our render (H, W, 3)})."""
    mat = generate("twill", size=SIZE, texel_mm=TEXEL_MM, seed=2)
    ex = exchange(mat.maps, TEXEL_MM)
    out = tmp_path_factory.mktemp("mtlx_render") / "asis"
    out.mkdir()
    files = mtlx.write(ex, ExportContext(name="twill", repeat_mm=ex.size_mm), out)
    keys = [(e, a) for a in (0, ORIENT_AZIMUTH) for e in ELEVATIONS]
    lights = np.stack([mtlx_render.sun(e, a) for e, a in keys])
    ours = evaluate(mat.maps, torch.as_tensor(lights, dtype=torch.float32),
                    torch.as_tensor(VIEW, dtype=torch.float32)).double().numpy()
    return out, files[0], dict(zip(keys, ours))


def _errors(path: Path, shader: str, ours: dict, azimuth: float = 0) -> dict[int, float]:
    r = mtlx_render.MtlxRenderer(path, (SIZE, SIZE))
    return {e: float(relative_error(r.render(shader, mtlx_render.sun(e, azimuth))[None],
                                    ours[(e, azimuth)][None])[0]) for e in ELEVATIONS}


@pytest.mark.parametrize("shader", mtlx_render.SHADERS)
def test_materialx_renders_the_export_close_to_our_renderer(gl, twill, shader):
    _, path, ours = twill
    err = _errors(path, shader, ours)
    table = ", ".join(f"{e}°: {100 * v:.2f} %" for e, v in err.items())
    for e in ELEVATIONS:
        assert err[e] < TOLERANCE[e], f"{shader} at {e}°: relative L1 {table}"
    # the light is really there and really directional: the image darkens towards grazing
    r = mtlx_render.MtlxRenderer(path, (SIZE, SIZE))
    means = [r.render(shader, mtlx_render.sun(e)).mean() for e in ELEVATIONS]
    assert means[0] > 0.05 and all(a > b for a, b in zip(means, means[1:])), means


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst / next(p.name for p in src.iterdir() if p.suffix == ".mtlx")


def _negate_green(path: Path) -> None:
    img = np.asarray(read_exr(path), np.float64)
    img[..., 1] = 1.0 - img[..., 1]  # 0.5 v + 0.5 with v_y -> -v_y
    write_float(path, img, ("R", "G", "B"))


def _wrong(kind: str, asis: Path, root: Path) -> Path:
    """The export, edited the wrong way: a document MaterialX still renders."""
    path = _copy(asis, root / kind)
    folder = path.parent
    stem = path.stem
    if kind == "normal_green_negated":
        _negate_green(folder / f"{stem}_normal.exr")
    elif kind == "tangent_mirrored":  # (cos phi, sin phi) -> (cos -phi, sin -phi)
        _negate_green(folder / f"{stem}_tangent.exr")
    elif kind == "rows_flipped":
        import OpenImageIO as oiio

        for tex in folder.iterdir():
            if tex.suffix in (".exr", ".png"):
                buf = oiio.ImageBuf(str(tex))
                flipped = oiio.ImageBufAlgo.flip(buf)
                tmp = tex.with_name("tmp_" + tex.name)
                assert flipped.write(str(tmp)), flipped.geterror()
                tmp.replace(tex)
    elif kind == "srgb_read_as_linear":
        doc = mx.createDocument()
        mx.readFromXmlFile(doc, str(path))
        n = 0
        for elem in doc.traverseTree():
            if elem.isA(mx.Input) and elem.getType() == "filename" and elem.getColorSpace() == "srgb_texture":
                elem.setColorSpace("lin_rec709")
                n += 1
        assert n >= 1
        mx.writeToXmlFile(doc, str(path))
    else:  # pragma: no cover
        raise AssertionError(kind)
    return path


WRONG = ["normal_green_negated", "rows_flipped", "tangent_mirrored", "srgb_read_as_linear"]


@pytest.mark.parametrize("kind", WRONG)
def test_each_wrong_orientation_or_colour_space_scores_worse(gl, twill, tmp_path, kind):
    """The export as written beats each wrong alternative by WORSE_BY[kind] in the mean over the
    elevations, and is never worse at any elevation (standard_surface: the orientation and
    colour networks are shared by both shaders)."""
    asis, path, ours = twill
    good = _errors(path, "standard_surface", ours, ORIENT_AZIMUTH)
    bad = _errors(_wrong(kind, asis, tmp_path), "standard_surface", ours, ORIENT_AZIMUTH)
    print(kind, {e: f"{100 * good[e]:.2f} / {100 * bad[e]:.2f} %" for e in ELEVATIONS})
    g, b = np.mean(list(good.values())), np.mean(list(bad.values()))
    assert b > WORSE_BY[kind] * g, f"{kind}: {100 * b:.2f} % vs ours {100 * g:.2f} %"
    assert all(bad[e] > good[e] for e in ELEVATIONS), (kind, good, bad)
