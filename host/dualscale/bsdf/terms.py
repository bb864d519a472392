"""The seed's BSDF terms (supplementary Section 5) as pure tensor functions.

All return BSDF values in [1/sr] *without* the cosine factor; ``model.evaluate`` multiplies
by ``n.l`` (reflection) or ``|m.l|`` (transmission).  Cosines are w.r.t. the micro normal
``n``; ``cos_lv = l.v``.  RGB inputs are linear, shape ``(..., 3)``; scalars are ``(..., 1)``.

Half-angle convention: ``theta_h`` in the retro-reflection term is the angle between ``l`` and
the half vector ``h`` (Burley's theta_d), so ``cos^2 theta_h = (1 + l.v) / 2`` -- it needs no
normal, no square root, and is symmetric in ``l`` and ``v``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .fresnel import fresnel_weighted
from .ggx import ggx_d_aniso, ggx_d_iso, smith_visibility

INV_PI = 1.0 / math.pi


def schlick_weight(cos: Tensor) -> Tensor:
    """``F_x = (1 - cos)^5`` with ``cos`` clamped to [0, 1] (three multiplications, not ``pow``)."""
    t = 1.0 - torch.clamp(cos, 0.0, 1.0)
    t2 = t * t
    return t2 * t2 * t


def diffuse_base(albedo: Tensor, cos_l: Tensor, cos_v: Tensor) -> Tensor:
    """Burley's diffuse ``b/pi (1 - F_l/2)(1 - F_v/2)``."""
    return albedo * INV_PI * (1.0 - 0.5 * schlick_weight(cos_l)) * (1.0 - 0.5 * schlick_weight(cos_v))


def retro_reflection(albedo: Tensor, roughness: Tensor, cos_l: Tensor, cos_v: Tensor, cos_lv: Tensor) -> Tensor:
    """``b/pi R_R (F_l + F_v + F_l F_v (R_R - 1))`` with ``R_R = 2 sigma_r cos^2 theta_h = sigma_r (1 + l.v)``."""
    fl = schlick_weight(cos_l)
    fv = schlick_weight(cos_v)
    rr = roughness * (1.0 + torch.clamp(cos_lv, -1.0, 1.0))
    return albedo * INV_PI * rr * (fl + fv + fl * fv * (rr - 1.0))


def diffuse(albedo: Tensor, roughness: Tensor, cos_l: Tensor, cos_v: Tensor, cos_lv: Tensor) -> Tensor:
    """Full diffuse term: ``diffuse_base + retro_reflection``, with the Schlick weights computed
    once and the angular factor on one channel before it scales the RGB albedo."""
    fl = schlick_weight(cos_l)
    fv = schlick_weight(cos_v)
    rr = roughness * (1.0 + torch.clamp(cos_lv, -1.0, 1.0))
    return albedo * (INV_PI * ((1.0 - 0.5 * fl) * (1.0 - 0.5 * fv) + rr * (fl + fv + fl * fv * (rr - 1.0))))


def diffuse_lambert(albedo: Tensor, cos_l: Tensor) -> Tensor:
    """Lambert's diffuse ``b / pi``, broadcast against ``cos_l`` ``(..., 1)`` (the other
    :func:`diffuse` arguments play no part): the ``Components(diffuse="lambert")`` lobe."""
    return albedo * INV_PI * torch.ones_like(cos_l)


def chromaticity(albedo: Tensor, eps: float = 1e-6) -> Tensor:
    """``chr(b) = b / max(b_r, b_g, b_b)``; black (max <= eps) gives white (1, 1, 1)."""
    m = albedo.amax(dim=-1, keepdim=True)
    safe = torch.clamp(m, min=eps)
    return torch.where(m > eps, albedo / safe, torch.ones_like(albedo))


def specular_tint(albedo: Tensor, rho_s: Tensor) -> Tensor:
    """``chr(b) rho_s + 1 - rho_s``."""
    return chromaticity(albedo) * rho_s + (1.0 - rho_s)


def specular_aniso(l_loc: Tensor, v_loc: Tensor, ax: Tensor, ay: Tensor, eta: Tensor | float,
                   w_s: Tensor | float = 0.5, w_p: Tensor | float = 0.5) -> Tensor:
    """Untinted anisotropic specular ``D G F / (4 (n.l)(n.v))`` from local-frame unit ``l``, ``v``.

    ``F = w_s R_s + w_p R_p`` at ``cos = l.h``; (1/2, 1/2) is unpolarised, (1, 0) S-polarised.
    Returns 0 where ``n.l <= 0`` or ``n.v <= 0``.
    """
    hv = l_loc + v_loc
    h = hv * torch.rsqrt((hv * hv).sum(-1, keepdim=True) + 1e-20)
    lx, ly, lz = l_loc[..., 0:1], l_loc[..., 1:2], l_loc[..., 2:3]
    vx, vy, vz = v_loc[..., 0:1], v_loc[..., 1:2], v_loc[..., 2:3]
    d = ggx_d_aniso(h[..., 0:1], h[..., 1:2], h[..., 2:3], ax, ay)
    vis = smith_visibility(lz, (ax * lx) ** 2 + (ay * ly) ** 2, vz, (ax * vx) ** 2 + (ay * vy) ** 2)
    f = fresnel_weighted((l_loc * h).sum(-1, keepdim=True), eta, w_s, w_p)
    front = (lz > 0) & (vz > 0)
    return torch.where(front, d * vis * f, torch.zeros_like(d))


def specular_iso(cos_l: Tensor, cos_v: Tensor, cos_lv: Tensor, alpha: Tensor, eta: Tensor | float,
                 w_s: Tensor | float = 0.5, w_p: Tensor | float = 0.5) -> Tensor:
    """Untinted isotropic specular from cosines only (no tangent frame needed).

    With ``|l + v|^2 = 2 (1 + l.v)``: ``n.h = (n.l + n.v)/|l + v|`` and ``l.h = |l + v|/2``.
    """
    len2 = torch.clamp(2.0 + 2.0 * cos_lv, min=1e-20)
    inv_len = torch.rsqrt(len2)
    cos_h = (cos_l + cos_v) * inv_len
    cos_d = 0.5 * len2 * inv_len
    a2 = alpha * alpha
    d = ggx_d_iso(cos_h, alpha)
    vis = smith_visibility(cos_l, a2 * (1.0 - cos_l * cos_l), cos_v, a2 * (1.0 - cos_v * cos_v))
    f = fresnel_weighted(cos_d, eta, w_s, w_p)
    front = (cos_l > 0) & (cos_v > 0)
    return torch.where(front, d * vis * f, torch.zeros_like(d))


def transmittance(trans: Tensor, cos_ml: Tensor, cos_mv: Tensor) -> Tensor:
    """Diffuse transmission lobe about the macro normal ``m``: ``t/pi`` when ``l`` and ``v`` lie
    on opposite sides of the sample (``(m.l)(m.v) < 0``), else 0.  With a uniform back light of
    radiance L the camera sees ``t L``, i.e. ``t`` is the captured transmittance image."""
    through = (cos_ml * cos_mv) < 0
    return torch.where(through, trans * INV_PI, torch.zeros_like(trans))
