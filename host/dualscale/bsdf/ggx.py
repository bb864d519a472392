"""Anisotropic GGX (GTR2aniso) distribution and the Heitz 2014 Smith masking term.

Local-frame convention: a direction ``w`` has components ``(w_x, w_y, w_z)`` along the
tangent ``t`` (major anisotropy axis), the bitangent ``b = n x t`` and the micro normal ``n``.
Roughness and anisotropy are dimensionless in [0, 1].

Smith term (Heitz 2014, "Understanding the masking-shadowing function", eqs. 85-86)::

    Lambda(w) = (-1 + sqrt(1 + (ax^2 w_x^2 + ay^2 w_y^2) / w_z^2)) / 2,   G1 = 1 / (1 + Lambda)

The seed prints a different Lambda (a linear mix ``cos(phi) ax + sin(phi) ay`` and
``G1 = 1 / (1 + Lambda / 2)``); we implement Heitz, see docs/APPEARANCE.md.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .vec import TINY

ALPHA_MIN = 1e-3


def ggx_alphas(roughness: Tensor, anisotropy: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Burley 2015 mapping: ``aspect = sqrt(1 - 0.9 a)``, ``ax = max(1e-3, r^2/aspect)``,
    ``ay = max(1e-3, r^2 aspect)``.  ``anisotropy=None`` gives ``ax = ay = max(1e-3, r^2)``."""
    r2 = roughness * roughness
    if anisotropy is None:
        a = torch.clamp(r2, min=ALPHA_MIN)
        return a, a
    aspect = torch.sqrt(1.0 - 0.9 * torch.clamp(anisotropy, 0.0, 1.0))
    return torch.clamp(r2 / aspect, min=ALPHA_MIN), torch.clamp(r2 * aspect, min=ALPHA_MIN)


def ggx_d_aniso(hx: Tensor, hy: Tensor, hz: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    """GTR2aniso normal distribution ``1 / (pi ax ay (hx^2/ax^2 + hy^2/ay^2 + hz^2)^2)`` [1/sr].

    ``h`` is the unit half vector in the local frame; ``D`` is 0 for ``hz <= 0``.  For unit
    ``h`` the bracket is at least ``min(1, 1/ax^2, 1/ay^2)``; it is floored there so that a
    degenerate (zero) ``h`` cannot overflow the value or its gradient.
    """
    s = (hx / ax) ** 2 + (hy / ay) ** 2 + hz * hz
    floor = torch.clamp(1.0 / torch.maximum(ax, ay) ** 2, max=1.0)
    d = 1.0 / (math.pi * ax * ay * torch.maximum(s, floor) ** 2)
    return torch.where(hz > 0, d, torch.zeros_like(d))


def ggx_d_iso(cos_h: Tensor, alpha: Tensor) -> Tensor:
    """Isotropic GGX ``alpha^2 / (pi (cos_h^2 (alpha^2 - 1) + 1)^2)`` [1/sr]; 0 for ``cos_h <= 0``.

    The bracket is floored at its true minimum ``min(1, alpha^2)`` (reached at ``cos_h = 1``) so
    that rounding (``|cos_h| > 1``) cannot push it to 0.
    """
    a2 = alpha * alpha
    s = cos_h * cos_h * (a2 - 1.0) + 1.0
    d = a2 / (math.pi * torch.maximum(s, torch.clamp(a2, max=1.0)) ** 2)
    return torch.where(cos_h > 0, d, torch.zeros_like(d))


def _proj_alpha2(wx: Tensor, wy: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    return (ax * wx) ** 2 + (ay * wy) ** 2


def smith_lambda(wx: Tensor, wy: Tensor, wz: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    """Heitz 2014 anisotropic GGX Lambda.  Defined for ``wz > 0``; ``wz`` is clamped to 1e-6,
    so at grazing angles it is large but finite."""
    z = torch.clamp(wz, min=1e-6)
    return 0.5 * (torch.sqrt(z * z + _proj_alpha2(wx, wy, ax, ay)) / z - 1.0)


def smith_g1(wx: Tensor, wy: Tensor, wz: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    """``G1 = 1 / (1 + Lambda)`` evaluated as ``2 wz / (wz + sqrt(wz^2 + a^2))`` (no division by
    ``wz``, so it is exact and smooth down to grazing); 0 for ``wz <= 0``."""
    z = torch.clamp(wz, min=0.0)
    return 2.0 * z / (z + torch.sqrt(z * z + _proj_alpha2(wx, wy, ax, ay) + TINY))


def smith_g(l_loc: Tensor, v_loc: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    """Separable Smith ``G(l, v) = G1(l) G1(v)``; ``l_loc``/``v_loc`` are ``(..., 3)`` local."""
    return (smith_g1(l_loc[..., 0:1], l_loc[..., 1:2], l_loc[..., 2:3], ax, ay)
            * smith_g1(v_loc[..., 0:1], v_loc[..., 1:2], v_loc[..., 2:3], ax, ay))


def smith_visibility(lz: Tensor, a2_l: Tensor, vz: Tensor, a2_v: Tensor) -> Tensor:
    """``G1(l) G1(v) / (4 (n.l)(n.v)) = 1 / ((lz + sqrt(lz^2 + a_l^2)) (vz + sqrt(vz^2 + a_v^2)))``.

    ``a2_w = ax^2 w_x^2 + ay^2 w_y^2`` (``alpha^2 (1 - w_z^2)`` when isotropic).  This form is
    finite at grazing angles, where G and the cosines go to 0 together.  Cosines are clamped at 0;
    the caller masks back-facing directions.
    """
    zl = torch.clamp(lz, min=0.0)
    zv = torch.clamp(vz, min=0.0)
    sl = torch.sqrt(zl * zl + torch.clamp(a2_l, min=0.0) + TINY)
    sv = torch.sqrt(zv * zv + torch.clamp(a2_v, min=0.0) + TINY)
    return 1.0 / ((zl + sl) * (zv + sv))
