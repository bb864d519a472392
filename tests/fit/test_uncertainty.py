"""Per-pixel covariance of an LM fit (``fit.uncertainty``, issue 26 part): the normal matrix against
a brute-force finite-difference Hessian of the same cost, the undetermined cases, and a calibration
smoke check on a synthetic dataset with Gaussian noise of known sigma."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from dualscale.fit.checkpoint import Checkpointer
from dualscale.fit.init import initial_params
from dualscale.fit.lm import Loss, cost, preset_loss, run_lm
from dualscale.fit.loop import Loop, step_data
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components, pack, params_from_maps
from dualscale.fit.presets import PRESETS
from dualscale.fit.uncertainty import _offsets, map_sigmas, normal_matrices, pixel_covariance
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)


def _fit(obs, preset):
    params = {k: v.clone() for k, v in initial_params(obs, TWILL).items()}
    run_lm(params, TWILL, obs, Loop(preset, TWILL, Checkpointer(None, "test", 0)))
    return params


def _noisy_crop(root, n: int, noise: float, seed: int):
    """The ``n`` x ``n`` corner of a dataset with Gaussian noise of ``noise`` on every LED and
    back-lit sample."""
    obs = load_observations(root).crop(0, n, 0, n)
    g = torch.Generator().manual_seed(seed)
    return replace(obs, images=obs.images + noise * torch.randn(obs.images.shape, generator=g),
                   backlight=obs.backlight + noise * torch.randn(obs.backlight.shape, generator=g))


def test_normal_matrix_is_the_finite_difference_hessian(datasets):
    """At the true maps of a noise-free dataset the residuals vanish, so the Hessian of the L2 cost
    ``sum c r^2`` over the kept rows is exactly ``2 J^T C J``: the matrix the covariance inverts
    must equal half the central second differences of ``lm.cost`` (tolerance: 5e-3 of the largest
    entry: the O(h^2) truncation at h = 1e-3 and the float32 images' residuals, < 1e-3, times the
    second derivatives; measured 1e-5 to 2e-3)."""
    root = datasets("twill")
    obs = load_observations(root).crop(4, 6, 4, 6)
    gt, _ = load_maps(root / "maps")
    params = {k: v[4:6, 4:6].double().contiguous() for k, v in params_from_maps(gt, TWILL).items()}
    preset = PRESETS["standard"]
    m = normal_matrices(params, TWILL, obs, preset)
    names, x, a = m["names"], m["x"], m["A"]
    assert float(m["residuals"].abs().max()) < 1e-3  # the truth fits
    d = step_data(obs, "joint", "fused")
    loss = Loss("l2", back_weight=preset.back_weight)
    keep = m["keep"].to(torch.float64)
    h, p = 1e-3, x.shape[-1]

    def q(dx):
        return cost(x + dx, names, {}, TWILL, d, loss, keep=keep).double()

    hess = torch.zeros_like(a)
    for i in range(p):
        for j in range(i, p):
            ei = torch.zeros(p, dtype=torch.float64)
            ej = torch.zeros(p, dtype=torch.float64)
            ei[i], ej[j] = h, h
            v = (q(ei + ej) - q(ei - ej) - q(ej - ei) + q(-ei - ej)) / (4 * h * h)
            hess[..., i, j] = hess[..., j, i] = 0.5 * v
    # parameters within 2h of a bound or of the GGX alpha floor are clamped inside the model
    is_normal = torch.zeros(p, dtype=torch.bool)
    is_normal[_offsets(names)["normal"]] = True
    ok = ((x > 2 * h) | is_normal) & (x < 1 - 2 * h) & (x > -1 + 2 * h)
    ok[..., _offsets(names)["roughness"]] &= x[..., _offsets(names)["roughness"]] > 0.04
    outer = ok.unsqueeze(-1) & ok.unsqueeze(-2)
    assert int(ok.sum()) >= 4 * (p - 3)  # most parameters take part
    err = ((hess - a).abs() * outer).amax((-2, -1))
    scale = (a.abs() * outer).amax((-2, -1))
    print("max |FD - A| / max |A| per pixel:", (err / scale).flatten().tolist())
    assert torch.all(err <= 5e-3 * scale)


def test_undetermined_cases(datasets):
    obs = load_observations(datasets("twill")).crop(0, 4, 0, 4)
    preset = PRESETS["standard"].scaled(0.3)
    params = _fit(obs, preset)
    params["specular_tint"][0, 0] = 1.0  # pinned at its box
    params["albedo"][0, 1, 1] = 0.0
    params["anisotropy"][1, 0] = 0.0  # a round lobe: the tangent means nothing
    params["anisotropy"][1, 1] = 0.01
    valid = torch.ones(obs.images.shape[:3], dtype=torch.bool)
    valid[:, 2, 2] = False  # no valid sample at all
    back_valid = torch.ones(obs.shape, dtype=torch.bool)
    back_valid[2, 2] = False
    obs = replace(obs, valid=valid, back_valid=back_valid)
    cov, names, det = pixel_covariance(params, TWILL, obs, preset)
    off = _offsets(names)
    assert not bool(det[0, 0, off["specular_tint"]].any())
    assert bool(det[0, 0, off["roughness"]].all()) and bool(det[0, 0, off["albedo"]].all())
    assert not bool(det[0, 1, off["albedo"].start + 1]) and bool(det[0, 1, off["albedo"].start])
    assert not bool(det[2, 2].any()) and bool(torch.isnan(cov[2, 2]).all())
    assert float(det.float().mean()) > 0.8  # elsewhere the fit is determined
    assert torch.isnan(cov[0, 0, off["specular_tint"]]).all()
    sig, und = map_sigmas(params, cov, names, det, TWILL)
    assert bool(und["tangent"][1, 0].all()) and bool(und["tangent"][1, 1].all())
    assert bool(und["specular_tint"][0, 0].all()) and bool(torch.isnan(sig["specular_tint"][0, 0]).all())
    assert all(bool(u[2, 2].all()) for u in und.values())
    assert set(sig) == set(names) and sig["normal"].shape == (4, 4, 1) and sig["albedo"].shape == (4, 4, 3)
    assert int((~und["roughness"]).sum()) >= 14 and bool(torch.isfinite(sig["roughness"][~und["roughness"]]).all())


def test_calibration_smoke(datasets):
    """Gaussian noise of sigma 0.003 (the images' median is ~0.02) on a 12 x 12 twill crop, fitted
    with ``standard``: the z-scores of albedo and roughness over the determined pixels must have
    a spread in [0.6, 1.6] (a loose smoke bound, not the issue's calibration table)."""
    root = datasets("twill")
    n = 12
    obs = _noisy_crop(root, n, 0.003, seed=7)
    preset = PRESETS["standard"]
    params = _fit(obs, preset)
    cov, names, det = pixel_covariance(params, TWILL, obs, preset)
    sig, und = map_sigmas(params, cov, names, det, TWILL)
    gt, _ = load_maps(root / "maps")
    for name in ("albedo", "roughness"):
        z = ((params[name].double() - getattr(gt, name)[:n, :n].double()) / sig[name])[~und[name]]
        sd, cover = float(z.std()), float((z.abs() < 1.96).double().mean())
        print(f"{name}: {z.numel()} determined, z sd {sd:.3f}, 95% coverage {cover:.3f}, "
              f"median sigma {float(sig[name][~und[name]].median()):.4g}")
        assert z.numel() >= 0.8 * n * n * getattr(gt, name).shape[-1]
        assert 0.6 <= sd <= 1.6


def test_back_lit_rows_weighted_twice_match_the_kernels_pass(datasets):
    """``B = J^T C^2 J`` of a translucent material (the back-lit rows weigh ``back_weight`` in
    ``A``, its square in ``B``) equals the fused kernel's own pass with the row multipliers
    ``C keep``, and differs from ``A``."""
    from dualscale.bsdf import Components
    from dualscale.fit import lm
    from dualscale.fit.loop import free_names

    root = datasets("sheer")
    obs = load_observations(root).crop(0, 4, 0, 4)
    gt, meta = load_maps(root / "maps")
    comps = Components(opaque=False, isotropic=True, tinted=False)
    params = {k: v[0:4, 0:4].double().contiguous() for k, v in params_from_maps(gt, comps).items()}
    preset = PRESETS["standard"]
    m = normal_matrices(params, comps, obs, preset)
    names = free_names("joint", params)
    assert "transmittance" in names and "opacity" in names
    d = step_data(obs, "joint", "fused")
    prob = lm.problem(lm._block(d, 0, 4), comps)
    x = pack(params, names)
    fixed = {k: v for k, v in params.items() if k not in names}
    r = prob.residuals(x, names, fixed)
    c = torch.from_numpy(prob.row_weights(preset.back_weight)).to(m["keep"].dtype)
    b_ref, _ = prob.normal_equations(x, names, fixed, r, c * m["keep"])
    assert not torch.allclose(m["A"], m["B"])  # the back-lit rows count
    torch.testing.assert_close(m["B"], b_ref, rtol=1e-9, atol=1e-9 * float(b_ref.abs().max()))


def test_row_noise_recovers_read_and_shot_noise():
    """Residuals drawn with ``var = a + b mu`` per pixel (read-noise and shot-noise dominated
    pixels, and one with a cast-shadow outlier set aside by ``keep``, another with a few gross
    outliers kept): the fitted per-row sigma is within 5 % of the truth on the median row and 12 %
    on the 95th percentile row of every pixel (the read term of a shot-dominated pixel is
    estimated worst: its few darkest rows are off by up to ~25 %)."""
    from dualscale.fit.uncertainty import row_noise

    g = torch.Generator().manual_seed(3)
    h, w, k = 2, 2, 800
    mu = torch.rand(h, w, k, generator=g, dtype=torch.float64) * 0.5
    a = torch.tensor([[1e-6, 1e-8], [4e-6, 1e-7]], dtype=torch.float64)
    b = torch.tensor([[0.0, 5e-5], [2e-5, 1e-4]], dtype=torch.float64)
    sd = (a[..., None] + b[..., None] * mu).sqrt()
    r = sd * torch.randn(h, w, k, generator=g, dtype=torch.float64)
    keep = torch.ones(h, w, k)
    r[0, 0, :40] = -0.3  # a cast shadow, not kept
    keep[0, 0, :40] = 0
    r[1, 1, :4] += 0.5  # four gross outliers, kept (the clip bounds them)
    est = row_noise(r, mu, keep)  # mu: the render (an outlier is in the image, not in it)
    ratio = est / sd
    dev = (ratio - 1).abs()
    print(dev.median(-1).values, dev.quantile(0.95, dim=-1))
    assert float(dev.median(-1).values.amax()) < 0.05 and float(dev.quantile(0.95, dim=-1).amax()) < 0.12


def test_row_noise_scales_each_images_read_and_shot_noise():
    """Images taken at different exposures (the rig meters each one) carry, in radiance, read
    noise ``a u^2`` and shot noise ``b u mu`` with ``u`` the image's signal scale (1 / exposure):
    with the recorded scales (:func:`.uncertainty.row_scales`' ``u``) the fitted per-row sigma is
    within 8 % of the truth on the median row and 12 % on the 95th percentile (measured 0.6-6.3 %
    and 5-8 %); the one-scale model (no ``u``) is off by 51-76 % on the median row."""
    from dualscale.fit.uncertainty import row_noise

    g = torch.Generator().manual_seed(5)
    h, w, k = 2, 2, 900
    u = torch.exp(torch.rand(k, generator=g, dtype=torch.float64) * 4.0)  # exposures over a range of e^4
    mu = torch.rand(h, w, k, generator=g, dtype=torch.float64) * 0.5
    a = torch.tensor([[1e-7, 1e-8], [4e-7, 1e-8]], dtype=torch.float64)
    b = torch.tensor([[1e-6, 5e-6], [2e-6, 1e-5]], dtype=torch.float64)
    sd = (a[..., None] * u ** 2 + b[..., None] * u * mu).sqrt()
    r = sd * torch.randn(h, w, k, generator=g, dtype=torch.float64)
    keep = torch.ones(h, w, k)
    dev = (row_noise(r, mu, keep, u.numpy()) / sd - 1).abs()
    assert float(dev.median(-1).values.amax()) < 0.08 and float(dev.quantile(0.95, dim=-1).amax()) < 0.12
    one = (row_noise(r, mu, keep) / sd - 1).abs()
    assert float(one.median(-1).values.amin()) > 0.3
    # u = 1 is the one-scale model, bit for bit
    assert torch.equal(row_noise(r, mu, keep, torch.ones(k, dtype=torch.float64).numpy()), row_noise(r, mu, keep))


def test_row_scales_follow_the_observations():
    """:func:`.uncertainty.row_scales`: per residual row (``3 k + c``, then the back light's
    three), relative to the largest; 1 everywhere without recorded scales; a subset keeps its
    images' scales."""
    from dualscale.fit.observations import Observations
    from dualscale.fit.uncertainty import row_scales

    n = 3
    obs = Observations.relative_p0(torch.rand(n, 2, 2, 3), torch.tensor([[0.0, 0.0, 1.0]] * n), [1, 2, 3], 0.01)
    assert (row_scales(obs, 3 * n) == 1).all()
    obs = replace(obs, signal_scale=torch.tensor([[1.0] * 3, [2.0] * 3, [4.0] * 3], dtype=torch.float64),
                  backlight=torch.rand(2, 2, 3), back_signal_scale=torch.full((3,), 0.5, dtype=torch.float64))
    assert row_scales(obs, 3 * n + 3).tolist() == [0.25] * 3 + [0.5] * 3 + [1.0] * 3 + [0.125] * 3
    assert row_scales(obs.select_leds({3}), 3).tolist() == [1.0] * 3


def test_calibration_under_shot_and_read_noise(datasets):
    """The sensor's noise (Poisson shot noise at 20 000 e- per unit radiance plus 5 e- read noise,
    as the virtual rig's realistic sensor) on a 12 x 12 twill crop, fitted with ``standard``: the
    per-pixel noise model (:func:`.uncertainty.row_noise`) makes the z-scores' spread of albedo,
    roughness and the normal's RMS angle land in [0.75, 1.33] (the issue's 0.8-1.25 with room for
    144 pixels' sampling error; the homoscedastic MAD scale gave 1.38-1.68 and 78-85 % here) and the 95 %
    interval cover 88-99 %."""
    from dualscale.fit.uncertainty import calibration

    root = datasets("twill")
    n, gain, read = 12, 20000.0, 5.0
    obs = load_observations(root).crop(0, n, 0, n)
    g = torch.Generator().manual_seed(11)

    def sensor(x):
        e = torch.poisson((x.clamp(min=0) * gain).double(), generator=g)
        return ((e + read * torch.randn(x.shape, generator=g, dtype=torch.float64)) / gain).float()

    obs = replace(obs, images=sensor(obs.images), backlight=sensor(obs.backlight))
    preset = PRESETS["standard"]
    params = _fit(obs, preset)
    cov, names, det = pixel_covariance(params, TWILL, obs, preset)
    sig, und = map_sigmas(params, cov, names, det, TWILL)
    gt, _ = load_maps(root / "maps")
    truth = {k: v[:n, :n] for k, v in vars(gt).items() if v is not None}
    from dualscale.fit.params import to_maps

    cal = calibration(to_maps(params), sig, und, truth)
    for name in ("albedo", "roughness", "normal"):
        c = cal[name]
        print(name, c)
        assert c["determined"] >= 0.8
        assert 0.75 <= c["z_sd"] <= 1.33 and 0.88 <= c["coverage_95"] <= 0.99


def test_one_pass_gives_the_lms_matrices_and_each_weightings(datasets):
    """The covariance's kernel pass (``_block_matrices``, which the LM's last iteration takes as
    its own) gives the LM's ``J^T W J`` and ``J^T W r`` bit for bit as
    :meth:`.fused.Problem.normal_equations`, and ``A``, ``B`` and ``N`` as that kernel run with
    their row multipliers (``sqrt(c) keep``, ``c keep``, and ``N``'s from :func:`row_noise`'s
    sigmas), on a translucent material whose back-lit rows weigh ``back_weight``."""
    from dualscale.bsdf import Components
    from dualscale.fit import lm
    from dualscale.fit.loop import free_names
    from dualscale.fit.uncertainty import _block_matrices, row_noise

    root = datasets("sheer")
    obs = load_observations(root).crop(0, 3, 0, 3)
    gt, _ = load_maps(root / "maps")
    comps = Components(opaque=False, isotropic=True, tinted=False)
    params = {k: v[0:3, 0:3].contiguous() for k, v in params_from_maps(gt, comps).items()}
    names = free_names("joint", params)
    prob = lm.problem(lm._block(step_data(obs, "joint", "fused"), 0, 3), comps)
    x, fixed = pack(params, names), {k: v for k, v in params.items() if k not in names}
    g = torch.Generator().manual_seed(5)
    r = prob.residuals(x, names, fixed)
    r = r + 0.003 * torch.randn(r.shape, generator=g, dtype=r.dtype)  # non-zero residuals: J^T W r is tested too
    loss = preset_loss(PRESETS["standard"])
    keep, sw, _, _ = prob.irls(r, loss)
    keep[0, 0, :40] = 0.0  # some rows set aside
    u = np.linspace(0.5, 1.0, r.shape[-1])
    h, jtr, m = _block_matrices(prob, x, names, fixed, r, keep, sw, loss, u)
    ref, ref_r = prob.normal_equations(x, names, fixed, r, sw)
    assert torch.equal(h, ref) and torch.equal(jtr, ref_r)
    c = torch.from_numpy(prob.row_weights(loss.back_weight))
    y = torch.from_numpy(prob.rows_and_back()).reshape(r.shape)
    s = row_noise(r, (y + r).double(), keep, u)
    for name, mult in (("A", c.sqrt() * keep.double()), ("B", c * keep.double()), ("N", (c * keep / s).sqrt())):
        want, _ = prob.normal_equations(x.double(), names, {k: v.double() for k, v in fixed.items()}, r.double(), mult)
        torch.testing.assert_close(m[name], want, rtol=1e-7, atol=1e-9 * float(want.abs().max()), msg=name)
    assert not torch.allclose(m["A"], m["B"])  # the back-lit rows count


def test_a_fit_stopped_short_reports_the_optimisers_remaining_step(datasets):
    """The same noisy crop fitted for 2 and for the full ``standard`` iterations: the short fit's
    remaining Gauss-Newton step (``normal_matrices``' ``step``) is many times the converged fit's,
    and its sigma grows with it: the short fit's roughness z-scores' spread stays within [0.6, 1.7]
    (measured 1.57; the noise-only sigma gave 2.14)."""
    root = datasets("twill")
    n = 8
    obs = _noisy_crop(root, n, 0.003, seed=2)
    full = PRESETS["standard"]
    short = replace(full, iterations=(1, 1, 1))
    gt, _ = load_maps(root / "maps")
    steps, zs = {}, {}
    for label, preset in (("full", full), ("short", short)):
        params = _fit(obs, preset)
        m = normal_matrices(params, TWILL, obs, full)
        steps[label] = float(m["step"].abs().median())
        cov, names, det = pixel_covariance(params, TWILL, obs, full)
        sig, und = map_sigmas(params, cov, names, det, TWILL)
        z = ((params["roughness"].double() - gt.roughness[:n, :n].double()) / sig["roughness"])[~und["roughness"]]
        zs[label] = float(z.std())
    print(steps, zs)
    assert steps["short"] > 10 * steps["full"]
    assert 0.6 <= zs["full"] <= 1.6 and 0.6 <= zs["short"] <= 1.7


def test_the_lms_last_iteration_gathers_the_covariance(datasets):
    """With a :class:`Gather`, the LM's last joint iteration builds the covariance in its own
    kernel pass: the fitted parameters are bit for bit those of the fit without it, and sigma
    matches a separate pass at the solution (one converged step later): median ratio within 2 %,
    95 % of the determined texel channels within 10 %, the same undetermined mask on >= 99 %."""
    from dualscale.fit.uncertainty import Gather, pixel_uncertainty

    obs = _noisy_crop(datasets("twill"), 8, 0.003, seed=3)
    preset = PRESETS["standard"]
    plain = _fit(obs, preset)
    params = {k: v.clone() for k, v in initial_params(obs, TWILL).items()}
    gather = Gather(obs, preset)
    run_lm(params, TWILL, obs, Loop(preset, TWILL, Checkpointer(None, "test", 0)), gather=gather)
    assert all(torch.equal(params[k], plain[k]) for k in plain)
    assert gather.point() is not None
    a = pixel_uncertainty(params, TWILL, obs, preset, gathered=gather)
    b = pixel_uncertainty(params, TWILL, obs, preset)
    agree, n = 0, 0
    for name in a.sigma:
        same = a.undetermined[name] == b.undetermined[name]
        agree, n = agree + int(same.sum()), n + same.numel()
        both = ~a.undetermined[name] & ~b.undetermined[name]
        ratio = (a.sigma[name][both] / b.sigma[name][both]).double()
        print(name, float(ratio.median()), float((ratio - 1).abs().quantile(0.95)))
        assert abs(float(ratio.median()) - 1) < 0.02, name
        assert float((ratio - 1).abs().quantile(0.95)) < 0.10, name
    assert agree >= 0.99 * n


def test_pixels_the_last_step_moved_are_evaluated_again_at_the_solution(datasets):
    """A fit stopped short (4 joint iterations): where its last accepted step moved a determined
    parameter by more than ``STALE_STEP`` sigmas the gathered matrices are stale, and those
    pixels are evaluated again at the solution: their sigma is the separate pass's, bit for bit
    (pixels are independent); elsewhere it is the gathered one."""
    from dualscale.fit.loop import free_names
    from dualscale.fit.uncertainty import STALE_STEP, Gather, _gone, pixel_uncertainty

    obs = _noisy_crop(datasets("twill"), 8, 0.003, seed=4)
    preset = replace(PRESETS["standard"], iterations=(3, 3, 4))
    params = {k: v.clone() for k, v in initial_params(obs, TWILL).items()}
    gather = Gather(obs, preset)
    run_lm(params, TWILL, obs, Loop(preset, TWILL, Checkpointer(None, "test", 0)), gather=gather)
    pt = gather.point()
    names = free_names("joint", params)
    sd = torch.diagonal(pt["cov"], dim1=-2, dim2=-1).clamp(min=1e-300).sqrt()
    moved = ((_gone(pack(params, names).double(), pt["x"], names).abs() > STALE_STEP * sd)
             & pt["determined"]).any(-1)
    assert 0 < int(moved.sum()) < moved.numel()  # some pixels, not all
    a = pixel_uncertainty(params, TWILL, obs, preset, gathered=gather)
    b = pixel_uncertainty(params, TWILL, obs, preset)
    for name in a.sigma:
        sa, sb = a.sigma[name][moved].nan_to_num(-1.0), b.sigma[name][moved].nan_to_num(-1.0)
        assert torch.equal(sa, sb), name
        assert torch.equal(a.undetermined[name][moved], b.undetermined[name][moved]), name
