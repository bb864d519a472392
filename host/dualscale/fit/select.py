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
  light validates once), on the mean absolute error (the fit's L1 loss); the lobe is kept only
  if it lowers that error by more than ``MARGIN``.  A dozen lights rarely catch a highlight
  twice, and an unconstrained lobe then predicts highlights where there are none.  Polarised
  captures keep the lobe (their P0 - P90 difference *is* the specular evidence).  Without a
  lobe, anisotropy and tint are moot and not tried.

The decision, with its evidence, goes into the fit's metadata.  ``overrides`` (True/False per
component) replaces a decision; the report then says so.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from dualscale.bsdf import Components

from .core import fit_observations, split_holdout
from .lm import preset_loss
from .loop import StepData
from .observations import Observations
from .params import fit_components
from .presets import PRESETS
from .render import clamp_images, pixel_rows, render_leds

TRANS_LEVEL = 0.02
SPECULAR_FOLDS = 4
#: the IOR of a diffuse-only model: eta 1 reflects nothing (Fresnel 0)
NO_SPECULAR_IOR = 1.0
TRANS_FRACTION = 0.01
MARGIN = 0.02
PIXELS = 512


def transmission_evidence(obs: Observations) -> dict[str, Any]:
    """Statistics of the back-lit capture (radiance relative to the panel, per pixel luminance)."""
    if obs.backlight is None:
        return {"backlit_capture": False, "transmits": False}
    y = (obs.backlight / obs.back_wd).mean(-1)
    frac = float((y > TRANS_LEVEL).to(torch.float64).mean())
    return {"backlit_capture": True, "backlit_mean": float(y.mean()), "backlit_p99": float(torch.quantile(y.flatten().to(torch.float64), 0.99)),
            "fraction_above_level": frac, "level": TRANS_LEVEL, "fraction_needed": TRANS_FRACTION,
            "transmits": frac > TRANS_FRACTION}


class _Validation:
    """RMS error on the validation LEDs of ``standard`` fits, over the captures the first fit
    does not find in cast shadow."""

    def __init__(self, train: Observations, val: Observations, iters_scale: float) -> None:
        self.train, self.val = train, val
        self.preset = PRESETS["standard"].scaled(iters_scale)
        self.images = clamp_images(val.images)
        self.keep: torch.Tensor | None = None

    def rmse(self, comps: Components) -> float:
        return self.errors(comps)["rmse"]

    def errors(self, comps: Components) -> dict[str, float]:
        """RMS and mean absolute error over the kept validation samples."""
        res = fit_observations(self.train, self.preset, comps)
        with torch.no_grad():
            r = pixel_rows(render_leds(res.maps.to(self.images.dtype), comps, self.val) - self.images)
        if self.keep is None:
            keep = preset_loss(self.preset).keep(r, StepData(self.val, self.images, None))
            self.keep = torch.ones_like(r) if keep is None else keep
        n = self.keep.sum().clamp(min=1.0)
        return {"rmse": float(((r * r * self.keep).sum() / n).sqrt()), "mae": float((r.abs() * self.keep).sum() / n)}

    def shadowed_share(self) -> float:
        return 0.0 if self.keep is None else float(1.0 - self.keep.mean())


def diffuse_only(opaque: bool = True) -> Components:
    """Components without a specular lobe: isotropic, untinted, IOR 1 (no Fresnel
    reflection), normal-mapped."""
    return Components(opaque=opaque, isotropic=True, tinted=False, normal_mapped=True, ior_mapped=False,
                      ior=NO_SPECULAR_IOR)


def has_specular(comps: Components) -> bool:
    """False for :func:`diffuse_only` components (IOR 1 and not mapped)."""
    return comps.ior_mapped or comps.ior != NO_SPECULAR_IOR


def specular_evidence(sub: Observations, translucent: bool, iters_scale: float, folds: int = SPECULAR_FOLDS
                      ) -> dict[str, Any]:
    """Cross-validated errors of diffuse-only and specular fits over ``sub`` (module doc)."""
    ids = sorted(set(sub.led_ids.tolist()))
    k = max(2, min(folds, len(ids)))
    cand = {"diffuse_only": diffuse_only(not translucent), "specular": fit_components(not translucent, True, False)}
    err = {name: [] for name in cand}
    for off in range(k):
        train, val = split_holdout(sub, every=k, offset=off)
        if val is None:
            continue
        v = _Validation(train, val, iters_scale)
        for name, c in cand.items():
            err[name].append(v.errors(c)["mae"])
    mae = {name: float(np.mean(e)) for name, e in err.items()}
    gain = (mae["diffuse_only"] - mae["specular"]) / max(mae["diffuse_only"], 1e-12)
    return {"folds": k, "val_mae_diffuse_only": mae["diffuse_only"], "val_mae_specular": mae["specular"],
            "relative_gain": gain, "chosen": bool(gain > MARGIN)}


def select_components(obs: Observations, overrides: dict[str, bool | None] | None = None, seed: int = 0,
                      pixels: int = PIXELS, iters_scale: float = 0.6, val_every: int = 5) -> tuple[Components, dict]:
    """``(components, report)`` for the observations (see module docstring)."""
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(overrides) - {"transmittance", "anisotropy", "tint", "specular"}
    if unknown:
        raise ValueError(f"unknown component overrides {sorted(unknown)}")
    report: dict[str, Any] = {"method": "held-out validation", "margin": MARGIN}
    ev = transmission_evidence(obs)
    translucent = overrides.get("transmittance", ev["transmits"])
    report["transmittance"] = {"chosen": bool(translucent), "overridden": "transmittance" in overrides,
                               "evidence": ev}
    h, w = obs.shape
    g = torch.Generator().manual_seed(seed)
    flat = torch.randperm(h * w, generator=g)[:min(pixels, h * w)].sort().values
    sub = obs.pixels(flat)
    train, val = split_holdout(sub, every=val_every, offset=1)
    report["validation"] = {"pixels": int(flat.numel()), "train_images": train.n,
                            "val_leds": sorted(set(val.led_ids.tolist())) if val is not None else []}
    if "specular" in overrides:
        report["specular"] = {"chosen": bool(overrides["specular"]), "overridden": True}
    elif overrides.get("anisotropy") or overrides.get("tint"):
        report["specular"] = {"chosen": True, "overridden": True, "evidence": "implied by an anisotropy or tint "
                                                                              "override"}
    elif obs.has_polarisation:
        report["specular"] = {"chosen": True, "overridden": False,
                              "evidence": "polarised captures: the P0 - P90 difference is the specular reflection"}
    else:
        ev = specular_evidence(sub, translucent, iters_scale)
        report["specular"] = {"chosen": ev["chosen"], "overridden": False, "evidence": ev}
    if not report["specular"]["chosen"]:
        for name in ("anisotropy", "tint"):
            report[name] = {"chosen": False, "overridden": name in overrides, "reason": "no specular lobe"}
        comps = diffuse_only(not translucent)
        report["components"] = asdict(comps)
        return comps, report
    need_fit = "anisotropy" not in overrides or "tint" not in overrides
    if val is None and need_fit:
        raise ValueError("component selection needs at least two LEDs; set --anisotropy and --tint explicitly")
    v = _Validation(train, val, iters_scale) if need_fit else None
    base = v.rmse(fit_components(not translucent, True, False)) if need_fit else None
    if "anisotropy" in overrides:
        aniso = overrides["anisotropy"]
        report["anisotropy"] = {"chosen": bool(aniso), "overridden": True}
        ref = None
    else:
        a = v.rmse(fit_components(not translucent, False, False))
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
            ref = v.rmse(fit_components(not translucent, not aniso, False))
        t = v.rmse(fit_components(not translucent, not aniso, True))
        gain = (ref - t) / max(ref, 1e-12)
        tint = gain > MARGIN
        report["tint"] = {"chosen": bool(tint), "overridden": False,
                          "evidence": {"val_rmse_untinted": ref, "val_rmse_tinted": t, "relative_gain": gain}}
    comps = fit_components(not translucent, not aniso, bool(tint))
    if v is not None:
        report["validation"]["shadowed_share"] = v.shadowed_share()
    report["components"] = asdict(comps)
    return comps, report
