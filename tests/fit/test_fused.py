"""The fused kernel (``fit.fused``) against the eager torch reference: residuals equal the torch
render's, and the analytic Jacobian equals torch autograd's, in float64, for every component
combination, over random parameters that include the extremes (rim normals, alpha floor,
anisotropy near 1, IOR near 1, grazing and below-horizon lights, clamped renders)."""

from __future__ import annotations

import itertools

import pytest
import torch

from dualscale.bsdf import Components
from dualscale.fit import fused
from dualscale.fit.lm import _residual
from dualscale.fit.loop import StepData
from dualscale.fit.observations import Observations
from dualscale.fit.params import PARAM_CHANNELS, pack, param_names
from dualscale.fit.render import clamp_images

H, W = 3, 4


def _dirs(gen: torch.Generator, n: int) -> torch.Tensor:
    """Unit directions: most above the sample, some grazing, some below (transmission)."""
    d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    d[: n // 2, 2] = d[: n // 2, 2].abs() + 0.2
    d[-2] = torch.tensor([0.9999, 0.0, 0.0141], dtype=torch.float64)  # grazing
    d[-1] = torch.tensor([0.3, 0.1, -0.9], dtype=torch.float64)  # under the sample
    return d / d.norm(dim=-1, keepdim=True)


def _problem(comps: Components, seed: int, view_per_pixel: bool, back: bool, n: int = 18):
    gen = torch.Generator().manual_seed(seed)
    names = param_names(comps)
    params = {k: torch.rand(H, W, PARAM_CHANNELS[k], generator=gen, dtype=torch.float64) for k in names}
    if "normal" in params:
        params["normal"] = params["normal"] * 2.0 - 1.0
        params["normal"][0, 0] = torch.tensor([0.97, -0.95])  # near the rim of the hemisphere
    params["roughness"][0, 1] = 0.02  # GGX alpha at its 1e-3 floor
    params["roughness"][0, 2] = 0.04
    if "anisotropy" in params:
        params["anisotropy"][1, 0] = 0.995
    if "ior" in params:
        params["ior"][1, 1] = 0.002  # eta 1.004
    if "specular_tint" in params:
        params["albedo"][1, 2] = torch.tensor([0.3, 0.7, 0.5])  # an unambiguous max channel
    if "opacity" in params:
        params["opacity"][2, 0] = 0.0
    dirs = _dirs(gen, n)
    if view_per_pixel:
        v = torch.randn(H, W, 3, generator=gen, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, 1.0],
                                                                                         dtype=torch.float64)
        view = v / v.norm(dim=-1, keepdim=True)
    else:
        view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    ws = torch.rand(n, generator=gen, dtype=torch.float64)
    obs = Observations(images=torch.rand(n, H, W, 3, generator=gen, dtype=torch.float64) * 0.3, dirs=dirs, w_s=ws,
                       w_p=torch.rand(n, generator=gen, dtype=torch.float64) * 0.5,
                       w_d=torch.rand(n, generator=gen, dtype=torch.float64) + 0.2, led_ids=torch.arange(n),
                       backlight=torch.rand(H, W, 3, generator=gen, dtype=torch.float64) if back else None,
                       view=view)
    images = clamp_images(obs.images) * 4.0  # some images above the clamp, as captured peaks are
    data = StepData(obs, clamp_images(images), None if not back else clamp_images(obs.backlight))
    return names, params, data


def _jacobian(prob, x, names, fixed):
    """The fused kernel's dense Jacobian ``(H, W, K, P)``, which it never stores: row ``k`` is
    ``J^T W r`` with ``W = e_k e_k^T`` and ``r = 1`` (one normal-equations call per row)."""
    r = prob.residuals(x, names, fixed).double()
    h, w = prob.shape
    out = torch.zeros(h, w, prob.k, x.shape[-1], dtype=torch.float64)
    for k in range(prob.k):
        sw = torch.zeros(h, w, prob.k, dtype=torch.float64)
        sw[..., k] = 1.0
        out[..., k, :] = prob.normal_equations(x, names, fixed, torch.ones_like(r), sw)[1]
    return out


COMBOS = [Components(opaque=o, isotropic=i, tinted=t, normal_mapped=nm, ior_mapped=True, ior=1.5)
          for o, i, t, nm in itertools.product((True, False), (True, False), (True, False), (True, False))]


@pytest.mark.parametrize("comps", COMBOS, ids=lambda c: f"o{int(c.opaque)}i{int(c.isotropic)}t{int(c.tinted)}"
                                                        f"n{int(c.normal_mapped)}")
def test_residuals_and_jacobian_match_torch_autograd(comps):
    for seed, (view_pp, back) in enumerate(((False, True), (True, False))):
        names, params, d = _problem(comps, seed, view_pp, back)
        x = pack(params, names)
        prob = fused.Problem(d.obs, d.images, d.back, comps)
        want = _residual(x, names, {}, comps, d)
        got = prob.residuals(x, names, {})
        assert got.shape == want.shape
        assert torch.allclose(got, want, rtol=1e-9, atol=1e-10), (got - want).abs().max()

        def f(xx):
            return _residual(xx, names, {}, comps, d)

        full = torch.autograd.functional.jacobian(f, x)  # (H, W, K, H, W, P)
        ref = torch.stack([torch.stack([full[i, j, :, i, j, :] for j in range(W)]) for i in range(H)])
        jac = _jacobian(prob, x, names, {})
        scale = ref.abs().amax().clamp(min=1.0)
        assert torch.allclose(jac, ref, rtol=1e-6, atol=1e-8 * float(scale)), \
            f"max |diff| {(jac - ref).abs().max():.3g} at {divmod(int((jac - ref).abs().argmax()), 1)}"


def test_normal_equations_equal_dense_products():
    comps = COMBOS[5]
    names, params, d = _problem(comps, 7, False, True)
    x = pack(params, names)
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    r = prob.residuals(x, names, {})
    sw = torch.rand(r.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sw[..., :9] = 0.0  # rows set aside
    jtj, jtr = prob.normal_equations(x, names, {}, r, sw)
    j = _jacobian(prob, x, names, {}) * sw.unsqueeze(-1)
    assert torch.allclose(jtj, torch.einsum("hwkp,hwkq->hwpq", j, j), rtol=1e-10, atol=1e-12)
    assert torch.allclose(jtr, torch.einsum("hwkp,hwk->hwp", j, r * sw), rtol=1e-10, atol=1e-12)


def test_frozen_maps_enter_as_constants():
    comps = COMBOS[0]
    names, params, d = _problem(comps, 3, False, True)
    free = ("roughness", "ior")
    fixed = {k: v for k, v in params.items() if k not in free}
    x = pack(params, free)
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    assert torch.allclose(prob.residuals(x, free, fixed), _residual(x, free, fixed, comps, d), rtol=1e-9, atol=1e-10)
    full = torch.autograd.functional.jacobian(lambda xx: _residual(xx, free, fixed, comps, d), x)
    ref = torch.stack([torch.stack([full[i, j, :, i, j, :] for j in range(W)]) for i in range(H)])
    assert torch.allclose(_jacobian(prob, x, free, fixed), ref, rtol=1e-6, atol=1e-8)


def _polarised_problem(seed: int = 5, n_led: int = 12):
    """LED pairs P0/P90 (the P90 one diffuse-only), a sample mask and clipped samples."""
    names, params, d = _problem(COMBOS[2], seed, False, True, n=2 * n_led)
    o = d.obs
    o.led_ids = torch.arange(n_led).repeat_interleave(2)
    o.dirs = o.dirs.clone()
    o.dirs[1::2] = o.dirs[0::2]
    o.dirs[0] = o.dirs[1] = torch.tensor([0.05, 0.0, 0.99875], dtype=torch.float64)  # near the camera's axis
    o.w_s = torch.tensor([1.0, 0.0] * n_led, dtype=torch.float64)
    o.w_p = torch.zeros(2 * n_led, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    o.valid = torch.rand(2 * n_led, H, W, generator=gen) > 0.15
    o.back_valid = torch.rand(H, W, generator=gen) > 0.3
    o.images[3, 1, 1] = 0.0  # a dark capture: a cast shadow
    return names, params, StepData(o, clamp_images(o.images), clamp_images(o.backlight))


@pytest.mark.parametrize("kind,ratio", [("l1", 0.5), ("l2", 0.5), ("l1", 0.0)])
def test_reweighting_and_cost_match_the_eager_loss(kind, ratio):
    from dualscale.fit.lm import Loss, cost, valid_rows

    comps = COMBOS[2]
    names, params, d = _polarised_problem()
    x = pack(params, names).float()
    d = StepData(d.obs.to(torch.float32), d.images.float(), d.back.float())
    loss = Loss(kind, 1e-4, 16.0, (), ratio)
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    r = prob.residuals(x, names, {})
    keep, sw, c, k = prob.irls(r, loss)
    want_keep = loss.keep(r, d)
    assert want_keep is not None and torch.equal(keep, want_keep)
    if ratio > 0:
        assert bool((keep[..., : 3 * d.obs.n] == 0).any() & d.obs.valid.any())
    cw = loss.row_weights(3 * d.obs.n, True, r) * want_keep
    assert torch.allclose(sw, loss.sqrt_weights(r, cw), rtol=1e-6)
    assert torch.allclose(c, loss.cost(r, cw), rtol=1e-5)
    assert torch.allclose(k, loss.scale(r, valid_rows(d.obs, True, r.dtype)), rtol=1e-6)
    fused_d = StepData(d.obs, d.images, d.back, "fused")
    for kp in (keep, None):
        assert torch.allclose(cost(x, names, {}, comps, fused_d, loss, keep=kp), cost(x, names, {}, comps, d, loss, keep=kp),
                              rtol=1e-5)


def test_fused_fit_matches_the_eager_reference(datasets):
    """The same `standard` fit through both kernels: the maps agree, and so do their errors
    against the ground truth (analytic Jacobians instead of forward differences move LM's path
    a little, so a pixel may settle in a neighbouring minimum)."""
    from dataclasses import replace

    from dualscale.fit.core import fit_observations
    from dualscale.fit.metrics import map_errors
    from dualscale.fit.observations import load_observations
    from dualscale.fit.params import fit_components
    from dualscale.fit.presets import PRESETS
    from dualscale.formats.maps import load_maps

    root = datasets("twill")
    obs = load_observations(root).crop(0, 8, 0, 8)
    gt = load_maps(root / "maps")[0].crop(0, 8, 0, 8)
    comps = fit_components(opaque=True, isotropic=False, tinted=True)
    p = PRESETS["standard"].scaled(0.4)
    assert p.kernel == "fused"
    fast = fit_observations(obs, p, comps)
    ref = fit_observations(obs, replace(p, kernel="eager"), comps)
    assert torch.allclose(fast.maps.albedo, ref.maps.albedo, atol=5e-3)
    assert torch.allclose(fast.maps.normal, ref.maps.normal, atol=5e-3)
    e, f = map_errors(ref.maps, gt), map_errors(fast.maps, gt)
    for k in ("albedo_rmse", "normal_mean_deg", "roughness_mae"):
        assert f[k] <= 1.2 * e[k] + 1e-4, (k, f[k], e[k])
    assert abs(fast.history[-1][2] - ref.history[-1][2]) <= 0.01 * ref.history[-1][2]


def test_a_normal_on_the_rim_keeps_an_inward_derivative():
    """A normal at the box's edge (the square's border maps to the hemisphere's rim, n_z = 0)
    has an infinite exact derivative there, 0 through the guard; the kernel gives the inward
    secant, as the eager forward differences do, so LM can bring the normal back (a twill pixel
    of the test set was pinned on the rim before)."""
    comps = COMBOS[0]
    names, params, d = _problem(comps, 11, False, False)
    params["normal"][1, 1] = torch.tensor([-1.0, 0.2], dtype=torch.float64)
    x = pack(params, names)
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    jac = _jacobian(prob, x, names, {})[1, 1]
    col = sum(PARAM_CHANNELS[n] for n in names[:names.index("normal")])
    step = 3e-4
    xp = x.clone()
    xp[1, 1, col] += step  # inward
    fd = (_residual(xp, names, {}, comps, d) - _residual(x, names, {}, comps, d))[1, 1] / step
    lit = fd.abs() > 1e-3
    assert bool(lit.any())
    assert torch.allclose(jac[:, col][lit], fd[lit], rtol=0.15, atol=1e-3)  # two secants: the render's, n_z's


def test_carried_residuals_are_the_ones_a_fresh_render_gives(datasets, monkeypatch):
    """The fused LM renders once per iteration: the accepted trial's residuals are carried into
    the next one.  They are used (every iteration but the first of each step) and the fit is bit
    for bit the fit that renders afresh every iteration."""
    from dualscale.fit import lm
    from dualscale.fit.core import fit_observations
    from dualscale.fit.observations import load_observations
    from dualscale.fit.params import fit_components
    from dualscale.fit.presets import PRESETS

    obs = load_observations(datasets("twill")).crop(0, 6, 0, 6)
    comps = fit_components(opaque=True, isotropic=False, tinted=True)
    p = PRESETS["standard"].scaled(0.4)
    used = []
    carried = lm._carried

    def counted(db, x, fixed):
        r = carried(db, x, fixed)
        used.append(r is not None)
        return r

    monkeypatch.setattr(lm, "_carried", counted)
    with_carry = fit_observations(obs, p, comps)
    assert sum(used) == p.total - 3, used  # the first iteration of each step renders
    monkeypatch.setattr(lm, "_carried", lambda db, x, fixed: None)
    fresh = fit_observations(obs, p, comps)
    for name, t in with_carry.maps.items():
        assert torch.equal(t, getattr(fresh.maps, name)), name


def test_select_is_the_lower_median_and_any_order_statistic():
    """The likelihood scale's median (``fused._select``, in place) equals sorting's, ties and
    small sizes included (torch's median is the lower one for an even count)."""
    import numpy as np

    rng = np.random.default_rng(0)
    for m in (1, 2, 3, 4, 7, 24, 25, 26, 100, 669):
        for t in range(20):
            a = rng.random(m) if t % 2 else rng.integers(0, 3, m).astype(float)
            for k in {(m - 1) // 2, 0, m - 1, int(rng.integers(0, m))}:
                assert fused._select(a.copy(), m, k, np.empty(m)) == np.sort(a)[k]
            assert fused._select(a.copy(), m, (m - 1) // 2, np.empty(m)) == torch.from_numpy(a).median().item()


@pytest.mark.parametrize("comps", [COMBOS[2], COMBOS[13]], ids=["masked-opaque-aniso-tinted", "translucent-aniso-flat"])
def test_adam_loss_and_gradient_match_autograd(comps):
    """The paper preset's loss through the fused kernel (numba renders, gradient by the analytic
    vector-Jacobian product) equals the eager ``l1_loss`` and its autograd gradient."""
    from dualscale.fit.optimize import fused_l1_loss, l1_loss

    names, params, d = _polarised_problem() if comps is COMBOS[2] else _problem(comps, 4, False, True)
    for k in params:
        params[k].requires_grad_(True)
    fixed = {}
    want = l1_loss(params, fixed, comps, d.obs, d.images, d.back, 16.0)
    gw = torch.autograd.grad(want, [params[k] for k in names])
    prob = fused.Problem(d.obs, d.images, d.back, comps)
    got = fused_l1_loss(params, fixed, prob, 16.0)
    gg = torch.autograd.grad(got, [params[k] for k in names])
    assert torch.allclose(got, want, rtol=1e-9)
    for n, a, b in zip(names, gg, gw):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-9), n
