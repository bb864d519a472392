"""Procedural woven and knitted fabrics with yarn tangents and fly-out fibres.

Warp yarns run along image y, weft along x; ``pitch_mm`` is the yarn spacing.  A weave is a
predicate ``warp_up(i, j)`` on warp index ``i`` and weft index ``j``.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
from scipy import ndimage

from dualscale.errors import InputError
from dualscale.formats.relief import SurfaceGeometry

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
          yarn_width: float = 0.85, twist_deg: float = 20.0, flyouts_per_mm2: float = 10.0, sheer: bool = False) -> SyntheticMaterial:
    """Woven fabric ``kind`` in :data:`WEAVES` (``sheer=True``: thin yarns with open gaps)."""
    if kind not in WEAVES:
        raise InputError(f"unknown weave {kind!r}; choose from {sorted(WEAVES)}")
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
    rng.uniform(size=(2, 4096))  # drawn as before, so the fly-outs drawn after it stay put
    # per-yarn shade from its own stream: the same sample at every size and texel (micro vs mid)
    yarn_var = np.random.default_rng((seed, 1)).uniform(0.85, 1.15, size=(2, 4096))
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
    add_flyouts(mat, rng, flyouts_per_mm2, c_weft if kind == "denim" else c_warp, height)
    return mat


def rib_knit(size: int = 512, texel_mm: float = 0.0018, seed: int = 0, wale_mm: float = 0.6,
             course_mm: float = 0.4, flyouts_per_mm2: float = 8.0) -> SyntheticMaterial:
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
    rng.uniform(0.9, 1.1)  # drawn as before (fly-outs); the colour is the same at every size and texel:
    colour = np.array([0.12, 0.35, 0.45]) * np.random.default_rng((seed, 1)).uniform(0.9, 1.1)
    albedo = colour * ((0.5 + 0.5 * loop) * (1 + 0.08 * fibre))[..., None]
    maps = dict(albedo=np.clip(albedo, 0, 1), roughness=np.clip(0.55 + 0.05 * fibre, 0, 1),
                anisotropy=np.where(loop > 0, 0.7, 0.1), tangent=np.remainder(tang, np.pi) / np.pi,
                normal=normals_from_height(height, texel_mm),
                specular_tint=np.full((size, size), 0.2))
    mat = SyntheticMaterial(to_maps(**maps), dict(material="rib_knit", seed=seed, size=size, texel_mm=texel_mm,
                                                  wale_mm=wale_mm, course_mm=course_mm))
    add_flyouts(mat, rng, flyouts_per_mm2, colour, height)
    return mat


FIBRE_BUDGET_PX = 256
"""At most one drawn fly-out per this many texels (:func:`flyout_budget`)."""


def flyout_budget(h: int, w: int) -> int:
    """How many fly-outs :func:`add_flyouts` draws at most on an ``h`` x ``w`` map: the cost
    scales with the pixel budget, never with the field in mm^2."""
    return max(2, (h * w) // FIBRE_BUDGET_PX)


def add_flyouts(mat: SyntheticMaterial, rng: np.random.Generator, per_mm2: float, colour: np.ndarray,
                height_mm: np.ndarray, length_mm: tuple[float, float] = (0.3, 0.6), radius_mm: float = 0.006,
                rise_mm: tuple[float, float] = (0.04, 0.15), incline_deg: tuple[float, float] = (10.0, 35.0)) -> None:
    """Add fly-out fibres, ``per_mm2`` of them per mm^2 of sample (at least 2), above the
    fabric of relief ``height_mm`` (mm).

    *Resolved fibres* (diameter ``2 radius_mm`` at least one texel, as on the micro camera):
    each fibre is a cylinder of ``radius_mm`` (cotton: 6 um) along a smooth random walk of
    ``length_mm`` (at most 0.8 of the field), drawn so that the whole fibre is in view.  It is
    anchored in the fabric at its first end, lifts over its first third to ``rise_mm`` above
    the highest yarn, and climbs at ``incline_deg`` from there: a free end standing out of the
    fabric.  Its texels get the cylinder's normal (across the fibre, tilted by its slope), a
    glossy anisotropic BSDF along the fibre and full opacity.  Records the polylines
    ``[(col, row), ...]``, the footprint mask, and the fibre layer of ``mat.geometry`` that
    casts and receives shadows.  Each fibre only looks at the texels of its bounding box.

    *Sub-texel fibres* (thinner than a texel, as on the 100 mm mid-range camera, 0.4 mm
    texels): no texel is a fibre, so none is drawn as geometry; their texel-averaged effect
    is kept: each texel blends the fibre BSDF (albedo, roughness, opacity) by the fraction of
    its area the fibres cover (about ``per_mm2 x length x diameter``, 5 % for 10/mm^2).
    Tangent, anisotropy and normal are left: randomly oriented fibres average out to none.
    The mask is empty and there are no polylines.

    Either way at most :func:`flyout_budget` fibres are drawn (each drawn sub-texel fibre then
    stands for ``count / drawn`` of the field's), so the cost is bounded by the map size.
    ``mat.meta["flyouts"]`` records ``per_mm2``, ``count`` (on the field), ``drawn`` and
    ``resolved``."""
    h, w = mat.maps.shape
    texel = float(mat.meta["texel_mm"])
    count = max(2, int(round(per_mm2 * h * w * texel * texel)))
    drawn = min(count, flyout_budget(h, w))
    resolved = 2 * radius_mm >= texel
    mat.meta["flyouts"] = {"per_mm2": float(per_mm2), "count": count, "drawn": drawn, "resolved": resolved}
    if not resolved:
        _subtexel_flyouts(mat, rng, count, drawn, colour, height_mm, length_mm, radius_mm)
        return
    from scipy.spatial import cKDTree

    mask = np.zeros((h, w), bool)
    axis_h = np.full((h, w), -np.inf)
    top_h = np.zeros((h, w))
    tangent = np.zeros((h, w))
    normal = np.zeros((h, w, 3))
    lines = []
    rad_px = max(radius_mm / texel, 0.5)
    top = float(height_mm.max())
    for _ in range(drawn):
        n_seg = int(rng.integers(8, 20))
        seg = min(rng.uniform(*length_mm) / texel, 0.8 * min(h, w)) / n_seg
        for _attempt in range(100):  # redraw until the whole fibre is in view
            p = rng.uniform([0, 0], [w, h])
            ang = rng.uniform(0, 2 * np.pi)
            pts = [p]
            for _ in range(n_seg):
                ang += rng.normal(0, 0.15)
                p = p + seg * np.array([np.cos(ang), -np.sin(ang)])  # y up, rows down
                pts.append(p)
            arr = np.asarray(pts)
            if (arr >= 2).all() and (arr[:, 0] < w - 2).all() and (arr[:, 1] < h - 2).all():
                break
        else:
            continue
        lines.append([(float(a), float(b)) for a, b in pts])
        # dense samples along the polyline (0.25 px), with arclength and unit direction
        dense, dirs = [], []
        for a, b in zip(pts[:-1], pts[1:]):
            k = max(2, int(np.ceil(np.linalg.norm(b - a) / 0.25)))
            t = np.linspace(0, 1, k, endpoint=False)[:, None]
            dense.append(a + t * (b - a))
            dirs.append(np.repeat(((b - a) / np.linalg.norm(b - a))[None], k, 0))
        dense.append(pts[-1][None])
        dirs.append(dirs[-1][-1:])
        ps, ds = np.concatenate(dense), np.concatenate(dirs)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ps, axis=0), axis=1))])
        frac = arc / arc[-1]
        ground = ndimage.map_coordinates(height_mm, [ps[:, 1] - 0.5, ps[:, 0] - 0.5], order=1, mode="wrap")
        rise = np.sin(0.5 * np.pi * np.minimum(1.0, frac / (1 / 3)))
        ax_h = (1 - rise) * ground + rise * (top + rng.uniform(*rise_mm))
        ax_h = ax_h + arc * texel * np.tan(np.radians(rng.uniform(*incline_deg)))
        slope = np.gradient(ax_h, arc * texel)  # mm per mm along the fibre
        # only the texels of the fibre's bounding box (grown by its radius) can be within reach
        (c0, r0), (c1, r1) = ps.min(0) - rad_px - 1, ps.max(0) + rad_px + 1
        rows, cols = np.mgrid[max(0, int(r0)):min(h, int(np.ceil(r1)) + 1), max(0, int(c0)):min(w, int(np.ceil(c1)) + 1)]
        pix = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], -1)  # (col, row) pixel centres
        flat = rows.ravel() * w + cols.ravel()
        dist, idx = cKDTree(ps).query(pix, distance_upper_bound=rad_px + 1.0)
        near = np.isfinite(dist) & (dist <= rad_px)
        near_pix, near_idx = np.nonzero(near)[0], idx[near]
        d_img = ds[near_idx]  # (dcol, drow)
        a_world = np.stack([d_img[:, 0], -d_img[:, 1], slope[near_idx]], -1)
        a_world /= np.linalg.norm(a_world, axis=1, keepdims=True)
        side = np.stack([d_img[:, 1], d_img[:, 0], np.zeros(len(d_img))], -1)  # in-plane, left of the fibre
        rel = pix[near_pix] - ps[near_idx]  # (dcol, drow); in world (x, y) = (dcol, -drow)
        q = np.clip((rel[:, 0] * d_img[:, 1] - rel[:, 1] * d_img[:, 0]) / rad_px, -0.95, 0.95)  # along `side`
        up = np.array([0.0, 0.0, 1.0]) - a_world[:, 2:3] * a_world
        up /= np.linalg.norm(up, axis=1, keepdims=True)
        side -= (side * a_world).sum(-1, keepdims=True) * a_world
        side /= np.linalg.norm(side, axis=1, keepdims=True)
        n = q[:, None] * side + np.sqrt(1 - q * q)[:, None] * up
        r_, c_ = np.divmod(flat[near_pix], w)
        higher = ax_h[near_idx] > axis_h[r_, c_]  # where fibres cross, the upper one is seen
        r_, c_, near_idx, n, q = r_[higher], c_[higher], near_idx[higher], n[higher], q[higher]
        mask[r_, c_] = True
        axis_h[r_, c_] = ax_h[near_idx]
        top_h[r_, c_] = ax_h[near_idx] + radius_mm * np.sqrt(1 - q * q)
        normal[r_, c_] = n
        tangent[r_, c_] = np.remainder(np.arctan2(-ds[near_idx, 1], ds[near_idx, 0]), np.pi) / np.pi
    m = mat.maps
    mt = torch.from_numpy(mask[..., None])

    def put(name, value):
        t = getattr(m, name)
        if t is not None:
            v = torch.as_tensor(np.asarray(value, np.float32))
            setattr(m, name, torch.where(mt, v if v.ndim == 3 else v.expand_as(t), t))

    put("albedo", np.clip(np.asarray(colour) * 1.3, 0, 1))
    put("roughness", 0.35)
    put("anisotropy", 0.9)
    put("tangent", tangent[..., None])
    put("normal", normal)
    put("opacity", 1.0)
    mat.flyouts = lines
    mat.flyout_mask = mask
    mat.geometry = SurfaceGeometry(height_mm, texel, mask, np.where(mask, axis_h, 0.0), top_h, radius_mm)


def _subtexel_flyouts(mat: SyntheticMaterial, rng: np.random.Generator, count: int, drawn: int, colour: np.ndarray,
                      height_mm: np.ndarray, length_mm: tuple[float, float], radius_mm: float,
                      n_seg: int = 12) -> None:
    """The texel-averaged effect of ``count`` fibres thinner than a texel (see
    :func:`add_flyouts`), from ``drawn`` random walks of ``n_seg`` segments, vectorised."""
    h, w = mat.maps.shape
    texel = float(mat.meta["texel_mm"])
    length_px = rng.uniform(*length_mm, drawn) / texel
    start = rng.uniform([0, 0], [w, h], (drawn, 2))
    ang = rng.uniform(0, 2 * np.pi, drawn)[:, None] + np.cumsum(rng.normal(0, 0.15, (drawn, n_seg)), 1)
    seg = length_px / n_seg  # px
    step = seg[:, None, None] * np.stack([np.cos(ang), -np.sin(ang)], -1)  # (drawn, n_seg, 2); y up, rows down
    begin = start[:, None] + np.cumsum(step, 1) - step
    k = max(1, int(np.ceil(seg.max() / 0.25)))  # samples per segment, at most 0.25 px apart
    t = (np.arange(k) + 0.5) / k
    pts = begin[:, :, None] + t[None, None, :, None] * step[:, :, None]  # (drawn, n_seg, k, 2)
    col = np.floor(pts[..., 0]).astype(np.int64) % w  # the field wraps: no fibre is cut at the edge
    row = np.floor(pts[..., 1]).astype(np.int64) % h
    # each sample covers (seg / k) px x texel along the fibre by its diameter across it
    area = (count / drawn) * np.broadcast_to((seg / k)[:, None, None], pts.shape[:3]) * 2 * radius_mm / texel
    cov = np.bincount((row * w + col).ravel(), weights=area.ravel(), minlength=h * w).reshape(h, w)
    c = torch.from_numpy(np.clip(cov, 0, 1)[..., None].astype(np.float32))
    m = mat.maps
    fibre = {"albedo": np.clip(np.asarray(colour) * 1.3, 0, 1), "roughness": 0.35, "opacity": 1.0}
    for name, value in fibre.items():
        t_ = getattr(m, name)
        if t_ is not None:
            v = torch.as_tensor(np.asarray(value, np.float32))
            setattr(m, name, (1 - c) * t_ + c * v)
    mat.flyouts = []
    mat.flyout_mask = np.zeros((h, w), bool)
    mat.geometry = SurfaceGeometry(height_mm, texel)
    mat.meta["flyouts"]["mean_coverage"] = float(cov.mean())
