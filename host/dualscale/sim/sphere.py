"""A virtual mirror (chrome) sphere photographed under one light per image: the input of the
reflective-sphere light calibration (:mod:`dualscale.calib.lightsphere`), with known truth.

Conventions (the same as the calibration's): orthographic camera looking down ``-z``, view
``v = (0, 0, 1)``; camera frame ``+x`` image right, ``+y`` image up, ``+z`` towards the camera;
pixel ``(x, y)`` = (column, row), rows go *down*, pixel centres at integers.  Light directions
are unit vectors from the sphere towards the light.

Model.  Each light is a disc of angular half-angle ``half_angle_deg`` and radiance ``peak``
(a small area light, so the highlight is a small ellipse, flattened towards the limb); the
sphere also mirrors a dim "room", ``ambient * (0.6 + 0.4 R_y)`` along the reflected ray ``R``
(brighter from above), so that it stands out of the black background.  Each pixel averages
``supersample**2`` rays (anti-aliasing).  Optional Gaussian sensor noise (linear units) and
8-bit sRGB quantisation (:func:`to_srgb8`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MirrorSphereShots:
    """``images`` ``(N, H, W)`` float32 linear; ``coverage`` ``(H, W)`` float32 in [0, 1], the
    sphere's anti-aliased mask; ``centre`` ``(cx, cy)`` and ``radius`` [px]; ``directions``
    ``(N, 3)`` the true unit light directions."""

    images: np.ndarray
    coverage: np.ndarray
    centre: tuple[float, float]
    radius: float
    directions: np.ndarray


def _subsamples(x0: int, x1: int, s: int) -> np.ndarray:
    """Sub-pixel sample positions of pixels ``x0 .. x1 - 1`` (centres at integers), ``((x1-x0) s,)``."""
    return (np.arange(x0, x1)[:, None] + (np.arange(s)[None, :] + 0.5) / s - 0.5).ravel()


def _normals(xs: np.ndarray, ys: np.ndarray, cx: float, cy: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    X, Y = np.meshgrid(xs, ys)
    nx, ny = (X - cx) / r, (cy - Y) / r
    rho2 = nx * nx + ny * ny
    on = rho2 < 1.0
    nz = np.sqrt(np.clip(1.0 - rho2, 0.0, 1.0))
    return np.stack([nx, ny, nz], -1), on


def _reflect(n: np.ndarray) -> np.ndarray:
    """``R = 2 (n . v) n - v`` for ``v = +z``."""
    R = 2.0 * n[..., 2:3] * n
    R[..., 2] -= 1.0
    return R


def _pool(a: np.ndarray, s: int) -> np.ndarray:
    h, w = a.shape[0] // s, a.shape[1] // s
    return a.reshape(h, s, w, s).mean(axis=(1, 3))


def render_mirror_sphere(directions: np.ndarray, size: tuple[int, int] = (256, 256),
                         centre: tuple[float, float] | None = None, radius: float | None = None,
                         half_angle_deg: float = 1.5, peak: float = 4.0, ambient: float = 0.05,
                         supersample: int = 4, noise_sigma: float = 0.0,
                         rng: np.random.Generator | None = None) -> MirrorSphereShots:
    """Render ``N`` images of a mirror sphere, one per light.

    ``directions`` ``(N, 3)`` unit light directions (camera frame); ``size`` ``(H, W)`` [px];
    ``centre`` ``(cx, cy)`` [px] (default: the image centre) and ``radius`` [px] (default: 0.4
    of the smaller side); ``half_angle_deg`` the lights' angular radius; ``peak`` their
    reflected radiance (above 1 saturates an 8-bit rendition, as real chrome highlights do);
    ``noise_sigma`` Gaussian noise added to every pixel (linear units, ``rng`` or a fixed seed).
    Lights at or below the horizon still render (their highlight lies in the outer ring of the
    disc, or off it when behind the sphere)."""
    L = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    L = L / np.linalg.norm(L, axis=1, keepdims=True)
    H, W = size
    cx, cy = centre if centre is not None else ((W - 1) / 2.0, (H - 1) / 2.0)
    r = float(radius) if radius is not None else 0.4 * min(H, W)
    s = int(supersample)
    cos_a = math.cos(math.radians(half_angle_deg))

    n, on = _normals(_subsamples(0, W, s), _subsamples(0, H, s), cx, cy, r)
    env = np.where(on, ambient * (0.6 + 0.4 * _reflect(n)[..., 1]), 0.0)
    base = _pool(env, s)
    coverage = _pool(on.astype(np.float64), s).astype(np.float32)

    images = np.empty((len(L), H, W), np.float32)
    half = int(math.ceil(r * math.radians(half_angle_deg) + 3))  # window around the highlight
    for i, l in enumerate(L):
        img = base.copy()
        h = l + np.array([0.0, 0.0, 1.0])
        if np.linalg.norm(h) > 1e-9:
            h /= np.linalg.norm(h)
            px, py = cx + r * h[0], cy - r * h[1]
            x0, x1 = max(0, int(px) - half), min(W, int(px) + half + 2)
            y0, y1 = max(0, int(py) - half), min(H, int(py) + half + 2)
            if x1 > x0 and y1 > y0:
                nn, oo = _normals(_subsamples(x0, x1, s), _subsamples(y0, y1, s), cx, cy, r)
                lit = oo & (_reflect(nn) @ l >= cos_a)
                img[y0:y1, x0:x1] += peak * _pool(lit.astype(np.float64), s)
        images[i] = img
    if noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        images += rng.normal(0.0, noise_sigma, images.shape).astype(np.float32)
    return MirrorSphereShots(images, coverage, (float(cx), float(cy)), r, L)


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear values (1 = full scale) to 8-bit sRGB codes, clipped and rounded (same shape, uint8)."""
    v = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    e = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.round(e * 255.0).astype(np.uint8)
