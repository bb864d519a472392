"""Virtual photographs from another rig: a matte (optionally glossy) object under a dozen distant
lights, through a known camera response, for the radiometric self-calibration and the import
of photographs (:mod:`dualscale.calib.response`, :mod:`dualscale.calib.photo_import`) with
known truth.

Scene.  Orthographic camera looking down ``-z``; camera frame ``+x`` image right, ``+y`` image
up, ``+z`` towards the camera; pixel centres at integers, rows go down (as
:mod:`dualscale.sim.sphere`).  Objects (:func:`render_photos` ``shape``):

* ``"sphere"`` -- a sphere filling most of the frame;
* ``"relief"`` -- a height field of Gaussian bumps on a plane, which casts shadows onto itself
  (a ray marched towards each light; ``shadows=False`` turns them off).

Radiance: Lambert ``albedo / pi * e_k * max(0, n . l_k)`` per channel (albedo per pixel, a
smooth colour pattern), plus an optional Blinn-Phong highlight ``spec * e_k * (n . h)^shininess``
(untinted; it clips), times ``exposure``; the response ``encode`` (linear in [0, 1] -> code in
[0, 1]) and the quantisation to ``bits`` follow.  :data:`PSM_LIGHTS` are the 12 directions of
the psm-12lights captures (docs/PHOTOS.md), all on one side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

#: the psm-12lights light directions as recovered from its chrome sphere (docs/PHOTOS.md)
PSM_LIGHTS = np.array([
    [0.4972, 0.4669, 0.7313], [0.2431, 0.1353, 0.9605], [-0.0386, 0.1738, 0.9840], [-0.0945, 0.4429, 0.8916],
    [-0.3176, 0.5053, 0.8024], [-0.1101, 0.5603, 0.8209], [0.2812, 0.4220, 0.8619], [0.1007, 0.4298, 0.8973],
    [0.2070, 0.3338, 0.9196], [0.0875, 0.3317, 0.9393], [0.1292, 0.0447, 0.9906], [-0.1400, 0.3608, 0.9221]])
PSM_LIGHTS = PSM_LIGHTS / np.linalg.norm(PSM_LIGHTS, axis=1, keepdims=True)


def film_curve(x: np.ndarray, contrast: float = 1.6, pivot: float = 0.18) -> np.ndarray:
    """An S-shaped film-like response (a logistic in log exposure, toe and shoulder), linear
    ``x`` in [0, 1] -> code in [0, 1], ``f(0) = 0``, ``f(1) = 1``, monotone."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    z = contrast * (np.log(np.maximum(x, 1e-300)) - math.log(pivot))
    top = 1.0 / (1.0 + math.exp(contrast * math.log(pivot)))
    return np.where(x > 0, 1.0 / (1.0 + np.exp(-np.clip(z, -700, 700))) / top, 0.0)


def inverse_of(encode: Callable[[np.ndarray], np.ndarray], n: int = 1 << 16) -> Callable[[np.ndarray], np.ndarray]:
    """The inverse response ``g`` (code -> linear) of a monotone ``encode``, by interpolation."""
    x = np.linspace(0.0, 1.0, n + 1) ** 3  # dense near black
    c = encode(x)
    return lambda code: np.interp(np.asarray(code, np.float64), c, x)


@dataclass(frozen=True)
class PhotoShots:
    """``codes`` ``(K, H, W, 3)`` uint8/uint16 code values; ``mask`` ``(H, W)`` bool (the object);
    ``normal`` ``(H, W, 3)`` the true unit normals; ``albedo`` ``(H, W, 3)``; ``dirs`` ``(K, 3)``;
    ``intensities`` ``(K,)`` the true relative intensities; ``shadow`` ``(K, H, W)`` bool cast
    shadows; ``linear`` ``(K, H, W, 3)`` the radiance before the response (exposure applied)."""

    codes: np.ndarray
    mask: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    dirs: np.ndarray
    intensities: np.ndarray
    shadow: np.ndarray
    linear: np.ndarray
    bits: int


def _height(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.zeros((h, w))
    for _ in range(9):
        cx, cy = rng.uniform(0.15 * w, 0.85 * w), rng.uniform(0.15 * h, 0.85 * h)
        s, a = rng.uniform(0.06, 0.12) * min(h, w), rng.uniform(0.15, 0.35) * min(h, w)
        z += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    return z


def _cast_shadows(z: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``(K, H, W)`` True where the ray from a texel towards light ``k`` passes below the height
    field ``z`` [px] (bilinear samples every half pixel)."""
    from scipy.ndimage import map_coordinates

    h, w = z.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.zeros((len(dirs), h, w), bool)
    zmax = z.max()
    for k, (lx, ly, lz) in enumerate(dirs):
        horiz = math.hypot(lx, ly)
        if horiz < 1e-9:
            continue
        rise = lz / horiz  # height per pixel along the ray
        steps = int(math.ceil((zmax - z.min()) / max(rise, 1e-6) * 2)) + 2
        for t in np.arange(0.5, steps / 2 + 0.5, 0.5):
            x, y = xx + lx / horiz * t, yy - ly / horiz * t  # +y is up: rows decrease
            inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
            zt = map_coordinates(z, [np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)], order=1)
            out[k] |= inside & (zt > z + rise * t + 1e-6)
            if z.min() + rise * t > zmax:
                break
    return out


def render_photos(shape: str = "sphere", dirs: np.ndarray = PSM_LIGHTS, size: tuple[int, int] = (96, 128),
                  encode: Callable[[np.ndarray], np.ndarray] | None = None, intensities: np.ndarray | None = None,
                  exposure: float = 0.9, spec: float = 0.0, shininess: float = 60.0, bits: int = 8,
                  shadows: bool = True, noise: float = 0.0, seed: int = 0) -> PhotoShots:
    """Render the photographs (module doc).  ``size`` ``(H, W)``; ``encode``: the camera response
    (default the identity); ``intensities``: relative light intensities ``(K,)`` (default 1);
    ``exposure``: the linear value of a white Lambertian surface facing a light of intensity 1
    (``albedo = 1``); ``noise``: Gaussian noise (linear, relative to ``exposure``)."""
    h, w = size
    dirs = np.asarray(dirs, np.float64)
    K = len(dirs)
    e = np.ones(K) if intensities is None else np.asarray(intensities, np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    rng = np.random.default_rng(seed)
    if shape == "sphere":
        r = 0.46 * min(h, w)
        nx, ny = (xx - (w - 1) / 2) / r, ((h - 1) / 2 - yy) / r
        rho2 = nx * nx + ny * ny
        mask = rho2 < 1.0
        n = np.stack([nx, ny, np.sqrt(np.clip(1 - rho2, 0, 1))], -1)
        shadow = np.zeros((K, h, w), bool)
    elif shape == "relief":
        z = _height(h, w, seed)
        gy, gx = np.gradient(z)
        n = np.stack([-gx, gy, np.ones_like(z)], -1)  # +y up: d/dy_up = -d/drow
        mask = np.ones((h, w), bool)
        mask[:2] = mask[-2:] = False
        mask[:, :2] = mask[:, -2:] = False
        shadow = _cast_shadows(z, dirs) if shadows else np.zeros((K, h, w), bool)
    else:
        raise ValueError(f"shape {shape!r}: 'sphere' or 'relief'")
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    u, v = xx / w, yy / h
    albedo = np.stack([0.55 + 0.3 * np.sin(6.1 * u + 1.0) * np.cos(4.3 * v),
                       0.5 + 0.25 * np.cos(5.2 * v + 0.5),
                       0.35 + 0.2 * np.sin(7.7 * u * v + 2.0)], -1).clip(0.05, 0.95)
    cos = np.clip(np.einsum("hwc,kc->khw", n, dirs), 0.0, None)
    lit = cos * ~shadow
    lin = exposure * e[:, None, None, None] * albedo[None] * lit[..., None]
    if spec > 0:
        hv = dirs + np.array([0.0, 0.0, 1.0])
        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
        nh = np.clip(np.einsum("hwc,kc->khw", n, hv), 0.0, None)
        lin = lin + (exposure * spec * e[:, None, None] * nh ** shininess * (lit > 0))[..., None]
    if noise > 0:
        lin = lin + rng.normal(0.0, noise * exposure, lin.shape)
    lin = np.where(mask[None, ..., None], lin, 0.0)
    code = (encode or (lambda x: np.clip(x, 0, 1)))(np.clip(lin, 0.0, 1.0))
    top = 2 ** bits - 1
    q = np.round(np.clip(code, 0.0, 1.0) * top).astype(np.uint8 if bits == 8 else np.uint16)
    return PhotoShots(q, mask, n, albedo, dirs, e, shadow, lin.astype(np.float32), bits)


def write_photos(folder: str | Path, shots: PhotoShots, name: str = "obj") -> tuple[Path, Path]:
    """Write ``shots`` as ``folder/name.K.png`` + ``name.mask.png`` and the light file
    ``<folder>.lp`` beside the folder (the true directions; no intensities); returns
    ``(folder, light file)``."""
    import OpenImageIO as oiio

    from dualscale.formats.lightfile import LightRecord, write_lp

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fmt = oiio.UINT8 if shots.bits == 8 else oiio.UINT16
    for k in range(len(shots.dirs)):
        img = np.ascontiguousarray(shots.codes[k])
        spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, fmt)
        out = oiio.ImageOutput.create(str(folder / f"{name}.{k}.png"))
        out.open(str(folder / f"{name}.{k}.png"), spec)
        out.write_image(img)
        out.close()
    m = (shots.mask * 255).astype(np.uint8)
    spec = oiio.ImageSpec(m.shape[1], m.shape[0], 1, oiio.UINT8)
    out = oiio.ImageOutput.create(str(folder / f"{name}.mask.png"))
    out.open(str(folder / f"{name}.mask.png"), spec)
    out.write_image(np.ascontiguousarray(m[..., None]))
    out.close()
    lp = folder.parent / f"{folder.name}.lp"
    write_lp(lp, [LightRecord(f"{name}.{k}.png", tuple(float(c) for c in d)) for k, d in enumerate(shots.dirs)])
    return folder, lp
