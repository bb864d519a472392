"""Renders of the fit: the observations' images predicted from maps, clamped at 2.

The paper limits images and renders to a maximum of 2 (supplementary Sec. 4) so that
under-exposed specular peaks cannot dominate the fit; :func:`clamp_images` and
:func:`render_leds` apply that limit.  The specular Fresnel factor of LED images is ``R_s``
(S-polarised LEDs, weights from :mod:`.observations`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps, evaluate

from .observations import Observations

CLAMP = 2.0


def clamp_images(x: Tensor) -> Tensor:
    """The paper's limit: values above 2 become 2 (applied to images and renders alike)."""
    return torch.clamp(x, max=CLAMP)


def render_leds(maps: MaterialMaps, comps: Components, obs: Observations, light_chunk: int | None = 32,
                compiled: bool = False) -> Tensor:
    """Predicted LED images ``(N, H, W, 3)``, clamped at 2; ``compiled`` runs the BSDF kernel
    through ``torch.compile`` (``bsdf.evaluate``; the first call per shape compiles)."""
    f = evaluate(maps, obs.dirs, obs.view, comps, w_s=obs.w_s, w_p=obs.w_p, diffuse_weight=obs.w_d,
                 light_chunk=light_chunk, validate=False, compiled=compiled)
    return clamp_images(f)


def pixel_rows(images: Tensor) -> Tensor:
    """``(N, H, W, 3)`` image stack -> ``(H, W, 3 N)`` rows per pixel (image-major, then channel):
    the residual layout of the per-pixel solvers."""
    return images.permute(1, 2, 0, 3).reshape(*images.shape[1:3], -1)


def valid_rows(obs: Observations, back: bool, dtype: torch.dtype = torch.float32) -> Tensor | None:
    """1/0 weights ``(H, W, 3 N)`` of the residual rows in :func:`pixel_rows` layout, followed by
    the 3 back-lit rows when ``back``: 0 for a sample that is clipped or outside the sample
    mask (``obs.valid`` / ``obs.back_valid``); ``None`` when every sample is valid."""
    if obs.valid is None and (not back or obs.back_valid is None):
        return None
    n, (h, w) = obs.n, obs.shape
    v = obs.valid if obs.valid is not None else torch.ones((n, h, w), dtype=torch.bool)
    rows = v.permute(1, 2, 0).repeat_interleave(3, -1)
    if back:
        bv = obs.back_valid if obs.back_valid is not None else torch.ones((h, w), dtype=torch.bool)
        rows = torch.cat([rows, bv.unsqueeze(-1).expand(h, w, 3)], -1)
    return rows.to(dtype)


def render_back(maps: MaterialMaps, comps: Components, obs: Observations) -> Tensor | None:
    """Predicted back-lit image ``(H, W, 3)`` (``None`` without a back-lit capture); an opaque
    model predicts black."""
    if obs.backlight is None:
        return None
    if comps.opaque:
        return torch.zeros_like(obs.backlight)
    return clamp_images(obs.back_wd * (maps.transmittance * maps.opacity + 1.0 - maps.opacity))
