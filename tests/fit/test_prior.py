"""The LM presets' Gaussian prior on the IOR map (a MAP fit)."""

from dataclasses import replace

import pytest
import torch

from dualscale.bsdf import DEFAULT_IOR, map_from_ior
from dualscale.fit.core import fit_observations
from dualscale.fit.init import initial_params
from dualscale.fit.lm import Loss, Prior, _residual, cost, lm_iteration, preset_loss
from dualscale.fit.loop import step_data
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components, pack, param_names
from dualscale.fit.presets import PRESETS, Preset
from dualscale.fit.render import render_leds
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)
NAMES = param_names(TWILL)


@pytest.mark.parametrize("kind", ["l1", "l2"])
def test_prior_gradient_and_curvature_match_its_cost(kind):
    """The normal equations solve the Gauss-Newton surrogate of the cost: for L1 (IRLS) the
    surrogate is the cost itself, for L2 half of it, so the prior's gradient and curvature must be
    those of ``cost`` (L1) or ``cost / 2`` (L2)."""
    loss = Loss(kind, priors=(Prior("ior", 0.25, 0.05),))
    x = torch.rand(3, 4, sum({"albedo": 3, "normal": 2}.get(n, 1) for n in NAMES), dtype=torch.float64)
    x.requires_grad_(True)
    k = torch.rand(3, 4, dtype=torch.float64) + 0.1
    c, g, h = loss.prior_terms(x, NAMES, k)
    half = 1.0 if kind == "l1" else 0.5
    (grad,) = torch.autograd.grad((half * c).sum(), x, create_graph=True)
    assert torch.allclose(g, grad)
    j = sum({"albedo": 3, "normal": 2}.get(n, 1) for n in NAMES[:NAMES.index("ior")])
    (curv,) = torch.autograd.grad(grad[..., j].sum(), x)
    assert torch.allclose(h[..., j], curv[..., j])
    assert torch.count_nonzero(h) == h.shape[0] * h.shape[1]  # only the IOR channel


def test_prior_cost_never_rises_and_is_reported(datasets):
    obs = load_observations(datasets("twill")).crop(0, 6, 0, 6)
    params = initial_params(obs, TWILL)
    params["ior"].fill_(0.6)  # far from the prior mean: the prior term matters
    d = step_data(obs, "joint")
    loss = Loss("l1", priors=(Prior("ior", 0.25, 0.05),))
    x = pack(params, NAMES)
    lam = torch.full(obs.shape, 1e-2)
    for _ in range(4):
        k = loss.scale(_residual(x, NAMES, {}, TWILL, d))  # the scale the iteration weighs with
        c0 = cost(x, NAMES, {}, TWILL, d, loss, k)
        data = cost(x, NAMES, {}, TWILL, d, loss)
        assert torch.all(c0 >= data) and float(c0.sum()) > float(data.sum())  # IOR off the mean: the prior adds
        x, lam, c = lm_iteration(x, lam, NAMES, {}, TWILL, d, loss, {})
        assert torch.isfinite(c).all() and torch.all(c <= c0)
        assert torch.allclose(c, cost(x, NAMES, {}, TWILL, d, loss, k), rtol=1e-5)


def _noisy(obs, rel: float, seed: int):
    g = torch.Generator().manual_seed(seed)
    obs.images = (obs.images * (1 + rel * torch.randn(obs.images.shape, generator=g))).clamp(min=0)
    return obs


def test_prior_tames_ior_under_noise_and_leaves_the_rest(datasets):
    """Under 3 % noise the maximum-likelihood IOR scatters where the specular barely constrains
    it; the prior pulls those pixels in and changes albedo and normals by little."""
    root = datasets("twill")
    obs = _noisy(load_observations(root).crop(0, 12, 0, 12), 0.03, 0)
    gt = load_maps(root / "maps")[0].crop(0, 12, 0, 12)
    p = PRESETS["standard"]
    e_map = map_errors(fit_observations(obs, p, TWILL).maps, gt)
    e_ml = map_errors(fit_observations(obs, replace(p, ior_prior_sd=0.0), TWILL).maps, gt)
    assert e_map["ior_mae"] < 0.8 * e_ml["ior_mae"]
    assert e_map["albedo_rmse"] < 1.1 * e_ml["albedo_rmse"]
    assert e_map["normal_mean_deg"] < 1.1 * e_ml["normal_mean_deg"]


def test_noiseless_fit_is_not_biased_by_the_prior(datasets):
    """With exact data the residual scale collapses, so the prior stops mattering: an IOR three
    prior sds away from its mean (eta 1.8) is still recovered."""
    root = datasets("twill")
    obs = load_observations(root).crop(0, 8, 0, 8)
    gt = load_maps(root / "maps")[0].crop(0, 8, 0, 8)
    gt.ior = torch.full_like(gt.roughness, float(map_from_ior(1.8)))
    obs.images = render_leds(gt, TWILL, obs).detach()  # the exact forward model: no noise at all
    res = fit_observations(obs, PRESETS["standard"], TWILL)
    assert float((res.maps.ior - gt.ior).abs().mean()) < 0.01


def test_prior_settings():
    assert preset_loss(PRESETS["standard"]).priors == (Prior("ior", float(map_from_ior(DEFAULT_IOR)), 0.05),)
    assert preset_loss(replace(PRESETS["standard"], ior_prior_sd=0.0)).priors == ()
    assert PRESETS["paper"].ior_prior_sd == 0.0  # the paper's procedure has no prior
    with pytest.raises(ValueError, match="LM"):
        Preset("x", "adam", (1, 1, 1), ior_prior_sd=0.05)
    with pytest.raises(ValueError, match="ior_prior_sd"):
        Preset("x", "lm", (1, 1, 1), ior_prior_sd=-1.0)
