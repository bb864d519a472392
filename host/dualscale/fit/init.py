"""Data-driven starting point shared by every preset.

Albedo and normal come from Lambertian photometric stereo on the diffuse-only images (P90 when
the dataset is polarised, else all LED images): per pixel, the luminance ``Y_k`` under light
``l_k`` is fitted as ``Y_k = g . l_k`` over lights that are well above the horizon and neither
black nor clipped (nor invalid, ``Observations.valid``), ``n = g / |g|``; then each channel's albedo is
``b_c = (pi / w_d) sum_k I_kc (n.l_k) / sum_k (n.l_k)^2``.  Pixels without enough usable lights
keep ``n = +z``.  Other maps start at mid-range values; the transmittance starts from the
back-lit image.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dualscale.bsdf import Components, square_from_normal

from .observations import Observations
from .params import PARAM_CHANNELS, param_names

DEFAULTS = {"roughness": 0.5, "anisotropy": 0.5, "tangent": 0.25, "ior": 0.25, "specular_tint": 0.5,
            "transmittance": 0.5, "opacity": 1.0}


def diffuse_images(obs: Observations) -> Observations:
    """The images without specular (P90) when available, else all."""
    if obs.has_polarisation:
        return obs.select(torch.nonzero(obs.w_s < 1e-6).flatten())
    return obs


def photometric_stereo(obs: Observations, min_z: float = 0.3, clip: float = 1.9) -> tuple[Tensor, Tensor]:
    """``(albedo (H, W, 3), normal (H, W, 3))`` from the diffuse-only images (see module doc)."""
    d = diffuse_images(obs)
    img = d.images.to(torch.float64)
    dirs = d.dirs.to(torch.float64)
    wd = d.w_d.to(torch.float64).reshape(-1, 1, 1, 1)
    y = (img / wd).mean(-1)  # (K, H, W) luminance per unit diffuse weight
    use = ((dirs[:, 2] >= min_z).reshape(-1, 1, 1) & (y > 1e-6) & ((img < clip).all(-1))).to(torch.float64)
    if d.valid is not None:  # clipped or outside the sample mask (observations.py)
        use = use * d.valid.to(torch.float64)
    a = torch.einsum("khw,ki,kj->hwij", use, dirs, dirs) + 1e-6 * torch.eye(3, dtype=torch.float64)
    b = torch.einsum("khw,khw,ki->hwi", use, y, dirs)
    g = torch.linalg.solve(a, b.unsqueeze(-1)).squeeze(-1)
    enough = use.sum(0) >= 3
    g = torch.where(enough.unsqueeze(-1) & (g[..., 2:3] > 1e-9), g, torch.tensor([0.0, 0.0, 1.0], dtype=g.dtype))
    n = g / g.norm(dim=-1, keepdim=True)
    n = torch.where(n[..., 2:3] < 0.05, torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype), n)
    n = n / n.norm(dim=-1, keepdim=True)
    cos = torch.clamp((dirs.reshape(-1, 1, 1, 3) * n.unsqueeze(0)).sum(-1), min=0.0) * use  # (K, H, W)
    num = torch.einsum("khwc,khw->hwc", img / wd, cos)
    den = (cos * cos).sum(0).unsqueeze(-1)
    albedo = torch.where(den > 1e-9, math.pi * num / den.clamp(min=1e-9), torch.full_like(num, 0.5))
    return albedo.clamp(0.0, 1.0).to(obs.images.dtype), n.to(obs.images.dtype)


#: share of the sample's pixels whose photometric-stereo albedo may reach 1 before the fit warns
BRIGHT_SHARE = 0.02


def check_albedo_range(obs: Observations, normal: Tensor) -> float:
    """Share of the sample's pixels (``obs.fitted_pixels``) whose albedo, estimated robustly at
    the start normals ``(H, W, 3)`` (per pixel, the median over the diffuse images lit at
    ``n.l > 0.3`` of ``pi max_c I_c / (w_d n.l)``, so that a few bright outliers do not count),
    is 1 or more; warns (``RuntimeWarning``) above :data:`BRIGHT_SHARE`: the images are brighter
    than relative radiance allows (light power or exposure unknown, as with photographs), the
    fit will clip those albedos at 1 and bend normals towards the lights to make up the
    brightness (docs/PHOTOS.md)."""
    bright, ok = albedo_counts(obs, normal)
    share = bright / ok if ok else 0.0
    warn_bright(share, obs.imported)
    return share


def albedo_counts(obs: Observations, normal: Tensor) -> tuple[int, int]:
    """``(bright, counted)``: of the sample's pixels with a robust albedo estimate (counted), those
    at 1 or more (:func:`check_albedo_range`, whose share is ``bright / counted``): the counts
    add over the bands of a fit out of core (:mod:`.stream`)."""
    d = diffuse_images(obs)
    y = (d.images / d.w_d.reshape(-1, 1, 1, 1)).amax(-1).to(torch.float64)  # (K, H, W)
    cos = torch.einsum("kc,hwc->khw", d.dirs.to(torch.float64), normal.to(torch.float64))
    use = cos > 0.3
    if d.valid is not None:
        use = use & d.valid
    ratio = torch.where(use, math.pi * y / cos.clamp(min=0.3), torch.full_like(y, float("nan")))
    med = ratio.nanmedian(0).values
    ok = torch.isfinite(med)
    if obs.fitted_pixels is not None:
        ok = ok & obs.fitted_pixels
    return int((med[ok] >= 1.0).sum()), int(ok.sum())


def warn_bright(share: float, imported: bool) -> None:
    """The warning of :func:`check_albedo_range` when ``share`` is above :data:`BRIGHT_SHARE`
    (``imported``: the photographs came from ``dualscale import``, which the advice names)."""
    if share > BRIGHT_SHARE:
        import warnings

        advice = ("These photographs came from `dualscale import`, which already scaled them by the lights: check "
                  "the import's --lights, --intensities and --transfer (docs/RADIOMETRY.md), and that the photographs "
                  "show one sample under those lights") if imported else (
                  "Import photographs with `dualscale import` (it sets the light scale) or give the lights their "
                  "intensity")
        warnings.warn(f"{100 * share:.0f} % of the pixels have a Lambertian albedo >= 1: the images are not "
                      "radiance relative to the lights (unknown light power or exposure?); the fit clips the albedo "
                      f"at 1. {advice}", RuntimeWarning, stacklevel=4)


def initial_params(obs: Observations, comps: Components) -> dict[str, Tensor]:
    """Starting parameters for ``comps`` (normalised units, normal as a square point); warns
    when the albedo would leave its box (:func:`check_albedo_range`)."""
    params, (bright, counted) = start_params(obs, comps)
    warn_bright(bright / counted if counted else 0.0, obs.imported)
    return params


def start_params(obs: Observations, comps: Components) -> tuple[dict[str, Tensor], tuple[int, int]]:
    """:func:`initial_params` without the warning, and the bright-albedo counts of
    :func:`albedo_counts` at the same photometric stereo: a part of a map (the fit out of core,
    :mod:`.stream`) returns its counts, and the whole map's share is warned about once."""
    albedo, normal = photometric_stereo(obs)
    return _params(obs, comps, albedo, normal), albedo_counts(obs, normal)


def _params(obs: Observations, comps: Components, albedo: Tensor, normal: Tensor) -> dict[str, Tensor]:
    h, w = obs.shape
    dt = obs.images.dtype
    out: dict[str, Tensor] = {}
    for name in param_names(comps):
        if name == "albedo":
            out[name] = albedo.clone()
        elif name == "normal":
            out[name] = square_from_normal(normal).clone()
        elif name == "transmittance" and obs.backlight is not None:
            out[name] = (obs.backlight / obs.back_wd).clamp(0.0, 1.0).to(dt).clone()
        else:
            out[name] = torch.full((h, w, PARAM_CHANNELS[name]), DEFAULTS[name], dtype=dt)
    return out
