"""The twill's period on the real fabric photographs, against the measurement by hand recorded
in docs/TILE.md (issue 12 Sec. 2); the sub-texel lattice against an independent fine-grid search of
the periodic correlation, and the tile cut from it (issue 24 Sec. 6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data" / "fabric-rt"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real fabric photos not found at {DATA}")

# by hand (docs/TILE.md): twill1_R, 21 bright twill lines across 96 px of a row (4.6 px per line
# along the row), lines at 64 deg to the rows: 4.6 * sin(64 deg) = 4.1 px between lines
HAND_LINE_SPACING_PX = 4.13
TOLERANCE = 0.07  # +-1 line in 21 (5 %) and +-3 deg of slope (1.5 %)


def _photo(name):
    from dualscale.formats.photo import read_photo

    return read_photo(DATA / f"{name}.png", "srgb").rgb


def test_twill_line_spacing_matches_the_hand_measurement():
    from dualscale.tile.lattice import dominant_period

    period, angle = dominant_period(_photo("twill1_R"))
    assert abs(period / HAND_LINE_SPACING_PX - 1) < TOLERANCE, period
    assert abs(angle - (90 - 64)) < 6, angle  # the wave vector is normal to the lines (down-right at 64 deg)


def test_lattice_line_spacing_matches_the_hand_measurement():
    """The 2-D lattice found on the photo has the twill lines' spacing; its vector along the
    lines is locked to the texel grid (a finding, docs/TILE.md: the repeat along the lines,
    about 8.6 px in the spectrum, is 6x weaker than the lines and is not resolved)."""
    from dualscale.tile import find_lattice

    L = find_lattice(_photo("twill1_R"))
    assert abs(L.line_spacing_px / HAND_LINE_SPACING_PX - 1) < TOLERANCE, L.line_spacing_px


def test_satin_photo_shows_no_repeat():
    from dualscale.tile import NoRepeatError, find_lattice

    with pytest.raises(NoRepeatError):
        find_lattice(_photo("satin1_R"))


def test_reflection_and_transmission_agree():
    from dualscale.tile.lattice import dominant_period

    pr, _ = dominant_period(_photo("twill3_R"))
    pt, _ = dominant_period(_photo("twill3_T"))
    assert abs(pr / pt - 1) < 0.03, (pr, pt)


# rough lattices read off each photo's spectrum by hand (texels, (dcol, drow)): only the start of
# the reference's grid search (tests/tile/fine_reference.py), which moves them by up to 0.4 texel
ROUGH = {"twill1_R": [(1.2, 2.6), (3.5, -2.3)], "twill3_R": [(1.2, 2.8), (2.6, -2.6)]}
LATTICE_TOLERANCE = 0.02  # issue 24 Sec. 6: within 2 % of the truth


@pytest.fixture(scope="module", params=sorted(ROUGH))
def photo_lattice(request):
    from dualscale.tile import find_lattice
    from dualscale.tile.lattice import to_signal
    from fine_reference import reference_lattice

    img = _photo(request.param)
    return request.param, img, find_lattice(img), reference_lattice(to_signal(img), ROUGH[request.param])


def test_photo_lattice_is_sub_texel(photo_lattice):
    """The twills' periods are 2.8-3.8 texels: snapped to the texel grid they were 5-22 % off
    (twill1_R gave (1, 2), the reference is (1.24, 2.56)); measured on the finer grid, within
    2 % of the independent reference, vector by vector and in cell area."""
    from fine_reference import relative_error

    name, _, L, ref = photo_lattice
    assert relative_error(L.vectors_px, ref) < LATTICE_TOLERANCE, (name, L.vectors_px, ref)
    assert abs(L.cell_area_px / abs(np.linalg.det(ref)) - 1) < LATTICE_TOLERANCE, (name, L.cell_area_px, ref)
    assert L.extra["grid_factor"] > 1 and L.strength > 0.5


def test_photo_tile_is_whole_repeats_and_seamless(photo_lattice):
    import torch

    from dualscale.bsdf import MaterialMaps
    from dualscale.tile import make_tile

    name, img, L, _ = photo_lattice
    h, w = img.shape[:2]
    maps = MaterialMaps(albedo=torch.from_numpy(np.clip(img, 0, 1).astype(np.float32)),
                        roughness=torch.full((h, w, 1), 0.5))
    t = make_tile(maps, None, L)
    assert t.seam["tile"] <= 1.1, (name, t.seam)
    assert min(t.maps.shape) >= 32  # enough repeats for a tile of 32 texels a side, not one 3-texel repeat
    r = t.meta()["resampling"]
    A = np.array(r["affine_px"])[:, :2]
    # the tile's sides are whole repeats mapped onto the integer texel grid
    np.testing.assert_allclose(A @ np.array(r["cell_tile_px"]).T, t.cell_px.T, atol=1e-4)
    np.testing.assert_allclose(np.linalg.solve(A, L.vectors_px.T).T, r["lattice_tile_px"], atol=1e-3)
    assert r["texel_mm"] is None and all(abs(v - 1) < 0.05 for v in r["texel_px"])
