"""Locating the micro field in the guidance (dualscale.propagate.bridge) on the two-scale test bed."""

import numpy as np
import pytest
import torch

from dualscale.errors import GeometryError
from dualscale.geometry.cameras import micro_camera, mid_camera
from dualscale.propagate.bridge import MIN_TEMPLATE_PX, prior_box, project, register_micro

from .conftest import BED, bed_truth


@pytest.mark.parametrize("cam", [mid_camera(64, field_mm=12.0), micro_camera(48, 6.0), mid_camera(40)])
def test_project_inverts_pixel_geometry(cam):
    pts, _ = cam.pixel_geometry()
    xy = project(cam, pts.reshape(-1, 2).numpy())
    rows, cols = np.mgrid[0:cam.height, 0:cam.width]
    assert np.allclose(xy[:, 0], cols.ravel() + 0.5, atol=1e-6)
    assert np.allclose(xy[:, 1], rows.ravel() + 0.5, atol=1e-6)


def test_prior_box_at_the_rig_scales():
    """512 px of 1.8 um in the rig's 4072 px over 100 mm: a 37.5 px box at the image centre."""
    box = prior_box((4072, 4072), 100 / 4072, (0.9216, 0.9216), mid_camera(4072))
    assert box == pytest.approx((2036 - 18.765, 2036 - 18.765, 37.53, 37.53), abs=0.01)
    # a calibrated centre 1 mm right, 2 mm up moves it by (+40.7, -81.4) px
    moved = prior_box((4072, 4072), 100 / 4072, (0.9216, 0.9216), mid_camera(4072), centre_mm=(1.0, 2.0))
    assert moved[0] - box[0] == pytest.approx(40.72, abs=0.01) and moved[1] - box[1] == pytest.approx(-81.44, abs=0.01)
    # no camera: an orthographic view centred on the origin
    assert prior_box((100, 200), 0.01, (0.5, 0.3)) == pytest.approx((75, 35, 50, 30))


def _bed_images(bed):
    from dualscale.propagate.data import load_source
    from dualscale.propagate.guidance import LUMA, read_guidance

    g = read_guidance(bed / "mid")
    src = load_source(bed)
    return g, src, np.einsum("chw,c->hw", src.diffuse_image().numpy(), LUMA)


def test_testbed_depicts_one_sample_at_two_scales(bed):
    """`synth --dataset --mid`: the micro maps area-averaged to the guidance texel agree with the
    mid-scale maps in the micro field (same yarns, same per-yarn shades)."""
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.resample import resize
    from dualscale.sim.materials import generate

    micro, _ = load_maps(bed / "maps")
    mid = generate("twill", BED["mid"], BED["mid_um"] / 1000, 0).maps
    x, y, w, _ = (int(round(v)) for v in bed_truth())
    a = resize(micro.albedo.numpy(), (w, w)).mean(-1)
    b = mid.albedo.numpy()[y:y + w, x:x + w].mean(-1)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.6
    assert abs(a.mean() - b.mean()) < 0.05 * b.mean()
    # and the guidance shows them where the rig geometry says
    g, src, lum = _bed_images(bed)
    assert g.texel_mm == pytest.approx(BED["mid_um"] / 1000) and src.texel_mm == pytest.approx(BED["micro_um"] / 1000)
    r = register_micro(g.luminance(), lum, src.texel_mm / g.texel_mm, bed_truth(), g.texel_mm, search_mm=0.0)
    assert r.score > 0.5


@pytest.mark.parametrize("shift_mm", [(0.0, 0.0), (0.25, -0.15), (-0.4, 0.3)])
def test_registration_recovers_the_field(bed, shift_mm):
    """From a prior off by up to 0.5 mm (42 guidance px), NCC + ECC find the field within 1 px."""
    g, src, lum = _bed_images(bed)
    truth = bed_truth()
    tex = g.texel_mm
    prior = (truth[0] + shift_mm[0] / tex, truth[1] - shift_mm[1] / tex, truth[2], truth[3])
    r = register_micro(g.luminance(), lum, src.texel_mm / tex, prior, tex, search_mm=0.6)
    assert r.method == "ncc+ecc" and not r.warnings, r.to_json()
    assert np.hypot(r.box_px[0] - truth[0], r.box_px[1] - truth[1]) < 1.0, r.to_json()
    assert r.box_px[2:] == pytest.approx(truth[2:])
    assert r.score > 0.5 and r.second < r.score


def test_poor_correlation_falls_back_to_the_prior(bed):
    """An unrelated guidance: the NCC is low, the prior is kept with a warning; strict raises."""
    g, src, lum = _bed_images(bed)
    noise = np.random.default_rng(0).random(g.shape).astype(np.float32)
    prior = bed_truth()
    r = register_micro(noise, lum, 0.5, prior, g.texel_mm)
    assert r.method == "prior" and r.box_px == pytest.approx(prior) and r.score < 0.5
    assert "normalised cross-correlation" in r.warnings[0] and "prior" in r.warnings[0]
    with pytest.raises(GeometryError, match="cannot locate the micro field"):
        register_micro(noise, lum, 0.5, prior, g.texel_mm, strict=True)


def test_tiny_field_and_flat_images_are_not_registered(bed):
    g, src, lum = _bed_images(bed)
    scale = (MIN_TEMPLATE_PX - 1) / lum.shape[1]  # the micro field becomes 7 guidance px
    r = register_micro(g.luminance(), lum, scale, (10, 10, 7, 7), g.texel_mm)
    assert r.method == "prior" and "fewer than" in r.warnings[0]
    r = register_micro(g.luminance(), np.ones_like(lum), 0.5, bed_truth(), g.texel_mm)
    assert r.method == "prior" and "flat" in r.warnings[0]


def test_periodic_texture_is_ambiguous_and_the_prior_decides():
    """Stripes of period 10 px: every 10 px is an equal match; the peak nearest the prior wins."""
    yy, xx = np.mgrid[0:200, 0:200]
    guide = (np.sin(2 * np.pi * xx / 10) + 0.3 * np.sin(2 * np.pi * yy / 37)).astype(np.float32)
    micro = torch.nn.functional.interpolate(torch.from_numpy(guide[80:112, 83:115])[None, None], scale_factor=4,
                                            mode="bilinear")[0, 0].numpy()
    r = register_micro(guide, micro, 0.25, (85.0, 80.0, 32.0, 32.0), 0.01, search_mm=0.3)
    assert r.ambiguous and r.candidates >= 3 and any("ambiguous" in w for w in r.warnings)
    assert abs(r.box_px[0] - 83) < 1.0 and abs(r.box_px[1] - 80) < 1.0
