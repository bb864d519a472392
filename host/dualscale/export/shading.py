"""The formats' own shading models, to measure what each export's approximation costs.

Each function evaluates a format's BSDF (times the cosine, like
:func:`dualscale.bsdf.model.evaluate`) from the *format's* parameters ``(H, W, C)`` numpy arrays
as read back from the exported files, for distant lights ``light_dirs`` ``(L, 3)`` and an
orthographic view ``view`` ``(3,)`` (unit vectors, macro frame, +z out of the sample); the
result is ``(L, H, W, 3)`` [1/sr], comparable with our model's render of the same sample.

* :func:`gltf_bsdf` -- glTF 2.0 Appendix B (metallic 0) with ``KHR_materials_ior``,
  ``KHR_materials_specular`` (``fresnel_mix`` with the specular colour, F90 = 1) and
  ``KHR_materials_anisotropy`` (``alpha_t = mix(r^2, 1, s^2)``, ``alpha_b = r^2``); Lambert
  diffuse; Schlick Fresnel; height-correlated Smith visibility (the form of the anisotropy
  extension and of three.js).  Transmission only scales the diffuse lobe in reflection
  (``(1 - T) base``); the dome's reflection LEDs do not see the BTDF.
* :func:`standard_surface_bsdf` -- Autodesk Standard Surface v1.0.1 (MaterialX's implementation,
  single scattering): GGX with the exact dielectric Fresnel of ``specular_IOR`` tinted by
  ``specular_color`` at all angles, over a Lambert base (``diffuse_roughness`` 0) attenuated by
  ``1 - E_spec(v)``, the specular lobe's directional albedo at the view (integrated numerically
  here; MaterialX uses a fitted table).  No multiple-scattering compensation.

* :func:`principled_bsdf` -- the Principled BSDF (Burley 2012, Disney; Blender's Principled)
  that U3M's ``"principled"`` shader names: Burley's diffuse with retro-reflection (which
  expands to exactly our diffuse term), ``(1 - transmission)`` in reflection, GGX with
  Burley's anisotropy (ours) rotated by ``2 pi * rotation``, Schlick Fresnel from
  ``F0 = 0.08 specular mix(1, base / Y(base), specular_tint)`` to 1, diffuse not attenuated.

All reuse the microfacet functions of :mod:`dualscale.bsdf.ggx` (one GGX for the project).
Directions below the horizon are refused (``GeometryError``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import MaterialMaps
from dualscale.bsdf.ggx import ALPHA_MIN, ggx_d_aniso, smith_visibility
from dualscale.errors import GeometryError

from .exchange import LUMINANCE


def _t(a: np.ndarray | None, dtype=torch.float64) -> Tensor | None:
    if a is None:
        return None
    t = torch.as_tensor(np.asarray(a), dtype=dtype)
    return t[..., None] if t.ndim == 2 else t


def _check(light_dirs: Tensor, view: Tensor) -> None:
    if bool((light_dirs[:, 2] <= 0).any()) or float(view[2]) <= 0:
        raise GeometryError("shading: light and view directions must lie above the sample plane (z > 0)")


def _frame(normal: Tensor | None, direction: Tensor | None, shape: tuple[int, int]):
    """Per-pixel (t, b, n) ``(1, H, W, 3)``: ``n`` from the tangent-space normal map (the tangent
    space is the macro frame, +x right, +y up), ``t`` the anisotropy direction projected onto the
    plane normal to ``n`` (Gram-Schmidt), ``b = n x t``."""
    h, w = shape
    n = torch.zeros(h, w, 3, dtype=torch.float64)
    n[..., 2] = 1
    if normal is not None:
        n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t0 = torch.zeros(h, w, 3, dtype=torch.float64)
    t0[..., 0] = 1
    if direction is not None:
        t0 = torch.cat([direction, torch.zeros(h, w, 1, dtype=torch.float64)], -1)
    t = t0 - (t0 * n).sum(-1, keepdim=True) * n
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = torch.linalg.cross(n, t, dim=-1)
    return t[None], b[None], n[None]


def _microfacet(l: Tensor, v: Tensor, t: Tensor, b: Tensor, n: Tensor, at: Tensor, ab: Tensor):
    """``D * V`` (no Fresnel), ``l.h`` and the cosines, for ``l`` ``(L, 1, 1, 3)``."""
    at, ab = at.clamp_min(ALPHA_MIN), ab.clamp_min(ALPHA_MIN)
    hv = l + v
    hvec = hv / hv.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cl, cv = (l * n).sum(-1, keepdim=True), (v * n).sum(-1, keepdim=True)
    lx, ly = (l * t).sum(-1, keepdim=True), (l * b).sum(-1, keepdim=True)
    vx, vy = (v * t).sum(-1, keepdim=True), (v * b).sum(-1, keepdim=True)
    hx, hy, hz = ((hvec * t).sum(-1, keepdim=True), (hvec * b).sum(-1, keepdim=True),
                  (hvec * n).sum(-1, keepdim=True))
    d = ggx_d_aniso(hx, hy, hz, at, ab)
    vis = smith_visibility(cl, (at * lx) ** 2 + (ab * ly) ** 2, cv, (at * vx) ** 2 + (ab * vy) ** 2)
    return d * vis, (l * hvec).sum(-1, keepdim=True).clamp(0, 1), cl, cv


def gltf_bsdf(params: dict[str, np.ndarray | float | None], light_dirs: np.ndarray, view: np.ndarray) -> np.ndarray:
    """glTF 2.0 BSDF times cosine (module docstring).  ``params``: ``base_color`` (H, W, 3) linear,
    ``roughness`` (H, W), ``anisotropy_strength`` (H, W) or None, ``anisotropy_direction``
    (H, W, 2) or None, ``normal`` (H, W, 3) tangent space or None, ``ior`` float,
    ``specular_color`` (H, W, 3) linear F0 colour (texture x factor) or None,
    ``transmission`` (H, W) or None, ``alpha`` (H, W) coverage or None."""
    l = torch.as_tensor(np.asarray(light_dirs), dtype=torch.float64)
    v = torch.as_tensor(np.asarray(view), dtype=torch.float64)
    _check(l, v)
    base = _t(params["base_color"])
    h, w = base.shape[:2]
    r = _t(params["roughness"])
    a = r * r
    s = _t(params.get("anisotropy_strength"))
    at = a if s is None else a + (1 - a) * s * s
    t, b, n = _frame(_t(params.get("normal")), _t(params.get("anisotropy_direction")), (h, w))
    l4, v4 = l.reshape(-1, 1, 1, 3), v.reshape(1, 1, 1, 3)
    dv, cos_d, cl, cv = _microfacet(l4, v4, t, b, n, at[None], a[None])
    eta = float(params.get("ior", 1.5))
    f0 = ((eta - 1) / (eta + 1)) ** 2
    spec_col = _t(params.get("specular_color"))
    f0c = torch.full((1, h, w, 3), f0, dtype=torch.float64) if spec_col is None else (f0 * spec_col[None]).clamp(max=1)
    fr = f0c + (1 - f0c) * (1 - cos_d) ** 5
    diffuse = base[None] / math.pi
    trans = _t(params.get("transmission"))
    if trans is not None:
        diffuse = diffuse * (1 - trans[None])
    f = (1 - fr.amax(-1, keepdim=True)) * diffuse + fr * dv
    front = (cl > 0) & (cv > 0) & (l4[..., 2:3] > 0)
    out = torch.where(front, f * cl.clamp_min(0), torch.zeros_like(f))
    alpha = _t(params.get("alpha"))
    if alpha is not None:
        out = out * alpha[None]
    return out.numpy()


def _specular_maps(params: dict, h: int, w: int) -> MaterialMaps:
    """Our model's maps with a black albedo: its specular lobe alone (untinted), whose GGX,
    Smith and exact Fresnel are Standard Surface's (module docstring)."""
    rough = _t(params["specular_roughness"], torch.float32)
    aniso = params.get("specular_anisotropy")
    tangent = None
    if aniso is not None:
        aniso = _t(np.clip(np.asarray(aniso) / 0.9, 0, 1), torch.float32)
        tangent = _t(np.remainder(np.asarray(params["specular_rotation"]), 1.0), torch.float32)  # phi / pi
    eta = params.get("specular_IOR")
    ior = None if eta is None or np.isscalar(eta) else _t((np.asarray(eta) - 1.0) / 2.0, torch.float32)
    normal = _t(params.get("normal"), torch.float32)
    return MaterialMaps(albedo=torch.zeros(h, w, 3), roughness=rough, anisotropy=aniso, tangent=tangent,
                        normal=normal, ior=ior)


def _dir_albedo(maps: MaterialMaps, ior: float, view: Tensor, n_u: int = 16, n_phi: int = 32) -> Tensor:
    """``E(v) = integral of f_spec(l, v) (n.l) dl`` per pixel ``(H, W, 1)``, by importance sampling:
    stratified half vectors drawn from the isotropic GGX ``D(h) (n.h)`` of ``alpha = r^2`` about
    each pixel's normal (``tan^2 theta_h = alpha^2 u / (1 - u)``), ``l`` the mirror of ``v``,
    weight ``f cos / pdf_l`` with ``pdf_l = D (n.h) / (4 v.h)``.  Anisotropic lobes are evaluated
    exactly and sampled with their geometric-mean alpha (unbiased, slightly noisier)."""
    from dualscale.bsdf.ggx import ggx_d_iso
    from dualscale.bsdf.model import evaluate

    h, w = maps.shape
    alpha = (maps.roughness.double() ** 2).clamp_min(ALPHA_MIN)  # sqrt(alpha_t alpha_b) = r^2 (Burley)
    n = (maps.normal.double() if maps.normal is not None
         else torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(h, w, 3))
    helper = torch.where(n[..., 2:3].abs() < 0.9, torch.tensor([0.0, 0, 1], dtype=torch.float64),
                         torch.tensor([1.0, 0, 0], dtype=torch.float64))
    t = torch.linalg.cross(helper, n, dim=-1)
    t = t / t.norm(dim=-1, keepdim=True)
    b = torch.linalg.cross(n, t, dim=-1)
    v = view.double().reshape(1, 1, 3)
    total = torch.zeros(h, w, 3, dtype=torch.float64)
    for i in range(n_u):
        u = (i + 0.5) / n_u
        tan2 = alpha * alpha * u / (1 - u)
        cos_t = torch.rsqrt(1 + tan2)
        sin_t = torch.sqrt((1 - cos_t * cos_t).clamp_min(0))
        phi = (torch.arange(n_phi, dtype=torch.float64) + 0.5) / n_phi * 2 * math.pi
        c, s_ = torch.cos(phi).reshape(-1, 1, 1, 1), torch.sin(phi).reshape(-1, 1, 1, 1)
        hv = sin_t[None] * (c * t[None] + s_ * b[None]) + cos_t[None] * n[None]  # (P, H, W, 3)
        vh = (v[None] * hv).sum(-1, keepdim=True)
        l = 2 * vh * hv - v[None]
        ok = (l[..., 2:3] > 1e-4) & (vh > 0)
        l = torch.where(ok, l, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        f = evaluate(maps, l.float(), view.float(), maps.components(ior=ior), validate=False).double()
        pdf = ggx_d_iso(cos_t, alpha)[None] * cos_t[None] / (4 * vh.clamp_min(1e-9))
        total += torch.where(ok, f / pdf.clamp_min(1e-12), torch.zeros_like(f)).sum(0)
    return (total / (n_u * n_phi))[..., :1]


def standard_surface_bsdf(params: dict[str, np.ndarray | float | None], light_dirs: np.ndarray,
                          view: np.ndarray) -> np.ndarray:
    """Standard Surface BSDF times cosine (module docstring).  ``params`` use the input names of
    :mod:`.exr`: ``base_color``, ``specular_roughness``, ``specular_anisotropy`` / ``specular_rotation``
    (or None), ``specular_IOR`` (H, W) or float, ``specular_color`` or None, ``normal`` or None,
    ``subsurface`` (thin-walled) or None, ``opacity`` or None."""
    from dualscale.bsdf.model import evaluate

    l = torch.as_tensor(np.asarray(light_dirs), dtype=torch.float64)
    v = torch.as_tensor(np.asarray(view), dtype=torch.float64)
    _check(l, v)
    base = _t(params["base_color"])
    h, w = base.shape[:2]
    eta = params.get("specular_IOR")
    ior_const = float(eta) if eta is not None and np.isscalar(eta) else 1.5
    maps = _specular_maps(params, h, w)
    comps = maps.components(ior=ior_const)
    spec = evaluate(maps, l.float(), v.float(), comps).double()  # (L, H, W, 3) untinted, with n.l
    tint = _t(params.get("specular_color"))
    if tint is not None:
        spec = spec * tint[None]
    e_v = _dir_albedo(maps, ior_const, v)
    e_v = e_v if tint is None else e_v * tint
    n = _t(params.get("normal"))
    cl = (l.reshape(-1, 1, 1, 3) * (n[None] if n is not None else torch.tensor([0.0, 0, 1]).reshape(1, 1, 1, 3))
          ).sum(-1, keepdim=True).clamp_min(0)
    diffuse = base[None] / math.pi * (1 - e_v[None]).clamp_min(0) * cl
    trans = _t(params.get("subsurface"))
    if trans is not None:
        diffuse = diffuse * (1 - trans[None])
    out = diffuse + spec
    opacity = _t(params.get("opacity"))
    if opacity is not None:
        out = out * opacity[None]
    return out.numpy()


def principled_bsdf(params: dict[str, np.ndarray | float | None], light_dirs: np.ndarray,
                    view: np.ndarray) -> np.ndarray:
    """Principled BSDF times cosine (module docstring).  ``params`` as read from U3M
    (:func:`.readback.read_u3ma`): ``base_color`` (H, W, 3) linear, ``roughness``, ``anisotropy``,
    ``rotation`` (fraction of a full turn CCW from +u), ``normal`` or None, ``specular``
    (F0 / 0.08), ``specular_tint``, ``transmission``, ``alpha`` -- arrays (H, W) or floats."""
    from dualscale.bsdf.terms import diffuse as burley_diffuse

    l = torch.as_tensor(np.asarray(light_dirs), dtype=torch.float64)
    v = torch.as_tensor(np.asarray(view), dtype=torch.float64)
    _check(l, v)
    base = _t(params["base_color"])
    h, w = base.shape[:2]

    def field(key: str, default: float) -> Tensor:
        val = params.get(key, default)
        if val is None:
            val = default
        if np.isscalar(val):
            return torch.full((h, w, 1), float(val), dtype=torch.float64)
        return _t(val)

    r, a = field("roughness", 0.5), field("anisotropy", 0.0).clamp(0, 1)
    aspect = torch.sqrt(1 - 0.9 * a)
    at, ab = r * r / aspect, r * r * aspect
    phi = 2 * math.pi * field("rotation", 0.0)
    direction = torch.cat([torch.cos(phi), torch.sin(phi)], -1)
    t, b, n = _frame(_t(params.get("normal")), direction, (h, w))
    l4, v4 = l.reshape(-1, 1, 1, 3), v.reshape(1, 1, 1, 3)
    dv, cos_d, cl, cv = _microfacet(l4, v4, t, b, n, at[None], ab[None])
    lum = (base * torch.as_tensor(LUMINANCE, dtype=torch.float64)).sum(-1, keepdim=True)
    ctint = torch.where(lum > 1e-6, base / lum.clamp_min(1e-6), torch.ones_like(base))
    st = field("specular_tint", 0.0)
    f0 = 0.08 * field("specular", 0.5) * (1 - st + st * ctint)
    fr = f0[None] + (1 - f0[None]) * (1 - cos_d) ** 5
    clv = (l4 * v4).sum(-1, keepdim=True)
    diff = burley_diffuse(base[None], r[None], cl, cv, clv) * (1 - field("transmission", 0.0)[None])
    f = diff + fr * dv
    front = (cl > 0) & (cv > 0) & (l4[..., 2:3] > 0)
    out = torch.where(front, f * cl.clamp_min(0), torch.zeros_like(f)) * field("alpha", 1.0)[None]
    return out.numpy()


def relative_error(a: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per light ``(L,)``: ``sum |a - ref| / sum |ref|`` over pixels and channels."""
    a, ref = np.asarray(a, np.float64), np.asarray(ref, np.float64)
    axes = tuple(range(1, ref.ndim))
    return np.abs(a - ref).sum(axes) / np.maximum(np.abs(ref).sum(axes), 1e-12)
