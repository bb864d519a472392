"""Synthetic materials with known ground truth, reproducible from a seed.

``generate(name, size, texel_mm, seed)`` for every name in :data:`MATERIALS`.
"""

from __future__ import annotations

from functools import partial
from typing import Callable

from dualscale.errors import InputError

from .common import SyntheticMaterial
from .fabrics import rib_knit, woven
from .surfaces import from_photo, leather

MATERIALS: dict[str, Callable[..., SyntheticMaterial]] = {
    "plain": partial(woven, "plain"),
    "twill": partial(woven, "twill"),
    "satin": partial(woven, "satin"),
    "denim": partial(woven, "denim"),
    "rib_knit": rib_knit,
    "leather": leather,
    "sheer": partial(woven, "plain", sheer=True, flyouts_per_mm2=4.0),
    "brick": partial(from_photo, "brick"),
    "grass": partial(from_photo, "grass"),
    "gravel": partial(from_photo, "gravel"),
}


def generate(name: str, size: int = 512, texel_mm: float = 0.0018, seed: int = 0) -> SyntheticMaterial:
    """Ground truth for material ``name`` at ``size`` x ``size`` texels of ``texel_mm``; bad
    arguments raise :class:`~dualscale.errors.InputError` (a ``ValueError``)."""
    if name not in MATERIALS:
        raise InputError(f"unknown material {name!r}; choose from {sorted(MATERIALS)}")
    if size < 8:
        raise InputError(f"size must be at least 8 texels, got {size}")
    if not texel_mm > 0:
        raise InputError(f"texel_mm must be positive, got {texel_mm}")
    return MATERIALS[name](size=size, texel_mm=texel_mm, seed=seed)


__all__ = ["MATERIALS", "SyntheticMaterial", "generate"]
