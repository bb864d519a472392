"""The full SVBSDF ``f = (diffuse + specular)(n.l) + transmittance |m.l|`` over a map.

Directions are unit vectors in the macro frame (``m = +z``; x, y = image axes) pointing
*away* from the surface: ``light_dirs`` ``(L, 3)`` (distant lights) or ``(L, H, W, 3)``
(near-field lights) towards each light, ``view_dirs`` ``(3,)``
(orthographic) or ``(H, W, 3)`` (perspective) towards the camera.  The result is
``(L, H, W, 3)`` in [1/sr]: multiply by the irradiance a light delivers (normal to its
direction) to get radiance.

Reflection needs light and view above the sample (``m.l > 0``, ``m.v > 0``) and above the
micro facet; transmission needs them on opposite sides.  ``opacity`` scales the whole surface
response (``1 - opacity`` is open area; the dome renderer adds light seen through it).

The diffuse lobe is Burley's with retro-reflection (the paper's) or, for
``Components(diffuse="lambert")``, Lambert's ``b / pi`` (:mod:`.terms`).

Polarisation enters through per-light weights: the specular Fresnel factor is
``w_s R_s + w_p R_p`` and the diffuse lobes are scaled by ``diffuse_weight`` (see
``dualscale.sim.render`` for how LED polarisers and the analyser set them).
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from .ggx import ggx_alphas, ggx_d_aniso, ggx_d_iso, smith_visibility
from .fresnel import fresnel_weighted
from .maps import Components, MaterialMaps, ior_from_map, tangent_angle_from_map, validate_maps
from .mapping import tangent_frame
from .terms import diffuse, diffuse_lambert, specular_tint, transmittance
from .vec import check_finite

Weight = Tensor | float


def _per_light(w: Weight, n: int, like: Tensor) -> Tensor | float:
    if isinstance(w, (int, float)):
        return float(w)
    w = torch.as_tensor(w, dtype=like.dtype, device=like.device)
    if w.ndim == 0:
        return w
    if w.shape != (n,):
        raise ValueError(f"per-light weight must be a scalar or have shape ({n},), got {tuple(w.shape)}")
    return w.reshape(n, 1, 1, 1)


def _slice(w: Tensor | float, a: int, b: int) -> Tensor | float:
    return w[a:b] if isinstance(w, Tensor) and w.ndim == 4 else w


def _shade(l: Tensor, v: Tensor, w_s: Weight, w_p: Weight, w_d: Weight,
           albedo: Tensor, rough: Tensor, ax: Tensor, ay: Tensor,
           n: Tensor | None, t: Tensor | None, b: Tensor | None,
           eta: Tensor | float, tint: Tensor | None,
           trans: Tensor | None, opacity: Tensor | None, lambert: bool = False) -> Tensor:
    """Kernel for one chunk of lights.  ``l`` is ``(Lc, 1, 1, 3)``; per-pixel inputs are
    ``(1, H, W, C)``; ``ax`` is ``ay`` when isotropic (then ``t``/``b`` are None); ``lambert``:
    Lambert's diffuse instead of Burley's (:class:`~.maps.Components` ``diffuse``)."""
    lz_m = l[..., 2:3]
    vz_m = v[..., 2:3]
    if n is None:
        cl, cv = lz_m, vz_m
    else:
        cl = (l * n).sum(-1, keepdim=True)
        cv = (v * n).sum(-1, keepdim=True)
    clv = (l * v).sum(-1, keepdim=True)
    len2 = torch.clamp(2.0 + 2.0 * clv, min=1e-12)
    inv_len = torch.rsqrt(len2)
    cos_d = 0.5 * len2 * inv_len  # l.h
    if t is None:
        a2 = ax * ax
        d = ggx_d_iso((cl + cv) * inv_len, ax)
        vis = smith_visibility(cl, a2 * (1.0 - cl * cl), cv, a2 * (1.0 - cv * cv))
    else:
        lx, ly = (l * t).sum(-1, keepdim=True), (l * b).sum(-1, keepdim=True)
        vx, vy = (v * t).sum(-1, keepdim=True), (v * b).sum(-1, keepdim=True)
        d = ggx_d_aniso((lx + vx) * inv_len, (ly + vy) * inv_len, (cl + cv) * inv_len, ax, ay)
        vis = smith_visibility(cl, (ax * lx) ** 2 + (ay * ly) ** 2, cv, (ax * vx) ** 2 + (ay * vy) ** 2)
    spec = d * vis * fresnel_weighted(cos_d, eta, w_s, w_p)
    if tint is not None:
        spec = spec * tint
    lobe = (diffuse_lambert(albedo, cl) if lambert else diffuse(albedo, rough, cl, cv, clv)) * w_d + spec
    front = (cl > 0) & (cv > 0) & (lz_m > 0) & (vz_m > 0)
    out = torch.where(front, lobe * torch.clamp(cl, min=0.0), torch.zeros_like(lobe))
    if trans is not None:
        out = out + transmittance(trans, lz_m, vz_m) * w_d * lz_m.abs()
    if opacity is not None:
        out = out * opacity
    return out


_COMPILED: dict[str, Callable] = {}


def _compiled_shade() -> Callable:
    """``_shade`` through ``torch.compile``, falling back to eager (with a warning, for the rest
    of the process) if compiling fails: a missing C++ compiler must not stop a fit."""
    if "shade" not in _COMPILED:
        import torch._dynamo.config as dynamo_config

        # every pixel-block shape and set of active components is its own graph; one fit meets
        # about a dozen, a benchmark over several materials a few dozen (the default is 8)
        dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 64)
        fn = torch.compile(_shade, dynamic=False, fullgraph=True)

        def shade(*args, **kwargs) -> Tensor:
            if "failed" not in _COMPILED:
                try:
                    return fn(*args, **kwargs)
                except Exception as e:  # compiler or toolchain error: the eager kernel is equivalent
                    import warnings

                    _COMPILED["failed"] = shade
                    warnings.warn(f"torch.compile of the BSDF kernel failed ({type(e).__name__}: "
                                  f"{str(e).splitlines()[0][:200]}); using the eager kernel", RuntimeWarning)
            return _shade(*args, **kwargs)

        _COMPILED["shade"] = shade
    return _COMPILED["shade"]


def prepare(maps: MaterialMaps, comps: Components) -> dict[str, Tensor | float | None]:
    """Per-pixel quantities that do not depend on the light (computed once per map).

    Only the active components are read; an inactive map is never touched or allocated.
    """
    rough = maps.roughness
    if comps.isotropic:
        ax, _ = ggx_alphas(rough)
        ay = ax
    else:
        ax, ay = ggx_alphas(rough, maps.anisotropy)
    n = t = b = None
    if comps.normal_mapped:
        n = maps.normal
    if not comps.isotropic:
        phi = tangent_angle_from_map(maps.tangent)
        if n is None:  # flat: the frame is the image plane, no normal tensor needed
            c, s, z = torch.cos(phi), torch.sin(phi), torch.zeros_like(phi)
            t, b = torch.cat([c, s, z], -1), torch.cat([-s, c, z], -1)
        else:
            t, b = tangent_frame(n, phi)
    eta = ior_from_map(maps.ior) if comps.ior_mapped else float(comps.ior)
    tint = specular_tint(maps.albedo, maps.specular_tint) if comps.tinted else None
    trans = opacity = None
    if not comps.opaque:
        trans, opacity = maps.transmittance, maps.opacity
    out = dict(albedo=maps.albedo, rough=rough, ax=ax, ay=ay, n=n, t=t, b=b, eta=eta, tint=tint,
               trans=trans, opacity=opacity, lambert=comps.lambertian)
    return {k: (val.unsqueeze(0) if isinstance(val, Tensor) else val) for k, val in out.items()}


def _check_dirs(light_dirs: Tensor, view_dirs: Tensor, hw: tuple[int, int]) -> Tensor:
    if not (light_dirs.ndim == 2 and light_dirs.shape[-1] == 3) and tuple(light_dirs.shape[1:]) != (*hw, 3):
        raise ValueError(f"light_dirs must be (L, 3) or (L, {hw[0]}, {hw[1]}, 3), got {tuple(light_dirs.shape)}")
    if view_dirs.shape == (3,):
        view = view_dirs.reshape(1, 1, 1, 3)
    elif view_dirs.shape == (*hw, 3):
        view = view_dirs.unsqueeze(0)
    else:
        raise ValueError(f"view_dirs must be (3,) or {(*hw, 3)}, got {tuple(view_dirs.shape)}")
    check_finite("light_dirs", light_dirs)
    check_finite("view_dirs", view_dirs)
    return view


def evaluate(maps: MaterialMaps, light_dirs: Tensor, view_dirs: Tensor, comps: Components | None = None, *,
             w_s: Weight = 0.5, w_p: Weight = 0.5, diffuse_weight: Weight = 1.0,
             light_chunk: int | None = None, compiled: bool = False, validate: bool = True) -> Tensor:
    """Evaluate ``f`` for every light and pixel: ``(L, H, W, 3)`` [1/sr].

    ``comps`` defaults to the components implied by the maps present.  ``light_chunk`` bounds
    the working set (lights per kernel call; ``None`` = all at once).  ``compiled=True`` runs
    the kernel through ``torch.compile`` (fused forward and backward; first call compiles).
    """
    comps = maps.components() if comps is None else comps
    if validate:
        validate_maps(maps, comps)
    view = _check_dirs(light_dirs, view_dirs, maps.shape)
    n_l = light_dirs.shape[0]
    p = prepare(maps, comps)
    ws, wp, wd = (_per_light(w, n_l, light_dirs) for w in (w_s, w_p, diffuse_weight))
    l4 = (light_dirs.reshape(n_l, 1, 1, 3) if light_dirs.ndim == 2 else light_dirs).to(maps.albedo.dtype)
    view = view.to(maps.albedo.dtype)
    kernel = _compiled_shade() if compiled else _shade
    chunk = n_l if light_chunk is None else max(1, int(light_chunk))
    if chunk >= n_l:
        return kernel(l4, view, ws, wp, wd, **p)
    outs = []
    pad = (-n_l) % chunk if compiled else 0  # equal chunk shapes avoid recompiling
    if pad:
        l4 = torch.cat([l4, l4[-1:].expand(pad, *l4.shape[1:])], 0)
        ws, wp, wd = (torch.cat([w, w[-1:].expand(pad, 1, 1, 1)], 0) if isinstance(w, Tensor) and w.ndim == 4 else w
                      for w in (ws, wp, wd))
    for a in range(0, n_l + pad, chunk):
        bnd = a + chunk
        outs.append(kernel(l4[a:bnd], view, _slice(ws, a, bnd), _slice(wp, a, bnd), _slice(wd, a, bnd), **p))
    return torch.cat(outs, 0)[:n_l]
