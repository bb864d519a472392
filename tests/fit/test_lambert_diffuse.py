"""Lambert's diffuse (``Components(diffuse="lambert")``, chosen for matte photographs by
fit/select.py): the torch model, the plain reference and the fused kernel agree, and it is
``b / pi`` whatever the roughness."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import torch

from dualscale.bsdf import Components, MaterialMaps, evaluate, evaluate_reference
from dualscale.fit import fused
from dualscale.fit.lm import _residual
from dualscale.fit.params import pack
from dualscale.fit.select import diffuse_only
from test_fused import H, W, _jacobian, _problem

DIRS = np.array([[0.4972, 0.4669, 0.7313], [0.2431, 0.1353, 0.9605], [-0.0386, 0.1738, 0.9840],
                 [-0.3176, 0.5053, 0.8024], [0.1292, 0.0447, 0.9906], [0.6, -0.2, 0.3]])
DIRS = DIRS / np.linalg.norm(DIRS, axis=1, keepdims=True)


LAMBERT = [Components(opaque=o, isotropic=i, tinted=t, normal_mapped=True, ior_mapped=True, diffuse="lambert")
           for o, i, t in itertools.product((True, False), (True, False), (True, False))]


@pytest.mark.parametrize("comps", LAMBERT, ids=lambda c: f"o{int(c.opaque)}i{int(c.isotropic)}t{int(c.tinted)}")
def test_lambert_diffuse_fused_kernel_matches_torch(comps):
    """Residuals and the analytic Jacobian of the fused kernel equal the torch reference's (and
    autograd's) for Lambert's diffuse too, as tests/fit/test_fused.py checks Burley's."""
    names, params, d = _problem(comps, 2, True, not comps.opaque)
    x = pack(params, names)
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    want = _residual(x, names, {}, comps, d)
    assert torch.allclose(prob.residuals(x, names, {}), want, rtol=1e-9, atol=1e-10)
    assert not torch.allclose(want, _residual(x, names, {}, replace(comps, diffuse="burley"), d), atol=1e-4)
    full = torch.autograd.functional.jacobian(lambda xx: _residual(xx, names, {}, comps, d), x)
    ref = torch.stack([torch.stack([full[i, j, :, i, j, :] for j in range(W)]) for i in range(H)])
    scale = float(ref.abs().amax().clamp(min=1.0))
    assert torch.allclose(_jacobian(prob, x, names, {}), ref, rtol=1e-6, atol=1e-8 * scale)


def test_lambert_diffuse_is_b_over_pi_and_ignores_roughness():
    g = torch.Generator().manual_seed(3)
    h = w = 3
    n = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    n[..., 2] = n[..., 2].abs() + 1.0
    n = n / n.norm(dim=-1, keepdim=True)
    maps = MaterialMaps(albedo=torch.rand(h, w, 3, generator=g, dtype=torch.float64),
                        roughness=torch.rand(h, w, 1, generator=g, dtype=torch.float64), normal=n)
    comps = diffuse_only(diffuse="lambert")
    dirs = torch.tensor(DIRS)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    f = evaluate(maps, dirs, view, comps)
    cos = torch.einsum("kc,hwc->khw", dirs, n).clamp(min=0).unsqueeze(-1)
    assert torch.allclose(f, maps.albedo / torch.pi * cos, rtol=1e-12, atol=1e-15)
    assert torch.allclose(evaluate_reference(maps, dirs, view, comps), f, rtol=1e-12, atol=1e-15)
    rough = replace(maps, roughness=1.0 - maps.roughness)
    assert torch.equal(evaluate(rough, dirs, view, comps), f)
    with pytest.raises(ValueError, match="diffuse model"):
        Components(diffuse="oren-nayar")


@pytest.mark.parametrize("loss", ["l1", "l2"])
def test_lambert_fit_through_the_fused_kernel_matches_the_eager_reference(loss):
    """A `standard` fit of a Lambertian scene under unpolarised lights through both kernels:
    the same maps, near the truth, for both losses the component choice can pick."""
    from dualscale.bsdf import normal_from_square
    from dualscale.fit.core import fit_observations
    from dualscale.fit.observations import Observations
    from dualscale.fit.presets import PRESETS

    g = torch.Generator().manual_seed(4)
    h = w = 6
    sq = (torch.rand(h, w, 2, generator=g, dtype=torch.float64) - 0.5) * 0.8
    normal = normal_from_square(sq)
    albedo = torch.rand(h, w, 3, generator=g, dtype=torch.float64) * 0.6 + 0.2
    dirs = torch.tensor(DIRS[:5], dtype=torch.float64)
    dirs = torch.cat([dirs, torch.tensor([[-0.3, -0.4, 0.866], [0.0, 0.0, 1.0]], dtype=torch.float64)])
    n = dirs.shape[0]
    images = albedo / torch.pi * torch.einsum("kc,hwc->khw", dirs, normal).clamp(min=0).unsqueeze(-1)
    images = images + 1e-3 * torch.randn(images.shape, generator=g, dtype=torch.float64)
    obs = Observations(images.float(), dirs.float(), torch.full((n,), 0.5), torch.full((n,), 0.5), torch.ones(n),
                       torch.arange(n), pixel_mm=None)
    comps = diffuse_only(diffuse="lambert")
    p = replace(PRESETS["standard"].scaled(0.5), loss=loss)
    assert p.kernel == "fused"
    fast = fit_observations(obs, p, comps)
    ref = fit_observations(obs, replace(p, kernel="eager"), comps)
    assert torch.allclose(fast.maps.albedo, ref.maps.albedo, atol=2e-3)
    assert torch.allclose(fast.maps.normal, ref.maps.normal, atol=2e-3)
    ang = torch.rad2deg(torch.arccos((fast.maps.normal.double() * normal).sum(-1).clamp(-1, 1)))
    assert float(ang.mean()) < 1.0 and torch.allclose(fast.maps.albedo.double(), albedo, atol=0.02)
