"""Cast shadows of the sample's relief under the dome's collimated LEDs.

The renderer's BSDF is local: a texel sees every LED its normal faces.  Real fabric under a
grazing LED is partly in the shadow of its own yarns, while fly-out fibres that stand above it
stay lit -- the contrast fly-out detection relies on (supplementary Sec. 4.1).  This module
gives the renderer a per-LED visibility ``(L, H, W)`` in {0, 1} from two layers:

* ``height_mm`` -- the base relief, a height field (mm above the sample plane, ``+z``).  A texel
  is in shadow when the ray towards the LED passes below the relief anywhere along its way.
  The march samples the relief bilinearly every texel, periodic like the maps, up to the
  distance at which the ray clears the highest point.
* fly-out fibres -- thin cylinders of radius ``fibre_radius_mm`` whose axis runs at height
  ``fibre_axis_mm`` above the texels in ``fibre_mask``.  They are not a height field (light
  passes under them), so a fibre texel shades only the point where its shadow lands: along
  ``-l`` by ``(axis - ground) / tan(elevation)``.  A fibre texel itself is shaded only by
  the relief, at the height of its cylinder surface.

Conventions: maps and images share the layout of :mod:`.cameras` (row 0 at ``+y``); LEDs are
collimated, so the shadows are hard.  Units: mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

MAX_MARCH = 1024  # texels; a ray at 1 deg elevation over 18 texels of relief stops here


@dataclass(frozen=True)
class SurfaceGeometry:
    """Relief of a sample on its map grid.

    ``height_mm`` (H, W): base surface height; ``texel_mm``: map pitch; ``fibre_mask`` (H, W)
    bool: texels covered by fly-out fibres; ``fibre_axis_mm`` (H, W): height of the fibre axis
    there; ``fibre_top_mm`` (H, W): height of the fibre's visible surface there.
    """

    height_mm: np.ndarray
    texel_mm: float
    fibre_mask: np.ndarray | None = None
    fibre_axis_mm: np.ndarray | None = None
    fibre_top_mm: np.ndarray | None = None
    fibre_radius_mm: float = 0.0

    def __post_init__(self) -> None:
        h = np.asarray(self.height_mm)
        if h.ndim != 2 or not np.isfinite(h).all():
            raise ValueError("height_mm must be a finite (H, W) array")
        if not self.texel_mm > 0:
            raise ValueError("texel_mm must be positive")
        for name in ("fibre_mask", "fibre_axis_mm", "fibre_top_mm"):
            a = getattr(self, name)
            if a is not None and np.shape(a) != h.shape:
                raise ValueError(f"{name} is {np.shape(a)}, height_mm is {h.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(np.shape(self.height_mm))  # type: ignore[return-value]

    def surface_mm(self) -> np.ndarray:
        """Height of what the camera sees at each texel (fibre surface over fibre texels)."""
        if self.fibre_mask is None or self.fibre_top_mm is None:
            return np.asarray(self.height_mm, np.float64)
        return np.where(self.fibre_mask, self.fibre_top_mm, self.height_mm).astype(np.float64)


def _bilinear_shift(a: Tensor, drow: float, dcol: float) -> Tensor:
    """``a`` sampled at ``(row + drow, col + dcol)`` for every texel, periodic."""
    r0, c0 = math.floor(drow), math.floor(dcol)
    fr, fc = drow - r0, dcol - c0
    out = 0.0
    for dr, wr in ((r0, 1.0 - fr), (r0 + 1, fr)):
        for dc, wc in ((c0, 1.0 - fc), (c0 + 1, fc)):
            w = wr * wc
            if w > 1e-12:
                out = out + w * torch.roll(a, shifts=(-dr, -dc), dims=(0, 1))
    return out  # type: ignore[return-value]


def _relief_visibility(base: Tensor, z0: Tensor, drow: float, dcol: float, rise: float, tol: float) -> Tensor:
    """Texels whose ray (``drow, dcol`` texels per step, ``rise`` mm per step) clears ``base``."""
    lit = torch.ones_like(z0, dtype=torch.bool)
    top = float(base.max())
    steps = min(MAX_MARCH, int(math.ceil(max(0.0, top - float(z0.min())) / rise)) + 1)
    for k in range(1, steps + 1):
        under = _bilinear_shift(base, k * drow, k * dcol) > z0 + k * rise + tol
        lit &= ~under
    return lit


def _fibre_shadows(g: SurfaceGeometry, base: np.ndarray, u_rc: tuple[float, float], tan_el: float) -> np.ndarray:
    """Base texels shaded by a fibre: each fibre texel's shadow lands along ``-l``."""
    h, w = base.shape
    out = np.zeros((h, w), bool)
    if g.fibre_mask is None or g.fibre_axis_mm is None or not g.fibre_mask.any():
        return out
    rr, cc = np.nonzero(g.fibre_mask)
    axis = g.fibre_axis_mm[rr, cc]
    ground = base[rr, cc]
    for _ in range(2):  # land on the relief: refine the ground height once at the landing point
        d = np.maximum(axis - ground, 0.0) / tan_el / g.texel_mm
        lr = np.rint(rr - d * u_rc[0]).astype(int) % h
        lc = np.rint(cc - d * u_rc[1]).astype(int) % w
        ground = base[lr, lc]
    # the shadow is as wide as the fibre (at least one texel) across its length
    width = max(1, int(round(2 * g.fibre_radius_mm / g.texel_mm)))
    for k in range(width):
        off = k - (width - 1) / 2
        out[(lr + int(round(off * -u_rc[1]))) % h, (lc + int(round(off * u_rc[0]))) % w] = True
    return out & ~g.fibre_mask


def visibility(geom: SurfaceGeometry, dirs: Tensor, tol_texels: float = 0.05) -> Tensor:
    """Visibility ``(L, H, W)`` (float64, 0 or 1) of each texel from each light direction
    ``dirs`` ``(L, 3)`` (unit, towards the light).  Lights at or below the horizon give 0;
    the zenith casts no shadow."""
    base_np = np.asarray(geom.height_mm, np.float64)
    base = torch.from_numpy(base_np)
    z0 = torch.from_numpy(geom.surface_mm())
    tol = tol_texels * geom.texel_mm
    out = torch.ones(dirs.shape[0], *geom.shape, dtype=torch.float64)
    for i, l in enumerate(dirs.to(torch.float64)):
        lx, ly, lz = (float(v) for v in l)
        r = math.hypot(lx, ly)
        if lz <= 0:
            out[i] = 0.0
            continue
        if r < 1e-9:
            continue
        tan_el = lz / r
        u_rc = (-ly / r, lx / r)  # one texel towards the light, in (row, col): rows grow towards -y
        lit = _relief_visibility(base, z0, u_rc[0], u_rc[1], tan_el * geom.texel_mm, tol)
        lit &= ~torch.from_numpy(_fibre_shadows(geom, base_np, u_rc, tan_el))
        out[i] = lit.to(torch.float64)
    return out


GEOMETRY_CHANNELS = ("height", "fibre_mask", "fibre_axis", "fibre_top")


def save_geometry(path, geom: SurfaceGeometry) -> None:
    """Write ``geom`` as one float32 EXR: channels :data:`GEOMETRY_CHANNELS` (mm; mask 0/1,
    fibre channels 0 where there is no fibre) and the attributes ``dualscale:texel_mm`` and
    ``dualscale:fibre_radius_mm``."""
    from .exr import write_exr

    h = np.asarray(geom.height_mm, np.float64)
    zero = np.zeros_like(h)
    mask = zero if geom.fibre_mask is None else np.asarray(geom.fibre_mask, np.float64)
    axis = zero if geom.fibre_axis_mm is None else np.asarray(geom.fibre_axis_mm, np.float64)
    top = zero if geom.fibre_top_mm is None else np.asarray(geom.fibre_top_mm, np.float64)
    write_exr(path, np.stack([h, mask, axis, top], -1), GEOMETRY_CHANNELS,
              {"dualscale:texel_mm": repr(float(geom.texel_mm)),
               "dualscale:fibre_radius_mm": repr(float(geom.fibre_radius_mm))})


def load_geometry(path) -> SurfaceGeometry:
    """Read a file written by :func:`save_geometry`; a missing attribute or channel, or
    non-finite data, is a clear error."""
    from .exr import read_exr, read_exr_attributes

    data = read_exr(path, GEOMETRY_CHANNELS).astype(np.float64)
    attrs = read_exr_attributes(path)
    missing = [k for k in ("texel_mm", "fibre_radius_mm") if k not in attrs]
    if missing:
        raise ValueError(f"{path}: not a dualscale geometry file (missing {missing})")
    if not np.isfinite(data).all():
        raise ValueError(f"{path}: non-finite heights")
    mask = data[..., 1] > 0.5
    return SurfaceGeometry(data[..., 0], float(attrs["texel_mm"]), mask if mask.any() else None,
                           data[..., 2] if mask.any() else None, data[..., 3] if mask.any() else None,
                           float(attrs["fibre_radius_mm"]))
