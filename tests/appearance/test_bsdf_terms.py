"""Unit tests of each BSDF term: known values, identities and float64 gradcheck."""

import math

import pytest
import torch
from torch.autograd import gradcheck

import dualscale.bsdf as B
from helpers import hemisphere_dirs, random_maps, unit

D64 = torch.float64


def rand(*shape, lo=0.0, hi=1.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=D64)).requires_grad_(True)


# --- Fresnel -------------------------------------------------------------------------------

@pytest.mark.parametrize("eta", [1.0, 1.33, 1.5, 3.0])
def test_fresnel_normal_incidence(eta):
    c = torch.ones(1, dtype=D64)
    r0 = ((eta - 1) / (eta + 1)) ** 2
    for fn in (B.fresnel_s, B.fresnel_p, B.fresnel_dielectric):
        assert fn(c, eta).item() == pytest.approx(r0, abs=1e-12)


def test_fresnel_brewster_and_grazing():
    eta = 1.5
    cb = torch.tensor([math.cos(math.atan(eta))], dtype=D64)
    assert B.fresnel_p(cb, eta).item() == pytest.approx(0.0, abs=1e-12)
    assert B.fresnel_s(cb, eta).item() > 0.1
    c0 = torch.zeros(1, dtype=D64)
    assert B.fresnel_s(c0, eta).item() == pytest.approx(1.0, abs=1e-5)
    assert B.fresnel_p(c0, eta).item() == pytest.approx(1.0, abs=1e-5)


def test_fresnel_matches_snell_textbook():
    eta = 1.7
    ci = torch.linspace(0.05, 1.0, 50, dtype=D64)
    st = torch.sqrt(1 - ci ** 2) / eta
    ct = torch.sqrt(1 - st ** 2)
    rs = ((ci - eta * ct) / (ci + eta * ct)) ** 2
    rp = ((eta * ci - ct) / (eta * ci + ct)) ** 2
    torch.testing.assert_close(B.fresnel_s(ci, eta), rs)
    torch.testing.assert_close(B.fresnel_p(ci, eta), rp)
    torch.testing.assert_close(B.fresnel_weighted(ci, eta, 0.3, 0.7), 0.3 * rs + 0.7 * rp)


def test_fresnel_total_internal_reflection():
    eta = 1 / 1.5  # leaving glass
    crit = math.sqrt(1 - eta ** 2)
    c = torch.tensor([crit * 0.5, crit * 0.99], dtype=D64, requires_grad=True)
    for fn in (B.fresnel_s, B.fresnel_p, B.fresnel_dielectric):
        v = fn(c, eta)
        torch.testing.assert_close(v, torch.ones_like(v))
        (g,) = torch.autograd.grad(v.sum(), c)
        assert torch.isfinite(g).all()
    assert B.fresnel_s(torch.tensor([0.99], dtype=D64), eta).item() < 0.1


def test_fresnel_gradcheck():
    c = rand(6, 1, lo=0.05, hi=0.95)
    eta = rand(6, 1, lo=1.05, hi=2.9, seed=1)
    for fn in (B.fresnel_s, B.fresnel_p, B.fresnel_dielectric):
        assert gradcheck(fn, (c, eta))
    assert gradcheck(lambda a, b: B.fresnel_weighted(a, b, 0.8, 0.2), (c, eta))


# --- GGX -----------------------------------------------------------------------------------

def test_alphas_follow_burley():
    r = torch.tensor([[0.5]], dtype=D64)
    a = torch.tensor([[0.6]], dtype=D64)
    ax, ay = B.ggx_alphas(r, a)
    asp = math.sqrt(1 - 0.54)
    assert ax.item() == pytest.approx(0.25 / asp)
    assert ay.item() == pytest.approx(0.25 * asp)
    ax0, ay0 = B.ggx_alphas(torch.zeros(1, 1, dtype=D64), a)
    assert ax0.item() == ay0.item() == B.ALPHA_MIN
    assert gradcheck(B.ggx_alphas, (rand(5, 1, lo=0.2, hi=1.0), rand(5, 1, seed=2)))


def test_lambda_and_g1_are_heitz():
    w = unit(torch.randn(20, 3, dtype=D64))
    w[:, 2] = w[:, 2].abs() + 0.01
    w = unit(w)
    ax = rand(20, 1, lo=0.05, hi=1.0)
    ay = rand(20, 1, lo=0.05, hi=1.0, seed=3)
    x, y, z = w[:, 0:1], w[:, 1:2], w[:, 2:3]
    lam = (-1 + torch.sqrt(1 + (ax ** 2 * x ** 2 + ay ** 2 * y ** 2) / z ** 2)) / 2
    torch.testing.assert_close(B.smith_lambda(x, y, z, ax, ay), lam)
    torch.testing.assert_close(B.smith_g1(x, y, z, ax, ay), 1 / (1 + lam))
    assert gradcheck(B.smith_lambda, (x.detach().requires_grad_(), y.detach().requires_grad_(),
                                      z.detach().requires_grad_(), ax, ay))
    assert gradcheck(B.smith_g1, (x.detach().requires_grad_(), y.detach().requires_grad_(),
                                  z.detach().requires_grad_(), ax, ay))


def test_visibility_equals_g_over_cosines():
    l, v = hemisphere_dirs(30, seed=4), hemisphere_dirs(30, seed=5)
    ax, ay = rand(30, 1, lo=0.05, hi=1), rand(30, 1, lo=0.05, hi=1, seed=6)
    g = B.smith_g(l, v, ax, ay)
    vis = B.smith_visibility(l[:, 2:3], (ax * l[:, :1]) ** 2 + (ay * l[:, 1:2]) ** 2,
                             v[:, 2:3], (ax * v[:, :1]) ** 2 + (ay * v[:, 1:2]) ** 2)
    torch.testing.assert_close(vis, g / (4 * l[:, 2:3] * v[:, 2:3]))
    lz, vz = rand(6, 1, lo=0.1, hi=0.9), rand(6, 1, lo=0.1, hi=0.9, seed=7)
    assert gradcheck(B.smith_visibility, (lz, rand(6, 1, lo=0.01, hi=1), vz, rand(6, 1, lo=0.01, hi=1, seed=8)))
    assert gradcheck(lambda a, b, c, d: B.smith_g(torch.cat([a, b], -1), torch.cat([c, b], -1), d, d),
                     (rand(4, 2, lo=-0.5, hi=0.5), rand(4, 1, lo=0.3, hi=0.9), rand(4, 2, lo=-.5, hi=.5, seed=9),
                      rand(4, 1, lo=0.1, hi=0.8, seed=10)))


@pytest.mark.parametrize("rough,aniso", [(0.4, 0.0), (0.6, 0.8), (0.9, 0.5)])
def test_d_is_normalised(rough, aniso):
    # int D(h) (h.n) dh = 1 over the hemisphere (midpoint rule in theta, phi).
    ax, ay = B.ggx_alphas(torch.tensor([[rough]], dtype=D64), torch.tensor([[aniso]], dtype=D64))
    nt, nphi = 4000, 256
    th = (torch.arange(nt, dtype=D64) + 0.5) * (math.pi / 2 / nt)
    ph = (torch.arange(nphi, dtype=D64) + 0.5) * (2 * math.pi / nphi)
    th, ph = torch.meshgrid(th, ph, indexing="ij")
    hx, hy, hz = torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph), torch.cos(th)
    d = B.ggx_d_aniso(hx, hy, hz, ax.squeeze(), ay.squeeze())
    integral = (d * hz * torch.sin(th)).sum() * (math.pi / 2 / nt) * (2 * math.pi / nphi)
    assert integral.item() == pytest.approx(1.0, abs=2e-3)


def test_d_iso_matches_aniso_and_gradcheck():
    h = hemisphere_dirs(10, seed=11)
    a = rand(10, 1, lo=0.05, hi=1)
    torch.testing.assert_close(B.ggx_d_iso(h[:, 2:3], a), B.ggx_d_aniso(h[:, :1], h[:, 1:2], h[:, 2:3], a, a))
    hh = h.detach().requires_grad_()
    assert gradcheck(lambda x, ax, ay: B.ggx_d_aniso(x[:, :1], x[:, 1:2], x[:, 2:3], ax, ay),
                     (hh, a, rand(10, 1, lo=0.05, hi=1, seed=12)))
    assert gradcheck(B.ggx_d_iso, (rand(10, 1, lo=0.1, hi=0.99), a))


# --- diffuse, tint, specular, transmittance --------------------------------------------------

def test_diffuse_values():
    b = torch.tensor([[0.2, 0.5, 0.8]], dtype=D64)
    one = torch.ones(1, 1, dtype=D64)
    # at normal incidence and view F_l = F_v = 0: pure Lambert, no retro-reflection
    torch.testing.assert_close(B.diffuse(b, 0.7 * one, one, one, one), b / math.pi)
    # retro-reflection: R_R = sigma (1 + l.v)
    cl, cv, clv, s = 0.3 * one, 0.4 * one, 0.5 * one, 0.6 * one
    fl, fv, rr = 0.7 ** 5, 0.6 ** 5, 0.6 * 1.5
    torch.testing.assert_close(B.retro_reflection(b, s, cl, cv, clv), b / math.pi * rr * (fl + fv + fl * fv * (rr - 1)))
    # the fused diffuse (Schlick weights once, factor on one channel) is the sum of its two terms
    c = rand(64, 1, lo=-0.2, hi=1.2, seed=5)
    args = (rand(64, 3), rand(64, 1, seed=6), c, c.flip(0), rand(64, 1, lo=-1.1, hi=1.1, seed=7))
    torch.testing.assert_close(B.diffuse(*args), B.diffuse_base(args[0], c, c.flip(0)) + B.retro_reflection(*args),
                               rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(B.schlick_weight(c), (1 - c.clamp(0, 1)) ** 5, rtol=1e-13, atol=1e-15)


def test_diffuse_gradcheck():
    args = (rand(5, 3), rand(5, 1, seed=1), rand(5, 1, lo=0.05, hi=0.95, seed=2),
            rand(5, 1, lo=0.05, hi=0.95, seed=3), rand(5, 1, lo=-0.9, hi=0.9, seed=4))
    assert gradcheck(B.diffuse, args)
    assert gradcheck(B.retro_reflection, args)
    assert gradcheck(B.diffuse_base, (args[0], args[2], args[3]))
    assert gradcheck(B.schlick_weight, (args[2],))


def test_tint_is_safe_for_black_and_white():
    black = torch.zeros(1, 3, dtype=D64, requires_grad=True)
    rho = torch.full((1, 1), 0.7, dtype=D64)
    t = B.specular_tint(black, rho)
    torch.testing.assert_close(t, torch.ones_like(t))
    (g,) = torch.autograd.grad(t.sum(), black)
    assert torch.isfinite(g).all()
    b = torch.tensor([[0.2, 0.4, 0.8]], dtype=D64)
    torch.testing.assert_close(B.specular_tint(b, rho), torch.tensor([[0.25, 0.5, 1.0]], dtype=D64) * 0.7 + 0.3)
    assert gradcheck(B.specular_tint, (rand(4, 3, lo=0.1), rand(4, 1, seed=5)))
    assert gradcheck(B.chromaticity, (rand(4, 3, lo=0.1),))


def test_specular_iso_equals_aniso_and_gradcheck():
    l, v = hemisphere_dirs(12, seed=13), hemisphere_dirs(12, seed=14)
    a, eta = rand(12, 1, lo=0.05, hi=1), rand(12, 1, lo=1.0, hi=3.0, seed=15)
    iso = B.specular_iso(l[:, 2:3], v[:, 2:3], (l * v).sum(-1, keepdim=True), a, eta)
    torch.testing.assert_close(iso, B.specular_aniso(l, v, a, a, eta))
    assert gradcheck(lambda l_, v_, ax, ay, e: B.specular_aniso(unit(l_), unit(v_), ax, ay, e, 1.0, 0.0),
                     (l.requires_grad_(), v.requires_grad_(), a, rand(12, 1, lo=0.05, hi=1, seed=16), eta))
    assert gradcheck(lambda a_, b_, c_, al, e: B.specular_iso(a_, b_, c_, al, e),
                     (rand(5, 1, lo=0.2, hi=0.9), rand(5, 1, lo=0.2, hi=0.9, seed=17),
                      rand(5, 1, lo=-0.5, hi=0.9, seed=18), rand(5, 1, lo=0.1, hi=0.9, seed=19), 1.5 + rand(5, 1, seed=2)))


def test_specular_peak_value():
    # mirror configuration at normal incidence: D = 1/(pi ax ay), G ~ 1, F = R0
    z = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    a = torch.tensor([[0.2]], dtype=D64)
    s = B.specular_aniso(z, z, a, a, 1.5)
    g1 = 2 / (1 + math.sqrt(1 + 0))
    assert s.item() == pytest.approx(0.04 / (math.pi * 0.04) * g1 * g1 / 4, rel=1e-9)


def test_transmittance_sides_and_gradcheck():
    t = rand(3, 3)
    up, down = torch.full((3, 1), 0.5, dtype=D64), torch.full((3, 1), -0.5, dtype=D64)
    assert (B.transmittance(t, up, up) == 0).all()
    torch.testing.assert_close(B.transmittance(t, down, up), t / math.pi)
    torch.testing.assert_close(B.transmittance(t, up, down), t / math.pi)
    assert gradcheck(B.transmittance, (t, down.requires_grad_(), up.requires_grad_()))


# --- full model --------------------------------------------------------------------------------

@pytest.mark.parametrize("full", [True, False])
def test_evaluate_matches_reference_and_gradcheck(full):
    maps = random_maps(3, 2, full=full, seed=21)
    l = hemisphere_dirs(4, seed=22)
    l[0] = torch.tensor([0.3, 0.1, -0.9], dtype=D64)  # one from below (back light)
    v = unit(torch.tensor([0.1, -0.2, 0.9], dtype=D64))
    fast = B.evaluate(maps, unit(l), v, light_chunk=3)
    torch.testing.assert_close(fast, B.evaluate_reference(maps, unit(l), v))
    names = [k for k, _ in maps.items() if k != "normal"]

    def fn(*tensors):
        m = B.MaterialMaps(**{**dict(maps.items()), **dict(zip(names, tensors))})
        return B.evaluate(m, unit(l), v, w_s=0.9, w_p=0.1, diffuse_weight=0.5)

    assert gradcheck(fn, tuple(t.detach().clone().requires_grad_() for _, t in
                               [(k, getattr(maps, k)) for k in names]))


def test_evaluate_gradcheck_normals_and_directions():
    maps = random_maps(2, 2, seed=23)
    sq = torch.rand(2, 2, 2, dtype=D64).mul(1.2).sub(0.6).requires_grad_()
    l = hemisphere_dirs(3, seed=24).requires_grad_()

    def fn(sq_, l_):
        maps.normal = B.normal_from_square(sq_)
        return B.evaluate(maps, unit(l_), torch.tensor([0.0, 0.0, 1.0], dtype=D64))

    assert gradcheck(fn, (sq, l))


def test_components_allocate_nothing_inactive():
    maps = random_maps(4, 4, full=False)
    comps = maps.components()
    assert comps.opaque and comps.isotropic and not comps.tinted and not comps.normal_mapped
    p = B.prepare(maps, comps)
    assert p["n"] is None and p["t"] is None and p["tint"] is None and p["trans"] is None
    assert p["ax"].data_ptr() == p["ay"].data_ptr() and isinstance(p["eta"], float)
    with pytest.raises(ValueError, match="need maps"):
        B.evaluate(maps, hemisphere_dirs(2), torch.tensor([0.0, 0.0, 1.0], dtype=D64),
                   B.Components(isotropic=False))


def test_bad_inputs_raise():
    maps = random_maps(4, 4, full=False)
    v = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    bad = B.MaterialMaps(albedo=maps.albedo, roughness=maps.roughness[:3])
    with pytest.raises(ValueError, match="roughness"):
        B.evaluate(bad, hemisphere_dirs(2), v)
    nan = maps.albedo.clone()
    nan[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        B.evaluate(B.MaterialMaps(albedo=nan, roughness=maps.roughness), hemisphere_dirs(2), v)
    with pytest.raises(ValueError, match="light_dirs"):
        B.evaluate(maps, torch.zeros(3, dtype=D64), v)
    with pytest.raises(ValueError, match="view_dirs"):
        B.evaluate(maps, hemisphere_dirs(2), torch.zeros(5, 5, 3, dtype=D64))
