"""Model only what the scene requires: choose components from the data.

* **transmittance** -- only when the back-lit capture shows transmission: more than
  ``TRANS_FRACTION`` of the pixels transmit more than ``TRANS_LEVEL`` of the panel's radiance
  (an opaque model predicts a black back-lit image, so this is its held-out error).
* **anisotropy** (with tangents) and **specular tint** -- by validation on held-out lights: a
  random subset of pixels is fitted (``standard`` LM, fewer iterations) with and without the
  component on the training LEDs, and the component is kept only if it lowers the RMS error on
  the validation LEDs by more than ``MARGIN`` (relative).  Anisotropy is decided first (both
  candidates untinted), then tint on top of that choice.

The decision, with its evidence, goes into the fit's metadata.  ``overrides`` (True/False per
component) replaces a decision; the report then says so.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch

from dualscale.bsdf import Components

from .core import fit_observations, split_holdout
from .metrics import image_losses
from .observations import Observations
from .params import fit_components
from .presets import PRESETS

TRANS_LEVEL = 0.02
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


def _val_rmse(train: Observations, val: Observations, comps: Components, iters_scale: float) -> float:
    preset = PRESETS["standard"].scaled(iters_scale)
    res = fit_observations(train, preset, comps)
    return image_losses(res.maps, comps, val)["rmse"]


def select_components(obs: Observations, overrides: dict[str, bool | None] | None = None, seed: int = 0,
                      pixels: int = PIXELS, iters_scale: float = 0.6, val_every: int = 5) -> tuple[Components, dict]:
    """``(components, report)`` for the observations (see module docstring)."""
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(overrides) - {"transmittance", "anisotropy", "tint"}
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
    need_fit = "anisotropy" not in overrides or "tint" not in overrides
    if val is None and need_fit:
        raise ValueError("component selection needs at least two LEDs; set --anisotropy and --tint explicitly")
    base = _val_rmse(train, val, fit_components(not translucent, True, False), iters_scale) if need_fit else None
    if "anisotropy" in overrides:
        aniso = overrides["anisotropy"]
        report["anisotropy"] = {"chosen": bool(aniso), "overridden": True}
        ref = None
    else:
        a = _val_rmse(train, val, fit_components(not translucent, False, False), iters_scale)
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
            ref = _val_rmse(train, val, fit_components(not translucent, not aniso, False), iters_scale)
        t = _val_rmse(train, val, fit_components(not translucent, not aniso, True), iters_scale)
        gain = (ref - t) / max(ref, 1e-12)
        tint = gain > MARGIN
        report["tint"] = {"chosen": bool(tint), "overridden": False,
                          "evidence": {"val_rmse_untinted": ref, "val_rmse_tinted": t, "relative_gain": gain}}
    comps = fit_components(not translucent, not aniso, bool(tint))
    report["components"] = asdict(comps)
    return comps, report
