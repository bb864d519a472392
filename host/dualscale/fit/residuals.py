"""What a fit leaves unexplained: the per-pixel residual map over the lights it was fitted on and
re-renders beside their captures (the evidence the digitize report shows; the held-out errors
come from the cross-validation pass of :mod:`.holdout`).

Conventions: images are linear radiance ``(N, H, W, 3)`` as in :mod:`.observations`, renders
are clamped at 2 like the fit (:mod:`.render`, supplementary Sec. 4).  The relative L1 error of
a set of images is ``sum |render - capture| / sum capture`` over valid samples (unclipped, inside
the sample mask when the observations carry one).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps

from .observations import Observations
from .render import clamp_images, render_leds

EPS = 1e-6


def _valid(obs: Observations) -> Tensor:
    v = getattr(obs, "valid", None)
    return torch.ones(obs.images.shape[:3], dtype=torch.bool) if v is None else v.bool()


def residual_map(maps: MaterialMaps, comps: Components, obs: Observations) -> Tensor:
    """``(H, W)`` float: per pixel, mean over lights and channels of ``|render - capture|``
    divided by the mean capture there (relative, unitless).  A pixel with no valid sample
    (outside the sample mask, or clipped under every light) is NaN: it was not fitted, and
    statistics of the residual must leave it out."""
    with torch.no_grad():
        pred = render_leds(maps.to(obs.images.dtype), comps, obs)
    cap = clamp_images(obs.images)
    w = _valid(obs).unsqueeze(-1).to(cap.dtype)
    err = ((pred - cap).abs() * w).sum((0, 3))
    ref = (cap * w).sum((0, 3))
    rel = torch.where(ref > EPS, err / ref.clamp_min(EPS), torch.zeros_like(ref))
    return torch.where(w[..., 0].sum(0) > 0, rel, torch.full_like(rel, float("nan")))


def relative_l1(pred: Tensor, cap: Tensor, valid: Tensor | None = None) -> float:
    """``sum |pred - cap| / sum cap`` over valid samples (``valid``: ``(..., H, W)`` bool)."""
    w = torch.ones_like(cap) if valid is None else valid.unsqueeze(-1).to(cap.dtype).expand_as(cap)
    den = float((cap.clamp_min(0) * w).sum())
    return float(((pred - cap).abs() * w).sum()) / max(den, EPS)


@dataclass
class LightView:
    """One light: its LED id, direction ``(3,)``, capture and render ``(H, W, 3)`` (linear
    radiance, clamped at 2; pixels that were never fitted -- outside the sample mask -- are 0 in
    both, since the maps there are start values), and the relative L1 error of the render over
    the valid samples."""

    led_id: int
    direction: list[float]
    capture: Tensor
    render: Tensor
    relative_l1: float


def light_views(maps: MaterialMaps, comps: Components, held: Observations) -> list[LightView]:
    """For every LED of ``held`` (increasing id), the image that passes the most specular (P0
    when polarised) beside its render by ``maps``.  Whether the light was held out of the fit
    that made ``maps`` is the caller's to say: the digitize fit stage renders lights of the
    final fit, which saw them."""
    with torch.no_grad():
        pred = render_leds(maps.to(held.images.dtype), comps, held)
    cap = clamp_images(held.images)
    valid = _valid(held)
    fitted = held.fitted_pixels
    if fitted is not None:
        keep = fitted.unsqueeze(-1).to(cap.dtype)
        pred, cap = pred * keep, cap * keep
    out: list[LightView] = []
    for led, k in _shown(held):
        out.append(LightView(led, [float(x) for x in held.dirs[k]], cap[k], pred[k],
                               relative_l1(pred[k], cap[k], valid[k])))
    return out


def _shown(held: Observations) -> list[tuple[int, int]]:
    """``(led id, image index)`` of each LED of ``held`` (increasing id): its image passing the
    most specular."""
    out = []
    for led in sorted(set(held.led_ids.tolist())):
        idx = [k for k, i in enumerate(held.led_ids.tolist()) if i == led]
        out.append((led, max(idx, key=lambda j: float(held.w_s[j]))))
    return out


def residual_by_bands(maps_root, comps: Components, origin, boxes: list[tuple[int, int, int, int]],
                      shape: tuple[int, int]) -> Tensor:
    """:func:`residual_map` ``(H, W)`` of a fit out of core (:mod:`.stream`): the maps under
    ``maps_root`` and the observations ``origin`` names (a :class:`~.observations.DatasetOrigin`)
    are read a part of ``boxes`` at a time, so that neither is held whole.  The same values as
    the whole-map function up to the renderer's float32 rounding, which may differ with the size
    of the tensor a pixel sits in."""
    from dualscale.formats.maps import load_maps

    from .observations import read_tile

    residual = torch.empty(shape, dtype=torch.float32)
    for y0, y1, x0, x1 in boxes:
        maps, _ = load_maps(maps_root, box=(y0, y1, x0, x1))
        residual[y0:y1, x0:x1] = residual_map(maps, comps, read_tile(origin, (y0, y1, x0, x1)))
    return residual


def views_by_bands(maps_root, comps: Components, origin, boxes: list[tuple[int, int, int, int]],
                   shape: tuple[int, int], leds: list[int]) -> list[LightView]:
    """:func:`light_views` of the LEDs ``leds`` for a fit out of core, read as in
    :func:`residual_by_bands` (one LED's images at a time); each view's two ``(H, W, 3)`` images
    are held whole."""
    from dataclasses import replace

    from dualscale.formats.maps import load_maps

    from .observations import read_tile

    h, w = shape
    views: list[LightView] = []
    for led in leds:
        one = replace(origin, leds=(int(led),))
        cap = torch.zeros((h, w, 3), dtype=torch.float32)
        ren = torch.zeros((h, w, 3), dtype=torch.float32)
        ok = torch.zeros((h, w), dtype=torch.bool)
        direction: list[float] = []
        for y0, y1, x0, x1 in boxes:
            maps, _ = load_maps(maps_root, box=(y0, y1, x0, x1))
            held = read_tile(one, (y0, y1, x0, x1))
            (v,) = light_views(maps, comps, held)
            k = _shown(held)[0][1]
            cap[y0:y1, x0:x1], ren[y0:y1, x0:x1], ok[y0:y1, x0:x1] = v.capture, v.render, _valid(held)[k]
            direction = v.direction
        views.append(LightView(int(led), direction, cap, ren, relative_l1(ren, cap, ok)))
    return views
