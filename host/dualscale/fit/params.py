"""Fit parameters: the normalised maps as free tensors, their bounds and schedules.

Every map is optimised directly in its normalised unit (see ``dualscale.bsdf.maps``), kept
inside its box by projection after each update.  The normal is optimised as a point of the
square ``[-1, 1]^2`` (Fong's elliptical grid mapping, ``normal_from_square``), so every square
point is a valid upper-hemisphere normal.  The tangent is axial (value ``v`` and ``v + 1``
give the same frame), so it wraps instead of being clamped.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps, normal_from_square, square_from_normal

#: parameter name -> channels (``normal`` is the 2-channel square point)
PARAM_CHANNELS: dict[str, int] = {"albedo": 3, "roughness": 1, "anisotropy": 1, "tangent": 1, "normal": 2,
                                  "ior": 1, "specular_tint": 1, "transmittance": 3, "opacity": 1}
#: static box of every parameter (normalised units)
BOX: dict[str, tuple[float, float]] = {"normal": (-1.0, 1.0)}


@dataclass(frozen=True)
class Bound:
    """``kind`` ('min' or 'max') ``value`` on map ``name`` while progress < ``until`` (fraction
    of all iterations of the fit)."""

    name: str
    kind: str
    value: float
    until: float


#: the paper's schedule (supplementary Sec. 4), on the normalised maps
PAPER_BOUNDS: tuple[Bound, ...] = (
    Bound("roughness", "min", 0.3, 0.6),
    Bound("ior", "min", 0.1, 0.8),
    Bound("anisotropy", "min", 0.1, 0.9),
    Bound("anisotropy", "max", 0.9, 0.8),
)


def param_names(comps: Components) -> tuple[str, ...]:
    """Free parameters for ``comps`` (the fit always maps normals and IOR per pixel)."""
    return tuple(comps.required_maps())


def fit_components(opaque: bool, isotropic: bool, tinted: bool, ior: float = 1.5) -> Components:
    return Components(opaque=opaque, isotropic=isotropic, tinted=tinted, normal_mapped=True, ior_mapped=True, ior=ior)


def bounds_at(progress: float, schedule: tuple[Bound, ...]) -> dict[str, tuple[float, float]]:
    """``name -> (lo, hi)`` in force at ``progress`` in [0, 1]."""
    out: dict[str, tuple[float, float]] = {}
    for b in schedule:
        if progress < b.until:
            lo, hi = out.get(b.name, BOX.get(b.name, (0.0, 1.0)))
            out[b.name] = (max(lo, b.value), hi) if b.kind == "min" else (lo, min(hi, b.value))
    return out


def project(params: dict[str, Tensor], bounds: dict[str, tuple[float, float]]) -> None:
    """In place: wrap the tangent, clamp the rest into their box and the scheduled bounds;
    non-finite values (never expected) are reset to the box centre."""
    with torch.no_grad():
        for name, t in params.items():
            lo, hi = BOX.get(name, (0.0, 1.0))
            if not bool(torch.isfinite(t).all()):
                t.copy_(torch.where(torch.isfinite(t), t, torch.full_like(t, 0.5 * (lo + hi))))
            if name == "tangent":
                t.copy_(torch.remainder(t, 1.0))
                continue
            blo, bhi = bounds.get(name, (lo, hi))
            t.clamp_(max(lo, blo), min(hi, bhi))


def to_maps(params: dict[str, Tensor], fixed: dict[str, Tensor] | None = None) -> MaterialMaps:
    """``MaterialMaps`` from free (and frozen) parameters; the normal goes through Fong's mapping."""
    allp = {**(fixed or {}), **params}
    kw = {k: v for k, v in allp.items() if k != "normal"}
    if "normal" in allp:
        kw["normal"] = normal_from_square(allp["normal"])
    return MaterialMaps(**kw)


def params_from_maps(maps: MaterialMaps, comps: Components) -> dict[str, Tensor]:
    """Inverse of :func:`to_maps` for the parameters ``comps`` needs (missing maps get defaults)."""
    h, w = maps.shape
    like = maps.albedo
    defaults = {"roughness": 0.5, "anisotropy": 0.5, "tangent": 0.25, "ior": 0.25, "specular_tint": 0.5,
                "transmittance": 0.5, "opacity": 1.0}
    out = {}
    for name in param_names(comps):
        if name == "normal":
            n = maps.normal if maps.normal is not None else torch.tensor([0.0, 0.0, 1.0]).to(like).expand(h, w, 3)
            out[name] = square_from_normal(n).clone()
        else:
            t = getattr(maps, name)
            out[name] = (t.clone() if t is not None else torch.full((h, w, PARAM_CHANNELS[name]), defaults[name])
                         .to(like))
    return out


def pack(params: dict[str, Tensor], names: tuple[str, ...]) -> Tensor:
    """Concatenate ``names`` along channels: ``(H, W, P)``."""
    return torch.cat([params[n] for n in names], -1)


def unpack(x: Tensor, names: tuple[str, ...]) -> dict[str, Tensor]:
    out, c = {}, 0
    for n in names:
        k = PARAM_CHANNELS[n]
        out[n] = x[..., c:c + k]
        c += k
    return out
