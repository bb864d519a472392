"""A straightforward, unfused implementation of the same model, for tests and benchmarks.

Every map is broadcast to ``(L, H, W, C)``, the frame and the per-pixel parameters are
recomputed for every light, and the public vector-form terms are applied one after the other.
It shares no kernel with :mod:`.model`, so agreement between the two is a real check.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .ggx import ggx_alphas
from .maps import Components, MaterialMaps, ior_from_map, tangent_angle_from_map
from .terms import diffuse, diffuse_lambert, specular_aniso, specular_tint, transmittance


def evaluate_reference(maps: MaterialMaps, light_dirs: Tensor, view_dirs: Tensor, comps: Components | None = None, *,
                       w_s: float | Tensor = 0.5, w_p: float | Tensor = 0.5,
                       diffuse_weight: float | Tensor = 1.0) -> Tensor:
    """Same contract as :func:`dualscale.bsdf.model.evaluate`, computed the plain way."""
    comps = maps.components() if comps is None else comps
    n_l = light_dirs.shape[0]
    h, w = maps.shape
    full = (n_l, h, w)

    def ex(x: Tensor) -> Tensor:
        return x.unsqueeze(0).expand(*full, x.shape[-1])

    def per_light(x):
        return x.reshape(n_l, 1, 1, 1) if isinstance(x, Tensor) and x.ndim == 1 else x

    l = (light_dirs.reshape(n_l, 1, 1, 3) if light_dirs.ndim == 2 else light_dirs).expand(*full, 3)
    v = view_dirs.expand(*full, 3) if view_dirs.ndim == 1 else view_dirs.unsqueeze(0).expand(*full, 3)
    albedo, rough = ex(maps.albedo), ex(maps.roughness)
    if comps.normal_mapped:
        n = F.normalize(ex(maps.normal), dim=-1)
    else:
        n = torch.zeros_like(l)
        n[..., 2] = 1.0
    if comps.isotropic:
        t0 = torch.zeros_like(l)
        t0[..., 0] = 1.0
        ax, ay = ggx_alphas(rough)
    else:
        phi = tangent_angle_from_map(ex(maps.tangent))
        t0 = torch.cat([torch.cos(phi), torch.sin(phi), torch.zeros_like(phi)], -1)
        ax, ay = ggx_alphas(rough, ex(maps.anisotropy))
    t = t0 - (t0 * n).sum(-1, keepdim=True) * n
    t = t / torch.sqrt((t * t).sum(-1, keepdim=True) + 1e-12)
    b = torch.linalg.cross(n, t, dim=-1)
    frame = torch.stack([t, b, n], -2)  # (L, H, W, 3, 3)
    l_loc = (frame @ l.unsqueeze(-1)).squeeze(-1)
    v_loc = (frame @ v.unsqueeze(-1)).squeeze(-1)
    eta = ior_from_map(ex(maps.ior)) if comps.ior_mapped else comps.ior
    spec = specular_aniso(l_loc, v_loc, ax, ay, eta, per_light(w_s), per_light(w_p))
    if comps.tinted:
        spec = spec * specular_tint(albedo, ex(maps.specular_tint))
    cl, cv = l_loc[..., 2:3], v_loc[..., 2:3]
    if comps.lambertian:
        diff = diffuse_lambert(albedo, cl)
    else:
        diff = diffuse(albedo, rough, cl, cv, (l * v).sum(-1, keepdim=True))
    diff = diff * per_light(diffuse_weight)
    above = (l[..., 2:3] > 0) & (v[..., 2:3] > 0) & (cl > 0) & (cv > 0)
    out = torch.where(above, (diff + spec) * cl.clamp(min=0), torch.zeros_like(diff))
    if not comps.opaque:
        lz = l[..., 2:3]
        out = out + transmittance(ex(maps.transmittance), lz, v[..., 2:3]) * per_light(diffuse_weight) * lz.abs()
        out = out * ex(maps.opacity)
    return out
