"""Small vector helpers shared by the BSDF terms.

Every quantity is channel-last and keeps its channel axis: directions are ``(..., 3)``,
scalars are ``(..., 1)``, RGB is ``(..., 3)``.  All helpers are differentiable with finite
gradients everywhere (the square roots and normalisations are guarded).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Guard added under square roots / denominators.  1e-12 is representable in float32 and
#: keeps d sqrt(x)/dx <= 5e5, which is finite in both precisions.
TINY = 1e-12


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last axis, keeping it: ``(..., 3) x (..., 3) -> (..., 1)``."""
    return (a * b).sum(dim=-1, keepdim=True)


def safe_sqrt(x: Tensor, eps: float = TINY) -> Tensor:
    """``sqrt(max(x, eps))``: finite value and gradient for any finite ``x``."""
    return torch.sqrt(torch.clamp(x, min=eps))


def safe_normalize(x: Tensor, eps: float = TINY) -> Tensor:
    """Unit vector along ``x`` (last axis); a zero vector maps to (almost) zero, not NaN."""
    return x * torch.rsqrt((x * x).sum(dim=-1, keepdim=True) + eps)


def check_finite(name: str, x: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` when ``x`` holds NaN or Inf."""
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or Inf values")
