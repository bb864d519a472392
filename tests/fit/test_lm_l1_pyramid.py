"""LM on the paper's L1 loss (IRLS) and the coarse-to-fine preset."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from dualscale.bsdf import normal_from_square
from dualscale.fit.checkpoint import FitInterrupted
from dualscale.fit.core import fit_observations
from dualscale.fit.init import initial_params
from dualscale.fit.lm import Loss, cost, lm_iteration
from dualscale.fit.loop import step_data
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.optimize import l1_loss
from dualscale.fit.params import fit_components, pack, param_names
from dualscale.fit.presets import PRESETS, Preset
from dualscale.fit.pyramid import downsample, upsample_params
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)
SHEER = fit_components(opaque=False, isotropic=False, tinted=True)
C2F = PRESETS["coarse-to-fine"]


def _finite(res):
    for name, t in res.maps.items():
        assert torch.isfinite(t).all(), name


def test_l1_cost_is_the_adam_loss_with_back_weight(datasets):
    """LM's L1 cost weights the back-lit residuals exactly as the paper's Adam loss does."""
    obs = load_observations(datasets("sheer")).crop(0, 6, 0, 6)
    assert obs.backlight is not None
    params = initial_params(obs, SHEER)
    names = param_names(SHEER)
    d = step_data(obs, "joint")
    loss = Loss("l1", back_weight=16.0)
    lm_total = float(cost(pack(params, names), names, {}, SHEER, d, loss).sum())
    adam = float(l1_loss(params, {}, SHEER, obs, d.images, d.back, 16.0)) * 6 * 6 * 3 * (obs.n + 16.0)
    assert lm_total == pytest.approx(adam, rel=1e-4)


def test_l1_cost_decreases_monotonically_per_pixel(datasets):
    obs = load_observations(datasets("sheer")).crop(4, 10, 4, 10)
    params = initial_params(obs, SHEER)
    names = param_names(SHEER)
    d = step_data(obs, "joint")
    loss = Loss("l1", eps=1e-4, back_weight=16.0)
    x = pack(params, names)
    lam = torch.full(obs.shape, 1e-2)
    c_prev = cost(x, names, {}, SHEER, d, loss)
    c_start = c_prev
    for _ in range(6):
        x, lam, c = lm_iteration(x, lam, names, {}, SHEER, d, loss, {})
        assert torch.all(c <= c_prev), "a pixel's L1 cost rose"
        # the reported cost is the true L1 cost of the new point, not the reweighted one
        assert torch.allclose(c, cost(x, names, {}, SHEER, d, loss), rtol=1e-5, atol=0)
        c_prev = c
    assert float(c_prev.mean()) < 0.5 * float(c_start.mean())


def test_l1_beats_l2_with_sparse_outliers(datasets):
    """5 % of the LED image values replaced by large values (hot pixels, specks): L1 shrugs them
    off, L2 does not."""
    root = datasets("twill")
    obs = load_observations(root).crop(0, 10, 0, 10)
    gt = load_maps(root / "maps")[0].crop(0, 10, 0, 10)
    g = torch.Generator().manual_seed(0)
    hit = torch.rand(obs.images.shape, generator=g) < 0.05
    obs.images = torch.where(hit, 1.0 + torch.rand(obs.images.shape, generator=g), obs.images)
    p = PRESETS["standard"].scaled(0.6)
    e1 = map_errors(fit_observations(obs, replace(p, loss="l1"), TWILL).maps, gt)
    e2 = map_errors(fit_observations(obs, replace(p, loss="l2"), TWILL).maps, gt)
    assert e1["albedo_rmse"] < 0.01 and e1["normal_mean_deg"] < 1.0
    assert e1["albedo_rmse"] < 0.2 * e2["albedo_rmse"]
    assert e1["normal_mean_deg"] < 0.2 * e2["normal_mean_deg"]


def test_coarse_to_fine_no_nan_with_black_saturated_shadowed_pixels(datasets):
    obs = load_observations(datasets("twill")).crop(0, 12, 0, 12)
    imgs = obs.images.clone()
    imgs[:, 0:2, 0:2] = 0.0  # fully black
    imgs[:, 3:5, 3:5] = 1e4  # saturated far beyond the clamp
    imgs[obs.dirs[:, 2] < 0.45, 6:10, 6:10] = 0.0  # shadows under grazing lights
    obs.images = imgs
    res = fit_observations(obs, C2F, TWILL)
    _finite(res)
    assert all(np.isfinite(v) for v in res.losses.values())
    assert float(res.maps.albedo[0:2, 0:2].max()) < 0.05  # black pixels fit black


def test_coarse_to_fine_interrupt_and_resume(datasets, tmp_path):
    obs = load_observations(datasets("twill")).crop(0, 10, 0, 10)
    full = fit_observations(obs, C2F, TWILL)
    ck = tmp_path / "ck.pt"
    with pytest.raises(FitInterrupted):
        fit_observations(obs, C2F, TWILL, checkpoint=ck, checkpoint_every=3, stop_after=5)
    resumed = fit_observations(obs, C2F, TWILL, checkpoint=ck, checkpoint_every=3)
    assert resumed.resumed_from == 5
    for (name, a), (_, b) in zip(full.maps.items(), resumed.maps.items()):
        assert torch.allclose(a, b, atol=1e-6, rtol=0), name


def test_downsample_is_a_box_mean():
    n, h, w = 3, 5, 7
    imgs = torch.rand(n, h, w, 3)
    from dualscale.fit.observations import Observations

    obs = Observations(images=imgs, dirs=torch.tensor([[0.0, 0.0, 1.0]] * n), w_s=torch.ones(n), w_p=torch.zeros(n),
                       w_d=torch.ones(n), led_ids=torch.arange(n), backlight=imgs[0].clone())
    lo = downsample(obs, 2)
    assert lo.shape == (3, 4) and lo.n == n
    assert torch.allclose(lo.images[:, 0, 0], imgs[:, 0:2, 0:2].mean((1, 2)))
    assert torch.allclose(lo.images[:, 2, 3], imgs[:, 4, 6])  # a corner block holds one pixel
    assert torch.allclose(lo.backlight[1, 1], imgs[0, 2:4, 2:4].mean((0, 1)))


def test_upsample_respects_parametrisations():
    # tangent 0.95 and 0.05 are 18 deg apart across the wrap: the blend is ~0, not 0.5
    tan = torch.tensor([[[0.95], [0.05]]])
    normal = torch.tensor([[[0.6, 0.0], [-0.6, 0.0]]])
    up = upsample_params({"tangent": tan, "normal": normal, "roughness": torch.tensor([[[0.2], [0.6]]])}, 2, (2, 4))
    mid = up["tangent"][0, 1:3, 0]
    assert torch.all(torch.minimum(mid, 1.0 - mid) < 0.06)
    n = normal_from_square(up["normal"])
    assert torch.allclose(n.norm(dim=-1), torch.ones(2, 4), atol=1e-5) and torch.all(n[..., 2] > 0)
    assert torch.allclose(up["roughness"][0, :, 0], torch.tensor([0.2, 0.3, 0.5, 0.6]))


def test_loss_and_coarse_settings_are_validated():
    with pytest.raises(ValueError, match="loss"):
        Preset("x", "lm", (1, 1, 1), loss="huber")
    with pytest.raises(ValueError, match="L1"):
        Preset("x", "adam", (1, 1, 1), loss="l2")
    with pytest.raises(ValueError, match="coarse"):
        Preset("x", "adam", (1, 1, 1), coarse_factor=2)
    assert C2F.scaled(0.5).iterations == (1, 1, 3) and C2F.scaled(0.5).coarse_iterations == (2, 2, 5)
    assert PRESETS["standard"].loss == "l1" and math.isclose(PRESETS["standard"].l1_eps, 1e-4)
