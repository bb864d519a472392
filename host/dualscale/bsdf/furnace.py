"""White-furnace integrals of the reflectance lobes (numerical quadrature, float64).

Used by the tests and by docs/APPEARANCE.md to record where the model loses or gains energy.
Directions are in the local frame of the micro normal (``n = +z``, tangent = +x).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .ggx import ggx_alphas, ggx_d_aniso, smith_g1, smith_visibility
from .terms import diffuse

D64 = torch.float64


def _view(theta_v_deg: float, phi_v_deg: float = 0.0) -> Tensor:
    t, p = math.radians(theta_v_deg), math.radians(phi_v_deg)
    return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=D64)


def _h_grid(alpha_min: float, n_theta: int, n_phi: int) -> tuple[Tensor, Tensor]:
    # theta_h = atan(k tan(u)): concentrates samples where a narrow GGX lobe lives.
    k = max(alpha_min, 1e-3) * 2.0
    u = (torch.arange(n_theta, dtype=D64) + 0.5) * (math.pi / 2 / n_theta)
    th = torch.atan(k * torch.tan(u))
    dth = k / (torch.cos(u) ** 2 + (k * torch.sin(u)) ** 2) * (math.pi / 2 / n_theta)
    ph = (torch.arange(n_phi, dtype=D64) + 0.5) * (2 * math.pi / n_phi)
    th2, ph2 = torch.meshgrid(th, ph, indexing="ij")
    h = torch.stack([torch.sin(th2) * torch.cos(ph2), torch.sin(th2) * torch.sin(ph2), torch.cos(th2)], -1)
    dw = (torch.sin(th2) * dth[:, None]) * (2 * math.pi / n_phi)
    return h, dw


def weak_furnace(roughness: float, anisotropy: float, theta_v_deg: float, phi_v_deg: float = 0.0,
                 n_theta: int = 1500, n_phi: int = 256) -> float:
    """``int D(h) G1(v) <v, h>+ / <v, n> dh`` -- equals 1 exactly iff Lambda matches D (Heitz 2014)."""
    ax, ay = ggx_alphas(torch.tensor(roughness, dtype=D64), torch.tensor(anisotropy, dtype=D64))
    h, dw = _h_grid(float(min(ax, ay)), n_theta, n_phi)
    v = _view(theta_v_deg, phi_v_deg)
    d = ggx_d_aniso(h[..., 0], h[..., 1], h[..., 2], ax, ay)
    g1 = smith_g1(v[0], v[1], v[2], ax, ay)
    return float((d * g1 * torch.clamp(h @ v, min=0) / v[2] * dw).sum())


def specular_albedo(roughness: float, anisotropy: float, theta_v_deg: float, phi_v_deg: float = 0.0,
                    n_theta: int = 1500, n_phi: int = 256) -> float:
    """Directional albedo ``int D G / (4 n.l n.v) (n.l) dl`` of the specular lobe with F = 1."""
    ax, ay = ggx_alphas(torch.tensor(roughness, dtype=D64), torch.tensor(anisotropy, dtype=D64))
    h, dw = _h_grid(float(min(ax, ay)), n_theta, n_phi)
    v = _view(theta_v_deg, phi_v_deg)
    vh = (h @ v).unsqueeze(-1)
    l = 2 * vh * h - v
    lx, ly, lz = l[..., 0], l[..., 1], l[..., 2]
    d = ggx_d_aniso(h[..., 0], h[..., 1], h[..., 2], ax, ay)
    vis = smith_visibility(lz, (ax * lx) ** 2 + (ay * ly) ** 2, v[2], (ax * v[0]) ** 2 + (ay * v[1]) ** 2)
    ok = (lz > 0) & (vh[..., 0] > 0)
    integrand = torch.where(ok, d * vis * lz * 4 * vh[..., 0], torch.zeros_like(d))  # dl = 4 (v.h) dh
    return float((integrand * dw).sum())


def diffuse_albedo(roughness: float, theta_v_deg: float, n_theta: int = 512, n_phi: int = 256) -> float:
    """Directional albedo ``int diffuse(b = 1) (n.l) dl`` (Burley diffuse + retro-reflection)."""
    u = (torch.arange(n_theta, dtype=D64) + 0.5) / n_theta  # u = cos(theta_l)
    ph = (torch.arange(n_phi, dtype=D64) + 0.5) * (2 * math.pi / n_phi)
    c, p = torch.meshgrid(u, ph, indexing="ij")
    s = torch.sqrt(1 - c * c)
    l = torch.stack([s * torch.cos(p), s * torch.sin(p), c], -1)
    v = _view(theta_v_deg)
    one = torch.ones((), dtype=D64)
    f = diffuse(one, torch.tensor(roughness, dtype=D64), c, v[2].expand_as(c), l @ v)
    return float((f * c).sum() * (1.0 / n_theta) * (2 * math.pi / n_phi))
