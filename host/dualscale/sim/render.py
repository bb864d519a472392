"""What a camera of the virtual dome sees: polarised rendering of a set of maps.

Units: an LED at intensity 1 delivers unit irradiance (measured normal to its direction) at the
dome centre; a back light or the diffuse group at intensity 1 has unit radiance.  The result
is linear scene radiance in the maps' colour space ("relative radiance, linear RGB").

Polarisation model (what the fit relies on):

* LED light is linearly polarised along the LED's polariser axis (S, see :mod:`.geometry`).
  Single-bounce specular keeps that polarisation with Fresnel factor ``R_s``; through an
  analyser it is scaled by Malus' law ``cos^2`` of the angle between the analyser and the
  polariser axis projected on the image plane -- 1 when aligned (P0), 0 when crossed (P90).
* Diffuse and transmitted light are depolarised: half passes any analyser.
* Unpolarised sources (diffuse group, back lights) reflect ``(R_s + R_p)/2``; through an
  analyser the S part follows Malus' law about the S axis and the P part about the P axis.

The Malus factor uses the camera's central viewing direction for every pixel (exact for the
orthographic micro camera, an approximation for the perspective cameras).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from dualscale.bsdf import MaterialMaps, evaluate
from dualscale.bsdf.maps import Components

from dualscale.geometry.cameras import Camera
from dualscale.geometry.dome import DomeGeometry, polarizer_axis
from .shadow import SurfaceGeometry, visibility


@dataclass(frozen=True)
class LightState:
    """Which sources are on, with intensities (fractions of full scale)."""

    leds: tuple[tuple[int, float], ...] = ()
    backlights: tuple[tuple[int, float], ...] = ()
    diffuse: float = 0.0

    @classmethod
    def led(cls, index: int, intensity: float = 1.0) -> "LightState":
        return cls(leds=((int(index), float(intensity)),))

    @classmethod
    def backlight(cls, index: int = 0, intensity: float = 1.0) -> "LightState":
        return cls(backlights=((int(index), float(intensity)),))

    @classmethod
    def diffuse_group(cls, intensity: float = 1.0) -> "LightState":
        return cls(diffuse=float(intensity))


@dataclass(frozen=True)
class Analyzer:
    """Linear analyser in front of the camera.  ``relative=True`` measures ``angle_deg`` from
    each LED's own polariser axis (0 = aligned/P0, 90 = crossed/P90) instead of the image +x."""

    angle_deg: float
    relative: bool = False


@dataclass(frozen=True)
class LightRealism:
    """Switchable light-side effects (all off by default).

    ``near_field``: per-pixel LED direction and inverse-square falloff from LEDs at
    ``radius_mm``; ``beam_exponent``: LED beam profile ``cos^k`` about its axis (0 = flat);
    ``led_gain_sigma``: relative std of a fixed per-LED irradiance error, drawn from ``seed``;
    ``shadows``: cast shadows of the sample's relief (needs ``render(..., geometry=...)``, see
    :mod:`.shadow`).
    """

    near_field: bool = False
    beam_exponent: float = 0.0
    led_gain_sigma: float = 0.0
    seed: int = 0
    shadows: bool = False

    def led_gains(self, n: int) -> Tensor:
        if self.led_gain_sigma <= 0:
            return torch.ones(n, dtype=torch.float64)
        g = torch.Generator().manual_seed(self.seed)
        return (1.0 + self.led_gain_sigma * torch.randn(n, generator=g, dtype=torch.float64)).clamp(min=0.0)


def sample_maps(maps: MaterialMaps, points_mm: Tensor, texel_mm: float) -> MaterialMaps:
    """Nearest-texel lookup of ``maps`` at sample-plane points ``(H, W, 2)``; the map is centred
    on the origin with ``texel_mm`` per texel and tiles periodically."""
    if texel_mm <= 0:
        raise ValueError("texel_mm must be positive")
    h, w = maps.shape
    col = torch.floor(points_mm[..., 0] / texel_mm + w / 2).long() % w
    row = torch.floor(h / 2 - points_mm[..., 1] / texel_mm).long() % h
    return replace(maps, **{k: v[row, col] for k, v in maps.items()})


def _malus(axis: Tensor, analyzer: Tensor, view: Tensor) -> Tensor:
    p = axis - (axis @ view)[..., None] * view
    p = p / p.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    return ((p @ analyzer) ** 2).clamp(0.0, 1.0)


def render(maps: MaterialMaps, camera: Camera, light: LightState, dome: DomeGeometry | None = None,
           analyzer: Analyzer | float | None = None, texel_mm: float | None = None,
           realism: LightRealism = LightRealism(), comps: Components | None = None,
           light_chunk: int | None = 16, geometry: SurfaceGeometry | None = None) -> Tensor:
    """Radiance image ``(H, W, 3)`` seen by ``camera`` (dtype/device of the maps).

    ``texel_mm=None`` requires the camera to be the micro camera at map resolution (texel =
    pixel); otherwise the maps are looked up with :func:`sample_maps`.  ``geometry`` is the
    sample's relief on the map grid, used when ``realism.shadows`` (map resolution only).
    """
    dome = DomeGeometry.from_regmap() if dome is None else dome
    if isinstance(analyzer, (int, float)):
        analyzer = Analyzer(float(analyzer))
    if analyzer is not None and not camera.has_analyzer:
        raise ValueError(f"camera {camera.name!r} has no analyser")
    dtype, dev = maps.albedo.dtype, maps.albedo.device
    pts, view = camera.pixel_geometry()
    if texel_mm is None:
        if camera.kind != "orthographic" or (camera.height, camera.width) != maps.shape:
            raise ValueError(f"maps are {maps.shape}, camera {camera.name!r} is {(camera.height, camera.width)}; "
                             "pass texel_mm to resample")
    else:
        maps = sample_maps(maps, pts.to(dev), texel_mm)
    if realism.shadows:
        if geometry is None:
            raise ValueError("realism.shadows needs the sample's geometry (render(..., geometry=...))")
        if texel_mm is not None or geometry.shape != maps.shape:
            raise ValueError(f"cast shadows are computed on the map grid {geometry.shape}: render with the micro "
                             "camera at map resolution (texel_mm=None)")
    comps = maps.components() if comps is None else comps
    _, _, fwd = camera.basis()
    axis_view = -fwd
    a_axis = camera.analyzer_axis(analyzer.angle_deg) if analyzer is not None else None
    view_t = view.to(dtype=dtype, device=dev)
    out = torch.zeros(*maps.shape, 3, dtype=dtype, device=dev)

    def shade(dirs: Tensor, scale: Tensor, w_s: Tensor, w_p: Tensor, w_d: float) -> Tensor:
        conv = dict(dtype=dtype, device=dev)
        vis = visibility(geometry, dirs).to(**conv).unsqueeze(-1) if realism.shadows else None
        if realism.near_field:
            pos = dirs * dome.radius_mm
            p3 = torch.cat([pts, torch.zeros_like(pts[..., :1])], -1)
            vec = pos[:, None, None, :] - p3[None]
            dist2 = (vec * vec).sum(-1, keepdim=True)
            l = vec / dist2.sqrt()
            fall = dome.radius_mm ** 2 / dist2
            if realism.beam_exponent > 0:
                fall = fall * ((l * dirs[:, None, None, :]).sum(-1, keepdim=True).clamp(min=0) ** realism.beam_exponent)
            f = evaluate(maps, l.to(**conv), view_t, comps, w_s=w_s.to(**conv), w_p=w_p.to(**conv),
                         diffuse_weight=w_d, light_chunk=light_chunk, validate=False)
            f = f if vis is None else f * vis
            return (f * fall.to(**conv) * scale.to(**conv).reshape(-1, 1, 1, 1)).sum(0)
        f = evaluate(maps, dirs.to(**conv), view_t, comps, w_s=w_s.to(**conv), w_p=w_p.to(**conv),
                     diffuse_weight=w_d, light_chunk=light_chunk, validate=False)
        f = f if vis is None else f * vis
        return torch.einsum("lhwc,l->hwc", f, scale.to(**conv))

    w_d = 0.5 if analyzer is not None else 1.0
    if light.leds:
        ids = torch.tensor([i for i, _ in light.leds])
        if bool(((ids < 0) | (ids >= dome.n_leds)).any()):
            raise ValueError(f"LED ids must be in 0..{dome.n_leds - 1}")
        dirs = dome.led_dirs[ids]
        scale = torch.tensor([s for _, s in light.leds], dtype=torch.float64) * realism.led_gains(dome.n_leds)[ids]
        if analyzer is None:
            t = torch.ones(len(ids), dtype=torch.float64)
        elif analyzer.relative:
            t = torch.cos(torch.deg2rad(torch.full((len(ids),), analyzer.angle_deg, dtype=torch.float64))) ** 2
        else:
            t = _malus(dome.polarizer_axes[ids], a_axis, axis_view)
        out = out + shade(dirs, scale, t, torch.zeros_like(t), w_d)
    if light.diffuse > 0:
        dirs = dome.led_dirs
        scale = dome.diffuse_weights() * light.diffuse
        if analyzer is None or analyzer.relative:
            ts = torch.full((dome.n_leds,), 0.5 if analyzer is None else 0.5, dtype=torch.float64)
            ws, wp = (0.5 * torch.ones_like(ts), 0.5 * torch.ones_like(ts)) if analyzer is None else (0.5 * ts, 0.5 * ts)
        else:
            ts = _malus(polarizer_axis(dirs, "s"), a_axis, axis_view)
            ws, wp = 0.5 * ts, 0.5 * (1.0 - ts)
        out = out + shade(dirs, scale, ws, wp, w_d)
    if light.backlights:
        if any(not 0 <= i < dome.n_backlights for i, _ in light.backlights):
            raise ValueError(f"back-light ids must be in 0..{dome.n_backlights - 1}")
        level = sum(s for _, s in light.backlights)
        if not comps.opaque:
            # uniform panel of radiance L below: int t/pi |l_z| L dw = t L through the fabric
            out = out + level * w_d * maps.transmittance * maps.opacity
            out = out + level * w_d * (1.0 - maps.opacity)  # seen directly through the holes
    return out
