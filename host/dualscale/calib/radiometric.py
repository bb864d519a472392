"""Radiometric calibration and white balance (supplementary Sec. 2).

All images are linear camera RGB in DN/s (merged HDR, dark-subtracted).  Notation:

* ``r_ws = i_ws / i_wp * r_wp`` -- white-sheet reflectance from the anchor: the mid-range
  camera's diffuse captures of the white sheet ``i_ws`` and of the ColorChecker white patch
  ``i_wp``, and the white patch's reference reflectance ``r_wp`` (output linear RGB, D65);
* ``r_c`` -- one RGB value per (camera, light) from a white-sheet capture: the whole-image
  mean for the micro camera (both analyser modes summed), the mean over the micro camera's
  footprint for the mid-range and polar cameras;
* ``i_hat = i / r_c * r_ws`` -- calibrated, white-balanced relative reflectance/transmittance.
"""

from __future__ import annotations

import numpy as np

from dualscale.geometry.cameras import Camera

from . import colourref as cr
from dualscale.errors import ImageSizeError


def white_sheet_reflectance(i_ws: np.ndarray, i_wp: np.ndarray, r_wp: np.ndarray | None = None) -> np.ndarray:
    """``r_ws = i_ws i_wp^-1 r_wp`` per channel (Eq. 1); default ``r_wp`` is the reference
    output RGB of the ColorChecker white patch."""
    r_wp = cr.reference_rgb()[cr.WHITE_PATCH] if r_wp is None else np.asarray(r_wp, dtype=np.float64)
    i_ws, i_wp = np.asarray(i_ws, np.float64), np.asarray(i_wp, np.float64)
    if np.any(i_wp <= 0):
        raise ValueError(f"white patch measurement must be positive, got {i_wp}")
    return i_ws / i_wp * r_wp


MIN_REGION_PIXELS = 25  # low-resolution cameras: at least the 25 pixels nearest the centre


def micro_footprint_mask(camera: Camera, micro: Camera, min_pixels: int = MIN_REGION_PIXELS) -> np.ndarray:
    """Pixels ``(H, W)`` of ``camera`` whose sample-plane point lies in the micro camera's field
    (the region used for ``r_c``); at least the ``min_pixels`` nearest to the centre."""
    pts, _ = camera.pixel_geometry()
    p = pts.numpy()
    hx, hy = micro.field_mm[0] / 2, micro.field_mm[1] / 2
    mask = (np.abs(p[..., 0]) <= hx) & (np.abs(p[..., 1]) <= hy)
    if mask.sum() < min_pixels:
        d = np.hypot(p[..., 0], p[..., 1]).ravel()
        mask = np.zeros(d.shape, bool)
        mask[np.argsort(d)[:min_pixels]] = True
        mask = mask.reshape(p.shape[:2])
    return mask


def irradiance_value(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``r_c``: mean RGB of a white-sheet image over ``mask`` (whole image if ``None``)."""
    img = np.asarray(image, dtype=np.float64)
    if mask is None:
        return img.reshape(-1, img.shape[-1]).mean(0)
    if mask.shape != img.shape[:2]:
        raise ImageSizeError(f"region mask is {mask.shape}, image is {img.shape[:2]}")
    return img[mask].mean(0)


def apply_white_balance(image: np.ndarray, r_c: np.ndarray, r_ws: np.ndarray) -> np.ndarray:
    """``i_hat = i r_c^-1 r_ws`` per channel (reflection and transmission alike)."""
    r_c = np.asarray(r_c, dtype=np.float64)
    if np.any(r_c <= 0):
        raise ValueError(f"r_c must be positive, got {r_c}")
    return np.asarray(image, dtype=np.float64) / r_c * np.asarray(r_ws, dtype=np.float64)


# ---- dark frames -------------------------------------------------------------------------

def fit_dark(frames: list[np.ndarray], exposures_s: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel dark model ``dark(t) = bias + rate t`` (normalised DN, DN/s) from dark frames
    at one or more exposures; with one exposure the rate is 0."""
    d = np.stack([np.asarray(f, np.float64) for f in frames])
    if len({f.shape for f in d}) != 1:
        raise ImageSizeError("dark frames have different sizes")
    t = np.asarray(exposures_s, np.float64)
    if len(np.unique(t)) < 2:
        return d.mean(0), np.zeros_like(d[0])
    tc = t - t.mean()
    rate = np.tensordot(tc, d - d.mean(0), axes=(0, 0)) / float(tc @ tc)
    return d.mean(0) - rate * t.mean(), rate


def dark_at(bias: np.ndarray, rate: np.ndarray, exposure_s: float) -> np.ndarray:
    return bias + rate * exposure_s


# ---- flat fields -------------------------------------------------------------------------

def _poly_terms(h: int, w: int, degree: int) -> np.ndarray:
    y, x = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    return np.stack([x ** i * y ** j for i in range(degree + 1) for j in range(degree + 1 - i)], -1)


def fit_flat_field(image: np.ndarray, degree: int = 4) -> np.ndarray:
    """Smooth flat-field model: per-channel 2-D polynomial coefficients ``(n_terms, C)`` fitted
    to a uniformly lit white-sheet image, normalised so the model's mean is 1."""
    img = np.asarray(image, dtype=np.float64)
    h, w, c = img.shape
    a = _poly_terms(h, w, degree).reshape(-1, (degree + 1) * (degree + 2) // 2)
    coef = np.linalg.lstsq(a, img.reshape(-1, c), rcond=None)[0]
    return coef / (a @ coef).mean(0)


def flat_field_map(coef: np.ndarray, height: int, width: int) -> np.ndarray:
    """Evaluate a flat-field model on an ``(height, width)`` grid -> ``(H, W, C)``."""
    coef = np.asarray(coef, dtype=np.float64)
    n = coef.shape[0]
    degree = int(round((np.sqrt(8 * n + 1) - 3) / 2))
    if (degree + 1) * (degree + 2) // 2 != n:
        raise ValueError(f"{n} is not a number of 2-D polynomial terms")
    return _poly_terms(height, width, degree) @ coef


def apply_flat_field(image: np.ndarray, coef: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    ff = flat_field_map(coef, *img.shape[:2])
    if np.any(ff <= 0):
        raise ValueError("flat field has non-positive values")
    return img / ff
