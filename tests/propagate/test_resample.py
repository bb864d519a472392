"""Resampling micro images and maps to the guidance texel (dualscale.propagate.resample)."""

import numpy as np
import pytest

from dualscale.propagate.resample import new_size, resample_source, resize, resize_map


def test_area_average_of_blocks():
    """Shrinking by 1/2 averages each 2x2 block exactly; a constant stays constant at any scale."""
    rng = np.random.default_rng(0)
    img = rng.random((8, 12, 3)).astype(np.float32)
    out = resize(img, (4, 6))
    assert np.allclose(out, img.reshape(4, 2, 6, 2, 3).mean((1, 3)), atol=1e-6)
    const = np.full((37, 53, 2), 0.25, np.float32)
    assert np.allclose(resize(const, new_size(37, 53, 0.31)), 0.25, atol=1e-6)


def test_many_channels_match_per_channel():
    """More channels than cv2.resize takes at once (4 at a fractional scale) are resized in chunks,
    identically."""
    rng = np.random.default_rng(1)
    img = rng.random((20, 20, 700)).astype(np.float32)
    out = resize(img, (7, 7))
    assert out.shape == (7, 7, 700)
    assert np.allclose(out[..., 650], resize(img[..., 650], (7, 7)), atol=1e-6)


def test_normals_renormalised_and_up():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(16, 16, 3)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) + 0.05
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    out = resize_map("normal", n, (5, 5))
    assert np.allclose(np.linalg.norm(out, axis=-1), 1, atol=1e-5) and (out[..., 2] > 0).all()
    # the average direction, not the average vector's length
    ref = n[:8, :8].mean((0, 1))
    assert np.allclose(resize_map("normal", n, (2, 2))[0, 0], ref / np.linalg.norm(ref), atol=1e-5)


def test_tangent_averages_axially():
    """0.02 and 0.98 are nearly the same axis: their average is ~0 (or ~1), never 0.5."""
    t = np.where((np.indices((8, 8)).sum(0) % 2) == 0, 0.02, 0.98).astype(np.float32)[..., None]
    out = resize_map("tangent", t, (2, 2))
    assert np.all(np.minimum(out, 1 - out) < 1e-4)
    plain = resize(t, (2, 2))
    assert np.allclose(plain, 0.5, atol=1e-4)  # what a plain average would have given


def test_resample_source(tmp_path):
    import torch

    from dualscale.propagate.data import Source

    pairs = torch.rand(3, 2, 3, 40, 40).half()
    maps = {"albedo": torch.rand(3, 40, 40), "normal": torch.nn.functional.normalize(
        torch.rand(3, 40, 40) + torch.tensor([0, 0, 1.0])[:, None, None], dim=0)}
    src = Source("d", pairs, maps, ["led000", "led001", "diffuse"], texel_mm=0.006)
    small = resample_source(src, 0.25)
    assert small.size == (10, 10) and small.pairs.dtype == torch.float16
    assert small.texel_mm == pytest.approx(0.024) and small.name == "d@0.024mm"
    assert torch.allclose(small.maps["normal"].norm(dim=0), torch.ones(10, 10), atol=1e-5)
    assert torch.allclose(small.pairs[2, 0, 1].float(), torch.nn.functional.avg_pool2d(
        pairs[2, 0, 1].float()[None, None], 4)[0, 0], atol=2e-3)
    with pytest.raises(ValueError, match="positive"):
        resample_source(src, 0.0)
