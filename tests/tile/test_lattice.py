"""Finding the repeat: synthetic lattices with known sub-texel vectors, the synthetic fabrics,
and the refusals (issue 12 Sec. 2)."""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.errors import InputError
from dualscale.tile import NoRepeatError, find_lattice
from dualscale.tile.lattice import reduce_basis
from tile_known import known_lattice_px, lattice_error_px, weave_lattice


def lattice_image(B: np.ndarray, size: int = 256, seed: int = 0, noise: float = 0.05) -> np.ndarray:
    """A periodic image with lattice rows ``B`` (dcol, drow): a random motif of the dual
    lattice's low harmonics (every harmonic ``h K`` with |h| <= 3), plus white noise."""
    rng = np.random.default_rng(seed)
    K = np.linalg.inv(B).T  # reciprocal rows: B K^T = I
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    img = np.zeros((size, size))
    for a in range(-3, 4):
        for b in range(0, 4):
            if (a, b) == (0, 0) or (b == 0 and a < 0):
                continue
            k = a * K[0] + b * K[1]
            img += rng.uniform(0.3, 1.0) * np.cos(2 * np.pi * (k[0] * cols + k[1] * rows) + rng.uniform(0, 2 * np.pi))
    return img + noise * img.std() * rng.standard_normal(img.shape)


@pytest.mark.parametrize("B", [
    np.array([[17.3, 0.0], [0.0, 23.65]]),           # rectangular, sub-texel periods
    np.array([[19.37, 6.12], [-4.8, 21.9]]),         # oblique (sheared, rotated)
    np.array([[13.1, -13.1], [26.2, 26.2]]),         # a twill-like diagonal lattice
])
def test_sub_texel_lattice_is_found(B):
    L = find_lattice(lattice_image(B), texel_mm=0.01)
    assert abs(L.cell_area_px - abs(np.linalg.det(B))) < 0.01 * abs(np.linalg.det(B))
    assert lattice_error_px(L.vectors_px, reduce_basis(B)) < 0.05  # sub-texel: < 1/20 texel
    assert L.strength > 0.5
    np.testing.assert_allclose(L.vectors_mm, L.vectors_px * [1, -1] * 0.01)


def test_weave_lattices_from_the_predicates():
    assert lattice_area(weave_lattice("plain")) == 2
    assert lattice_area(weave_lattice("twill")) == 4  # 2/2 twill: 4 x 4 yarns, 4 floats per repeat
    assert lattice_area(weave_lattice("satin")) == 5
    assert lattice_area(weave_lattice("denim")) == 4


def lattice_area(B):
    return round(abs(np.linalg.det(B)))


@pytest.mark.parametrize("name", ["plain", "twill", "satin", "denim", "rib_knit"])
def test_synthetic_fabric_repeat(name):
    from dualscale.sim.materials import generate

    texel = 0.0113  # yarn pitch 26.55 texels: not a whole number
    m = generate(name, 320, texel, seed=1)
    L = find_lattice(m.maps, texel)
    known = known_lattice_px(name, texel)
    assert abs(L.cell_area_px / abs(np.linalg.det(known)) - 1) < 0.01, (L.vectors_px, known)
    err_um = lattice_error_px(L.vectors_px, known) * texel * 1000
    assert err_um < 1.0, err_um  # under a micrometre on a 0.3 mm pitch


def test_albedo_alone_misses_the_rib_knits_relief_repeat():
    """The rib's albedo repeats every wale; its relief (knit/purl) every two: the default search
    (albedo and normals together) finds the material's repeat, the albedo alone the wale."""
    from dualscale.sim.materials import generate

    m = generate("rib_knit", 320, 0.01, seed=0)
    assert round(find_lattice(m.maps, 0.01).cell_area_px / 4800, 2) == 1.0
    assert round(find_lattice(m.maps, 0.01, source="albedo").cell_area_px / 2400, 2) == 1.0


def test_noise_has_no_repeat():
    rng = np.random.default_rng(0)
    from scipy import ndimage

    with pytest.raises(NoRepeatError, match="repeat"):
        find_lattice(ndimage.gaussian_filter(rng.standard_normal((256, 256)), 2.0))


def test_real_texture_without_repeat_is_refused():
    from skimage import data

    with pytest.raises(NoRepeatError):
        find_lattice(data.gravel().astype(float))


def test_repeat_longer_than_half_the_field_is_refused():
    B = np.array([[150.0, 0.0], [0.0, 40.0]])  # fits 1.7 times across 256 texels
    with pytest.raises(NoRepeatError):
        find_lattice(lattice_image(B, size=256))


def test_one_dimensional_stripes_are_refused():
    cols = np.arange(256)[None, :] * np.ones((256, 1))
    with pytest.raises(NoRepeatError):
        find_lattice(np.cos(2 * np.pi * cols / 7.3))


def test_bad_inputs():
    with pytest.raises(NoRepeatError, match="uniform"):
        find_lattice(np.ones((64, 64)))
    with pytest.raises(NoRepeatError, match="too small"):
        find_lattice(np.random.default_rng(0).random((10, 10)))
    with pytest.raises(InputError, match="texel_mm"):
        find_lattice(lattice_image(np.array([[10.0, 0], [0, 10.0]]), 128), texel_mm=-1)
    assert issubclass(NoRepeatError, InputError)
