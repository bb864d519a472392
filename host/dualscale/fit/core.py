"""Fit driver: one preset, one set of components, one set of observations -> maps."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps

from .checkpoint import Checkpointer, fingerprint
from .init import initial_params
from .lm import run_lm
from .loop import Loop
from .metrics import image_losses, rerender_ssim
from .observations import Observations, stride_leds
from .optimize import run_adam
from .params import to_maps
from .presets import Preset
from .uncertainty import Gather, Uncertainty, pixel_uncertainty
from .pyramid import coarse_preset, downsample, fine_preset, start_from_coarse


@dataclass
class FitResult:
    """Fitted maps plus what produced them (all JSON-able except the tensors)."""

    maps: MaterialMaps
    comps: Components
    preset: Preset
    iterations: int
    seconds: float
    losses: dict[str, float]
    history: list = field(default_factory=list)
    resumed_from: int = 0
    #: the maps' per-pixel uncertainty (:class:`.uncertainty.Uncertainty`); ``None`` when not computed
    uncertainty: Uncertainty | None = None


def split_holdout(obs: Observations, every: int = 8, offset: int = 3) -> tuple[Observations, Observations | None]:
    """``(train, held_out)``: every ``every``-th distinct LED (from ``offset``) is held out, with
    all its analyser images; ``held_out`` is ``None`` when ``every <= 0`` or nothing (or
    everything) would be held out.  LED ids run ring by ring, so the held-out LEDs span all rings.
    Used by the component selection's validation, the light-subset study and the benchmarks;
    ``fit_dataset`` holds no light out of the final maps (its held-out figure is the
    cross-validation of :mod:`.holdout`)."""
    if every <= 0:
        return obs, None
    ids = sorted(set(obs.led_ids.tolist()))
    held = {i for k, i in enumerate(ids) if k % every == offset % every}
    if not held or len(held) == len(ids):
        return obs, None
    return obs.select_leds(held, keep=False), obs.select_leds(held, keep=True)


def _fingerprint(obs: Observations, preset: Preset, comps: Components, seed: int) -> str:
    sample = obs.images.flatten()[:: max(1, obs.images.numel() // 4096)]
    # the valid-sample mask (clipping, the sample mask) changes the fit: its counts per image,
    # row and column (only when there is one, so fits without keep their fingerprints)
    valid = {} if obs.valid is None else {"valid": torch.cat([obs.valid.sum(dim=(1, 2)), obs.valid.sum(dim=(0, 2)),
                                                               obs.valid.sum(dim=(0, 1))])}
    return fingerprint(preset=asdict(preset), comps=asdict(comps), seed=seed, ids=obs.led_ids, ws=obs.w_s,
                       sample=sample, sums=obs.images.sum(dim=(1, 2, 3)),
                       back=obs.backlight if obs.backlight is not None else torch.zeros(1), **valid)


def fit_observations(obs: Observations, preset: Preset, comps: Components, *, held_out: Observations | None = None,
                     checkpoint: str | Path | None = None, checkpoint_every: int = 50, progress: bool = False,
                     stop_after: int | None = None, seed: int = 0,
                     init: dict[str, Tensor] | None = None, uncertainty: bool = False) -> FitResult:
    """Fit ``comps`` to ``obs`` with ``preset``; resumes from ``checkpoint`` when it exists.
    A preset with a coarse level starts from its upsampled coarse fit unless ``init`` is given.
    ``uncertainty``: also compute the maps' per-pixel uncertainty at the solution
    (:func:`.uncertainty.pixel_uncertainty`, ``FitResult.uncertainty``; issue 26).  Off by
    default here: the coarse level, the component selection, the study and the
    cross-validation fit many times and need no uncertainty; :func:`.api.fit_dataset` (every
    ``dualscale fit``) turns it on.

    ``stop_after`` (testing/interruption) stops after that many global iterations, with the
    checkpoint saved, by raising :class:`~dualscale.fit.checkpoint.FitInterrupted`.
    """
    t0 = time.perf_counter()
    obs = stride_leds(obs, preset.led_stride)
    ck = Checkpointer(None if checkpoint is None else Path(checkpoint), _fingerprint(obs, preset, comps, seed),
                      checkpoint_every)
    resume = ck.load()
    if init is None and resume is None and preset.coarse_factor > 1:  # a resumed fit is past the coarse level
        init = coarse_start(obs, preset, comps, seed)
    params = {k: v.clone() for k, v in (init if init is not None else initial_params(obs, comps)).items()}
    loop = Loop(fine_preset(preset), comps, ck, progress=progress, stop_after=stop_after)
    done0 = 0
    if resume is not None:
        loop.history = list(resume.get("history", []))
        done0 = loop.global_index(resume["step"], resume["iteration"])
        loop.bar.update(done0)
    try:
        # the LM's last joint iteration builds the covariance's matrices in its own kernel pass
        gather = Gather(obs, preset) if uncertainty and preset.optimizer == "lm" else None
        with torch.no_grad() if preset.optimizer == "lm" else torch.enable_grad():
            if preset.optimizer == "adam":
                run_adam(params, comps, obs, loop, resume, seed)
            elif preset.optimizer == "lm":
                run_lm(params, comps, obs, loop, resume, gather)
            else:
                raise ValueError(f"unknown optimizer {preset.optimizer!r}")
    except KeyboardInterrupt:
        loop.close()
        raise
    loop.close()
    final = {k: v.detach() for k, v in params.items()}
    maps = to_maps(final)
    unc = None
    if uncertainty:
        with torch.no_grad():  # obs is strided already
            unc = pixel_uncertainty(final, comps, obs, replace(preset, led_stride=1), gathered=gather)
    return FitResult(maps, comps, preset, preset.total, time.perf_counter() - t0, fit_losses(maps, comps, obs, held_out),
                     loop.history, done0, unc)


def coarse_start(obs: Observations, preset: Preset, comps: Components, seed: int = 0) -> dict[str, Tensor]:
    """The full-resolution start of a preset with a coarse level (``coarse_factor`` > 1): the
    coarse fit of the box-downsampled ``obs`` (already strided to the preset's LEDs), upsampled
    (:mod:`.pyramid`)."""
    coarse = fit_observations(downsample(obs, preset.coarse_factor), coarse_preset(preset), comps, seed=seed,
                              uncertainty=False)
    return start_from_coarse(coarse.maps, obs, preset, comps)


def fit_losses(maps: MaterialMaps, comps: Components, obs: Observations,
               held_out: Observations | None = None) -> dict[str, float]:
    """The fit's report figures: ``train_*`` (re-render errors on ``obs``, the fitted images)
    and, with ``held_out`` lights (the study and the benchmarks pass them; ``fit_dataset`` does
    not), ``heldout_*`` and ``heldout_ssim``.  Raises ``RuntimeError`` for non-finite maps
    (guarded by the optimisers; must never happen)."""
    losses = {f"train_{k}": v for k, v in image_losses(maps, comps, obs).items()}
    if held_out is not None and held_out.n:
        losses.update({f"heldout_{k}": v for k, v in image_losses(maps, comps, held_out).items()})
        losses["heldout_ssim"] = rerender_ssim(maps, comps, held_out)
    for name, t in maps.items():
        if not bool(torch.isfinite(t).all()):
            raise RuntimeError(f"fit produced non-finite values in {name}")
    return losses
