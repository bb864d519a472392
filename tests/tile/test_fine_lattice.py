"""Weave periods of a few texels (issue 24 Sec. 6): the synthetic fabrics, area-averaged down
until their shortest repeat vector is 3-5 texels, give their known lattice within 2 % and a
seamless tile of whole repeats whose resampling is recorded."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from dualscale.tile import find_lattice, make_tile
from fine_reference import relative_error
from tile_known import known_lattice_px

FACTOR = 4  # generated at 4 x 4 texels per final texel, then area-averaged (a camera's pixels)
SIZE = 256


def downsampled(name: str, pitch_px: float, seed: int = 0):
    """Synthetic ``name`` with a yarn pitch of ``pitch_px`` final texels (0.3 mm yarns), ``SIZE^2``."""
    from dualscale.propagate.resample import resize_maps
    from dualscale.sim.materials import generate

    texel = 0.3 / pitch_px
    m = generate(name, SIZE * FACTOR, texel / FACTOR, seed=seed).maps
    small = resize_maps({k: v.numpy() for k, v in m.items()}, (SIZE, SIZE))
    return replace(m, **{k: torch.from_numpy(v) for k, v in small.items()}), texel


# (material, yarn pitch in final texels): shortest repeat vectors 3.25-4.92 texels.  The satin's
# repeat is sqrt(5) pitches, so 3-5 texels means a pitch of 1.3-2.2 texels: below 2 (the yarns past
# the sampling limit) the yarn grid aliases and no lattice of the weave is in the image (docs/TILE.md)
CASES = [("plain", 2.6), ("twill", 2.3), ("twill", 2.9), ("denim", 3.2), ("satin", 2.0), ("satin", 2.1),
         ("satin", 2.2)]


@pytest.fixture(scope="module", params=CASES, ids=[f"{n}-{p}" for n, p in CASES])
def case(request):
    name, pitch = request.param
    maps, texel = downsampled(name, pitch)
    return name, maps, texel, known_lattice_px(name, texel)


def test_known_lattice_within_two_percent(case):
    name, maps, texel, known = case
    assert 3 <= np.linalg.norm(known, axis=1).min() <= 5  # the period asked for
    L = find_lattice(maps, texel)
    assert relative_error(L.vectors_px, known) < 0.02, (name, L.vectors_px, known)
    assert abs(L.cell_area_px / abs(np.linalg.det(known)) - 1) < 0.02
    assert L.extra["grid_factor"] > 1  # found on the finer grid
    if name == "satin":  # the 5-harness repeat is an index-5 sub-lattice of the yarn grid
        assert L.extra["sublattice_index"] == 5, L.extra


def test_tile_of_whole_repeats_is_seamless_and_recorded(case):
    name, maps, texel, known = case
    t = make_tile(maps, texel)
    # a user's tile wraps every map: each one's seam is held to the goal (the crop origin is chosen
    # on the worst map's score; with the albedo's alone the normals scored 1.1-2.1 here)
    assert set(t.seam["maps"]) == {n for n, _ in maps.items()}
    assert all(v <= 1.1 for v in t.seam["maps"].values() if np.isfinite(v)), (name, t.seam["maps"])
    assert sum(np.isfinite(v) for v in t.seam["maps"].values()) >= 5  # not a pass by constant (nan) maps
    assert t.seam["worst"]["score"] == max(v for v in t.seam["maps"].values() if np.isfinite(v))
    assert t.seam["tile"] == t.seam["maps"]["albedo"]
    # whole repeats: each side is an integer combination of the known lattice
    coeff = np.linalg.solve(known.T, t.cell_px.T)
    np.testing.assert_allclose(coeff, np.round(coeff), rtol=0.02, atol=0.02)  # within the lattice's 2 %
    assert min(t.maps.shape) >= 32
    r = t.meta()["resampling"]
    np.testing.assert_allclose(np.array(r["texel_mm"]), np.array(t.size_mm) / t.maps.shape[::-1], rtol=1e-6)
    assert all(abs(v / texel - 1) < 0.05 for v in r["texel_mm"])  # within 1/(2N) of the input's
    J = np.array(r["jacobian"])
    np.testing.assert_allclose(J, np.diag(np.diag(J)), atol=0.02)  # an axis-aligned cell: a rescale only
    n = t.maps.normal.numpy()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    assert (n[..., 2] > 0).all()
    tan = t.maps.tangent.numpy()
    assert (tan >= 0).all() and (tan < 1).all()


def test_origin_search_scores_the_exact_border():
    """The origin search scores each candidate on eight sampled lines: they are the feathered
    tile's first and last columns and rows, exactly; and the spline sampler is scipy's cubic."""
    from scipy import ndimage

    from dualscale.tile import cut

    rng = np.random.default_rng(0)
    field = ndimage.gaussian_filter(rng.random((80, 90, 3)), (1, 1, 0))
    sp = cut._Spline(field)
    origins = np.array([[20.3, 22.7], [25.1, 21.9]])
    A = np.array([[1.02, 0.1], [-0.05, 0.98]])  # sheared and rescaled
    n1, n2 = 34, 29
    i, j = np.arange(-3, n1 + 3), np.arange(-3, n2 + 3)
    I, Jj = np.meshgrid(i + 0.5, j + 0.5)
    col = origins[0, 0] + A[0, 0] * I + A[0, 1] * Jj - 0.5
    row = origins[0, 1] + A[1, 0] * I + A[1, 1] * Jj - 0.5
    ref = np.stack([ndimage.map_coordinates(field[..., c], [row, col], order=3, mode="nearest") for c in range(3)], -1)
    np.testing.assert_allclose(sp.at(origins[0], A, i, j), ref, atol=1e-12)
    for b in (3, 0):
        cols, rows = cut._border_lines(sp, origins, A, n1, n2, b)
        for k, o in enumerate(origins):
            t = cut._feather(sp.at(o, A, np.arange(-b, n1 + b), np.arange(-b, n2 + b)), n1, n2, b)
            np.testing.assert_allclose(cols[k], t[:, [0, -1]], atol=1e-12)
            np.testing.assert_allclose(rows[k], t[[0, -1]], atol=1e-12)


def test_fine_autocorrelation_is_the_texel_one_at_whole_shifts():
    from dualscale.tile.lattice import autocorrelation, autocorrelation_fine

    rng = np.random.default_rng(0)
    x = rng.standard_normal((48, 64))
    a, f = autocorrelation(x), autocorrelation_fine(x, 16, 3)
    cy, cx = np.array(a.shape) // 2
    np.testing.assert_allclose(f[::3, ::3], a[cy - 16:cy + 17, cx - 16:cx + 17], atol=1e-12)
    assert f[48, 48] == pytest.approx(1.0)


def test_oblique_tile_rotates_tangents_and_normals_with_the_shear():
    """A sheared cell: the recorded jacobian is the one the tangent and normal maps went through."""
    from test_lattice import lattice_image

    from dualscale.bsdf import MaterialMaps

    B = np.array([[21.37, 7.12], [-5.8, 23.9]])
    img = lattice_image(B, 256, noise=0.0)
    img = (img - img.min()) / (img.max() - img.min())
    h = w = 256
    phi0 = 0.1  # a uniform tangent azimuth (pi * 0.1) and a uniform tilted normal
    n0 = np.array([0.3, 0.1, 1.0]) / np.linalg.norm([0.3, 0.1, 1.0])
    maps = MaterialMaps(albedo=torch.from_numpy(np.repeat(img[..., None], 3, -1).astype(np.float32)),
                        roughness=torch.full((h, w, 1), 0.5), anisotropy=torch.full((h, w, 1), 0.5),
                        tangent=torch.full((h, w, 1), phi0),
                        normal=torch.from_numpy(np.broadcast_to(n0, (h, w, 3)).astype(np.float32).copy()))
    t = make_tile(maps, 0.01, find_lattice(img, 0.01), repeats=(1, 1), blend_px=0)
    assert not t.axis_aligned
    J = np.array(t.meta()["resampling"]["jacobian"])
    d = J @ [np.cos(np.pi * phi0), np.sin(np.pi * phi0)]
    np.testing.assert_allclose(t.maps.tangent.numpy(), (np.arctan2(d[1], d[0]) % np.pi) / np.pi, atol=1e-4)
    g = np.linalg.inv(J).T @ (-n0[:2] / n0[2])
    n = np.array([-g[0], -g[1], 1.0]) / np.linalg.norm([-g[0], -g[1], 1.0])
    np.testing.assert_allclose(t.maps.normal.numpy().reshape(-1, 3), np.broadcast_to(n, (t.maps.normal[..., 0].numel(), 3)),
                               atol=1e-4)


def test_export_tile_info_carries_the_resampling(tmp_path):
    from dualscale.export.material import export_material
    from dualscale.formats.maps import save_maps

    maps, texel = downsampled("twill", 2.9)
    save_maps(tmp_path / "maps", maps, texel_mm=texel)
    doc = export_material(tmp_path / "maps", tmp_path / "export", ["exr"], tile=True)
    r = doc["tile"]["resampling"]
    assert len(r["affine_px"]) == 2 and len(r["affine_px"][0]) == 3
    assert len(r["texel_mm"]) == 2 and r["lattice_tile_px"] and doc["tile"]["lattice"]["vectors_px"]
