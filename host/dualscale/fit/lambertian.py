"""Classic Lambertian photometric stereo (Woodham 1980): the baseline every fit of photographs
is compared with.

Per pixel, the luminance ``Y_k = mean_c I_kc`` of the images under unit distant lights ``l_k``
is fitted in least squares as ``Y_k = g . l_k`` over the pixel's valid images (unclipped, inside
the mask; :func:`fit_lambertian` takes the validity as weights), ``n = g / |g|``; then each
channel's albedo is the least-squares ``a_c`` of ``I_kc = a_c max(0, n . l_k)`` over the same
images.  Prediction (:func:`render_lambertian`): ``a_c max(0, n . l)``.

This is the textbook method, deliberately without shadow or highlight handling (dark and bright
outliers enter the least squares like any other value); the robust variant that starts our fit
is :func:`dualscale.fit.init.robust_photometric_stereo`.  Units: ``a_c`` is in image units
per unit ``n . l`` (``pi x`` the diffuse albedo of :mod:`dualscale.bsdf` when the images are
relative radiance); directions are unit vectors in the images' frame (+x right, +y up, +z
towards the camera).  Pixels with fewer than 3 valid images, or with ``g`` pointing away from
the camera, get ``n = +z`` and the albedo of that normal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_LIGHTS = 3


@dataclass(frozen=True)
class Lambertian:
    """``albedo`` ``(P, 3)`` (image units per unit cosine), ``normal`` ``(P, 3)`` unit, and
    ``solved`` ``(P,)`` bool (False: fewer than 3 valid images, ``n = +z``)."""

    albedo: np.ndarray
    normal: np.ndarray
    solved: np.ndarray


def fit_lambertian(images: np.ndarray, dirs: np.ndarray, valid: np.ndarray | None = None) -> Lambertian:
    """Fit ``images`` ``(K, P, 3)`` linear, under ``dirs`` ``(K, 3)`` unit lights, with
    ``valid`` ``(K, P)`` bool (None = all valid).  Float64 throughout; raises ``ValueError``
    for mismatched shapes or non-finite input."""
    x = np.asarray(images, np.float64)
    d = np.asarray(dirs, np.float64)
    if x.ndim != 3 or x.shape[-1] != 3 or d.shape != (x.shape[0], 3):
        raise ValueError(f"images must be (K, P, 3) and dirs (K, 3); got {x.shape} and {d.shape}")
    if not (np.isfinite(x).all() and np.isfinite(d).all()):
        raise ValueError("images and directions must be finite")
    w = np.ones(x.shape[:2]) if valid is None else np.asarray(valid, np.float64)
    y = x.mean(-1)  # (K, P)
    a = np.einsum("kp,ki,kj->pij", w, d, d) + 1e-9 * np.eye(3)
    b = np.einsum("kp,kp,ki->pi", w, y, d)
    g = np.linalg.solve(a, b[..., None])[..., 0]
    solved = (w.sum(0) >= MIN_LIGHTS) & (g[:, 2] > 1e-12)
    n = np.where(solved[:, None], g, np.array([0.0, 0.0, 1.0]))
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.clip(d @ n.T, 0.0, None) * w  # (K, P)
    den = (cos * cos).sum(0)
    albedo = np.where(den[:, None] > 1e-12, np.einsum("kpc,kp->pc", x, cos) / np.maximum(den, 1e-12)[:, None], 0.0)
    return Lambertian(albedo, n, solved)


def render_lambertian(model: Lambertian, dirs: np.ndarray) -> np.ndarray:
    """Predicted images ``(L, P, 3)`` under ``dirs`` ``(L, 3)``: ``a_c max(0, n . l)``."""
    cos = np.clip(np.asarray(dirs, np.float64) @ model.normal.T, 0.0, None)
    return cos[..., None] * model.albedo[None]
