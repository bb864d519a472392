"""Shared builders for the appearance tests."""

from __future__ import annotations

import torch

from dualscale.bsdf import MaterialMaps, normal_from_square


def unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def random_maps(h: int, w: int, dtype=torch.float64, seed: int = 0, full: bool = True) -> MaterialMaps:
    g = torch.Generator().manual_seed(seed)

    def r(c, lo=0.05, hi=0.95):
        return lo + (hi - lo) * torch.rand(h, w, c, generator=g, dtype=dtype)

    if not full:
        return MaterialMaps(albedo=r(3), roughness=r(1, 0.2, 0.9))
    n = normal_from_square(r(2, -0.6, 0.6))
    return MaterialMaps(albedo=r(3), roughness=r(1, 0.2, 0.9), anisotropy=r(1), tangent=r(1), normal=n,
                        ior=r(1), specular_tint=r(1), transmittance=r(3), opacity=r(1))


def hemisphere_dirs(n: int, dtype=torch.float64, seed: int = 1, zmin: float = 0.05) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=dtype)
    d[:, 2] = d[:, 2].abs() + zmin
    return unit(d)
