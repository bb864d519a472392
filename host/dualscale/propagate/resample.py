"""Resampling images and maps between texel sizes (micro capture -> guidance texel).

Shrinking is an area average (``cv2.resize``, ``INTER_AREA``: each output texel is the mean of
the input texels it covers, fractions weighted), enlarging is bilinear (``INTER_LINEAR``).  Maps
keep their conventions (:data:`dualscale.formats.maps.CONVENTIONS`):

* ``normal``: the unit vectors are averaged and renormalised (the mean of normals with z > 0 has
  z > 0; a floor of 1e-6 guards the degenerate case);
* ``tangent``: axial (value v is the azimuth pi v, so v and v + 1 are the same axis): averaged in
  doubled-angle form ``(cos 2 pi v, sin 2 pi v)`` and converted back, so 0.02 and 0.98 average to
  0, not 0.5;
* every other map: averaged as is (all lie in [0, 1] and stay there).

The new size is ``round(size * scale)`` (at least 1), so the realised scale differs from the
asked one by at most half a texel over the image (:func:`resampled_texel`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

MAX_CV_CHANNELS = 4  # cv2.resize's area average at a fractional scale takes at most 4 channels per call
LIGHTS_PER_CALL = 2
"""Lights of a :class:`~dualscale.propagate.data.DiskSource` resampled together: 2 lights are 12
channels (P0 and P90, RGB), 3 whole groups of :data:`MAX_CV_CHANNELS`, so every OpenCV call sees
the very channels it sees when the whole ``(H, W, 6 L)`` array is resized at once (groups start
at multiples of 4 either way): the streamed result is the in-memory one bit for bit."""


def new_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """``(h, w)`` after scaling by ``scale`` (rounded, at least 1)."""
    return max(1, int(round(height * scale))), max(1, int(round(width * scale)))


def resampled_texel(texel_mm: float, width: int, new_width: int) -> float:
    """The texel size after resampling ``width`` texels of ``texel_mm`` to ``new_width``."""
    return texel_mm * width / new_width


def resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(H, W[, C])`` float -> ``size`` = ``(h, w)``: area average when shrinking, bilinear when
    enlarging; any channel count (OpenCV is called on groups of :data:`MAX_CV_CHANNELS`)."""
    import cv2

    img = np.ascontiguousarray(image, np.float32)
    h, w = size
    if img.shape[:2] == (h, w):
        return img.copy()
    interp = cv2.INTER_AREA if h <= img.shape[0] and w <= img.shape[1] else cv2.INTER_LINEAR
    if img.ndim == 2 or img.shape[2] <= MAX_CV_CHANNELS:
        out = cv2.resize(img, (w, h), interpolation=interp)
        return out.reshape(h, w, *img.shape[2:])
    parts = [cv2.resize(np.ascontiguousarray(img[..., c:c + MAX_CV_CHANNELS]), (w, h), interpolation=interp)
             .reshape(h, w, -1) for c in range(0, img.shape[2], MAX_CV_CHANNELS)]
    return np.concatenate(parts, -1)


def resize_map(name: str, value: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """One map ``(H, W, C)`` -> ``(h, w, C)`` keeping its convention (module docstring)."""
    v = np.asarray(value, np.float32)
    if name == "tangent":
        a = 2 * np.pi * v[..., 0]
        cs = resize(np.stack([np.cos(a), np.sin(a)], -1), size)
        return (np.mod(np.arctan2(cs[..., 1], cs[..., 0]), 2 * np.pi) / (2 * np.pi))[..., None].astype(np.float32)
    out = resize(v, size)
    if name == "normal":
        out[..., 2] = np.maximum(out[..., 2], 1e-6)
        out /= np.linalg.norm(out, axis=-1, keepdims=True)
    else:
        out = np.clip(out, 0.0, 1.0)
    return out.reshape(size[0], size[1], v.shape[-1])


def resize_maps(maps: dict[str, np.ndarray], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Every map of ``{name: (H, W, C)}`` resized to ``size`` = ``(h, w)``."""
    return {k: resize_map(k, v, size) for k, v in maps.items()}


def resample_source(src, scale: float, texel_mm: float | None = None):
    """A :class:`dualscale.propagate.data.Source` resampled by ``scale`` (new texel = old / scale):
    every image of ``pairs`` ``(L, 2, 3, H, W)`` and every map.  ``texel_mm`` (the new texel, for
    the record) defaults to ``src.texel_mm / scale``.  The name gets ``@<texel> mm`` so that a
    training checkpoint of another scale is not resumed.

    A :class:`~dualscale.propagate.data.DiskSource` (a capture over the in-memory threshold) is
    resampled streaming: :data:`LIGHTS_PER_CALL` lights read from disk at a time and one map at a
    time, into an in-memory :class:`~dualscale.propagate.data.Source` at the new size that equals
    the one of the in-memory capture bit for bit (peak: the small source plus a few full-size
    images, not the whole capture in float32)."""
    from .data import Source

    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"resampling scale must be a positive number, got {scale!r}")
    H, W = src.size
    h, w = new_size(H, W, scale)
    if hasattr(src, "pairs"):
        L, P, C = src.pairs.shape[:3]
        imgs = src.pairs.float().reshape(L * P * C, H, W).permute(1, 2, 0).numpy()
        pairs = _resize_pairs(imgs, L, (h, w), scale)
        maps = {k: _resize_map_chw(k, v.permute(1, 2, 0).numpy(), (h, w)) for k, v in src.maps.items()}
    else:
        L = src.n_lights
        pairs = torch.empty((L, 2, 3, h, w), dtype=torch.float16)
        for l0 in range(0, L, LIGHTS_PER_CALL):
            n = min(LIGHTS_PER_CALL, L - l0)
            block = np.stack([src.pair(li) for li in range(l0, l0 + n)])  # (n, 2, 3, H, W) float16
            imgs = block.astype(np.float32).reshape(n * 6, H, W).transpose(1, 2, 0)
            del block
            pairs[l0:l0 + n] = _resize_pairs(imgs, n, (h, w), scale)
            del imgs
        maps = {k: _resize_map_chw(k, v, (h, w)) for k, v in _disk_maps(src)}
    tex = texel_mm if texel_mm is not None else (None if src.texel_mm is None else
                                                  resampled_texel(src.texel_mm, W, w))
    name = src.name if tex is None else f"{src.name}@{tex:.6g}mm"
    if isinstance(src, Source):
        return replace(src, name=name, pairs=pairs, maps=maps, texel_mm=tex)
    return Source(name, pairs, maps, list(src.light_names), tex)


def _resize_pairs(imgs: np.ndarray, n: int, size: tuple[int, int], scale: float) -> torch.Tensor:
    """``(H, W, 6 n)`` float32 images of ``n`` lights -> ``(n, 2, 3, h, w)`` float16."""
    h, w = size
    small = resize(imgs, size)
    pairs = torch.from_numpy(np.ascontiguousarray(small.transpose(2, 0, 1))).reshape(n, 2, 3, h, w)
    if scale > 1:
        pairs = pairs.clamp(min=0)
    return pairs.to(torch.float16)


def _resize_map_chw(name: str, value: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    """``(H, W, C)`` map -> ``(C, h, w)`` float32 tensor (:func:`resize_map`)."""
    return torch.from_numpy(np.ascontiguousarray(resize_map(name, value, size).transpose(2, 0, 1)))


def _disk_maps(src):
    """``(name, (H, W, C) float32)`` for every map of a DiskSource, one at a time: the held maps,
    else each read whole from its EXR file (checked when the source was loaded)."""
    from dualscale.formats.exr import read_exr
    from dualscale.formats.maps import channel_names

    for k in src.map_names:
        if src.maps is not None:
            yield k, src.maps[k].permute(1, 2, 0).numpy()
        else:
            yield k, read_exr(src.maps_dir / f"{k}.exr", channel_names(k))
