"""Chart detection that cannot be silently wrong (issue 13 section 4): small, rotated,
sub-pixel-placed, tilted, low-contrast and partly occluded ColorCheckers, rendered here
synthetically and reproducibly (fixed seeds), are either located to a fraction of a pixel or
refused with a ChartNotFoundError naming the failed check.  docs/CALIBRATION.md, "Chart
detection", holds the table these cases produce."""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.calib import chart as ch
from dualscale.calib import colourref as cr
from dualscale.calib.chart import ChartLayout, detect_chart, homography, sample_patches, verify_chart
from dualscale.errors import ChartNotFoundError

LAYOUT = ChartLayout()


def render_chart(shape=(64, 96), centre=(48.0, 32.0), px_per_mm=0.9, angle_deg=0.0, tilt=0.0, background=0.3,
                 gain=1.0, flare=0.0, noise=0.0, occlude=None, seed=0, ss=8):
    """A linear-RGB ``(H, W, 3)`` image of the ColorChecker (reference RGB swatches, 0.03 body) on
    a flat ``background`` and its true swatch-area corners ``(4, 2)`` (TL, TR, BR, BL, image x/y,
    pixel centres at integers).  The chart is centred at ``centre`` (sub-pixel), scaled by
    ``px_per_mm``, rotated by ``angle_deg`` and keystoned by ``tilt`` (relative growth of the
    right side); each pixel is the mean of ``ss x ss`` point samples (area coverage).  Then
    ``gain * img + flare``, an ``occlude`` box ``(x0, y0, x1, y1, value)`` painted over it, and
    shot-like noise ``noise * sqrt(img)`` (seeded)."""
    h, w = shape
    cw, chh = LAYOUT.size_mm
    a = np.deg2rad(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    mm = np.array([[-cw / 2, chh / 2], [cw / 2, chh / 2], [cw / 2, -chh / 2], [-cw / 2, -chh / 2]])
    pts = (mm * [1, -1]) * (1 + tilt * mm[:, [0]] / cw)
    corners = pts @ rot.T * px_per_mm + np.asarray(centre, float)
    to_mm = homography(corners, mm)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    xs = (np.arange(w)[:, None] + off[None]).ravel()
    ys = (np.arange(h)[:, None] + off[None]).ravel()
    x, y = np.meshgrid(xs, ys)
    p = np.stack([x, y, np.ones_like(x)], -1) @ to_mm.T
    lab = LAYOUT.patch_of(p[..., 0] / p[..., 2], p[..., 1] / p[..., 2])
    colours = np.concatenate([cr.reference_rgb(), [[0.03] * 3, [background] * 3]])
    img = colours[np.where(lab >= 0, lab, np.where(lab == -1, 24, 25))].reshape(h, ss, w, ss, 3).mean((1, 3))
    img = gain * img + flare
    if occlude is not None:
        x0, y0, x1, y1, val = occlude
        img[int(y0):int(y1), int(x0):int(x1)] = val
    if noise:
        img = img + noise * np.sqrt(np.clip(img, 0, None)) * np.random.default_rng(seed).standard_normal(img.shape)
    return img, corners


# name: (render arguments, expected outcome: None = detected, else a fragment of the refusal)
CASES = {
    "small, sub-pixel (82x54, 0.62 px/mm)": (dict(shape=(54, 82), centre=(41.3, 26.8), px_per_mm=0.62, angle_deg=5,
                                                  noise=0.03, seed=1), None),
    "small, sub-pixel, 8.7 px pitch": (dict(shape=(74, 115), centre=(56.6, 37.2), px_per_mm=0.56, angle_deg=-2,
                                            noise=0.01, seed=5), None),
    "rotated 17 deg": (dict(shape=(110, 110), centre=(55.3, 54.6), px_per_mm=0.9, angle_deg=17), None),
    "keystone 20 %": (dict(shape=(100, 120), centre=(60.3, 49.6), px_per_mm=1.0, tilt=0.2), None),
    "low contrast (gain 0.3, flare 0.3)": (dict(shape=(54, 91), centre=(45.2, 26.6), px_per_mm=0.52, angle_deg=-8,
                                                background=0.1, gain=0.3, flare=0.3, noise=0.01, seed=7), None),
    "below the segmentation detector's reach (48x40, 5.6 px pitch)": (dict(shape=(40, 48), centre=(23.7, 19.2),
                                                                           px_per_mm=0.4), None),
    "very low contrast (gain 0.1, flare 0.5)": (dict(shape=(60, 90), centre=(45.3, 30.2), px_per_mm=0.8, gain=0.1,
                                                     flare=0.5, noise=0.02, seed=3), None),
    "occluded: 2 swatches, black card": (dict(shape=(86, 114), centre=(57.4, 43.3), px_per_mm=1.0,
                                              occlude=(30, 20, 45, 35, 0.02)), "swatch 1 (light skin) residual"),
    "occluded: magenta, black card": (dict(shape=(86, 114), centre=(57.4, 43.3), px_per_mm=1.0,
                                           occlude=(70, 50, 80, 60, 0.02)), "swatch 16 (magenta) residual"),
    "occluded: a whole row": (dict(shape=(86, 114), centre=(57.4, 43.3), px_per_mm=1.0,
                                   occlude=(15, 15, 100, 25, 0.5)), "residual"),
}


def _outcome(img: np.ndarray):
    try:
        return detect_chart(img), None
    except ChartNotFoundError as e:
        return None, str(e)


@pytest.mark.parametrize("name", list(CASES))
def test_detection_is_right_or_refused(name):
    kw, refusal = CASES[name]
    img, true = render_chart(**kw)
    clean, _ = render_chart(**{**kw, "noise": 0.0})
    corners, err = _outcome(img)
    if refusal is None:
        assert err is None, err
        assert np.abs(corners - true).max() < 0.25  # px
        # the swatches sampled where it says match those sampled at the truth (noise-free image)
        assert np.abs(sample_patches(clean, corners) - sample_patches(clean, true)).max() < 1e-3
    else:
        assert corners is None, f"a {name} chart was accepted"
        assert refusal in err and "\n" not in err


def test_refinement_turns_a_biased_quad_into_the_chart():
    """A guess 1/3 of a pitch off (what the segmentation detector gives on small charts) is refined
    to a few hundredths of a pixel, whatever the quad's orientation."""
    img, true = render_chart(shape=(54, 82), centre=(41.3, 26.8), px_per_mm=0.62, angle_deg=5)
    pitch = np.linalg.norm(true[1] - true[0]) / 6
    guess = true + pitch / 3 * np.array([[1, 1], [-1, 0.5], [0.5, -1], [1, -1]])
    fixed = ch.refine_corners(img, guess)
    assert np.abs(fixed - true).max() < 0.05


def test_verify_accepts_truth_and_orients_it():
    img, true = render_chart(shape=(100, 140), centre=(70.2, 49.7), px_per_mm=1.2, angle_deg=-10)
    for start in (true, np.roll(true, 2, axis=0), true[::-1]):
        c, check = verify_chart(img, start)
        assert np.allclose(c, true)
        assert check.colour_residual < 1e-6 and check.orientation_residual < 1e-6
        assert abs(check.aspect - 1.5) < 1e-6 and check.neutral_step > 0.99


def _sub_quad(true: np.ndarray, u0, v0, u1, v1) -> np.ndarray:
    h = homography(np.array([[0, 0], [6, 0], [6, 4], [0, 4]], float), true)
    p = np.array([[u0, v0, 1], [u1, v0, 1], [u1, v1, 1], [u0, v1, 1]], float) @ h.T
    return p[:, :2] / p[:, 2:]


@pytest.mark.parametrize("quad, reason", [
    ((0, 0, 3, 4), "aspect"),             # the left half of the chart
    ((0, 0, 6, 2), "aspect"),             # the top half
    ((0.5, 0.5, 6.5, 4.5), "residual"),   # half a pitch off: samples straddle swatches and the body
    ((0.33, 0, 6.33, 4), "residual"),     # a third of a pitch off along the rows
    ((0.6, 0.4, 3.6, 2.4), "residual"),   # a 3x2 window inside the chart
    ((0.6, 0.4, 2.1, 1.4), "pitch"),      # a 1.5x1 window: swatches of 2 px
])
def test_verify_refuses_a_wrong_quad(quad, reason):
    """What detect_chart returned before the checks (a quad on part of the chart, or shifted)
    is now refused with a one-line reason naming the check and its bound."""
    img, true = render_chart(shape=(54, 82), centre=(41.3, 26.8), px_per_mm=0.62, angle_deg=5)
    with pytest.raises(ChartNotFoundError, match=reason) as e:
        verify_chart(img, _sub_quad(true, *quad))
    assert "\n" not in str(e.value) and "check failed" in str(e.value)


def test_verify_refuses_geometry():
    img, true = render_chart(shape=(100, 140), centre=(70.2, 49.7), px_per_mm=1.2)
    with pytest.raises(ChartNotFoundError, match="convex"):
        verify_chart(img, true[[0, 2, 1, 3]])  # a bow tie
    with pytest.raises(ChartNotFoundError, match="not decreasing|residual"):
        flat = img.copy()
        flat[..., :] = flat.mean(-1, keepdims=True)  # a grey print of the chart: neutrals fine, colours not
        verify_chart(flat, true)


def test_verify_refuses_a_chart_without_its_neutral_order():
    """Swapping two neutrals (white <-> neutral 5) keeps every colour in the image but breaks the
    rank order of the neutral row: refused."""
    img, true = render_chart(shape=(100, 140), centre=(70.2, 49.7), px_per_mm=1.2)
    xy, half = ch.patch_centres(true)
    r = int(half)
    out = img.copy()
    (xa, ya), (xb, yb) = np.round(xy[18]).astype(int), np.round(xy[21]).astype(int)
    a = img[ya - r:ya + r + 1, xa - r:xa + r + 1].copy()
    out[ya - r:ya + r + 1, xa - r:xa + r + 1] = img[yb - r:yb + r + 1, xb - r:xb + r + 1]
    out[yb - r:yb + r + 1, xb - r:xb + r + 1] = a
    with pytest.raises(ChartNotFoundError, match="neutral|residual"):
        verify_chart(out, true)


def test_too_small_chart_is_refused_not_guessed():
    """A 3.5 px pitch: the window sampled in each swatch would touch its edges."""
    img, _ = render_chart(shape=(40, 48), centre=(23.7, 19.2), px_per_mm=0.25)
    with pytest.raises(ChartNotFoundError):
        detect_chart(img)
