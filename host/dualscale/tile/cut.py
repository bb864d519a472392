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
3. **Origin.**  The crop origin whose feathered tile has the lowest seam score of its worst map
   (a user's tile wraps every map; issue 24 Sec. 6): a grid over one primitive cell scored on
   each candidate's exact border lines, the best cut whole and scored exactly, the search
   refined where none meets the goal (:func:`_best_origin`).
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

from .lattice import Lattice, NoRepeatError, find_lattice
from .seam import GOAL, border_energy, maps_seam_scores, scored_channels, seam_score, worst_seam

MAX_MULTIPLE = 6
AXIS_TOL_PX = 0.35
MIN_TILE_PX = 32  # by default a side of the tile spans whole repeats of at least this many texels
ORIGIN_STEP_PX = 0.5  # candidate crop origins about this far apart along each primitive vector,
MAX_ORIGIN_GRID = 8  # at most this many along each
ORIGIN_FINALISTS = 6  # candidates refined and cut whole when the first half cut whole misses the goal
PROXY_LINES = 8  # rows and columns that estimate a candidate tile's inside energy,
PROXY_SEGMENT_PX = 48  # each at most this long


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


def _carry(arr: np.ndarray, layout: list[tuple[str, int]], J: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`_stack` after the warp, on any ``(..., C)`` array: each map's values
    ``(..., c)`` (float64) by name; normals and tangents carried through ``J`` (2 x 2, physical,
    in the maps' (x, y-up) frame) and renormalised, other maps clipped to [0, 1]."""
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
        else:
            a = np.clip(a, 0.0, 1.0)
        out[name] = a
    return out


def _unstack(arr: np.ndarray, layout: list[tuple[str, int]], J: np.ndarray, like: MaterialMaps) -> MaterialMaps:
    """The tile's maps (float32 tensors) from the warped stack ``arr`` (:func:`_carry`)."""
    return replace(like, **{k: torch.from_numpy(np.ascontiguousarray(a.astype(np.float32)))
                            for k, a in _carry(arr, layout, J).items()})


class _Spline:
    """The cubic-spline coefficients of an ``(H, W, C)`` field, computed once: the prefilter
    that ``scipy.ndimage.map_coordinates(order=3, mode="nearest")`` runs on every call (the
    field edge-padded by :attr:`PAD` texels, then ``spline_filter``), so that sampling many
    candidate tiles costs only the interpolation."""

    PAD = 12

    def __init__(self, arr: np.ndarray):
        pad = ((self.PAD, self.PAD), (self.PAD, self.PAD))
        self.coef = [ndimage.spline_filter(np.pad(arr[..., c], pad, mode="edge"), 3, output=np.float64,
                                           mode="nearest") for c in range(arr.shape[-1])]

    def at(self, origin: np.ndarray, A: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """The field at output texels ``(i, j)`` (1-D arrays of column and row indices, any
        integers) of the tile at ``origin``: ``(len(j), len(i), C)``, sampled at ``origin + A
        (i + 1/2, j + 1/2)`` (continuous input coordinates, texel ``(c, r)`` spanning ``[c, c +
        1) x [r, r + 1)``); ``origin`` ``(K, 2)`` gives ``(K, len(j), len(i), C)``."""
        o = np.asarray(origin, float)
        I, Jj = np.meshgrid(np.asarray(i, float) + 0.5, np.asarray(j, float) + 0.5)
        oc, orow = (o[..., k].reshape(o.shape[:-1] + (1, 1)) for k in (0, 1))
        col = oc + (A[0, 0] * I + A[0, 1] * Jj - 0.5 + self.PAD)
        row = orow + (A[1, 0] * I + A[1, 1] * Jj - 0.5 + self.PAD)
        return np.stack([ndimage.map_coordinates(c, [row.ravel(), col.ravel()], order=3, mode="nearest",
                                                 prefilter=False).reshape(row.shape) for c in self.coef], -1)


def _feather(ext: np.ndarray, n1: int, n2: int, b: int) -> np.ndarray:
    """Blend the border bands of the padded sample ``ext`` (pad ``b``) with the content one
    repeat away; returns the ``(n2, n1, C)`` tile (module step 4)."""
    if b == 0:
        return ext
    r = _ramp(b)
    return _blend_axis(_blend_axis(ext, n1, b, r, 1), n2, b, r, 0)  # along x: (n2 + 2b, n1, C); then along y


def _ramp(b: int) -> np.ndarray:
    """The blend weight of the content one repeat away: 1/2 at the border, falling to 0 inward."""
    return 0.5 * (1 - np.arange(b) / b)


def _blend_axis(a: np.ndarray, n: int, b: int, r: np.ndarray, axis: int) -> np.ndarray:
    """Step 4 along ``axis`` of ``a`` (``n + 2 b`` samples, pad ``b``): the ``n`` inner samples,
    the first and last ``b`` blended with the samples one repeat (``n``) away by weights ``r``."""
    a = np.moveaxis(a, axis, 0)
    t = a[b:b + n].copy()
    k = np.arange(b)
    w = r.reshape((b,) + (1,) * (a.ndim - 1))
    t[k] = (1 - w) * a[b + k] + w * a[b + n + k]
    t[n - 1 - k] = (1 - w) * a[b + n - 1 - k] + w * a[b - 1 - k]
    return np.moveaxis(t, 0, axis)


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
    ``0`` = none); ``origin_candidates``: the least number of candidate crop origins along each
    primitive vector (more where the vector is longer, up to :data:`MAX_ORIGIN_GRID`).
    ``Tile.resampling`` records the affine map, the tile's texel and the lattice in tile texels.

    ``Tile.seam``: ``{"tile": s, "untreated": s0, "maps": {...}, "worst": {"map", "score"},
    "goal": 1.1, "signal": ..., "untreated_maps": {...}, "origin_search": {...}}`` -- the seam
    score (:func:`~dualscale.tile.seam.seam_score`) of the tile's albedo luminance, of the
    untreated crop of the same size (the plain crop at the field's top-left corner), of each of
    the tile's maps and the worst of them (the one the origin is chosen on; a
    ``RuntimeWarning`` when it is above the goal), and the search's record.  Raises
    :class:`~dualscale.tile.lattice.NoRepeatError` (no repeat) or
    :class:`~dualscale.errors.InputError` (the tile with its band does not fit in the field; bad
    ``repeats``/``blend_px``).
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
    size_px = (float(np.linalg.norm(u)), float(np.linalg.norm(wv)))
    J = _physical_map(A, n1, n2, size_px)
    origin, tmaps, scores, searched = _best_origin(_Spline(stack), layout, J, maps, lattice.vectors_px, plan,
                                                   origin_candidates)
    validate_maps(tmaps)
    cos = float(u @ wv / (np.linalg.norm(u) * np.linalg.norm(wv)))
    shear = math.degrees(math.acos(np.clip(cos, -1, 1))) - 90.0
    untreated = maps.crop(0, n2, 0, n1)
    lum = _luma(tmaps)
    worst_map, worst = worst_seam(scores)
    seam = {"tile": round(seam_score(lum), 4), "untreated": round(seam_score(_luma(untreated)), 4),
            "signal": "albedo luminance", "goal": GOAL, "maps": scores,
            "worst": {"map": worst_map, "score": None if worst_map is None else round(worst, 4)},
            "untreated_maps": maps_seam_scores(untreated), "origin_search": searched}
    if worst_map is not None and worst > GOAL:
        import warnings

        warnings.warn(f"the tile's seam score {worst:.3g} ({worst_map} map) is above the goal {GOAL} (blend band {b} "
                      "texels): its border will show when it repeats", RuntimeWarning, stacklevel=2)
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


def _border_lines(field: _Spline, origins: np.ndarray, A: np.ndarray, n1: int, n2: int, b: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The first and last columns ``(K, n2, 2, C)`` and rows ``(K, 2, n1, C)`` of the feathered
    tiles at ``origins`` ``(K, 2)``, exactly as :func:`_feather` gives them, from eight sampled
    lines each: the feather at a border mixes the lines just inside and one repeat away (weight
    1/2 each)."""
    if b == 0:
        return (field.at(origins, A, np.array([0, n1 - 1]), np.arange(n2)),
                field.at(origins, A, np.arange(n1), np.array([0, n2 - 1])))
    r = _ramp(b)
    c = field.at(origins, A, np.array([-1, 0, n1 - 1, n1]), np.arange(-b, n2 + b))  # (K, n2 + 2b, 4, C)
    cols = _blend_axis(np.stack([0.5 * (c[:, :, 1] + c[:, :, 3]), 0.5 * (c[:, :, 2] + c[:, :, 0])], 2), n2, b, r, 1)
    x = _blend_axis(field.at(origins, A, np.arange(-b, n1 + b), np.array([-1, 0, n2 - 1, n2])), n1, b, r, 2)
    return cols, np.stack([0.5 * (x[:, 1] + x[:, 3]), 0.5 * (x[:, 2] + x[:, 0])], 1)


def _origin_grid(B: np.ndarray, centre: np.ndarray, least: int) -> tuple[np.ndarray, float]:
    """A grid of crop origins over one primitive cell of ``B`` around ``centre``: ``least`` to
    :data:`MAX_ORIGIN_GRID` points along each vector, about :data:`ORIGIN_STEP_PX` apart.
    Returns ``(K, 2)`` and the grid's finest spacing in texels."""
    ks = [max(least, min(MAX_ORIGIN_GRID, math.ceil(float(np.linalg.norm(v)) / ORIGIN_STEP_PX))) for v in B]
    g1, g2 = ((np.arange(k) + 0.5) / k - 0.5 for k in ks)
    a, c = (x.ravel() for x in np.meshgrid(g1, g2))
    return centre + a[:, None] * B[0] + c[:, None] * B[1], min(float(np.linalg.norm(v)) / k for v, k in zip(B, ks))


def _proxy_seams(field: _Spline, origins: np.ndarray, layout: list[tuple[str, int]], J: np.ndarray, plan: dict
                 ) -> np.ndarray:
    """The worst map's seam score of the feathered tile at each of ``origins`` ``(K, 2)``,
    estimated cheaply: the border energy exact (:func:`_border_lines`), the inside energy from
    the neighbours along :data:`PROXY_LINES` rows and as many columns spread over the tile,
    each its middle :data:`PROXY_SEGMENT_PX` texels inside the blend bands.
    The inside energy is estimated per origin because it depends on the origin's sub-texel
    part: a cubic spline sampled half way between texels attenuates a pattern near the
    sampling limit (a normal map of 2.1-texel yarns loses 90 % of its neighbour-difference
    energy there)."""
    A, n1, n2, b = plan["A"], plan["n1"], plan["n2"], plan["band"]
    cols, rows = (_carry(a, layout, J) for a in _border_lines(field, origins, A, n1, n2, b))
    # segments of rows and columns inside the bands (untouched by the feather), spread over the tile
    lines = []
    for n in (n1, n2):
        q, (s0, s1) = min(PROXY_LINES, n - 2 * b), _middle(b, n - b, PROXY_SEGMENT_PX)
        lines.append((b + (np.arange(q) + 0.5) * (n - 2 * b) // q, np.arange(s0, s1)))
    lr = _carry(field.at(origins, A, lines[0][1], lines[1][0]), layout, J)  # (K, rows, segment, C)
    lc = _carry(field.at(origins, A, lines[0][0], lines[1][1]), layout, J)  # (K, segment, columns, C)
    k = len(origins)
    worst = np.zeros(k)
    for name in cols:
        dx = (np.diff(scored_channels(name, lr[name]), axis=2) ** 2).sum(-1).reshape(k, -1)
        dy = (np.diff(scored_channels(name, lc[name]), axis=1) ** 2).sum(-1).reshape(k, -1)
        e_in = np.concatenate([dx, dy], 1).mean(1)
        e_b = border_energy(scored_channels(name, cols[name]), scored_channels(name, rows[name]))
        ok = e_in > 1e-12 * max(1.0, float(np.max(e_in)))  # a constant map scores nan: it takes no part
        worst = np.maximum(worst, np.where(ok, e_b / np.where(ok, e_in, 1.0), 0.0))
    return worst


def _middle(lo: int, hi: int, most: int) -> tuple[int, int]:
    """The middle ``min(most, hi - lo)`` integers of ``[lo, hi)`` as ``(start, stop)``."""
    k = min(most, hi - lo)
    start = lo + (hi - lo - k) // 2
    return start, start + k


def _best_origin(field: _Spline, layout: list[tuple[str, int]], J: np.ndarray, like: MaterialMaps, B: np.ndarray,
                 plan: dict, least: int) -> tuple[np.ndarray, MaterialMaps, dict, dict]:
    """Module step 3: the crop origin whose feathered tile has the lowest seam score over every
    map (the worst map's; a user's tile wraps all of them).  Candidates: a grid over one
    primitive cell (:func:`_origin_grid`) and the centre of the allowed box, scored by
    :func:`_proxy_seams`; the best half of :data:`ORIGIN_FINALISTS` are cut whole and scored exactly
    (:func:`~dualscale.tile.seam.maps_seam_scores`).  When none meets the goal
    (:data:`~dualscale.tile.seam.GOAL`), a grid a quarter of the spacing fine around each of
    the :data:`ORIGIN_FINALISTS` best is scored the same way and its best
    :data:`ORIGIN_FINALISTS` are cut whole too.  Returns the origin, its tile's maps, their seam scores
    and a record of the search."""
    A, n1, n2, b = plan["A"], plan["n1"], plan["n2"], plan["band"]
    lo, hi = plan["lo"], plan["hi"]
    centre = 0.5 * (lo + hi)

    def whole(o):
        tm = _unstack(_feather(field.at(o, A, np.arange(-b, n1 + b), np.arange(-b, n2 + b)), n1, n2, b), layout, J,
                      like)
        sc = maps_seam_scores(tm)
        v = worst_seam(sc)[1]
        return (v if np.isfinite(v) else 0.0), tm, sc, o  # every map constant: any origin will do

    coarse, spacing = _origin_grid(B, centre, least)
    coarse = np.concatenate([centre[None], np.clip(coarse, lo, hi)])
    ranked = coarse[np.argsort(_proxy_seams(field, coarse, layout, J, plan), kind="stable")]
    cut_whole = [whole(o) for o in ranked[:ORIGIN_FINALISTS // 2]]
    searched = len(coarse)
    if min(f[0] for f in cut_whole) > GOAL:
        d = np.arange(-2, 3) * spacing / 4
        dd = np.stack([x.ravel() for x in np.meshgrid(d, d)], 1)
        fine = np.clip((ranked[:ORIGIN_FINALISTS, None, :] + dd[None]).reshape(-1, 2), lo, hi)
        fine = fine[np.argsort(_proxy_seams(field, fine, layout, J, plan), kind="stable")]
        cut_whole += [whole(o) for o in fine[:ORIGIN_FINALISTS]]
        searched += len(fine)
    best = min(cut_whole, key=lambda f: f[0])
    record = {"candidates": searched, "cut_whole": len(cut_whole), "score": "the worst map's seam score",
              "best": round(best[0], 4), "refined": len(cut_whole) > ORIGIN_FINALISTS // 2}
    return best[3], best[1], best[2], record


def _physical_map(A: np.ndarray, n1: int, n2: int, size_px: tuple[float, float]) -> np.ndarray:
    """The warp's in-plane linear map ``J`` (output = J input) in the maps' (x, y-up) frame,
    in physical units: input texels of ``t`` mm, output texels of ``size / N``."""
    F = np.diag([1.0, -1.0])
    out_texel = np.diag([size_px[0] / n1, size_px[1] / n2])  # output texel in input-texel lengths
    return F @ out_texel @ np.linalg.inv(A) @ F


def _luma(maps: MaterialMaps) -> np.ndarray:
    """Albedo luminance ``(H, W)`` of ``maps``."""
    return maps.albedo.detach().cpu().numpy().astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
