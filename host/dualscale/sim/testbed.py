"""Synthetic captures for the fly-out detector: what it reads, rendered by the virtual dome.

The detector (``dualscale.fit.flyouts``) needs the most orthogonal LED and the most grazing ring
under the analyser mode that passes the specular (relative P0).  ``flyout_views`` renders exactly
those from a synthetic material, optionally with the cast shadows of its relief and fibres, so the
test and the benchmark measure the detector on the same captures.
"""

from __future__ import annotations

import torch

from dualscale.geometry.cameras import micro_camera
from dualscale.geometry.dome import DomeGeometry
from .render import Analyzer, LightRealism, LightState, render


def flyout_leds(dome: DomeGeometry) -> list[int]:
    """The zenith LED, then every LED of the most grazing ring (ids)."""
    z = dome.led_dirs[:, 2]
    return [int(torch.argmax(z))] + [i for i in range(dome.n_leds) if z[i] <= z.min() + 1e-3]


def flyout_views(mat, texel_um: float, shadows: bool = True) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """``(images (N, H, W, 3), directions (N, 3), LED ids)`` of ``mat`` (a ``SyntheticMaterial``
    with square maps of ``texel_um`` micrometre texels) under :func:`flyout_leds` at relative P0
    (specular passed, diffuse halved), noiseless; ``shadows`` casts the shadows of
    ``mat.geometry``.  ``dualscale.fit.observations.Observations.relative_p0`` wraps them."""
    size = mat.maps.shape[0]
    dome, cam = DomeGeometry.from_regmap(), micro_camera(size, texel_um)
    ids = flyout_leds(dome)
    real = LightRealism(shadows=shadows)
    imgs = torch.stack([render(mat.maps, cam, LightState.led(i), dome, Analyzer(0.0, True), realism=real,
                               geometry=mat.geometry if shadows else None) for i in ids])
    return imgs, dome.led_dirs[ids].float(), ids
