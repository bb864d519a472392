"""Cast-shadow rejection in the LM fit (``Preset.shadow_ratio``, ``lm.Loss.keep``)."""

from dataclasses import replace

import pytest
import torch

from dualscale.fit.core import fit_observations
from dualscale.fit.lm import Loss
from dualscale.fit.loop import StepData
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import Observations, load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import PRESETS, Preset
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)


def _two_leds(images: torch.Tensor) -> StepData:
    """LED 5 at P0 and P90, LED 9 at P0 only; images ``(3, 1, 2, 3)``."""
    obs = Observations(images=images, dirs=torch.tensor([[0.8, 0.0, 0.6], [0.8, 0.0, 0.6], [0.0, 0.8, 0.6]]),
                       w_s=torch.tensor([1.0, 0.0, 1.0]), w_p=torch.zeros(3), w_d=torch.full((3,), 0.5),
                       led_ids=torch.tensor([5, 5, 9]))
    return StepData(obs, images, None)


def test_keep_reads_shadows_on_the_diffuse_capture():
    render = torch.full((3, 1, 2, 3), 0.2)
    img = render.clone()
    img[1, 0, 0] = 0.05  # pixel 0: LED 5's diffuse-only capture is dark -> shadow, both its captures go
    img[0, 0, 1] = 0.01  # pixel 1: LED 5's P0 capture lacks a predicted highlight, its P90 matches -> kept
    img[2, 0, 1] = 0.01  # pixel 1: LED 9 has no P90 capture: tested on its own, dropped
    d = _two_leds(img)
    r = (render - img).permute(1, 2, 0, 3).reshape(1, 2, -1)
    keep = Loss("l1", shadow_ratio=0.5).keep(r, d).reshape(1, 2, 3, 3)
    assert keep[0, 0, :2].sum() == 0 and keep[0, 0, 2].sum() == 3
    assert keep[0, 1, :2].sum() == 6 and keep[0, 1, 2].sum() == 0
    assert Loss("l1").keep(r, d) is None  # off by default


def test_keep_never_sets_a_pixel_aside_that_is_dark_under_the_zenith():
    """The camera looks down the axis, so what it sees is lit from there: a pixel dark against
    its render under the near-zenith LEDs too is a model far off, not a shadow; dropping its
    captures would freeze it there (seen on a 16 x 16 sheer before this guard)."""
    render = torch.full((3, 1, 2, 3), 0.2)
    img = torch.full((3, 1, 2, 3), 0.05)
    d = _two_leds(img)
    d.obs.dirs[2] = torch.tensor([0.0, 0.0, 1.0])  # LED 9 at the zenith, dark too
    r = (render - img).permute(1, 2, 0, 3).reshape(1, 2, -1)
    assert bool(Loss("l1", shadow_ratio=0.5).keep(r, d).all())
    img2 = img.clone()
    img2[2] = 0.2  # lit under the zenith LED: LED 5's darkness is a shadow
    r2 = (render - img2).permute(1, 2, 0, 3).reshape(1, 2, -1)
    keep = Loss("l1", shadow_ratio=0.5).keep(r2, StepData(d.obs, img2, None))
    assert keep.reshape(1, 2, 3, 3)[..., :2, :].sum() == 0 and keep.reshape(1, 2, 3, 3)[..., 2, :].all()


def test_keep_ignores_renders_too_dark_to_call():
    img = torch.zeros(3, 1, 2, 3)
    render = torch.full((3, 1, 2, 3), 5e-4)  # a black pixel predicted almost black
    r = (render - img).permute(1, 2, 0, 3).reshape(1, 2, -1)
    assert bool(Loss("l1", shadow_ratio=0.5).keep(r, _two_leds(img)).all())


def test_rejection_undoes_cast_shadows(tmp_path):
    """Captures with cast shadows (``synth --shadows``): setting the shadowed LEDs aside brings
    the normal and albedo errors back towards the shadow-free fit."""
    from dualscale.cli import main

    root = tmp_path / "rk"
    assert main(["synth", "rib_knit", "-o", str(root), "--size", "16", "--texel-um", "9", "--dataset", "--shadows",
                 "--no-previews"]) == 0
    obs = load_observations(root)
    gt = load_maps(root / "maps")[0]
    p = PRESETS["standard"].scaled(0.6)
    on = map_errors(fit_observations(obs, p, TWILL).maps, gt)
    off = map_errors(fit_observations(obs, replace(p, shadow_ratio=0.0), TWILL).maps, gt)
    # measured: 0.04 against 3.3 deg, 0.001 against 0.08
    assert on["normal_mean_deg"] < 0.2 * off["normal_mean_deg"], (on, off)
    assert on["albedo_rmse"] < 0.2 * off["albedo_rmse"], (on, off)


def test_rejection_leaves_shadow_free_fits_alone(datasets):
    root = datasets("sheer")
    obs = load_observations(root).crop(0, 10, 0, 10)
    gt = load_maps(root / "maps")[0].crop(0, 10, 0, 10)
    comps = fit_components(opaque=False, isotropic=False, tinted=True)
    p = PRESETS["standard"].scaled(0.5)
    on = fit_observations(obs, p, comps)
    off = fit_observations(obs, replace(p, shadow_ratio=0.0), comps)
    e_on, e_off = map_errors(on.maps, gt), map_errors(off.maps, gt)
    assert e_on["normal_mean_deg"] < 1.1 * e_off["normal_mean_deg"] + 0.01
    assert e_on["albedo_opacity_rmse"] < 1.1 * e_off["albedo_opacity_rmse"] + 1e-3


def test_shadow_ratio_settings():
    assert PRESETS["standard"].shadow_ratio == 0.5 and PRESETS["paper"].shadow_ratio == 0.0
    with pytest.raises(ValueError, match="shadow_ratio"):
        Preset("x", "adam", (1, 1, 1), shadow_ratio=0.5)
    with pytest.raises(ValueError, match="shadow_ratio"):
        Preset("x", "lm", (1, 1, 1), shadow_ratio=1.5)


def test_selection_leaves_shadowed_validation_captures_out(tmp_path):
    from dualscale.cli import main
    from dualscale.fit.select import select_components

    root = tmp_path / "tw"
    assert main(["synth", "twill", "-o", str(root), "--size", "16", "--texel-um", "9", "--dataset", "--shadows",
                 "--no-previews"]) == 0
    comps, rep = select_components(load_observations(root))
    assert rep["validation"]["shadowed_share"] > 0.01
    assert not comps.isotropic and comps.opaque, rep
