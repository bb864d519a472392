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
#: how LM computes residuals and Jacobians (:class:`Preset` ``kernel``)
KERNELS = ("fused", "eager", "compiled")


@dataclass(frozen=True)
class Preset:
    """How to fit.  ``iterations``: per step; ``lr``: Adam learning rate (normalised units);
    ``light_batch``: LED images per Adam iteration (``None`` = all); ``grid_init``: LM presets
    search roughness x tangent per pixel before the specular step; ``led_stride``: use every
    n-th LED only; ``back_weight``: the back-lit image counts as that many LED images.

    ``loss``: 'l1' (sum of absolute residuals, the paper's loss; Adam always uses it) or 'l2'
    (sum of squares, LM only).  ``l1_eps``: LM's L1 reweighting floors ``|r|`` at this value
    (normalised image units, see :mod:`.lm`).

    ``coarse_factor`` > 1 (LM only): first fit images box-averaged over that many pixels per
    side for ``coarse_iterations`` (with ``grid_init`` and ``bounds``), then refine at full
    resolution for ``iterations`` from the upsampled maps (:mod:`.pyramid`).

    ``ior_prior_sd`` > 0 (LM only): MAP fit with a Gaussian prior of that sd (normalised units)
    on the IOR map, centred on eta 1.5 (:class:`.lm.Prior`); 0 is the maximum-likelihood fit.

    ``shadow_ratio`` > 0 (LM only): every iteration, set aside the captures of an LED whose
    diffuse-only (P90) capture is below that fraction of its render: a cast shadow, which the
    local model cannot produce (:meth:`.lm.Loss.keep`); 0 fits every capture.

    ``kernel`` computes the residuals and their derivatives: ``'fused'`` (every built-in preset's)
    is :mod:`.fused`, numba passes per pixel with analytic derivatives (LM: the normal equations;
    Adam: the gradient, :class:`.fused.Residuals`); ``'eager'`` is the reference, torch renders
    of whole maps (LM: forward-difference Jacobians; Adam: autograd); ``'compiled'`` (LM only)
    is the LM reference through ``torch.compile``d BSDF kernels (compiling costs seconds to a
    minute per distinct problem shape in a process, cached on disk by Inductor)."""

    name: str
    optimizer: str
    iterations: tuple[int, int, int]
    lr: float = 0.01
    light_batch: int | None = None
    bounds: tuple[Bound, ...] = PAPER_BOUNDS
    grid_init: bool = False
    led_stride: int = 1
    back_weight: float = 16.0
    loss: str = "l1"
    # half the median sensor-noise residual of the bench captures (2e-4): nearly every residual
    # is in the L1 regime, and exact zeros (black pixels, clamped peaks) keep a finite weight
    l1_eps: float = 1e-4
    coarse_factor: int = 1
    coarse_iterations: tuple[int, int, int] = (0, 0, 0)
    ior_prior_sd: float = 0.0
    kernel: str = "eager"
    shadow_ratio: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.shadow_ratio < 1.0 or (self.shadow_ratio > 0 and self.optimizer != "lm"):
            raise ValueError("shadow_ratio must be in [0, 1) and is implemented for the LM optimiser only")
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; choose from {KERNELS}")
        if self.kernel == "compiled" and self.optimizer != "lm":
            raise ValueError("the compiled kernel is implemented for the LM optimiser only")
        if self.ior_prior_sd < 0 or (self.ior_prior_sd > 0 and self.optimizer != "lm"):
            raise ValueError("ior_prior_sd must be >= 0 and is implemented for the LM optimiser only")
        if self.loss not in ("l1", "l2"):
            raise ValueError(f"unknown loss {self.loss!r}; choose 'l1' or 'l2'")
        if self.optimizer == "adam" and self.loss != "l1":
            raise ValueError("the Adam optimiser minimises the paper's L1 loss only")
        if self.coarse_factor > 1 and self.optimizer != "lm":
            raise ValueError("a coarse level is implemented for the LM optimiser only")

    @property
    def compiled(self) -> bool:
        """Whether the eager reference runs through ``torch.compile`` (``kernel='compiled'``)."""
        return self.kernel == "compiled"

    @property
    def total(self) -> int:
        return int(sum(self.iterations))

    def scaled(self, factor: float) -> "Preset":
        """Same preset with every step's iterations (and coarse level's) scaled: at least 1 each,
        a skipped step (0) stays skipped."""
        def sc(its: tuple[int, ...]) -> tuple[int, ...]:
            return tuple(max(1, round(i * factor)) if i else 0 for i in its)

        return replace(self, iterations=sc(self.iterations), coarse_iterations=sc(self.coarse_iterations))


#: sd of the LM presets' Gaussian prior on the normalised IOR map, centred on eta 1.5: eta sd
#: 0.1, so eta 1.3-1.7 is within 2 sd, the range of textile fibres and most finishes
IOR_PRIOR_SD = 0.05
#: an LED's diffuse capture below half its render is taken for a cast shadow (docs/FITTING.md)
SHADOW_RATIO = 0.5

PRESETS: dict[str, Preset] = {
    "paper": Preset("paper", "adam", (700, 500, 600), lr=0.01, loss="l1", kernel="fused"),
    # the joint step does the work: the first two only give it a start (docs/FITTING.md)
    "standard": Preset("standard", "lm", (3, 3, 15), grid_init=True, loss="l1", ior_prior_sd=IOR_PRIOR_SD,
                       shadow_ratio=SHADOW_RATIO, kernel="fused"),
    "draft": Preset("draft", "lm", (3, 3, 5), grid_init=True, led_stride=2, loss="l1", ior_prior_sd=IOR_PRIOR_SD,
                    shadow_ratio=SHADOW_RATIO, kernel="fused"),
    # measured slower than `standard` at equal accuracy (docs/FITTING.md); kept for comparison
    "coarse-to-fine": Preset("coarse-to-fine", "lm", (2, 2, 6), grid_init=True, loss="l1", coarse_factor=2,
                             coarse_iterations=(5, 5, 10), ior_prior_sd=IOR_PRIOR_SD, shadow_ratio=SHADOW_RATIO,
                             kernel="fused"),
    "adam-fast": Preset("adam-fast", "adam", (140, 100, 120), lr=0.03, light_batch=64, kernel="fused"),
}


# `standard` through the eager reference (forward differences), plain and torch.compile'd (docs/FITTING.md)
PRESETS["standard-compiled"] = replace(PRESETS["standard"], name="standard-compiled", kernel="compiled")


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return PRESETS[name]
