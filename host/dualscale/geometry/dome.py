"""Dome light geometry.  The layout comes from ``dualscale.protocol.regmap`` (generated from
protocol/rig.toml) or from a calibration file of measured directions; nothing is restated here.

Frame: macro frame of the sample, ``+z`` = macro normal ``m`` (towards the micro camera),
``x``/``y`` = micro image axes; ``phi`` is counter-clockwise from ``+x``.  Directions point
from the sample towards the light.  LED ids run row by row (zenith first), and within a row by
increasing azimuth ``phi = phi0 + 360 k / count``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from dualscale.protocol import regmap


def _sph(theta_deg: float, phi_deg: float) -> tuple[float, float, float]:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return (math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t))


def ring_layout() -> list[tuple[int, float, float]]:
    """``(row, theta_deg, phi_deg)`` of every LED, from the regmap ring layout."""
    out = []
    for row, (count, theta, phi0) in enumerate(zip(regmap.DOME_COUNTS, regmap.DOME_THETA_DEG, regmap.DOME_PHI0_DEG)):
        for k in range(count):
            out.append((row, float(theta), float((phi0 + 360.0 * k / count) % 360.0)))
    if len(out) != regmap.N_LEDS:
        raise ValueError(f"regmap ring layout has {len(out)} LEDs, N_LEDS is {regmap.N_LEDS}")
    return out


def led_directions(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """Unit directions ``(N_LEDS, 3)`` of the nominal ring layout."""
    return torch.tensor([_sph(t, p) for _, t, p in ring_layout()], dtype=dtype, device=device)


def polarizer_axis(direction: Tensor, kind: str = regmap.DOME_POLARIZER) -> Tensor:
    """Transmission axis ``(..., 3)`` of each LED's linear polariser, a horizontal unit vector.

    ``'s'``: perpendicular to the plane of incidence (azimuth ``phi + 90 deg``); ``'p'``: in it
    (azimuth ``phi``).  The zenith LED has no plane of incidence; it gets the ``phi = 0`` axis.
    """
    xy = direction[..., :2]
    r = xy.norm(dim=-1, keepdim=True)
    e = torch.where(r > 1e-9, xy / r.clamp(min=1e-9), torch.tensor([1.0, 0.0], dtype=direction.dtype))
    z = torch.zeros_like(r)
    if kind == "s":
        return torch.cat([-e[..., 1:2], e[..., 0:1], z], -1)
    if kind == "p":
        return torch.cat([e, z], -1)
    raise ValueError(f"unknown polariser kind {kind!r} (expected 's' or 'p')")


@dataclass(frozen=True)
class DomeGeometry:
    """Directional LEDs (with polariser axes), back lights and the diffuse group.

    ``led_dirs`` ``(N, 3)`` float64 unit vectors; ``radius_mm`` is the LED distance used for
    near-field falloff.  Back lights sit under the sample (``-z``) and are modelled as uniform
    diffuse panels; the diffuse group lights the upper hemisphere through a depolarising
    diffuser and is rendered as the LED directions with solid-angle weights.
    """

    led_dirs: Tensor
    polarizer: str = regmap.DOME_POLARIZER
    radius_mm: float = regmap.DOME_RADIUS_MM
    n_backlights: int = regmap.N_BACKLIGHTS
    n_diffuse: int = regmap.N_DIFFUSE
    source: str = "regmap"

    @property
    def n_leds(self) -> int:
        return int(self.led_dirs.shape[0])

    @property
    def polarizer_axes(self) -> Tensor:
        return polarizer_axis(self.led_dirs, self.polarizer)

    def led_theta_phi_deg(self) -> Tensor:
        d = self.led_dirs
        th = torch.rad2deg(torch.acos(d[:, 2].clamp(-1, 1)))
        ph = torch.remainder(torch.rad2deg(torch.atan2(d[:, 1], d[:, 0])), 360.0)
        return torch.stack([th, ph], -1)

    def diffuse_weights(self) -> Tensor:
        """Solid angle [sr] of each LED's cell (its ring's band split evenly), summing to ``2 pi``:
        ``sum_i w_i f(l_i)`` approximates the response to a uniform dome of unit radiance."""
        th = self.led_theta_phi_deg()[:, 0]
        w = torch.ones_like(th)
        rows = torch.unique(th)
        for i, t in enumerate(rows):  # each ring covers the band midway to its neighbours
            lo = 0.0 if i == 0 else 0.5 * (rows[i - 1] + t)
            hi = 90.0 if i == len(rows) - 1 else 0.5 * (rows[i + 1] + t)
            band = 2 * math.pi * (math.cos(math.radians(lo)) - math.cos(math.radians(hi)))
            sel = th == t
            w[sel] = band / int(sel.sum())
        return w

    def signature(self) -> str:
        """Short identity of the layout (LED count, radius and source), e.g.
        ``127leds/r300mm/regmap``: the ``layout`` of a dataset's or calibration's ``rig`` record."""
        return f"{self.n_leds}leds/r{self.radius_mm:g}mm/{self.source}"

    @classmethod
    def from_regmap(cls) -> "DomeGeometry":
        return cls(led_directions(torch.float64))

    @classmethod
    def from_calibration(cls, path: str | Path) -> "DomeGeometry":
        """Load measured LED directions from JSON ``{"leds": [{"id": i, "direction": [x, y, z]}
        | {"id": i, "theta_deg": t, "phi_deg": p}, ...]}`` with ids 0..N_LEDS-1, each once."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"calibration file not found: {path}")
        try:
            data = json.loads(path.read_text())
            leds = data["leds"]
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise ValueError(f"{path}: not a dome calibration file ({e})") from e
        dirs: dict[int, tuple[float, float, float]] = {}
        for entry in leds:
            i = int(entry["id"])
            if "direction" in entry:
                d = [float(x) for x in entry["direction"]]
            else:
                d = list(_sph(float(entry["theta_deg"]), float(entry["phi_deg"])))
            n = math.sqrt(sum(x * x for x in d))
            if len(d) != 3 or not math.isfinite(n) or n == 0 or d[2] <= 0:
                raise ValueError(f"{path}: LED {i} has an invalid direction {d}")
            if i in dirs:
                raise ValueError(f"{path}: LED {i} listed twice")
            dirs[i] = (d[0] / n, d[1] / n, d[2] / n)
        if sorted(dirs) != list(range(regmap.N_LEDS)):
            raise ValueError(f"{path}: expected LED ids 0..{regmap.N_LEDS - 1}, got {len(dirs)} ids")
        return cls(torch.tensor([dirs[i] for i in range(regmap.N_LEDS)], dtype=torch.float64),
                   radius_mm=float(data.get("radius_mm", regmap.DOME_RADIUS_MM)), source=str(path))

    def to_calibration(self, path: str | Path) -> None:
        """Write the directions in the format :meth:`from_calibration` reads."""
        from dualscale.formats.atomic import write_json

        write_json(path, {"radius_mm": self.radius_mm, "leds": [
            {"id": i, "direction": [float(x) for x in d]} for i, d in enumerate(self.led_dirs)]})
