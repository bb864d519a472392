"""Fit presets: the paper's procedure and faster alternatives.

Every preset runs the same three steps (what each fits is documented in docs/FITTING.md):

1. ``diffuse``  -- albedo, normal (and transmittance, opacity) from the diffuse-only images
   (P90, where the crossed analyser blocks the specular) and the back-lit image;
2. ``specular`` -- roughness, anisotropy, tangent, IOR and specular tint from all LED images
   with the diffuse maps frozen;
3. ``joint``    -- every map from every image.

Bounds follow the paper's schedule (``params.PAPER_BOUNDS``) as fractions of a preset's total
iterations.  ``optimizer='adam'`` is the paper's first-order fit of whole maps;
``optimizer='lm'`` is a per-pixel Levenberg-Marquardt (pixels are independent: there is no
spatial term), see :mod:`.lm`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from .params import PAPER_BOUNDS, Bound

STEP_NAMES = ("diffuse", "specular", "joint")
STEP_FITS: dict[str, tuple[str, ...]] = {
    "diffuse": ("albedo", "normal", "transmittance", "opacity"),
    "specular": ("roughness", "anisotropy", "tangent", "ior", "specular_tint"),
    "joint": ("albedo", "normal", "transmittance", "opacity", "roughness", "anisotropy", "tangent", "ior",
              "specular_tint"),
}
STEP_DATA = {"diffuse": "diffuse", "specular": "all", "joint": "all"}


@dataclass(frozen=True)
class Preset:
    """How to fit.  ``iterations``: per step; ``lr``: Adam learning rate (normalised units);
    ``light_batch``: LED images per Adam iteration (``None`` = all); ``grid_init``: LM presets
    search roughness x tangent per pixel before the specular step; ``led_stride``: use every
    n-th LED only."""

    name: str
    optimizer: str
    iterations: tuple[int, int, int]
    lr: float = 0.01
    light_batch: int | None = None
    bounds: tuple[Bound, ...] = PAPER_BOUNDS
    grid_init: bool = False
    led_stride: int = 1
    back_weight: float = 16.0

    @property
    def total(self) -> int:
        return int(sum(self.iterations))

    def scaled(self, factor: float) -> "Preset":
        """Same preset with every step's iterations scaled (at least 1 each)."""
        return replace(self, iterations=tuple(max(1, round(i * factor)) for i in self.iterations))


PRESETS: dict[str, Preset] = {
    "paper": Preset("paper", "adam", (700, 500, 600), lr=0.01),
    "standard": Preset("standard", "lm", (5, 5, 10), grid_init=True),
    "draft": Preset("draft", "lm", (3, 3, 5), grid_init=True, led_stride=2),
    "adam-fast": Preset("adam-fast", "adam", (140, 100, 120), lr=0.03, light_batch=64),
}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return PRESETS[name]
