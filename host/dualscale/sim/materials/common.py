"""Shared helpers for the synthetic materials: noise, height -> normal, map assembly."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy import ndimage

from dualscale.bsdf import MaterialMaps
from dualscale.formats.relief import SurfaceGeometry


@dataclass
class SyntheticMaterial:
    """Ground truth of a synthetic material.  ``maps`` in the canonical layout (float32);
    ``flyouts``: fibre polylines in pixel coordinates ``[(col, row), ...]``; ``flyout_mask``
    (H, W) bool; ``meta``: generator parameters (name, seed, texel_mm, ...); ``geometry``: the
    relief (height field and fly-out fibre layer) that casts shadows."""

    maps: MaterialMaps
    meta: dict
    flyouts: list[list[tuple[float, float]]] = field(default_factory=list)
    flyout_mask: np.ndarray | None = None
    geometry: SurfaceGeometry | None = None


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-std Gaussian-filtered white noise (periodic)."""
    n = ndimage.gaussian_filter(rng.standard_normal(shape), max(sigma_px, 0.5), mode="wrap")
    return (n - n.mean()) / (n.std() + 1e-12)


def pixel_grid_mm(size: int, texel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` in mm of every texel centre; row 0 is the top (+y), like the cameras."""
    c = (np.arange(size) + 0.5 - size / 2) * texel_mm
    x, y = np.meshgrid(c, -c)
    return x, y


def normals_from_height(height_mm: np.ndarray, texel_mm: float, max_tilt_deg: float = 80.0) -> np.ndarray:
    """Unit normals (H, W, 3) of a height field (mm), tilt clamped to ``max_tilt_deg``."""
    d_row, d_col = np.gradient(height_mm, texel_mm)
    gx, gy = d_col, -d_row
    lim = np.tan(np.radians(max_tilt_deg))
    g = np.hypot(gx, gy)
    s = np.where(g > lim, lim / np.maximum(g, 1e-12), 1.0)
    n = np.stack([-gx * s, -gy * s, np.ones_like(gx)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def to_maps(**arrays: np.ndarray | None) -> MaterialMaps:
    """MaterialMaps from numpy arrays (adds the channel axis to 2-D maps)."""
    out = {}
    for k, v in arrays.items():
        if v is None:
            continue
        a = np.asarray(v, dtype=np.float32)
        out[k] = torch.from_numpy(np.ascontiguousarray(a[..., None] if a.ndim == 2 else a))
    return MaterialMaps(**out)
