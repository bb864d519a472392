"""Exact Fresnel reflectance of a smooth dielectric interface with a real IOR.

``cos_i`` is the cosine between the incident direction and the (micro)facet normal, in
[0, 1]; ``eta`` = eta_2 / eta_1 is the relative IOR (transmitted over incident side).  The
material model always uses eta >= 1 (light arrives from air); eta < 1 is supported, and
total internal reflection returns exactly 1 for every polarisation.

With ``g = eta cos(theta_t) = sqrt(eta^2 - 1 + cos_i^2)`` (Snell) the amplitude ratios are
``r_s = (cos_i - g) / (cos_i + g)`` and ``r_p = (eta^2 cos_i - g) / (eta^2 cos_i + g)``.
Note: the seed's printed R_p is algebraically identical to its R_s (the eta's are swapped in
both numerator and denominator); we implement the textbook R_p.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .vec import TINY


def _g_and_tir(cos_i: Tensor, eta: Tensor | float) -> tuple[Tensor, Tensor, Tensor]:
    c = torch.clamp(cos_i, min=0.0, max=1.0)
    g2 = eta * eta - 1.0 + c * c
    tir = g2 <= 0.0
    g = torch.sqrt(torch.clamp(g2, min=TINY))
    return c, g, tir


def fresnel_s(cos_i: Tensor, eta: Tensor | float) -> Tensor:
    """R_s: reflectance for light polarised perpendicular to the plane of incidence."""
    c, g, tir = _g_and_tir(cos_i, eta)
    c = torch.clamp(c, min=TINY)
    r = (c - g) / (c + g)
    return torch.where(tir, torch.ones_like(r), r * r)


def fresnel_p(cos_i: Tensor, eta: Tensor | float) -> Tensor:
    """R_p: reflectance for light polarised in the plane of incidence."""
    c, g, tir = _g_and_tir(cos_i, eta)
    c = torch.clamp(c, min=TINY)
    e2c = eta * eta * c
    r = (e2c - g) / (e2c + g)
    return torch.where(tir, torch.ones_like(r), r * r)


def fresnel_dielectric(cos_i: Tensor, eta: Tensor | float) -> Tensor:
    """Unpolarised reflectance ``(R_s + R_p) / 2`` (used when rendering unpolarised light)."""
    return 0.5 * (fresnel_s(cos_i, eta) + fresnel_p(cos_i, eta))


def fresnel_weighted(cos_i: Tensor, eta: Tensor | float, w_s: Tensor | float, w_p: Tensor | float) -> Tensor:
    """``w_s R_s + w_p R_p`` sharing one square root.

    The weights describe the illumination and analyser: unpolarised light without analyser is
    (1/2, 1/2); S-polarised light (what fitting uses) is (1, 0); an analyser at angle
    ``delta`` from the S axis multiplies them by cos^2(delta) and sin^2(delta).
    """
    c, g, tir = _g_and_tir(cos_i, eta)
    c = torch.clamp(c, min=TINY)
    rs = (c - g) / (c + g)
    e2c = eta * eta * c
    rp = (e2c - g) / (e2c + g)
    val = w_s * rs * rs + w_p * rp * rp
    return torch.where(tir, (w_s + w_p) * torch.ones_like(val), val)
