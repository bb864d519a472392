"""Coarse-to-fine start for LM presets: fit box-downsampled images, upsample the maps.

A preset with ``coarse_factor = f > 1`` first runs its three steps for ``coarse_iterations`` on
the observations box-averaged over ``f x f`` pixel blocks (``f^2`` times fewer pixels, so each
LM iteration costs ``1/f^2``), with the preset's grid start and bounds schedule.  The
full-resolution fit then runs ``iterations`` (bounds schedule, no grid start) from:

* albedo, normal, transmittance, opacity: the usual full-resolution start (:mod:`.init`).
  Photometric stereo is pixel-exact on a Lambertian lobe, while a coarse pixel blends the
  shading of neighbouring yarns; starting from the coarse diffuse maps was measured worse;
* roughness, anisotropy, tangent, IOR, tint: per pixel, the best (lowest cost) of the coarse
  maps upsampled bilinearly and the four coarse cells around the pixel, in place of the grid.

Upsampling respects each parametrisation: normals are interpolated as unit vectors (then
renormalised and mapped back to the square), the axial tangent as the doubled-angle vector
``(cos 2 pi v, sin 2 pi v)`` (``v`` and ``v + 1`` are the same axis), the rest linearly, and
every map is clamped back into its box.

Measured (docs/FITTING.md): slower than ``standard`` at equal accuracy on our test bed.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from dualscale.bsdf import Components, normal_from_square, square_from_normal

from .init import initial_params
from .lm import cost, preset_loss
from .loop import step_data
from .observations import Observations
from .params import BOX, pack, params_from_maps, unpack
from .presets import STEP_FITS, Preset


def _pool(x: Tensor, factor: int) -> Tensor:
    """Box mean of ``(..., H, W, C)`` over ``factor`` blocks; edge blocks average only the
    pixels they hold (``ceil_mode``)."""
    lead, (h, w, c) = x.shape[:-3], x.shape[-3:]
    y = x.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    y = F.avg_pool2d(y, factor, factor, ceil_mode=True)
    return y.permute(0, 2, 3, 1).reshape(*lead, *y.shape[-2:], c)


def downsample(obs: Observations, factor: int) -> Observations:
    """The observations with LED and back-lit images box-averaged over ``factor x factor`` pixels
    (radiance per unit light intensity is preserved); lights and weights are unchanged.  With
    valid-sample masks, a block averages its valid pixels only and is valid if it has any."""
    if factor <= 1:
        return obs
    if obs.valid is None and obs.back_valid is None:
        back = None if obs.backlight is None else _pool(obs.backlight, factor)
        return replace(obs, images=_pool(obs.images, factor), backlight=back, pixel_mm=None if obs.pixel_mm is None else obs.pixel_mm * factor)
    imgs, valid = _pool_valid(obs.images, obs.valid, factor)
    back, bv = (None, None) if obs.backlight is None else _pool_valid(obs.backlight, obs.back_valid, factor)
    return replace(obs, images=imgs, backlight=back, pixel_mm=None if obs.pixel_mm is None else obs.pixel_mm * factor, valid=valid, back_valid=bv)


def _pool_valid(x: Tensor, valid: Tensor | None, factor: int) -> tuple[Tensor, Tensor]:
    """Box mean of ``(..., H, W, C)`` over the valid pixels of each block, and the blocks'
    validity ``(..., h, w)`` (any valid pixel)."""
    v = torch.ones(x.shape[:-1], dtype=x.dtype) if valid is None else valid.to(x.dtype)
    num, den = _pool(x * v.unsqueeze(-1), factor), _pool(v.unsqueeze(-1), factor)
    return torch.where(den > 0, num / den.clamp(min=1e-12), torch.zeros_like(num)), den[..., 0] > 0


def _bilinear(x: Tensor, factor: int, shape: tuple[int, int], skip: int = 0) -> Tensor:
    """``(h, w, C)`` -> ``(H, W, C)``: coarse cell ``i`` covers fine pixels ``[i f, (i + 1) f)``;
    bilinear with edge clamping, the fine rows ``skip .. skip + H - 1`` and columns ``0 .. W - 1``
    of the ``(h f, w f)`` result."""
    y = x.permute(2, 0, 1).unsqueeze(0)
    y = F.interpolate(y, scale_factor=factor, mode="bilinear", align_corners=False)
    return y[0, :, skip:skip + shape[0], :shape[1]].permute(1, 2, 0).contiguous()


def upsample_params(params: dict[str, Tensor], factor: int, shape: tuple[int, int],
                    skip: int = 0) -> dict[str, Tensor]:
    """Fit parameters (normalised maps, normal as a square point) upsampled to ``shape``; with
    ``skip``, the fine rows from ``skip`` on (a band of the map: :func:`start_from_coarse`)."""
    out: dict[str, Tensor] = {}
    for name, t in params.items():
        if name == "normal":
            n = _bilinear(normal_from_square(t), factor, shape, skip)
            n = torch.cat([n[..., :2], n[..., 2:].clamp(min=0.0)], -1)  # mixes of upper normals stay upper
            out[name] = square_from_normal(n).clamp(*BOX["normal"])
        elif name == "tangent":
            a = 2.0 * math.pi * t
            v = _bilinear(torch.cat([torch.cos(a), torch.sin(a)], -1), factor, shape, skip)
            out[name] = torch.remainder(torch.atan2(v[..., 1:], v[..., :1]) / (2.0 * math.pi), 1.0)
        else:
            out[name] = _bilinear(t, factor, shape, skip).clamp(*BOX.get(name, (0.0, 1.0)))
    return out


def coarse_preset(preset: Preset) -> Preset:
    """The coarse level of ``preset``: its grid start, bounds schedule and loss for
    ``coarse_iterations``, on observations already strided to its LEDs."""
    return replace(preset, name=f"{preset.name}/coarse", iterations=preset.coarse_iterations, coarse_factor=1,
                   led_stride=1)


def fine_preset(preset: Preset) -> Preset:
    """The full-resolution level: ``iterations`` with the bounds schedule and no grid start (the
    coarse maps replace it); the identity for a preset without a coarse level."""
    if preset.coarse_factor <= 1:
        return preset
    return replace(preset, grid_init=False, coarse_factor=1)


def start_from_coarse(coarse_maps, obs: Observations, preset: Preset, comps: Components,
                      rows: tuple[int, int] = (0, 0), base: dict[str, Tensor] | None = None) -> dict[str, Tensor]:
    """Starting parameters for the full-resolution fit from the maps of the coarse fit
    (``fit_observations(downsample(obs, f), coarse_preset(preset), ...)``; see the module
    docstring).  ``base``: the usual start of ``obs`` (default :func:`.init.initial_params`,
    which warns about the albedo range).

    A band of full rows (the fit out of core, :mod:`.stream_coarse`): ``obs`` holds the map's
    rows from ``rows[0]`` (a multiple of ``f``), ``coarse_maps`` the coarse rows from
    ``rows[1]`` on, at least those the band's bilinear and nearest cells read (its coarse rows
    and one cell above and below, where the map has them: :func:`coarse_rows`).  Each fine pixel
    then gets the whole map's values: the same cells, and the same interpolation weights, which
    depend on the pixel's row within its ``f``-block only (exact for ``f`` a power of two)."""
    f = preset.coarse_factor
    y0, c0 = rows
    cp = params_from_maps(coarse_maps, comps)
    base = initial_params(obs, comps) if base is None else base
    skip = y0 - c0 * f
    cands = [upsample_params(cp, f, obs.shape, skip)] + [_nearest(cp, f, obs.shape, dy, dx, y0, c0)
                                                         for dy in (0, 1) for dx in (0, 1)]
    cands = [{k: (c[k] if k in STEP_FITS["specular"] else base[k]) for k in base} for c in cands]
    return best_per_pixel(cands, obs, comps, preset)


def coarse_rows(y0: int, y1: int, factor: int, coarse_h: int) -> tuple[int, int]:
    """``(c0, c1)``: the coarse rows (``c1`` excluded) of a ``coarse_h``-row coarse map that the
    fine rows ``y0 .. y1 - 1`` read in :func:`start_from_coarse` (bilinear corners and nearest
    cells): their own and a one-cell halo above and below, within the map."""
    return max(0, y0 // factor - 1), min(coarse_h, -(-y1 // factor) + 1)


def _nearest(params: dict[str, Tensor], factor: int, shape: tuple[int, int], dy: int, dx: int,
             y0: int = 0, c0: int = 0) -> dict[str, Tensor]:
    """Each fine pixel takes the values of one of the four coarse cells around its centre
    (the bilinear corners: ``dy, dx`` in {0, 1}); ``y0``, ``c0``: the map rows of the first fine
    row and coarse row given (a band, :func:`start_from_coarse`)."""
    h, w = next(iter(params.values())).shape[:2]
    iy = ((torch.floor((torch.arange(y0, y0 + shape[0]) + 0.5) / factor - 0.5).long() + dy).clamp(min=0) - c0)
    iy = iy.clamp(0, h - 1)
    ix = (torch.floor((torch.arange(shape[1]) + 0.5) / factor - 0.5).long() + dx).clamp(0, w - 1)
    return {k: v[iy][:, ix].clone() for k, v in params.items()}


def best_per_pixel(cands: list[dict[str, Tensor]], obs: Observations, comps: Components,
                   preset: Preset) -> dict[str, Tensor]:
    """Per pixel, the candidate parameter set with the lowest cost on all images (the preset's
    loss).  At a yarn boundary a fine pixel then takes the coarse cell of its own yarn rather
    than a blend of two tangents."""
    names = tuple(cands[0])
    data, loss = step_data(obs, "joint"), preset_loss(preset)
    best_x, best_c = None, None
    for cand in cands:
        x = pack(cand, names)
        c = cost(x, names, {}, comps, data, loss)
        if best_x is None or best_c is None:
            best_x, best_c = x, c
        else:
            best_x = torch.where((c < best_c).unsqueeze(-1), x, best_x)
            best_c = torch.minimum(c, best_c)
    return {k: v.clone() for k, v in unpack(best_x, names).items()}
