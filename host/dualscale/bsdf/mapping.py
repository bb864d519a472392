"""Normal and tangent parametrisations.

Normals are optimised as an unconstrained point of the square [-1, 1]^2, mapped to the unit
disc with Fong's elliptical grid mapping (Fong 2015, "Analytical methods for squaring the
disc") and lifted to the upper hemisphere: ``n = (u, v, sqrt(1 - u^2 - v^2))``.  Both
directions are provided; every square root is guarded so values and gradients stay finite at
the rim and the corners (where the exact inverse has an infinite derivative).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .vec import safe_normalize, safe_sqrt

_SQRT2 = math.sqrt(2.0)


def square_to_disc(xy: Tensor) -> Tensor:
    """``(..., 2)`` in [-1, 1]^2 -> ``(..., 2)`` in the unit disc: ``u = x sqrt(1 - y^2/2)``,
    ``v = y sqrt(1 - x^2/2)``.  Inputs are clamped to the square first."""
    xy = torch.clamp(xy, -1.0, 1.0)
    x, y = xy[..., 0:1], xy[..., 1:2]
    return torch.cat([x * torch.sqrt(1.0 - 0.5 * y * y), y * torch.sqrt(1.0 - 0.5 * x * x)], dim=-1)


def disc_to_square(uv: Tensor) -> Tensor:
    """Inverse of :func:`square_to_disc`.  Points outside the disc are pulled onto the rim.

    ``x = (sqrt(2 + u^2 - v^2 + 2 sqrt2 u) - sqrt(2 + u^2 - v^2 - 2 sqrt2 u)) / 2`` and
    symmetrically for ``y``; the radicands are clamped at a tiny positive value because they
    reach 0 at the corners and round slightly below it near the rim.
    """
    r2 = (uv * uv).sum(-1, keepdim=True)
    uv = uv * torch.where(r2 > 1.0, torch.rsqrt(torch.clamp(r2, min=1.0)), torch.ones_like(r2))
    u, v = uv[..., 0:1], uv[..., 1:2]
    d = u * u - v * v
    x = 0.5 * (safe_sqrt(2.0 + d + 2.0 * _SQRT2 * u) - safe_sqrt(2.0 + d - 2.0 * _SQRT2 * u))
    y = 0.5 * (safe_sqrt(2.0 - d + 2.0 * _SQRT2 * v) - safe_sqrt(2.0 - d - 2.0 * _SQRT2 * v))
    return torch.clamp(torch.cat([x, y], dim=-1), -1.0, 1.0)


def normal_from_square(xy: Tensor) -> Tensor:
    """Unit upper-hemisphere normal ``(..., 3)`` from square coordinates ``(..., 2)``."""
    uv = square_to_disc(xy)
    w = safe_sqrt(1.0 - (uv * uv).sum(-1, keepdim=True))
    return torch.cat([uv, w], dim=-1)


def square_from_normal(normal: Tensor) -> Tensor:
    """Square coordinates of a normal ``(..., 3)`` (normalised first; needs ``n_z >= 0``)."""
    if bool((normal[..., 2] < 0).any()):
        raise ValueError("normals must lie in the upper hemisphere (n_z >= 0)")
    n = safe_normalize(normal)
    return disc_to_square(n[..., 0:2])


def tangent_frame(normal: Tensor, tangent_angle: Tensor) -> tuple[Tensor, Tensor]:
    """Orthonormal ``(t, b)`` about ``normal``.

    ``tangent_angle`` ``(..., 1)`` is the azimuth [rad] of the major anisotropy axis in the
    macro (image) plane, counter-clockwise from +x; it is projected onto the plane normal to
    ``n`` (Gram-Schmidt) and ``b = n x t``.
    """
    t0 = torch.cat([torch.cos(tangent_angle), torch.sin(tangent_angle), torch.zeros_like(tangent_angle)], -1)
    t = safe_normalize(t0 - (t0 * normal).sum(-1, keepdim=True) * normal)
    return t, torch.linalg.cross(normal, t, dim=-1)
