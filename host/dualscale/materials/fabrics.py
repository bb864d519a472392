"""Procedural woven and knitted fabrics with yarn tangents and fly-out fibres.

Warp yarns run along image y, weft along x; ``pitch_mm`` is the yarn spacing.  A weave is a
predicate ``warp_up(i, j)`` on warp index ``i`` and weft index ``j``.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy import ndimage
from skimage.draw import line

from .common import SyntheticMaterial, normals_from_height, pixel_grid_mm, smooth_noise, to_maps

WEAVES: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "plain": lambda i, j: (i + j) % 2 == 0,
    "twill": lambda i, j: (i + j) % 4 < 2,  # 2/2 twill
    "satin": lambda i, j: (2 * i + j) % 5 != 0,  # 5-harness warp-faced satin
    "denim": lambda i, j: (i - j) % 4 != 0,  # 3/1 warp-faced twill
}
COLOURS = {  # (warp, weft) linear RGB
    "plain": ((0.55, 0.12, 0.10), (0.50, 0.10, 0.09)),
    "twill": ((0.20, 0.30, 0.18), (0.35, 0.40, 0.25)),
    "satin": ((0.60, 0.50, 0.15), (0.55, 0.45, 0.12)),
    "denim": ((0.03, 0.06, 0.18), (0.75, 0.72, 0.65)),
}


def _yarn_profile(u: np.ndarray, width: float) -> np.ndarray:
    """Elliptic cross-section height in [0, 1] for ``u`` in cell units (0 = yarn axis)."""
    r = np.clip(2 * np.abs(u) / width, 0, 1)
    return np.sqrt(1 - r * r)


def woven(kind: str, size: int = 512, texel_mm: float = 0.0018, seed: int = 0, pitch_mm: float = 0.3,
          yarn_width: float = 0.85, twist_deg: float = 20.0, n_flyouts: int = 12, sheer: bool = False) -> SyntheticMaterial:
    """Woven fabric ``kind`` in :data:`WEAVES` (``sheer=True``: thin yarns with open gaps)."""
    if kind not in WEAVES:
        raise ValueError(f"unknown weave {kind!r}; choose from {sorted(WEAVES)}")
    rng = np.random.default_rng(seed)
    x, y = pixel_grid_mm(size, texel_mm)
    gx, gy = x / pitch_mm, y / pitch_mm
    i, j = np.floor(gx).astype(int), np.floor(gy).astype(int)
    u, w = gx - i - 0.5, gy - j - 0.5
    up = WEAVES[kind](i, j)
    width = 0.45 if sheer else yarn_width
    warp_h = _yarn_profile(u, width) * (0.6 + 0.4 * np.cos(np.pi * w) * np.where(up, 1, -1))
    weft_h = _yarn_profile(w, width) * (0.6 + 0.4 * np.cos(np.pi * u) * np.where(up, -1, 1))
    warp_vis = (warp_h >= weft_h) & (warp_h > 0)
    yarn = np.where(warp_vis, warp_h, weft_h)
    covered = yarn > 0
    # fibre streaks: noise stretched along each yarn (rows = y = warp direction)
    white = rng.standard_normal((size, size))
    streak = [ndimage.gaussian_filter(white, s, mode="wrap") for s in ((12.0, 1.0), (1.0, 12.0))]
    fibre = np.where(warp_vis, streak[0], streak[1])
    fibre = (fibre - fibre.mean()) / (fibre.std() + 1e-12)
    height = 0.25 * pitch_mm * yarn * (1 + 0.02 * fibre)
    normal = normals_from_height(height, texel_mm)
    # fibres twist around the yarn: the surface tangent tilts by +-twist across the yarn
    across = np.where(warp_vis, u, w) / (width / 2)
    tang = np.where(warp_vis, np.pi / 2, 0.0) + np.radians(twist_deg) * np.clip(across, -1, 1)
    (c_warp, c_weft) = [np.array(c) for c in COLOURS[kind]]
    yarn_var = rng.uniform(0.85, 1.15, size=(2, 4096))
    var = np.where(warp_vis, yarn_var[0][i % 4096], yarn_var[1][j % 4096])
    shade = (1 + 0.08 * fibre) * var
    albedo = np.where(warp_vis[..., None], c_warp, c_weft) * shade[..., None]
    albedo = np.where(covered[..., None], albedo, 0.3 * albedo)
    rough = np.clip(np.where(covered, 0.45 + 0.05 * fibre, 0.9), 0, 1)
    aniso = np.where(covered, 0.85, 0.0)
    maps = dict(albedo=np.clip(albedo, 0, 1), roughness=rough, anisotropy=aniso,
                tangent=np.remainder(tang, np.pi) / np.pi, normal=normal,
                ior=np.where(warp_vis, 0.285, 0.265),  # warp and weft fibres differ (eta 1.57 / 1.53)
                specular_tint=np.where(covered, 0.3, 0.0))
    if sheer:
        maps["opacity"] = np.where(covered, 0.95, 0.0)
        maps["transmittance"] = np.clip(albedo * 0.8 + 0.1, 0, 1)
        maps["normal"] = np.where(covered[..., None], normal, np.array([0.0, 0.0, 1.0]))
    mat = SyntheticMaterial(to_maps(**maps), dict(material=("sheer" if sheer else kind), seed=seed, size=size,
                                                  texel_mm=texel_mm, pitch_mm=pitch_mm))
    add_flyouts(mat, rng, n_flyouts, c_weft if kind == "denim" else c_warp)
    return mat


def rib_knit(size: int = 512, texel_mm: float = 0.0018, seed: int = 0, wale_mm: float = 0.6,
             course_mm: float = 0.4, n_flyouts: int = 8) -> SyntheticMaterial:
    """1x1 rib knit: wales of V-shaped loops along y; alternate wales are knit/purl ridges."""
    rng = np.random.default_rng(seed)
    x, y = pixel_grid_mm(size, texel_mm)
    gx, gy = x / wale_mm, y / course_mm
    i = np.floor(gx).astype(int)
    u, w = gx - i - 0.5, gy - np.floor(gy) - 0.5
    leg = np.sign(u + 1e-9)  # left/right leg of the V
    along = u - leg * 0.25 - leg * 0.2 * w  # distance to the leg's centre line
    loop = _yarn_profile(along, 0.45)
    ridge = np.where(i % 2 == 0, 1.0, 0.45)  # rib: knit wales stand out, purl wales recede
    fibre = smooth_noise(rng, (size, size), 1.5)
    height = 0.2 * wale_mm * loop * ridge * (1 + 0.05 * fibre)
    tang = np.pi / 2 - leg * math.atan(0.2 * wale_mm / course_mm * 2.5)
    colour = np.array([0.12, 0.35, 0.45]) * rng.uniform(0.9, 1.1)
    albedo = colour * ((0.5 + 0.5 * loop) * (1 + 0.08 * fibre))[..., None]
    maps = dict(albedo=np.clip(albedo, 0, 1), roughness=np.clip(0.55 + 0.05 * fibre, 0, 1),
                anisotropy=np.where(loop > 0, 0.7, 0.1), tangent=np.remainder(tang, np.pi) / np.pi,
                normal=normals_from_height(height, texel_mm),
                specular_tint=np.full((size, size), 0.2))
    mat = SyntheticMaterial(to_maps(**maps), dict(material="rib_knit", seed=seed, size=size, texel_mm=texel_mm,
                                                  wale_mm=wale_mm, course_mm=course_mm))
    add_flyouts(mat, rng, n_flyouts, colour)
    return mat


def add_flyouts(mat: SyntheticMaterial, rng: np.random.Generator, count: int, colour: np.ndarray,
                min_len_px: int = 60) -> None:
    """Trace ``count`` fly-out fibres as smooth random walks on top of the maps, record their
    polylines ``[(col, row), ...]`` and mask, and paint them into the maps (bright, glossy,
    strongly anisotropic along the fibre, normal facing up)."""
    h, w = mat.maps.shape
    mask = np.zeros((h, w), bool)
    tangent = np.zeros((h, w))
    lines = []
    for _ in range(count):
        p = rng.uniform([0, 0], [w, h])
        ang = rng.uniform(0, 2 * np.pi)
        n_seg = int(rng.integers(8, 20))
        seg = max(min_len_px, min(h, w) // 3) / n_seg
        pts = [tuple(p)]
        for _ in range(n_seg):
            ang += rng.normal(0, 0.15)
            p = p + seg * np.array([np.cos(ang), np.sin(ang)])
            if not (0 <= p[0] < w and 0 <= p[1] < h):
                break
            pts.append(tuple(p))
        if len(pts) < 3:
            continue
        lines.append([(float(a), float(b)) for a, b in pts])
        for (c0, r0), (c1, r1) in zip(pts[:-1], pts[1:]):
            rr, cc = line(int(r0), int(c0), int(r1), int(c1))
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            rr, cc = rr[ok], cc[ok]
            mask[rr, cc] = True
            # image rows grow downwards, so the fibre azimuth (y up) is atan2(-d_row, d_col)
            tangent[rr, cc] = np.remainder(math.atan2(-(r1 - r0), c1 - c0), np.pi) / np.pi
    m = mat.maps
    mt = mask[..., None]
    import torch

    def put(name, value):
        t = getattr(m, name)
        if t is not None:
            setattr(m, name, torch.where(torch.from_numpy(mt), torch.as_tensor(np.asarray(value, np.float32)).expand_as(t), t))

    put("albedo", np.clip(np.asarray(colour) * 1.3, 0, 1))
    put("roughness", 0.35)
    put("anisotropy", 0.9)
    if m.tangent is not None:
        m.tangent = torch.where(torch.from_numpy(mt), torch.from_numpy(tangent[..., None].astype(np.float32)), m.tangent)
    put("normal", np.array([0.0, 0.0, 1.0]))
    put("opacity", 1.0)
    mat.flyouts = lines
    mat.flyout_mask = mask
