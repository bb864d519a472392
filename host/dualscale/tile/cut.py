"""Cut a seamless tile of an integer number of repeats out of a set of maps, at real-world size.

Issue 12 Sec. 2 ("cut the tile").  Steps:

1. **Cell.**  Two lattice vectors ``u, w`` (integer combinations of the found basis, up to
   :data:`MAX_MULTIPLE` of each) spanning the tile: an axis-aligned pair (``u`` along the
   columns, ``w`` along the rows, each within 0.35 texel of the axis) when the lattice has one,
   e.g. ``(4p, 0), (0, 4p)`` for a 2/2 twill whose primitive vectors are diagonal; otherwise
   the reduced basis itself (an oblique lattice), which the warp shears onto the axes.
   ``repeats = (nx, ny)`` multiplies them.
2. **Warp.**  The tile is ``N1 x N2`` texels with ``N = round(|repeat vector|)``; output texel
   ``(i, j)`` samples the field at ``origin + (i / N1) nx u + (j / N2) ny w`` (cubic spline,
   ``scipy.ndimage.map_coordinates``), so the tile spans exactly the repeat, also when the
   period is not a whole number of texels.  Every map is resampled the same way; the tangent
   (an axial angle) as ``cos 2 phi, sin 2 phi``; then normals and tangents are carried through
   the warp's in-plane linear map ``J`` (physical units): a tangent direction ``d -> J d``, a
   normal through its slope ``g -> J^-T g`` (renormalised).  For an axis-aligned cell ``J`` is
   the identity up to the sub-texel rescale.
3. **Origin.**  Of a grid of candidate origins in one cell, the one whose plain warp has the
   lowest seam score of the signal (border mismatch) is used.
4. **Feather.**  The tile is sampled with a band of ``blend`` texels beyond each border; each
   border band is blended with the content one repeat away (the same weave position), with a
   weight falling linearly from 1/2 at the border to 0 at the band's inner edge, first along x
   then along y, so the wrap-around is continuous.

The tile's physical size ``size_mm = (|nx u|, |ny w|) * texel_mm`` (the cell's side lengths,
and its shear angle when oblique) is exact; its texels are ``size_mm / (N1, N2)``, which differs
from the input's texel by the sub-texel rescale (<= 1/(2N)); ``texel_mm`` of the tile is their
mean, ``size_mm`` is authoritative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy import ndimage

from dualscale.bsdf import MaterialMaps, validate_maps
from dualscale.errors import InputError

from .lattice import Lattice, NoRepeatError, find_lattice, signals_from_maps
from .seam import GOAL, maps_seam_scores, seam_score

MAX_MULTIPLE = 6
AXIS_TOL_PX = 0.35
MIN_TILE_PX = 32  # by default a side of the tile spans whole repeats of at least this many texels


@dataclass
class Tile:
    """A seamless tile.  ``maps``: the tile's maps ``(N2, N1, C)``; ``size_mm``: ``(width,
    height)`` in mm (``None`` when the texel size is unknown); ``size_px``: the same in the
    input's texels (floats); ``texel_mm``: the tile's mean texel size (``None`` when unknown);
    ``lattice``: the repeat it was cut from; ``repeats``: ``(nx, ny)`` of the cell;
    ``cell_px``: ``(2, 2)`` rows ``u, w`` of the cell in input texels; ``axis_aligned``:
    whether the cell needed no shear; ``shear_deg``: the angle between the cell's sides minus
    90; ``origin_px``: ``(col, row)`` of the tile's corner in the input; ``seam``: scores (see
    :func:`make_tile`)."""

    maps: MaterialMaps
    size_mm: tuple[float, float] | None
    size_px: tuple[float, float]
    texel_mm: float | None
    lattice: Lattice
    repeats: tuple[int, int]
    cell_px: np.ndarray
    axis_aligned: bool
    shear_deg: float
    origin_px: tuple[float, float]
    blend_px: int
    seam: dict
    resampling: dict = field(default_factory=dict)

    def meta(self) -> dict:
        """JSON-able ``tile`` record for ``material.json`` (``meta["tile"]``)."""
        lat = self.lattice.meta()
        return {"size_mm": None if self.size_mm is None else [round(v, 6) for v in self.size_mm],
                "size_px": [round(v, 4) for v in self.size_px], "shape": list(self.maps.shape[::-1]),
                "texel_mm": self.texel_mm, "lattice_mm": lat["vectors_mm"], "lattice_px": lat["vectors_px"],
                "lattice": lat, "repeats": list(self.repeats), "cell_px": self.cell_px.round(4).tolist(),
                "axis_aligned": self.axis_aligned, "shear_deg": round(self.shear_deg, 4),
                "origin_px": [round(v, 3) for v in self.origin_px], "blend_px": self.blend_px, "seam": self.seam,
                "resampling": self.resampling,
                "frame": "vectors_px (dcol, drow) with row down; vectors_mm (x, y) with y up"}


def choose_cell(lattice: Lattice, max_multiple: int = MAX_MULTIPLE, shape: tuple[int, int] | None = None
                ) -> tuple[np.ndarray, bool]:
    """Rows ``u, w``: the shortest lattice vectors along the column and row axes (within
    :data:`AXIS_TOL_PX`) if both exist with multiples up to ``max_multiple`` (and fit in the
    field ``shape``), else the reduced basis.  Returns ``(cell, axis_aligned)``."""
    B = lattice.vectors_px
    h, w = shape or lattice.shape
    rng = range(-max_multiple, max_multiple + 1)
    vecs = [a * B[0] + b * B[1] for a in rng for b in rng if (a, b) != (0, 0)]
    horiz = [v for v in vecs if abs(v[1]) <= AXIS_TOL_PX and v[0] > 0 and v[0] < w]
    vert = [v for v in vecs if abs(v[0]) <= AXIS_TOL_PX and v[1] > 0 and v[1] < h]
    if horiz and vert:
        u = min(horiz, key=lambda v: v[0])
        wv = min(vert, key=lambda v: v[1])
        return np.stack([u, wv]), True
    return B.copy(), False


def _stack(maps: MaterialMaps) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """All maps as one ``(H, W, C)`` float64 array; the tangent as ``cos 2 phi, sin 2 phi``."""
    parts, layout = [], []
    for name, t in maps.items():
        a = t.detach().cpu().numpy().astype(np.float64)
        if name == "tangent":
            phi = math.pi * a[..., 0]
            a = np.stack([np.cos(2 * phi), np.sin(2 * phi)], -1)
        parts.append(a)
        layout.append((name, a.shape[-1]))
    return np.concatenate(parts, -1), layout


def _unstack(arr: np.ndarray, layout: list[tuple[str, int]], J: np.ndarray, like: MaterialMaps) -> MaterialMaps:
    """Inverse of :func:`_stack` after the warp; carries normals and tangents through ``J``
    (2 x 2, physical, in the maps' (x, y-up) frame)."""
    out, k = {}, 0
    for name, c in layout:
        a = arr[..., k:k + c]
        k += c
        if name == "tangent":
            phi = 0.5 * np.arctan2(a[..., 1], a[..., 0])
            d = np.stack([np.cos(phi), np.sin(phi)], -1) @ J.T
            a = (np.remainder(np.arctan2(d[..., 1], d[..., 0]), math.pi) / math.pi)[..., None]
            a = np.where(a >= 1.0, 0.0, a)
        elif name == "normal":
            nz = np.maximum(a[..., 2], 1e-6)
            g = -a[..., :2] / nz[..., None]  # height slope (x, y-up)
            g = g @ np.linalg.inv(J)  # g_out = J^-T g_in (row vectors: g @ J^-1)
            n = np.concatenate([-g, np.ones_like(nz)[..., None]], -1)
            a = n / np.linalg.norm(n, axis=-1, keepdims=True)
        elif name != "tangent":
            a = np.clip(a, 0.0, 1.0)
        out[name] = torch.from_numpy(np.ascontiguousarray(a.astype(np.float32)))
    return replace(like, **out)


def _sample(arr: np.ndarray, origin: np.ndarray, A: np.ndarray, n1: int, n2: int, pad: int, order: int) -> np.ndarray:
    """``arr`` sampled at ``origin + A (i, j)`` for output texels ``i in [-pad, n1 + pad)``,
    ``j in [-pad, n2 + pad)``; ``A`` columns: input (col, row) per output (col, row) step."""
    i = np.arange(-pad, n1 + pad) + 0.5
    j = np.arange(-pad, n2 + pad) + 0.5
    I, Jj = np.meshgrid(i, j)
    col = origin[0] + A[0, 0] * I + A[0, 1] * Jj - 0.5
    row = origin[1] + A[1, 0] * I + A[1, 1] * Jj - 0.5
    if arr.ndim == 2:
        return ndimage.map_coordinates(arr, [row, col], order=order, mode="nearest")
    return np.stack([ndimage.map_coordinates(arr[..., c], [row, col], order=order, mode="nearest")
                     for c in range(arr.shape[-1])], -1)


def _feather(ext: np.ndarray, n1: int, n2: int, b: int) -> np.ndarray:
    """Blend the border bands of the padded sample ``ext`` (pad ``b``) with the content one
    repeat away; returns the ``(n2, n1, C)`` tile (module step 4)."""
    if b == 0:
        return ext
    r = 0.5 * (1 - np.arange(b) / b)  # 1/2 at the border, falling to 0 inward

    def along_x(a):
        t = a[:, b:b + n1].copy()
        k = np.arange(b)
        t[:, k] = (1 - r)[None, :, None] * a[:, b + k] + r[None, :, None] * a[:, b + n1 + k]
        t[:, n1 - 1 - k] = (1 - r)[None, :, None] * a[:, b + n1 - 1 - k] + r[None, :, None] * a[:, b - 1 - k]
        return t

    x = along_x(ext)  # (n2 + 2b, n1, C)
    return _along_y(x, n2, b, r)


def _along_y(a: np.ndarray, n2: int, b: int, r: np.ndarray) -> np.ndarray:
    t = a[b:b + n2].copy()
    k = np.arange(b)
    t[k] = (1 - r)[:, None, None] * a[b + k] + r[:, None, None] * a[b + n2 + k]
    t[n2 - 1 - k] = (1 - r)[:, None, None] * a[b + n2 - 1 - k] + r[:, None, None] * a[b - 1 - k]
    return t


def _plan(cell: np.ndarray, nx: int, ny: int, blend_px: int | None, shape: tuple[int, int]) -> dict:
    """The tile of ``nx x ny`` cells: its repeat vectors ``u, w`` (input texels), its size ``n1 x
    n2`` texels (``round(|u|), round(|w|)``), the affine map ``A`` (columns: input texels per
    output texel step, so the repeat lands on the integer grid), the blend band and the box of
    origins that keep the padded parallelogram inside the field (``fits``)."""
    h, w = shape
    u, wv = nx * cell[0], ny * cell[1]
    n1, n2 = int(round(np.linalg.norm(u))), int(round(np.linalg.norm(wv)))
    if n1 < 2 or n2 < 2:
        raise NoRepeatError(f"the repeat ({n1} x {n2} texels) is too small to cut a tile")
    if blend_px is None:
        b = min(max(2, min(n1, n2) // 8), min(n1, n2) // 2)
    else:
        b = int(blend_px)
        if b < 0 or 2 * b > min(n1, n2):
            raise InputError(f"--blend must be between 0 and half the tile's shorter side ({min(n1, n2) // 2} "
                             f"texels), got {blend_px}")
    A = np.stack([u / n1, wv / n2], 1)  # columns: input texels per output texel step

    def room(band: int):
        # the padded parallelogram's corners relative to the origin; origins keeping it inside
        c = np.array([[i, j] for i in (-band, n1 + band) for j in (-band, n2 + band)], float) @ A.T
        return c, -c.min(0) + 1, np.array([w, h]) - c.max(0) - 1

    corners, lo, hi = room(b)
    while blend_px is None and (hi < lo).any() and b > 1:  # the default band shrinks to what the field holds
        b -= 1
        corners, lo, hi = room(b)
    need = np.ceil(corners.max(0) - corners.min(0) + 2).astype(int)
    return {"u": u, "w": wv, "n1": n1, "n2": n2, "A": A, "band": b, "lo": lo, "hi": hi,
            "fits": bool((hi >= lo).all()), "need": need}


def make_tile(maps: MaterialMaps, texel_mm: float | None, lattice: Lattice | None = None,
              repeats: tuple[int, int] | None = None, blend_px: int | None = None, source: str = "all",
              origin_candidates: int = 6) -> Tile:
    """A seamless tile of ``maps`` (see the module docstring).

    ``maps``: the propagated (or fitted) maps; ``texel_mm``: their texel size in mm, or
    ``None`` (then ``size_mm`` and the tile's ``texel_mm`` are ``None`` and only ``size_px``
    is known); ``lattice``: the repeat (default: :func:`~dualscale.tile.lattice.find_lattice`
    on ``source``); ``repeats``: ``(nx, ny)`` cells, default ``(1, 1)`` or, where a cell's side
    is shorter than :data:`MIN_TILE_PX` texels (a weave period of a few texels), enough cells
    to reach it (fewer where the field is too short); ``blend_px``: the feathered band
    (default: an eighth of the tile's shorter side, at least 2 texels and at most half of it,
    ``0`` = none).  ``Tile.resampling`` records the affine map, the tile's texel and the
    lattice in tile texels.

    ``Tile.seam``: ``{"tile": s, "untreated": s0, "maps": {...}, "goal": 1.1, "signal": ...}``
    -- the seam score (:func:`~dualscale.tile.seam.seam_score`) of the tile's albedo luminance,
    of the untreated crop of the same size (the plain crop at the field's top-left corner), and
    of each of the tile's maps.  Raises :class:`~dualscale.tile.lattice.NoRepeatError` (no
    repeat) or :class:`~dualscale.errors.InputError` (the tile with its band does not fit in
    the field; bad ``repeats``/``blend_px``).
    """
    validate_maps(maps)
    if texel_mm is not None and not (np.isfinite(texel_mm) and texel_mm > 0):
        raise InputError(f"texel_mm must be a positive number of mm, got {texel_mm!r}")
    if lattice is None:
        lattice = find_lattice(maps, texel_mm, source=source)
    h, w = maps.shape
    cell, aligned = choose_cell(lattice, shape=(h, w))
    if repeats is None:  # 1 x 1, or enough repeats for MIN_TILE_PX texels a side (fewer if the field is short)
        nx, ny = (max(1, math.ceil(MIN_TILE_PX / float(np.linalg.norm(v)))) for v in cell)
    else:
        nx, ny = repeats
        if int(nx) != nx or int(ny) != ny or nx < 1 or ny < 1:
            raise InputError(f"repeats must be two positive integers, got {repeats!r}")
    nx, ny = int(nx), int(ny)
    while True:
        plan = _plan(cell, nx, ny, blend_px, (h, w))
        if plan["fits"] or repeats is not None or (nx == 1 and ny == 1):
            break
        if nx * np.linalg.norm(cell[0]) >= ny * np.linalg.norm(cell[1]) and nx > 1 or ny == 1:
            nx -= 1
        else:
            ny -= 1
    u, wv, n1, n2, A, b = (plan[k] for k in ("u", "w", "n1", "n2", "A", "band"))
    lo, hi = plan["lo"], plan["hi"]
    if not plan["fits"]:
        need = plan["need"]
        raise InputError(f"the tile ({n1} x {n2} texels, {nx} x {ny} repeats) with a {b}-texel blend band on each side "
                         f"needs {need[0]} x {need[1]} texels of the field, which is {w} x {h}: give a larger field, or "
                         f"cut it with `dualscale tile` and fewer --repeats or a smaller --blend")
    stack, layout = _stack(maps)
    sig = np.mean([s / (s.std() + 1e-12) for s in signals_from_maps(maps, "albedo")], 0)
    # candidate origins: a grid over one primitive cell, kept inside the allowed box
    best = None
    centre = 0.5 * (lo + hi)
    g = (np.arange(origin_candidates) + 0.5) / origin_candidates - 0.5
    for a in g:
        for c in g:
            o = centre + a * lattice.vectors_px[0] + c * lattice.vectors_px[1]
            o = np.clip(o, lo, hi)
            s = seam_score(_sample(sig, o, A, n1, n2, 0, 1))
            if best is None or s < best[0]:
                best = (s, o)
    origin = best[1]
    ext = _sample(stack, origin, A, n1, n2, b, 3)
    tile_arr = _feather(ext, n1, n2, b)
    size_px = (float(np.linalg.norm(u)), float(np.linalg.norm(wv)))
    J = _physical_map(A, n1, n2, size_px)
    tmaps = _unstack(tile_arr, layout, J, maps)
    validate_maps(tmaps)
    cos = float(u @ wv / (np.linalg.norm(u) * np.linalg.norm(wv)))
    shear = math.degrees(math.acos(np.clip(cos, -1, 1))) - 90.0
    untreated = maps.crop(0, n2, 0, n1)
    lum = _luma(tmaps)
    seam = {"tile": round(seam_score(lum), 4), "untreated": round(seam_score(_luma(untreated)), 4),
            "signal": "albedo luminance", "goal": GOAL, "maps": maps_seam_scores(tmaps),
            "untreated_maps": maps_seam_scores(untreated), "origin_search": round(float(best[0]), 4)}
    if seam["tile"] > GOAL:
        import warnings

        warnings.warn(f"the tile's seam score {seam['tile']:.3g} is above the goal {GOAL} (blend band {b} texels): "
                      "its border will show when it repeats", RuntimeWarning, stacklevel=2)
    tmm = None if texel_mm is None else float(texel_mm)
    size_mm = None if tmm is None else (size_px[0] * tmm, size_px[1] * tmm)
    tile_texel = None if tmm is None else 0.5 * (size_mm[0] / n1 + size_mm[1] / n2)
    texel_px = (size_px[0] / n1, size_px[1] / n2)
    resampling = {
        "method": "affine resampling of whole repeats onto an integer texel grid (cubic spline)",
        "affine_px": np.concatenate([A, origin[:, None]], 1).round(6).tolist(),
        "affine_frame": "input (col, row) = A (i, j) + origin, continuous texel coordinates (texel (c, r) spans "
                        "[c, c + 1) x [r, r + 1)), (i, j) the tile's",
        "cell_tile_px": [[n1, 0], [0, n2]],
        "lattice_tile_px": (np.linalg.solve(A, lattice.vectors_px.T).T).round(4).tolist(),
        "texel_px": [round(v, 6) for v in texel_px],
        "texel_mm": None if tmm is None else [round(v * tmm, 8) for v in texel_px],
        "jacobian": J.round(6).tolist(),
        "maps": "every map resampled together; tangent as (cos 2 phi, sin 2 phi), then rotated by the jacobian; "
                "normal through its slope (jacobian^-T), renormalised; others clipped to [0, 1]",
    }
    return Tile(tmaps, size_mm, size_px, tile_texel, lattice, (nx, ny), np.stack([u, wv]), aligned, shear,
                (float(origin[0]), float(origin[1])), b, seam, resampling)


def _physical_map(A: np.ndarray, n1: int, n2: int, size_px: tuple[float, float]) -> np.ndarray:
    """The warp's in-plane linear map ``J`` (output = J input) in the maps' (x, y-up) frame,
    in physical units: input texels of ``t`` mm, output texels of ``size / N``."""
    F = np.diag([1.0, -1.0])
    out_texel = np.diag([size_px[0] / n1, size_px[1] / n2])  # output texel in input-texel lengths
    return F @ out_texel @ np.linalg.inv(A) @ F


def _luma(maps: MaterialMaps) -> np.ndarray:
    """Albedo luminance ``(H, W)`` of ``maps``."""
    return maps.albedo.detach().cpu().numpy().astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
