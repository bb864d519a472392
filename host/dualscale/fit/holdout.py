"""Cross-validation over the lights: how well a fit predicts lights it never saw, beside the
classic Lambertian photometric-stereo baseline (:mod:`.lambertian`) computed on the same pixels
in the same run.  ``dualscale fit`` and the ``digitize`` fit stage report their held-out figure
from :func:`cross_validate` while the final maps are fitted on every light (docs/FITTING.md,
"Held-out lights").

The distinct lights (LED ids) are split into folds (:func:`light_folds`): **leave-one-light-out**
when there are at most :data:`LOO_MAX_LIGHTS` of them (a dozen photographs: every fold keeps all
the other lights), else :data:`KFOLD` folds with the lights dealt round-robin in id order (LED ids
run ring by ring, so every fold spans the rings and azimuths).  For every fold: fit on the other
lights' images (component choice included, as ``dualscale fit`` would make it, when a chooser is
given instead of fixed components), render the fold's lights, and score each light's prediction
against its capture by the **relative L1**

    ``sum |prediction - capture| / sum capture``

over the valid samples of the held-out image (inside the sample mask and not clipped:
``Observations.valid``) and the three channels; a light with several images (P0 and P90) gets the
mean over its images.  Every light is held out exactly once, so every light gets an error.  The
baseline fits ``a_c max(0, n . l)`` per pixel by least squares on the same training images and
valid samples.  Both predictions are clamped like the fit's renders (at 2, :mod:`.render`).

A second reference, the **per-pixel constant predictor** (:func:`constant_prediction`), predicts
every held-out image of a pixel by that pixel's mean over the fold's training images (their valid
samples, clamped at 2): a prediction that ignores the light entirely.  It is scored the same way
(``constant``).  A real material's shading changes strongly with the light, so any fit that
describes it beats the constant predictor by far; images of random noise (no light dependence) do
not, whatever their absolute error (docs/DIGITIZE.md, "The run's check").

Cost: one fit per fold.  ``pixels`` limits the evaluation to a random subset of the sample's
pixels (pixels are independent in the per-pixel fit, so this is an unbiased estimate of the
mean over the mask, and both methods and every fold see the same subset).  The subset is laid
out as a ``1 x P`` row, so a preset's coarse level (box-averaging neighbours) has no meaning
there and is dropped (:func:`pixel_preset`).  :func:`fit_sample` fits the whole mask once (only
the pixels of the sample) for the maps.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps

from .core import fit_observations
from .lambertian import fit_lambertian, render_lambertian
from .observations import Observations
from .presets import Preset
from .render import clamp_images, render_leds

#: at most this many distinct lights: leave-one-light-out; more: :data:`KFOLD` folds
LOO_MAX_LIGHTS = 16
#: folds of the k-fold scheme (lights dealt round-robin in id order)
KFOLD = 8
#: pixels of the cross-validation sample of ``dualscale fit`` and ``digitize`` (docs/FITTING.md
#: measures the cost: on a 128^2 map of 32 LEDs the 8 folds of 2000 pixels take about the final fit's time)
CV_PIXELS = 2000


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
    ``pixels`` of them drawn at random (``None`` or 0: all); ``ValueError`` when no pixel has a
    valid sample."""
    return sample_pixels_of(obs.fitted_pixels, obs.shape, pixels, seed)


def sample_pixels_of(fitted: Tensor | None, shape: tuple[int, int], pixels: int | None, seed: int = 0) -> Tensor:
    """:func:`sample_pixels` from the map's ``fitted`` pixels ``(H, W)`` bool (``None``: all of
    the ``(H, W)`` map)."""
    h, w = shape
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


def constant_prediction(train: Observations, held: Observations) -> np.ndarray:
    """The per-pixel constant predictor's prediction ``(L, P, 3)`` of ``held``'s ``L`` images
    (module doc): every pixel's mean over ``train``'s images, each clamped at 2, over the valid
    samples of that pixel (``train.valid``; a pixel with none predicts 0), the same for every
    held-out light.  Both are ``1 x P`` pixel rows or any ``(H, W)`` (pixels are flattened)."""
    k = train.n
    x = clamp_images(train.images).reshape(k, -1, 3).double().numpy()
    v = np.ones(x.shape[:2], bool) if train.valid is None else train.valid.reshape(k, -1).numpy().astype(bool)
    n = v.sum(0)  # (P,)
    mean = (x * v[..., None]).sum(0) / np.maximum(n, 1)[:, None]
    mean[n == 0] = 0.0
    return np.broadcast_to(mean, (held.n, *mean.shape)).copy()


def light_folds(light_ids: Sequence[int] | Tensor, folds: int | str = "auto") -> list[list[int]]:
    """The folds of the distinct ids in ``light_ids``: lists of ids, every id in exactly one.

    ``folds``: ``"loo"`` (one light per fold), ``"auto"`` (``"loo"`` for at most
    :data:`LOO_MAX_LIGHTS` distinct lights, else :data:`KFOLD`), or an int ``k >= 2`` (``k``
    folds, fold ``j`` holding the ``j``-th, ``(j + k)``-th, ... id in increasing order; ``k`` is
    lowered to the number of lights).  Raises ``ValueError`` for fewer than two distinct lights
    or an unknown ``folds``."""
    ids = sorted({int(i) for i in (light_ids.tolist() if isinstance(light_ids, Tensor) else light_ids)})
    if len(ids) < 2:
        raise ValueError(f"cross-validation over the lights needs at least two distinct lights, got {len(ids)}")
    k = parse_folds(folds)
    if k == "auto":
        k = len(ids) if len(ids) <= LOO_MAX_LIGHTS else KFOLD
    elif k == "loo":
        k = len(ids)
    k = min(int(k), len(ids))
    return [ids[j::k] for j in range(k)]


def parse_folds(text: int | str) -> int | str:
    """``"auto"``, ``"loo"`` or an int ``>= 2`` from a user's ``--cv-folds`` value; raises
    ``ValueError`` otherwise."""
    if isinstance(text, str) and text.strip().lower() in ("auto", "loo"):
        return text.strip().lower()
    try:
        k = int(text)
    except (TypeError, ValueError):
        raise ValueError(f"cross-validation folds {text!r}: give auto, loo or a number of folds >= 2") from None
    if k < 2:
        raise ValueError(f"cross-validation folds {k}: a k-fold needs k >= 2 (or loo, or auto)")
    return k


def scheme_name(folds: list[list[int]]) -> str:
    """``"leave-one-light-out"`` when every fold holds one light, else ``"K-fold"``."""
    return "leave-one-light-out" if all(len(f) == 1 for f in folds) else f"{len(folds)}-fold"


def pixel_preset(preset: Preset) -> Preset:
    """``preset`` as fitted on a pixel sample laid out as a ``1 x P`` row: without its coarse
    level (``coarse_factor`` 1), whose box average would blend unrelated pixels; everything
    else unchanged."""
    return preset if preset.coarse_factor <= 1 else replace(preset, coarse_factor=1)


def _nanmean(x: Sequence[float]) -> float:
    a = np.asarray(x, np.float64)
    return float(np.nanmean(a)) if np.isfinite(a).any() else float("nan")


def _json_float(x: float) -> float | None:
    return float(x) if math.isfinite(float(x)) else None


@dataclass
class HoldoutReport:
    """Per held-out light (``light_ids`` order, increasing): our relative L1 ``ours``, the
    baseline's ``baseline``, the per-pixel constant predictor's ``constant`` (:func:`constant_prediction`;
    ``(L,)`` arrays, NaN for a light without a valid sample; ``constant`` empty in a report
    made without it), its
    direction ``directions`` (unit vectors, camera frame), its ``fold`` index; the ``folds``
    (lists of light ids), ``pixels`` evaluated, ``seconds`` (ours, baseline) of wall time, the
    ``components`` of each fold (one entry per fold, with its ``lights``), the preset's name
    and the ``scheme`` (``"leave-one-light-out"`` or ``"K-fold"``)."""

    light_ids: list[int]
    ours: np.ndarray
    baseline: np.ndarray
    pixels: int
    seconds: tuple[float, float]
    components: list[dict[str, Any]] = field(default_factory=list)
    preset: str = ""
    folds: list[list[int]] = field(default_factory=list)
    directions: list[list[float]] = field(default_factory=list)
    scheme: str = "leave-one-light-out"
    constant: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def fold(self) -> list[int]:
        """The fold index of every light (``light_ids`` order)."""
        where = {lid: j for j, f in enumerate(self.folds) for lid in f}
        return [where.get(lid, -1) for lid in self.light_ids]

    def summary(self) -> dict[str, Any]:
        """Means over the lights (NaN ones left out; ``constant_mean`` NaN without the constant
        predictor), their ratio, on how many lights ours is lower, and the scheme, folds, pixels,
        seconds and preset."""
        mo, mb = _nanmean(self.ours), _nanmean(self.baseline)
        mc = _nanmean(self.constant) if len(self.constant) else float("nan")
        return {"ours_mean": mo, "baseline_mean": mb, "constant_mean": mc,
                "ratio": mo / mb if mb > 0 else float("nan"),
                "wins": int((self.ours < self.baseline).sum()), "lights": len(self.light_ids),
                "pixels": self.pixels, "seconds_ours": self.seconds[0], "seconds_baseline": self.seconds[1],
                "preset": self.preset, "scheme": self.scheme, "folds": len(self.folds) or len(self.light_ids)}

    def as_json(self) -> dict[str, Any]:
        """:meth:`summary` plus the per-light lists (non-finite values as ``null``)."""
        s = {k: (_json_float(v) if isinstance(v, float) else v) for k, v in self.summary().items()}
        return {**s, "light_ids": self.light_ids, "ours": [_json_float(x) for x in self.ours],
                "baseline": [_json_float(x) for x in self.baseline],
                "constant": [_json_float(x) for x in self.constant], "fold": self.fold,
                "fold_lights": self.folds, "directions": self.directions, "components": self.components}


Chooser = Callable[[Observations], Components]


def cross_validate(obs: Observations, preset: Preset, comps: Components | Chooser, pixels: int | None = CV_PIXELS,
                   folds: int | str = "auto", seed: int = 0, progress: bool = False) -> HoldoutReport:
    """Cross-validation over the distinct lights of ``obs`` (module doc): ``folds`` as in
    :func:`light_folds`, on at most ``pixels`` random pixels of the sample (``None`` or 0: all;
    drawn with ``seed``), each fold fitted with :func:`pixel_preset` of ``preset``.  ``comps``:
    fixed components (``dualscale fit`` passes the decision it made once on all lights), or a
    function of the training observations that chooses them (e.g.
    ``lambda o: select_components(o, preset=preset)[0]``), called once per fold.  The Lambertian
    baseline and the per-pixel constant predictor are scored on the same folds, pixels and valid
    samples (module doc).  Raises
    ``ValueError`` for fewer than two distinct lights and ``RuntimeError`` if a prediction is not
    finite (never expected)."""
    return cross_validate_pixels(obs.pixels(sample_pixels(obs, pixels, seed)), preset, comps, folds, seed, progress)


def cross_validate_pixels(sub: Observations, preset: Preset, comps: Components | Chooser, folds: int | str = "auto",
                          seed: int = 0, progress: bool = False) -> HoldoutReport:
    """:func:`cross_validate` on its sample pixels ``sub`` (``1 x P``: the pixels of
    :func:`sample_pixels`), as the fit out of core calls it with the pixels it gathered from
    disk (:mod:`.stream`); the same report."""
    from tqdm import tqdm

    groups = light_folds(sub.led_ids, folds)
    scheme = scheme_name(groups)
    fit_preset = pixel_preset(preset)
    ours: dict[int, float] = {}
    base: dict[int, float] = {}
    const: dict[int, float] = {}
    dirs: dict[int, list[float]] = {}
    chosen = []
    t_ours = t_base = 0.0
    for fold in tqdm(groups, desc=f"cross-validation[{scheme}, {preset.name}]", disable=not progress, leave=False):
        train, held = sub.select_leds(set(fold), keep=False), sub.select_leds(set(fold), keep=True)
        t0 = time.perf_counter()
        c = comps if isinstance(comps, Components) else comps(train)
        res = fit_observations(train, fit_preset, c, seed=seed)
        with torch.no_grad():
            pred = render_leds(res.maps.to(held.images.dtype), c, held)
        t_ours += time.perf_counter() - t0
        t0 = time.perf_counter()
        pb = lambertian_prediction(train, held)
        pc = constant_prediction(train, held)
        t_base += time.perf_counter() - t0
        if not (bool(torch.isfinite(pred).all()) and np.isfinite(pb).all()):
            raise RuntimeError(f"cross-validation: non-finite prediction of light(s) {fold}")
        cap = clamp_images(held.images)
        v = held.valid
        ids = held.led_ids.tolist()
        for lid in fold:
            idx = [k for k, i in enumerate(ids) if i == lid]
            ours[lid] = float(np.mean([relative_l1(pred[k], cap[k], None if v is None else v[k]) for k in idx]))
            base[lid] = float(np.mean([relative_l1(pb[k].reshape(cap[k].shape), cap[k], None if v is None else v[k])
                                       for k in idx]))
            const[lid] = float(np.mean([relative_l1(pc[k].reshape(cap[k].shape), cap[k], None if v is None else v[k])
                                        for k in idx]))
            d = held.dirs[idx[0]].double()
            dirs[lid] = [float(x) for x in d / d.norm().clamp_min(1e-12)]
        chosen.append({"lights": list(fold), **asdict(c)})
    light_ids = sorted(ours)
    return HoldoutReport(light_ids, np.array([ours[i] for i in light_ids]), np.array([base[i] for i in light_ids]),
                         int(sub.images.shape[2]), (t_ours, t_base), chosen, preset.name, groups,
                         [dirs[i] for i in light_ids], scheme, np.array([const[i] for i in light_ids]))


def leave_one_light_out(obs: Observations, preset: Preset, comps: Components | Chooser, pixels: int | None = 4000,
                        seed: int = 0, progress: bool = False) -> HoldoutReport:
    """:func:`cross_validate` with one light per fold (``folds="loo"``), on at most ``pixels``
    random sample pixels (4000 by default, as ``bench/bench_photos.py`` measures)."""
    return cross_validate(obs, preset, comps, pixels, "loo", seed, progress)


def describe(cv: dict[str, Any] | None) -> str:
    """One line for a person: the cross-validated held-out figure of a ``fit_dataset`` record
    ``cv`` (``extra["cross_validation"]``, ``fit.json``), with its scheme, lights and pixels, or
    why there is none (``None``: the pass was not asked for)."""
    if cv is None:
        return "held-out error: not measured (--cv-pixels 0: no cross-validation pass)"
    if "skipped" in cv:
        return f"held-out error: not measured ({cv['skipped']})"

    def num(x: Any) -> str:
        return "n/a" if x is None or not math.isfinite(float(x)) else f"{float(x):.4g}"

    return (f"held-out relative L1 {num(cv.get('relative_l1'))} (cross-validated, {cv.get('scheme')} over "
            f"{cv.get('lights')} lights on {cv.get('pixels')} sample pixels; Lambertian baseline "
            f"{num(cv.get('baseline_relative_l1'))}, per-pixel constant predictor "
            f"{num(cv.get('constant_relative_l1'))}); no light is held out of the final maps")


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
