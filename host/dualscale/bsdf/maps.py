"""Canonical SVBSDF map names, layouts and value conventions.

In memory every map is a float tensor ``(H, W, C)`` (channel-last, like the terms).  On disk
(see ``dualscale.formats.maps``) each map is one EXR file ``<name>.exr`` with the same values.

=============== == ============================================================================
name            C  meaning
=============== == ============================================================================
albedo          3  diffuse albedo ``b``, linear RGB (scene-referred, no sRGB curve), [0, 1]
roughness       1  ``sigma_r`` in [0, 1]
anisotropy      1  ``alpha`` in [0, 1] (0 = isotropic)
tangent         1  major anisotropy axis, normalised: azimuth ``phi_t = pi * value`` [rad] CCW
                   from image +x; the axis is a line, so value 0 and 1 are the same direction
normal          3  unit micro normal ``(x, y, z)``, ``z >= 0``, in the macro frame
ior             1  normalised IOR: ``eta = 1 + 2 * value`` (value 0.25 -> 1.5), range [1, 3]
specular_tint   1  ``rho_s`` in [0, 1]
transmittance   3  diffuse transmittance ``t``, linear RGB, [0, 1]
opacity         1  coverage in [0, 1]; ``1 - opacity`` of a pixel is a hole (light passes)
=============== == ============================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

MAP_CHANNELS: dict[str, int] = {
    "albedo": 3, "roughness": 1, "anisotropy": 1, "tangent": 1, "normal": 3,
    "ior": 1, "specular_tint": 1, "transmittance": 3, "opacity": 1,
}
MAP_NAMES: tuple[str, ...] = tuple(MAP_CHANNELS)
IOR_MIN, IOR_MAX = 1.0, 3.0
DEFAULT_IOR = 1.5
#: the diffuse lobes :class:`Components` can ask for: ``"burley"`` is the paper's (supplementary
#: Sec. 5: Burley's diffuse with its Schlick grazing factors plus the retro-reflection term, which
#: reads the roughness map); ``"lambert"`` is ``b / pi``, no angular dependence and no roughness
DIFFUSE_MODELS = ("burley", "lambert")


def ior_from_map(value: Tensor | float) -> Tensor | float:
    """Normalised IOR map value in [0, 1] -> ``eta = 1 + 2 value`` in [1, 3]."""
    return IOR_MIN + (IOR_MAX - IOR_MIN) * value


def map_from_ior(eta: Tensor | float) -> Tensor | float:
    """Inverse of :func:`ior_from_map`."""
    return (eta - IOR_MIN) / (IOR_MAX - IOR_MIN)


def tangent_angle_from_map(value: Tensor) -> Tensor:
    """Normalised tangent map -> azimuth [rad]."""
    return math.pi * value


def map_from_tangent_angle(angle: Tensor) -> Tensor:
    """Azimuth [rad] -> normalised tangent map in [0, 1) (axial: angle modulo pi)."""
    return torch.remainder(angle, math.pi) / math.pi


@dataclass(frozen=True)
class Components:
    """Which parts of the model a scene needs; the renderer computes only these.

    ``opaque``: no transmittance/opacity maps.  ``isotropic``: no anisotropy/tangent maps
    (and no tangent frame).  ``tinted``: a specular-tint map is used (else the specular lobe
    is white).  ``normal_mapped``: a normal map is used (else ``n = m``).  ``ior_mapped``: an
    IOR map is used (else the constant ``ior``).  ``diffuse``: the diffuse lobe, one of
    :data:`DIFFUSE_MODELS` (``"burley"``, the paper's, by default; ``"lambert"`` ignores the
    roughness map in the diffuse term, which the specular lobe, when there is one, still reads).
    """

    opaque: bool = True
    isotropic: bool = True
    tinted: bool = False
    normal_mapped: bool = False
    ior_mapped: bool = False
    ior: float = DEFAULT_IOR
    diffuse: str = "burley"

    def __post_init__(self) -> None:
        if self.diffuse not in DIFFUSE_MODELS:
            raise ValueError(f"unknown diffuse model {self.diffuse!r}; choose from {DIFFUSE_MODELS}")

    @property
    def lambertian(self) -> bool:
        """True when the diffuse lobe is Lambert's ``b / pi``."""
        return self.diffuse == "lambert"

    def required_maps(self) -> tuple[str, ...]:
        names = ["albedo", "roughness"]
        if not self.isotropic:
            names += ["anisotropy", "tangent"]
        if self.normal_mapped:
            names.append("normal")
        if self.ior_mapped:
            names.append("ior")
        if self.tinted:
            names.append("specular_tint")
        if not self.opaque:
            names += ["transmittance", "opacity"]
        return tuple(names)


@dataclass
class MaterialMaps:
    """A set of SVBSDF maps ``(H, W, C)``; a map that is ``None`` is inactive."""

    albedo: Tensor
    roughness: Tensor
    anisotropy: Tensor | None = None
    tangent: Tensor | None = None
    normal: Tensor | None = None
    ior: Tensor | None = None
    specular_tint: Tensor | None = None
    transmittance: Tensor | None = None
    opacity: Tensor | None = None

    def items(self) -> list[tuple[str, Tensor]]:
        return [(f.name, getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None]

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.albedo.shape[0]), int(self.albedo.shape[1])

    def components(self, ior: float = DEFAULT_IOR) -> Components:
        """The :class:`Components` implied by which maps are present."""
        return Components(
            opaque=self.transmittance is None and self.opacity is None,
            isotropic=self.anisotropy is None and self.tangent is None,
            tinted=self.specular_tint is not None,
            normal_mapped=self.normal is not None,
            ior_mapped=self.ior is not None,
            ior=ior,
        )

    def to(self, *args, **kwargs) -> "MaterialMaps":
        return replace(self, **{k: v.to(*args, **kwargs) for k, v in self.items()})

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "MaterialMaps":
        return replace(self, **{k: v[y0:y1, x0:x1] for k, v in self.items()})


def validate_maps(maps: MaterialMaps, comps: Components | None = None) -> None:
    """Raise ``ValueError`` on wrong shapes, mismatched sizes, NaN/Inf, or a map that the
    components need but is missing."""
    h, w = maps.shape
    for name, t in maps.items():
        c = MAP_CHANNELS[name]
        if t.ndim != 3 or t.shape[-1] != c:
            raise ValueError(f"map {name!r} must have shape (H, W, {c}), got {tuple(t.shape)}")
        if tuple(t.shape[:2]) != (h, w):
            raise ValueError(f"map {name!r} is {tuple(t.shape[:2])}, expected {(h, w)} like albedo")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"map {name!r} contains NaN or Inf")
    if comps is not None:
        missing = [n for n in comps.required_maps() if getattr(maps, n) is None]
        if missing:
            raise ValueError(f"components {comps} need maps {missing}")
