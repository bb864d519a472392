"""Isotropic surfaces: bumpy leather and materials built from scikit-image's real texture
photographs (``skimage.data.brick/grass/gravel``, 512 x 512 grayscale, CC0)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from dualscale.errors import InputError
from dualscale.formats.relief import SurfaceGeometry

from .common import SyntheticMaterial, normals_from_height, smooth_noise, to_maps

PHOTO_TINTS = {"brick": (0.55, 0.25, 0.18), "grass": (0.20, 0.40, 0.12), "gravel": (0.45, 0.43, 0.40)}


def leather(size: int = 512, texel_mm: float = 0.0018, seed: int = 0, bump_mm: float = 0.02,
            grain_mm: float = 0.08) -> SyntheticMaterial:
    """Isotropic leather: pebbled grain (thresholded smooth noise cells) plus creases."""
    rng = np.random.default_rng(seed)
    sig = grain_mm / texel_mm
    cells = smooth_noise(rng, (size, size), sig)
    pebble = ndimage.gaussian_filter(np.tanh(2.0 * cells), max(sig / 4, 0.5), mode="wrap")
    crease = -np.abs(smooth_noise(rng, (size, size), 3 * sig))
    height = bump_mm * (0.7 * pebble + 0.3 * crease)
    base = np.array([0.30, 0.15, 0.07]) * rng.uniform(0.9, 1.1, 3)
    albedo = base * (1 + 0.15 * pebble)[..., None] * (1 + 0.3 * crease)[..., None]
    rough = np.clip(0.45 - 0.1 * pebble, 0.05, 1)
    maps = dict(albedo=np.clip(albedo, 0, 1), roughness=rough, normal=normals_from_height(height, texel_mm),
                specular_tint=np.full((size, size), 0.1))
    return SyntheticMaterial(to_maps(**maps), dict(material="leather", seed=seed, size=size, texel_mm=texel_mm),
                             geometry=SurfaceGeometry(height - height.min(), texel_mm))


def from_photo(name: str, size: int = 512, texel_mm: float = 0.0018, seed: int = 0,
               relief_mm: float = 0.03) -> SyntheticMaterial:
    """Material from a real texture photograph: intensity drives albedo, relief and roughness.

    The photo is tiled/cropped at a seeded offset and resampled to ``size``.
    """
    from skimage import data, transform

    if name not in PHOTO_TINTS:
        raise InputError(f"unknown photo {name!r}; choose from {sorted(PHOTO_TINTS)}")
    rng = np.random.default_rng(seed)
    img = getattr(data, name)().astype(np.float64) / 255.0
    img = np.roll(img, tuple(rng.integers(0, 512, 2)), axis=(0, 1))
    img = transform.resize(img, (size, size), order=1, anti_aliasing=True, mode="wrap")
    g = (img - img.min()) / max(img.max() - img.min(), 1e-6)
    tint = np.array(PHOTO_TINTS[name]) * rng.uniform(0.9, 1.1, 3)
    height = relief_mm * ndimage.gaussian_filter(g, 1.0, mode="wrap")
    maps = dict(albedo=np.clip(tint * (0.3 + 0.9 * g)[..., None], 0, 1), roughness=np.clip(0.9 - 0.5 * g, 0, 1),
                normal=normals_from_height(height, texel_mm * 512 / size))
    # the normals treat the photo's 512 px as 512 texels; the consistent relief at this size:
    geom = SurfaceGeometry(height * size / 512, texel_mm)
    return SyntheticMaterial(to_maps(**maps), dict(material=name, seed=seed, size=size, texel_mm=texel_mm),
                             geometry=geom)
