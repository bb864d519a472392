"""Leave-one-light-out evaluation: how well a fit predicts a light it never saw, beside the
classic Lambertian photometric-stereo baseline (:mod:`.lambertian`) computed on the same pixels
in the same run.

For every light ``k`` of the observations: fit on the others (component choice included, as
``dualscale fit`` would make it, unless the components are given), render light ``k``, and
score the prediction against its capture by the **relative L1**

    ``sum |prediction - capture| / sum capture``

over the valid samples of the held-out image (inside the sample mask and not clipped:
``Observations.valid``) and the three channels.  The baseline fits
``a_c max(0, n . l)`` per pixel by least squares on the same training images and valid
samples.  Both predictions are clamped like the fit's renders (at 2, :mod:`.render`).

Cost: one fit per light.  ``pixels`` limits the evaluation to a random subset of the sample's
pixels (pixels are independent in the per-pixel fit, so this is an unbiased estimate of the
mean over the mask, and both methods see the same subset); :func:`fit_sample` fits the whole
mask once (only the pixels of the sample) for the maps.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps

from .core import fit_observations
from .lambertian import fit_lambertian, render_lambertian
from .observations import Observations
from .presets import Preset
from .render import clamp_images, render_leds


def relative_l1(pred: np.ndarray | Tensor, capture: np.ndarray | Tensor, valid: np.ndarray | Tensor | None) -> float:
    """``sum |pred - capture| / sum capture`` over the valid pixels ``(..., )`` of ``(..., 3)``
    images (``None``: all); NaN when nothing is valid or the capture sums to 0."""
    p = np.asarray(pred.detach().cpu() if isinstance(pred, Tensor) else pred, np.float64)
    c = np.asarray(capture.detach().cpu() if isinstance(capture, Tensor) else capture, np.float64)
    v = np.ones(c.shape[:-1], bool) if valid is None else np.asarray(
        valid.detach().cpu() if isinstance(valid, Tensor) else valid, bool)
    den = float(c[v].sum())
    return float(np.abs(p - c)[v].sum() / den) if v.any() and den > 0 else float("nan")


def sample_pixels(obs: Observations, pixels: int | None, seed: int = 0) -> Tensor:
    """Sorted flat indices of the sample's pixels (those with a valid sample: the mask), at most
    ``pixels`` of them drawn at random (``None`` or 0: all)."""
    fitted = obs.fitted_pixels
    h, w = obs.shape
    flat = torch.arange(h * w) if fitted is None else torch.nonzero(fitted.reshape(-1)).flatten()
    if flat.numel() == 0:
        raise ValueError("no pixel of the observations has a valid sample")
    if pixels and flat.numel() > pixels:
        g = torch.Generator().manual_seed(seed)
        flat = flat[torch.randperm(flat.numel(), generator=g)[:pixels]].sort().values
    return flat


def lambertian_prediction(train: Observations, held: Observations) -> np.ndarray:
    """The baseline's prediction ``(L, P, 3)`` of ``held``'s images from ``train`` (both ``1 x P``
    pixel rows or any ``(H, W)``: pixels are flattened), clamped at 2."""
    k = train.n
    x = train.images.reshape(k, -1, 3).double().numpy()
    v = None if train.valid is None else train.valid.reshape(k, -1).numpy()
    model = fit_lambertian(x, train.dirs.double().numpy(), v)
    return np.minimum(render_lambertian(model, held.dirs.double().numpy()), 2.0)


@dataclass
class HoldoutReport:
    """Per held-out light (``light_ids`` order): our relative L1 ``ours``, the baseline's
    ``baseline``; ``pixels`` evaluated, ``seconds`` (ours, baseline) of wall time, the
    ``components`` chosen in each fold."""

    light_ids: list[int]
    ours: np.ndarray
    baseline: np.ndarray
    pixels: int
    seconds: tuple[float, float]
    components: list[dict[str, Any]] = field(default_factory=list)
    preset: str = ""

    def summary(self) -> dict[str, Any]:
        """Means, their ratio, and on how many lights ours is lower."""
        mo, mb = float(np.mean(self.ours)), float(np.mean(self.baseline))
        return {"ours_mean": mo, "baseline_mean": mb, "ratio": mo / mb if mb > 0 else float("nan"),
                "wins": int((self.ours < self.baseline).sum()), "lights": len(self.light_ids),
                "pixels": self.pixels, "seconds_ours": self.seconds[0], "seconds_baseline": self.seconds[1],
                "preset": self.preset}

    def as_json(self) -> dict[str, Any]:
        return {**self.summary(), "light_ids": self.light_ids, "ours": [float(x) for x in self.ours],
                "baseline": [float(x) for x in self.baseline], "components": self.components}


Chooser = Callable[[Observations], Components]


def leave_one_light_out(obs: Observations, preset: Preset, comps: Components | Chooser, pixels: int | None = 4000,
                        seed: int = 0, progress: bool = False) -> HoldoutReport:
    """Leave-one-light-out over the distinct lights of ``obs`` (module doc).  ``comps``: fixed
    components, or a function of the training observations that chooses them (e.g.
    ``lambda o: select_components(o, preset=preset)[0]``), called once per fold.  Raises
    ``RuntimeError`` if a prediction is not finite (never expected)."""
    from tqdm import tqdm

    sub = obs.pixels(sample_pixels(obs, pixels, seed))
    ids = sorted(set(sub.led_ids.tolist()))
    ours, base, chosen = [], [], []
    t_ours = t_base = 0.0
    for lid in tqdm(ids, desc=f"leave-one-light-out[{preset.name}]", disable=not progress, leave=False):
        train, held = sub.select_leds({lid}, keep=False), sub.select_leds({lid}, keep=True)
        t0 = time.perf_counter()
        c = comps if isinstance(comps, Components) else comps(train)
        res = fit_observations(train, preset, c, seed=seed)
        with torch.no_grad():
            pred = render_leds(res.maps.to(held.images.dtype), c, held)
        t_ours += time.perf_counter() - t0
        t0 = time.perf_counter()
        pb = lambertian_prediction(train, held)
        t_base += time.perf_counter() - t0
        if not (bool(torch.isfinite(pred).all()) and np.isfinite(pb).all()):
            raise RuntimeError(f"leave-one-light-out: non-finite prediction of light {lid}")
        cap = clamp_images(held.images)
        v = None if held.valid is None else held.valid
        ours.append(np.mean([relative_l1(pred[i], cap[i], None if v is None else v[i]) for i in range(held.n)]))
        base.append(np.mean([relative_l1(pb[i].reshape(cap[i].shape), cap[i], None if v is None else v[i])
                             for i in range(held.n)]))
        chosen.append({"light": lid, **asdict(c)})
    return HoldoutReport(ids, np.array(ours), np.array(base), int(sub.images.shape[2]), (t_ours, t_base), chosen,
                         preset.name)


def fit_sample(obs: Observations, preset: Preset, comps: Components, seed: int = 0,
               progress: bool = False) -> MaterialMaps:
    """Fit only the sample's pixels (those with a valid sample) and lay the maps out at the
    observations' size: pixels outside the sample get albedo 0, roughness 0.5, normal +z and
    the neutral value of every other map.  Same result as fitting the whole image (pixels are
    independent), at the cost of the sample only."""
    flat = sample_pixels(obs, None)
    res = fit_observations(obs.pixels(flat), preset, comps, seed=seed, progress=progress)
    h, w = obs.shape
    out: dict[str, Tensor] = {}
    neutral = {"roughness": 0.5, "ior": 0.25, "tangent": 0.0, "opacity": 1.0}
    for name, t in res.maps.items():
        full = torch.full((h * w, t.shape[-1]), neutral.get(name, 0.0), dtype=t.dtype)
        if name == "normal":
            full[:, 2] = 1.0
        full[flat] = t.reshape(-1, t.shape[-1])
        out[name] = full.reshape(h, w, -1)
    return MaterialMaps(**out)
