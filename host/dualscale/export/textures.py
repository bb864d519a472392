"""Texture files of the exports, through OpenImageIO and colour-science, written atomically.

* Colour textures (base colour, specular colour, transmission colour) are **sRGB-encoded**
  8-bit PNG (IEC 61966-2-1 transfer, colour-science ``eotf_inverse_sRGB``) -- what glTF
  requires for them and what MaterialX reads with ``colorspace="srgb_texture"``.
* Data textures (roughness, normals, anisotropy, IOR, opacity, transmission weight) are
  **linear** PNG (16-bit by default: 8 bits quantise a normal's tilt to ~0.45 deg) -- glTF and
  MaterialX (``raw``) read them without a transfer curve.
* Linear float EXR where a format accepts it (MaterialX, the exchange EXR set).

Values outside [0, 1] are refused (``ValueError``) rather than silently clipped: the exchange
conversion (:mod:`.exchange`) is responsible for the range.  Rows are written top row first
(row 0 = top of the image; glTF's and MaterialX's texture origin conventions are handled by
the writers' UV sets, not by flipping images).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualscale.formats.exr import write_exr, write_pixels

_RANGE_TOL = 1e-4


def _check(name: str, img: np.ndarray) -> np.ndarray:
    img = np.asarray(img, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"texture {name}: expected (H, W) or (H, W, 1..4), got {img.shape}")
    if not np.isfinite(img).all():
        raise ValueError(f"texture {name}: {int((~np.isfinite(img)).sum())} non-finite values")
    lo, hi = float(img.min()), float(img.max())
    if lo < -_RANGE_TOL or hi > 1 + _RANGE_TOL:
        raise ValueError(f"texture {name}: values span [{lo:.4g}, {hi:.4g}], outside [0, 1]")
    return np.clip(img, 0.0, 1.0)


def write_png(path: str | Path, image: np.ndarray, srgb: bool, bits: int = 8) -> Path:
    """Write ``(H, W[, C])`` values in [0, 1] as a PNG: ``srgb=True`` encodes with the sRGB
    transfer (colour textures), ``False`` stores the values linearly (data textures).
    ``bits``: 8 or 16.  A 2- or 4-channel image's last channel is *alpha*: stored linear (glTF 2.0
    Sec. 3.9.2, "the linear alpha coverage") and unassociated (PNG's straight alpha; OpenImageIO
    would otherwise treat the buffer as premultiplied and divide the colour by it).  Returns the
    path."""
    import OpenImageIO as oiio

    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    path = Path(path)
    img = _check(path.name, image)
    alpha = img.shape[2] in (2, 4)
    if srgb:
        import colour

        colour_part = img[..., :-1] if alpha else img
        enc = np.clip(colour.models.eotf_inverse_sRGB(colour_part), 0.0, 1.0)
        img = np.concatenate([enc, img[..., -1:]], -1) if alpha else enc
    scale = 255.0 if bits == 8 else 65535.0
    q = np.round(img * scale).astype(np.uint8 if bits == 8 else np.uint16)
    spec = oiio.ImageSpec(q.shape[1], q.shape[0], q.shape[2], oiio.UINT8 if bits == 8 else oiio.UINT16)
    spec.attribute("oiio:ColorSpace", "srgb_rec709_scene" if srgb else "lin_rec709_scene")
    if alpha:
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the values as given: no un-premultiply
    write_pixels(path, q, spec)
    return path


def read_png(path: str | Path, srgb: bool) -> np.ndarray:
    """Read a texture written by :func:`write_png` back to float64 ``(H, W, C)`` in [0, 1]
    (decoding the sRGB transfer of the colour channels when ``srgb``; alpha stays linear and
    unassociated).  Used to measure what an export keeps."""
    import OpenImageIO as oiio

    from dualscale.formats.photo import open_unassociated

    path = Path(path)
    inp = open_unassociated(path)
    try:
        fmt = inp.spec().format
        data = inp.read_image(fmt)
    finally:
        inp.close()
    if data is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    scale = 255.0 if data.dtype == np.uint8 else 65535.0
    img = np.asarray(data, np.float64) / scale
    if img.ndim == 2:
        img = img[..., None]
    if srgb:
        import colour

        alpha = img.shape[2] in (2, 4)
        dec = colour.models.eotf_sRGB(img[..., :-1] if alpha else img)
        img = np.concatenate([dec, img[..., -1:]], -1) if alpha else dec
    return img


def write_float(path: str | Path, image: np.ndarray, channels: tuple[str, ...] | None = None) -> Path:
    """Write linear float data as a float32 EXR (no range restriction, finite values only)."""
    img = np.asarray(image, np.float32)
    if not np.isfinite(img).all():
        raise ValueError(f"texture {Path(path).name}: non-finite values")
    write_exr(path, img, channels)
    return Path(path)


def encode_normal(normal: np.ndarray) -> np.ndarray:
    """Unit tangent-space normals ``(H, W, 3)`` in [-1, 1] -> texture values ``0.5 n + 0.5``."""
    return np.clip(0.5 * np.asarray(normal, np.float64) + 0.5, 0.0, 1.0)


def decode_normal(texel: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normal`, renormalised."""
    n = 2.0 * np.asarray(texel, np.float64) - 1.0
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
