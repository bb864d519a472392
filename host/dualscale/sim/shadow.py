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
import numpy as np
import torch
from torch import Tensor

from dualscale.formats.relief import SurfaceGeometry

MAX_MARCH = 1024  # texels; a ray at 1 deg elevation over 18 texels of relief stops here


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
