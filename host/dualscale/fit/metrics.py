"""Accuracy of a fit: map errors against ground truth and re-render SSIM on held-out lights.

Map errors are computed over the pixels where the ground truth has material (opacity > 0.5,
or every pixel for opaque materials); a map the fit left inactive counts as its neutral value
(anisotropy 0, IOR of ``comps.ior``, tint 0).  Units: albedo RMSE in linear reflectance;
normal errors in degrees; roughness, anisotropy and IOR MAE in normalised map units (IOR:
``eta = 1 + 2 v``, so 0.01 is 0.02 in eta).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps, map_from_ior

from .observations import Observations
from .render import clamp_images, render_leds


def normal_angle_deg(a: Tensor, b: Tensor) -> Tensor:
    """Angle between unit normals ``(..., 3)`` in degrees (atan2 form, exact near 0)."""
    cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    dot = (a * b).sum(-1)
    return torch.rad2deg(torch.atan2(cross, dot))


def _scalar(maps: MaterialMaps, name: str, neutral: float) -> Tensor:
    t = getattr(maps, name)
    return t if t is not None else torch.full((*maps.shape, 1), neutral, dtype=maps.albedo.dtype)


def map_errors(fit: MaterialMaps, gt: MaterialMaps, fit_ior: float = 1.5) -> dict[str, float]:
    """``albedo_rmse``, ``normal_mean_deg``, ``normal_p95_deg``, ``roughness_mae``,
    ``anisotropy_mae``, ``ior_mae`` (and ``transmittance_rmse`` and ``albedo_opacity_rmse``, the
    reflected ``opacity x albedo``, for translucent ground truth), over the ground truth's
    opaque texels (opacity > 0.5; all without an opacity map): :func:`error_values` reduced by
    :func:`reduce_errors`."""
    if fit.shape != gt.shape:
        raise ValueError(f"fit is {fit.shape}, ground truth {gt.shape}")
    return reduce_errors(error_values(fit, gt, fit_ior))


def error_values(fit: MaterialMaps, gt: MaterialMaps, fit_ior: float = 1.5) -> dict[str, Tensor]:
    """The per-texel terms of :func:`map_errors`, each a flat float64 tensor in row-major texel
    (then channel) order over the scored texels: ``albedo_sq``, ``normal_deg``,
    ``roughness_abs``, ``anisotropy_abs``, ``ior_abs`` (and ``transmittance_sq``,
    ``albedo_opacity_sq``).  A band of rows gives the rows' share of the whole map's, in order,
    so the bands' terms joined are the whole map's (:mod:`.score`)."""
    f = fit.to(torch.float64)
    g = gt.to(torch.float64)
    mask = (g.opacity[..., 0] > 0.5) if g.opacity is not None else torch.ones(g.shape, dtype=torch.bool)
    out = {"albedo_sq": ((f.albedo - g.albedo)[mask] ** 2).reshape(-1)}
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    nf = f.normal if f.normal is not None else up.expand(*f.shape, 3)
    ng = g.normal if g.normal is not None else up.expand(*g.shape, 3)
    out["normal_deg"] = normal_angle_deg(nf, ng)[mask].reshape(-1)
    out["roughness_abs"] = (f.roughness - g.roughness)[mask].abs().reshape(-1)
    out["anisotropy_abs"] = (_scalar(f, "anisotropy", 0.0) - _scalar(g, "anisotropy", 0.0))[mask].abs().reshape(-1)
    ior_f = _scalar(f, "ior", float(map_from_ior(fit_ior)))
    ior_g = _scalar(g, "ior", float(map_from_ior(1.5)))
    out["ior_abs"] = (ior_f - ior_g)[mask].abs().reshape(-1)
    if g.transmittance is not None:
        tf = f.transmittance if f.transmittance is not None else torch.zeros_like(g.transmittance)
        out["transmittance_sq"] = ((tf - g.transmittance)[mask] ** 2).reshape(-1)
    if g.opacity is not None:
        # a translucent texel reflects opacity x albedo; the split between the two is barely
        # observable (a lower opacity with a higher albedo and transmittance fits nearly as
        # well), so this product is the identifiable quantity
        of = f.opacity if f.opacity is not None else torch.ones_like(g.opacity)
        out["albedo_opacity_sq"] = ((of * f.albedo - g.opacity * g.albedo)[mask] ** 2).reshape(-1)
    return out


def reduce_errors(values: dict[str, Tensor]) -> dict[str, float]:
    """:func:`map_errors` from the terms of :func:`error_values` (flat float64 tensors; a memory
    map's will do): root means of the squares, means of the rest, and the normal angle's 95th
    percentile (``torch.quantile``, linear)."""
    v = values
    out = {"albedo_rmse": float(v["albedo_sq"].mean().sqrt()), "normal_mean_deg": float(v["normal_deg"].mean()),
           "normal_p95_deg": float(torch.quantile(v["normal_deg"], 0.95)),
           "roughness_mae": float(v["roughness_abs"].mean()), "anisotropy_mae": float(v["anisotropy_abs"].mean()),
           "ior_mae": float(v["ior_abs"].mean())}
    if "transmittance_sq" in v:
        out["transmittance_rmse"] = float(v["transmittance_sq"].mean().sqrt())
    if "albedo_opacity_sq" in v:
        out["albedo_opacity_rmse"] = float(v["albedo_opacity_sq"].mean().sqrt())
    return out


def ssim_images(pred: Tensor, ref: Tensor, valid: Tensor | None = None) -> np.ndarray:
    """SSIM per image of ``(N, H, W, 3)`` stacks (``skimage``, colour, Gaussian 7 px window
    or smaller for tiny images); the data range of each image is that of the reference, floored
    at 1e-3.  With ``valid`` ``(N, H, W)`` bool, invalid pixels of the reference take the
    prediction's value (so they add no error to their neighbours' windows), the range is taken
    over the valid pixels, and the mean of the SSIM map runs over the valid pixels only (an
    image without any scores NaN)."""
    from skimage.metrics import structural_similarity

    p = pred.detach().to(torch.float64).cpu().numpy()
    r = ref.detach().to(torch.float64).cpu().numpy()
    win = min(7, p.shape[1], p.shape[2])
    win = win if win % 2 == 1 else win - 1
    v = None if valid is None else valid.detach().cpu().numpy().astype(bool)
    out = []
    for k, (a, b) in enumerate(zip(p, r)):
        if v is None:
            rng = max(float(b.max() - b.min()), 1e-3)
            out.append(structural_similarity(a, b, data_range=rng, channel_axis=-1, win_size=win))
            continue
        ok = v[k]
        if not ok.any():
            out.append(float("nan"))
            continue
        b = np.where(ok[..., None], b, a)
        rng = max(float(b[ok].max() - b[ok].min()), 1e-3)
        _, s = structural_similarity(a, b, data_range=rng, channel_axis=-1, win_size=win, full=True)
        pad = (win - 1) // 2
        crop = (slice(pad, s.shape[0] - pad), slice(pad, s.shape[1] - pad))
        m = ok[crop]
        out.append(float(s[crop][m].mean()) if m.any() else float(s[ok].mean()))
    return np.asarray(out)


def rerender_ssim(maps: MaterialMaps, comps: Components, obs: Observations) -> float:
    """Mean SSIM between re-renders and the (clamped) images of ``obs`` (held-out lights), over
    the valid samples (``obs.valid``; images without one are skipped)."""
    with torch.no_grad():
        pred = render_leds(maps.to(obs.images.dtype), comps, obs)
    s = ssim_images(pred, clamp_images(obs.images), obs.valid)
    return float(np.nanmean(s)) if np.isfinite(s).any() else float("nan")


def image_losses(maps: MaterialMaps, comps: Components, obs: Observations) -> dict[str, float]:
    """Mean absolute and RMS error of the clamped re-renders of ``obs``, over its valid samples
    (``obs.valid``; NaN when there is none)."""
    with torch.no_grad():
        r = render_leds(maps.to(obs.images.dtype), comps, obs) - clamp_images(obs.images)
    if obs.valid is None:
        return {"l1": float(r.abs().mean()), "rmse": float((r * r).mean().sqrt())}
    sel = r[obs.valid]  # (M, 3)
    if sel.numel() == 0:
        return {"l1": float("nan"), "rmse": float("nan")}
    return {"l1": float(sel.abs().mean()), "rmse": float((sel * sel).mean().sqrt())}


def image_loss_sums(maps: MaterialMaps, comps: Components, obs: Observations) -> tuple[float, float, int]:
    """``(sum |r|, sum r^2, n)`` in float64 of the residuals ``r`` of :func:`image_losses` (each
    channel of each valid sample): they add over the bands or tiles of a map, and
    :func:`losses_from_sums` turns the totals into the whole map's ``l1`` and ``rmse``."""
    with torch.no_grad():
        r = (render_leds(maps.to(obs.images.dtype), comps, obs) - clamp_images(obs.images)).to(torch.float64)
    sel = r if obs.valid is None else r[obs.valid]
    return float(sel.abs().sum()), float((sel * sel).sum()), int(sel.numel())


def losses_from_sums(abs_sum: float, sq_sum: float, n: int) -> dict[str, float]:
    """``{"l1", "rmse"}`` of :func:`image_losses` from summed :func:`image_loss_sums` (NaN for
    ``n == 0``)."""
    if n == 0:
        return {"l1": float("nan"), "rmse": float("nan")}
    return {"l1": abs_sum / n, "rmse": (sq_sum / n) ** 0.5}
