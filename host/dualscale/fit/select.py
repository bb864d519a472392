"""Model only what the scene requires: choose components from the data.

* **transmittance** -- only when the back-lit capture shows transmission: more than
  ``TRANS_FRACTION`` of the pixels transmit more than ``TRANS_LEVEL`` of the panel's radiance
  (an opaque model predicts a black back-lit image, so this is its held-out error).
* **anisotropy** (with tangents) and **specular tint** -- by validation on held-out lights: a
  random subset of pixels is fitted (``standard`` LM, fewer iterations) with and without the
  component on the training LEDs, and the component is kept only if it lowers the RMS error on
  the validation LEDs by more than ``MARGIN`` (relative).  Anisotropy is decided first (both
  candidates untinted), then tint on top of that choice.  Validation captures that the first
  (isotropic, untinted) fit finds in cast shadow (``lm.Loss.keep``) are left out of every
  candidate's error, so all candidates are scored on the same captures and no local model is
  asked to explain a shadow.

* **specular** (any specular lobe at all) -- only for *unpolarised* captures (no crossed-analyser
  image separates the diffuse reflection, e.g. photographs from other rigs, docs/PHOTOS.md):
  diffuse-only (IOR 1, so no Fresnel reflection: :func:`diffuse_only`) against an isotropic,
  untinted specular lobe, by ``SPECULAR_FOLDS``-fold cross-validation over the lights (every
  light validates once), on the mean absolute error (the fit's L1 loss) of each held-out image
  scaled to the power that fits it best (:class:`LightFolds`: a photographed light's power is
  rarely known); the lobe is kept only if it lowers that error by more than ``MARGIN``.  A
  dozen lights rarely catch a highlight twice, and an unconstrained lobe then predicts
  highlights where there are none.  Polarised
  captures keep the lobe (their P0 - P90 difference *is* the specular evidence).  Without a
  lobe, anisotropy and tint are moot and not tried.
* **diffuse lobe** and **loss** -- also only for unpolarised captures, on the same folds and
  error, after the specular decision: Lambert's ``b / pi`` against Burley's diffuse with
  retro-reflection (the paper's), Burley kept only if it lowers the error by more than
  ``MARGIN``; then least squares (``l2``) against the paper's L1 loss for the chosen
  components, ``l2`` taken only if it lowers the error by more than ``MARGIN``.  The paper's
  choices are the rig's: 127 HDR captures per texel and polarisation-separated diffuse.  With a
  dozen 8-bit photographs, Burley's Schlick grazing factors and its roughness-driven
  retro-reflection bend the normals of a Lambertian surface, and the L1 loss, which fits a few
  of ~36 residuals exactly, has a larger variance than least squares under quantisation noise
  (docs/FITTING.md, *Matte photographs*); the data decide.  The chosen loss is applied to the
  fit's preset by :func:`preset_for`.

Pixels are drawn from the sample (``Observations.fitted_pixels``: inside the mask, with a valid
sample), not from the whole frame.

The decision, with its evidence, goes into the fit's metadata.  ``overrides`` (True/False per
component; ``"lambertian"`` True/False; ``"loss"`` ``"l1"``/``"l2"``) replaces a decision; the
report then says so.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np
import torch

from dualscale.bsdf import Components

from .core import fit_observations, split_holdout
from .lm import preset_loss
from .loop import StepData
from .observations import Observations
from .params import fit_components
from .presets import PRESETS, Preset
from .render import clamp_images, pixel_rows, render_leds

TRANS_LEVEL = 0.02
SPECULAR_FOLDS = 4
#: the IOR of a diffuse-only model: eta 1 reflects nothing (Fresnel 0)
NO_SPECULAR_IOR = 1.0
TRANS_FRACTION = 0.01
MARGIN = 0.02
PIXELS = 512
#: the losses tried for unpolarised captures, the paper's first (:class:`.presets.Preset` ``loss``)
LOSSES = ("l1", "l2")


def transmission_evidence(obs: Observations) -> dict[str, Any]:
    """Statistics of the back-lit capture (radiance relative to the panel, per pixel luminance)."""
    if obs.backlight is None:
        return {"backlit_capture": False, "transmits": False}
    y = (obs.backlight / obs.back_wd).mean(-1)
    return transmission_from(float((y > TRANS_LEVEL).to(torch.float64).mean()), float(y.to(torch.float64).mean()),
                             float(torch.quantile(y.flatten().to(torch.float64), 0.99)))


def transmission_from(fraction: float, mean: float, p99: float) -> dict[str, Any]:
    """:func:`transmission_evidence` from its statistics of the back-lit luminance: the share of
    pixels above :data:`TRANS_LEVEL`, the mean and the 99th percentile (what the fit out of core
    gathers band by band, :mod:`.stream`)."""
    return {"backlit_capture": True, "backlit_mean": mean, "backlit_p99": p99, "fraction_above_level": fraction,
            "level": TRANS_LEVEL, "fraction_needed": TRANS_FRACTION, "transmits": fraction > TRANS_FRACTION}


class _Validation:
    """RMS error on the validation LEDs of ``standard`` fits (``loss``: the preset's loss), over
    the captures the first fit does not find in cast shadow."""

    def __init__(self, train: Observations, val: Observations, iters_scale: float, loss: str = "l1") -> None:
        self.train, self.val = train, val
        self.preset = replace(PRESETS["standard"].scaled(iters_scale), loss=loss)
        self.images = clamp_images(val.images)
        self.keep: torch.Tensor | None = None

    def rmse(self, comps: Components) -> float:
        return self.errors(comps)["rmse"]

    def errors(self, comps: Components, loss: str | None = None) -> dict[str, float]:
        """RMS and mean absolute error over the kept validation samples of a fit of ``comps``
        with ``loss`` (None: the preset's), and ``mae_scaled``: the mean absolute error with each
        validation image scaled by :func:`light_scales` (:class:`LightFolds`)."""
        preset = self.preset if loss is None else replace(self.preset, loss=loss)
        res = fit_observations(self.train, preset, comps)
        with torch.no_grad():
            pred = render_leds(res.maps.to(self.images.dtype), comps, self.val)
            r = pixel_rows(pred - self.images)
        if self.keep is None:
            keep = preset_loss(self.preset).keep(r, StepData(self.val, self.images, None))
            self.keep = torch.ones_like(r) if keep is None else keep
        n = self.keep.sum().clamp(min=1.0)
        scales = light_scales(pixel_rows(pred), pixel_rows(self.images), self.keep, self.val.n)
        rs = pixel_rows(pred * scales.reshape(-1, 1, 1, 1).to(pred.dtype) - self.images)
        return {"rmse": float(((r * r * self.keep).sum() / n).sqrt()), "mae": float((r.abs() * self.keep).sum() / n),
                "mae_scaled": float((rs.abs() * self.keep).sum() / n)}

    def shadowed_share(self) -> float:
        return 0.0 if self.keep is None else float(1.0 - self.keep.mean())


def light_scales(pred: torch.Tensor, images: torch.Tensor, keep: torch.Tensor, n: int) -> torch.Tensor:
    """Per image, the scale ``s`` minimising ``sum |s p - y|`` over its kept samples (rows
    ``(h, w, 3 n)`` in :func:`.render.pixel_rows` layout; ``keep`` 1/0): the weighted median of
    ``y / p`` with weights ``p`` (1 where nothing is lit).  ``(n,)`` float64."""
    p = pred.reshape(-1, n, 3).transpose(0, 1).reshape(n, -1).to(torch.float64)
    y = images.reshape(-1, n, 3).transpose(0, 1).reshape(n, -1).to(torch.float64)
    k = keep.reshape(-1, n, 3).transpose(0, 1).reshape(n, -1) > 0
    out = torch.ones(n, dtype=torch.float64)
    for i in range(n):
        m = k[i] & (p[i] > 1e-6)
        if int(m.sum()) < 3:
            continue
        ratio, w = y[i][m] / p[i][m], p[i][m]
        order = torch.argsort(ratio)
        cw = torch.cumsum(w[order], 0)
        out[i] = ratio[order][int(torch.searchsorted(cw, 0.5 * cw[-1]))]
    return out


def diffuse_only(opaque: bool = True, diffuse: str = "burley") -> Components:
    """Components without a specular lobe: isotropic, untinted, IOR 1 (no Fresnel
    reflection), normal-mapped, with the ``diffuse`` lobe (``"burley"`` or ``"lambert"``)."""
    return Components(opaque=opaque, isotropic=True, tinted=False, normal_mapped=True, ior_mapped=False,
                      ior=NO_SPECULAR_IOR, diffuse=diffuse)


def has_specular(comps: Components) -> bool:
    """False for :func:`diffuse_only` components (IOR 1 and not mapped)."""
    return comps.ior_mapped or comps.ior != NO_SPECULAR_IOR


class LightFolds:
    """``folds``-fold cross-validation over the lights of ``sub`` (every light validates once):
    the mean absolute error on the held-out lights of a ``standard`` fit (iterations scaled by
    ``iters_scale``), averaged over the folds, per candidate ``(components, loss)``; each
    candidate is fitted once (:meth:`mae` caches).

    Each held-out image is first scaled by the factor that fits it best (:func:`light_scales`):
    the power of a photographed light is rarely known (the importer assumes them equal, and
    light 2 of psm-12lights is 6-29 % darker), and a candidate must not be credited for how well
    it guesses a held-out light's power, only for how well it predicts the image's shading.  On
    a synthetic sphere with powers off by up to 30 %, the plain error chose Burley's diffuse and
    least squares, which absorb the wrong powers and bent the normals past the Lambertian
    baseline's (docs/FITTING.md, *Matte photographs*).  With the right powers the scale is 1
    to within the noise and changes nothing."""

    def __init__(self, sub: Observations, iters_scale: float, folds: int = SPECULAR_FOLDS) -> None:
        ids = sorted(set(sub.led_ids.tolist()))
        self.k = max(2, min(folds, len(ids)))
        self.vals = []
        for off in range(self.k):
            train, val = split_holdout(sub, every=self.k, offset=off)
            if val is not None:
                self.vals.append(_Validation(train, val, iters_scale))
        self._mae: dict[tuple[Components, str], float] = {}

    def mae(self, comps: Components, loss: str = "l1") -> float:
        key = (comps, loss)
        if key not in self._mae:
            self._mae[key] = float(np.mean([v.errors(comps, loss)["mae_scaled"] for v in self.vals]))
        return self._mae[key]


def _gain(reference: float, candidate: float) -> float:
    """Relative decrease of the error from ``reference`` to ``candidate``."""
    return (reference - candidate) / max(reference, 1e-12)


def specular_evidence(sub: Observations, translucent: bool, iters_scale: float, folds: int = SPECULAR_FOLDS,
                      cv: LightFolds | None = None) -> dict[str, Any]:
    """Cross-validated errors (:class:`LightFolds`) of diffuse-only and specular fits (Burley's
    diffuse, L1) over ``sub`` (module doc); ``cv``: folds already made (their fits are reused)."""
    cv = LightFolds(sub, iters_scale, folds) if cv is None else cv
    d, s = cv.mae(diffuse_only(not translucent)), cv.mae(fit_components(not translucent, True, False))
    gain = _gain(d, s)
    return {"folds": cv.k, "val_mae_diffuse_only": d, "val_mae_specular": s, "relative_gain": gain,
            "chosen": bool(gain > MARGIN)}


def diffuse_evidence(cv: LightFolds, comps: Components) -> dict[str, Any]:
    """Lambert's diffuse against Burley's for ``comps`` (its other components kept), L1 loss:
    Burley is chosen only if it lowers the cross-validated error by more than ``MARGIN``."""
    b, lam = cv.mae(replace(comps, diffuse="burley")), cv.mae(replace(comps, diffuse="lambert"))
    gain = _gain(lam, b)
    return {"folds": cv.k, "val_mae_lambert": lam, "val_mae_burley": b, "relative_gain_of_burley": gain,
            "chosen": "burley" if gain > MARGIN else "lambert"}


def loss_evidence(cv: LightFolds, comps: Components) -> dict[str, Any]:
    """Least squares against the L1 loss for ``comps``: ``l2`` is chosen only if it lowers the
    cross-validated error (mean absolute, the same score for both) by more than ``MARGIN``."""
    l1, l2 = cv.mae(comps, "l1"), cv.mae(comps, "l2")
    gain = _gain(l1, l2)
    return {"folds": cv.k, "val_mae_l1": l1, "val_mae_l2": l2, "relative_gain_of_l2": gain,
            "chosen": "l2" if gain > MARGIN else "l1"}


def preset_for(preset: Preset, selection: dict[str, Any]) -> Preset:
    """``preset`` with the loss the component choice made (``selection["loss"]["chosen"]``, for
    unpolarised captures) when it is an LM preset; otherwise ``preset`` itself (Adam minimises
    the paper's L1 loss only; polarised captures keep the preset's loss)."""
    loss = (selection.get("loss") or {}).get("chosen")
    if loss not in LOSSES or preset.optimizer != "lm" or loss == preset.loss:
        return preset
    return replace(preset, loss=loss)


def selection_pixels(fitted: torch.Tensor | None, shape: tuple[int, int], pixels: int = PIXELS, seed: int = 0
                ) -> torch.Tensor:
    """Sorted flat indices of at most ``pixels`` random pixels of the sample: those with a valid
    sample (``fitted`` ``(H, W)`` bool, ``Observations.fitted_pixels``; ``None`` or none set:
    every pixel of the ``(H, W)`` map), drawn with ``seed``: the pixels
    :func:`select_components` chooses with."""
    h, w = shape
    g = torch.Generator().manual_seed(seed)
    if fitted is None or not bool(fitted.any()):
        return torch.randperm(h * w, generator=g)[:min(pixels, h * w)].sort().values
    idx = torch.nonzero(fitted.reshape(-1)).flatten()
    return idx[torch.randperm(idx.numel(), generator=g)[:min(pixels, idx.numel())]].sort().values


def check_overrides(overrides: dict[str, bool | str | None] | None) -> dict[str, bool | str]:
    """The overrides that are set (not ``None``); ``ValueError`` for an unknown one or loss."""
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(overrides) - {"transmittance", "anisotropy", "tint", "specular", "lambertian", "loss"}
    if unknown:
        raise ValueError(f"unknown component overrides {sorted(unknown)}")
    if "loss" in overrides and overrides["loss"] not in LOSSES:
        raise ValueError(f"loss override {overrides['loss']!r}; choose from {LOSSES}")
    return overrides


def select_components(obs: Observations, overrides: dict[str, bool | str | None] | None = None, seed: int = 0,
                      pixels: int = PIXELS, iters_scale: float = 0.6, val_every: int = 5) -> tuple[Components, dict]:
    """``(components, report)`` for the observations (see module docstring); ``ValueError`` for
    an unknown override."""
    check_overrides(overrides)
    return choose_components(obs.pixels(selection_pixels(obs.fitted_pixels, obs.shape, pixels, seed)),
                             transmission_evidence(obs), overrides, iters_scale, val_every)


def choose_components(sub: Observations, transmission: dict[str, Any],
                      overrides: dict[str, bool | str | None] | None = None, iters_scale: float = 0.6,
                      val_every: int = 5) -> tuple[Components, dict]:
    """:func:`select_components` from its sample pixels ``sub`` (``1 x P``, the pixels of
    :func:`selection_pixels`) and the map's :func:`transmission_evidence`: what the fit out of core
    (:mod:`.stream`) calls with the pixels it gathered from disk.  The same decision and report."""
    overrides = check_overrides(overrides)
    report: dict[str, Any] = {"method": "held-out validation", "margin": MARGIN}
    ev = transmission
    translucent = overrides.get("transmittance", ev["transmits"])
    report["transmittance"] = {"chosen": bool(translucent), "overridden": "transmittance" in overrides,
                               "evidence": ev}
    obs = sub  # the same lights and weights as the whole map's
    train, val = split_holdout(sub, every=val_every, offset=1)
    report["validation"] = {"pixels": int(sub.images.shape[2]), "train_images": train.n,
                            "val_leds": sorted(set(val.led_ids.tolist())) if val is not None else []}
    # unpolarised captures: one set of light folds for the specular, diffuse and loss choices
    cv = None if obs.has_polarisation else LightFolds(sub, iters_scale)
    if "specular" in overrides:
        report["specular"] = {"chosen": bool(overrides["specular"]), "overridden": True}
    elif overrides.get("anisotropy") or overrides.get("tint"):
        report["specular"] = {"chosen": True, "overridden": True, "evidence": "implied by an anisotropy or tint "
                                                                              "override"}
    elif obs.has_polarisation:
        report["specular"] = {"chosen": True, "overridden": False,
                              "evidence": "polarised captures: the P0 - P90 difference is the specular reflection"}
    else:
        ev = specular_evidence(sub, translucent, iters_scale, cv=cv)
        report["specular"] = {"chosen": ev["chosen"], "overridden": False, "evidence": ev}
    spec = bool(report["specular"]["chosen"])
    lobe = fit_components(not translucent, True, False) if spec else diffuse_only(not translucent)
    diffuse = "burley"
    if "lambertian" in overrides:
        diffuse = "lambert" if overrides["lambertian"] else "burley"
        report["diffuse"] = {"chosen": diffuse, "overridden": True}
    elif cv is not None:
        ev = diffuse_evidence(cv, lobe)
        diffuse = ev["chosen"]
        report["diffuse"] = {"chosen": diffuse, "overridden": False, "evidence": ev}
    else:
        report["diffuse"] = {"chosen": diffuse, "overridden": False,
                             "evidence": "polarised captures: the paper's diffuse (the P90 images isolate it)"}
    lobe = replace(lobe, diffuse=diffuse)
    if "loss" in overrides:
        report["loss"] = {"chosen": overrides["loss"], "overridden": True}
    elif cv is not None:
        ev = loss_evidence(cv, lobe)
        report["loss"] = {"chosen": ev["chosen"], "overridden": False, "evidence": ev}
    else:
        report["loss"] = {"chosen": None, "overridden": False, "evidence": "polarised captures: the preset's loss"}
    loss = report["loss"]["chosen"] or "l1"
    if not spec:
        for name in ("anisotropy", "tint"):
            report[name] = {"chosen": False, "overridden": name in overrides, "reason": "no specular lobe"}
        report["components"] = asdict(lobe)
        return lobe, report
    need_fit = "anisotropy" not in overrides or "tint" not in overrides
    if val is None and need_fit:
        raise ValueError("component selection needs at least two LEDs; set --anisotropy and --tint explicitly")

    def comps_of(isotropic: bool, tinted: bool) -> Components:
        return replace(fit_components(not translucent, isotropic, tinted), diffuse=diffuse)

    v = _Validation(train, val, iters_scale, loss) if need_fit else None
    base = v.rmse(comps_of(True, False)) if need_fit else None
    if "anisotropy" in overrides:
        aniso = overrides["anisotropy"]
        report["anisotropy"] = {"chosen": bool(aniso), "overridden": True}
        ref = None
    else:
        a = v.rmse(comps_of(False, False))
        gain = (base - a) / max(base, 1e-12)
        aniso = gain > MARGIN
        report["anisotropy"] = {"chosen": bool(aniso), "overridden": False,
                                "evidence": {"val_rmse_isotropic": base, "val_rmse_anisotropic": a,
                                             "relative_gain": gain}}
        ref = a if aniso else base
    if "tint" in overrides:
        tint = overrides["tint"]
        report["tint"] = {"chosen": bool(tint), "overridden": True}
    else:
        if ref is None:
            ref = v.rmse(comps_of(not aniso, False))
        t = v.rmse(comps_of(not aniso, True))
        gain = (ref - t) / max(ref, 1e-12)
        tint = gain > MARGIN
        report["tint"] = {"chosen": bool(tint), "overridden": False,
                          "evidence": {"val_rmse_untinted": ref, "val_rmse_tinted": t, "relative_gain": gain}}
    comps = comps_of(not aniso, bool(tint))
    if v is not None:
        report["validation"]["shadowed_share"] = v.shadowed_share()
    report["components"] = asdict(comps)
    return comps, report
