"""The one conversion from our maps to the formats' parameters (dualscale.export.exchange), and
the formats' shading models that measure what each approximation costs (export.shading)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dualscale.bsdf import MaterialMaps
from dualscale.bsdf.ggx import ggx_alphas
from dualscale.bsdf.model import evaluate
from dualscale.errors import GeometryError
from dualscale.export.exchange import (exchange, f0_from_ior, gltf_anisotropy, gltf_transmission, luminance,
                                       openpbr_anisotropy, specular_f0_color, standard_surface_anisotropy,
                                       thin_walled_translucency)
from dualscale.export.shading import gltf_bsdf, relative_error, standard_surface_bsdf


def _maps(h=6, w=5, seed=0, aniso=True, trans=False, tint=True, ior=True) -> MaterialMaps:
    g = torch.Generator().manual_seed(seed)
    r = lambda c, lo=0.0, hi=1.0: lo + (hi - lo) * torch.rand(h, w, c, generator=g)  # noqa: E731
    n = torch.cat([r(2, -0.3, 0.3), torch.ones(h, w, 1)], -1)
    n = n / n.norm(dim=-1, keepdim=True)
    return MaterialMaps(albedo=r(3, 0.05, 0.6), roughness=r(1, 0.2, 0.8),
                        anisotropy=r(1, 0.0, 0.9) if aniso else None, tangent=r(1) if aniso else None,
                        normal=n, ior=r(1, 0.1, 0.4) if ior else None, specular_tint=r(1) if tint else None,
                        transmittance=r(3, 0.0, 0.3) if trans else None, opacity=r(1, 0.7, 1.0) if trans else None)


def test_exchange_keeps_every_parameter():
    m = _maps(trans=True)
    ex = exchange(m, texel_mm=0.01)
    assert ex.shape == (6, 5) and ex.size_mm == pytest.approx((0.05, 0.06))
    np.testing.assert_allclose(ex.base_color, m.albedo.numpy())
    np.testing.assert_allclose(ex.roughness, m.roughness.numpy()[..., 0])
    np.testing.assert_allclose(ex.ior, 1 + 2 * m.ior.numpy()[..., 0], rtol=1e-6)
    assert ex.ior_scalar == pytest.approx(np.median(ex.ior))
    np.testing.assert_allclose(ex.tangent_angle, math.pi * m.tangent.numpy()[..., 0] % math.pi, atol=1e-6)
    at, ab = ex.alphas()
    ax, ay = ggx_alphas(m.roughness.double(), m.anisotropy.double())
    np.testing.assert_allclose(at, ax.numpy()[..., 0], rtol=1e-5)
    np.testing.assert_allclose(ab, ay.numpy()[..., 0], rtol=1e-5)
    assert exchange(m).size_mm is None


def test_gltf_anisotropy_reproduces_both_alphas():
    ex = exchange(_maps())
    r, s, d = gltf_anisotropy(ex)
    at, ab = ex.alphas()
    a = r.astype(np.float64) ** 2
    np.testing.assert_allclose(a, ab, rtol=1e-5)  # KHR_materials_anisotropy: alpha_b = r^2
    np.testing.assert_allclose(a + (1 - a) * s.astype(np.float64) ** 2, np.minimum(at, 1), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-6)
    np.testing.assert_allclose(np.arctan2(d[..., 1], d[..., 0]) % math.pi, ex.tangent_angle, atol=1e-5)
    iso = exchange(_maps(aniso=False))
    r2, s2, d2 = gltf_anisotropy(iso)
    assert s2 is None and d2 is None and r2 is iso.roughness


def test_standard_surface_and_openpbr_anisotropy_are_exact():
    ex = exchange(_maps())
    at, ab = ex.alphas()
    r, a_s, rot = standard_surface_anisotropy(ex)
    aspect = np.sqrt(1 - a_s.astype(np.float64))  # Standard Surface: aspect = sqrt(1 - anisotropy)
    np.testing.assert_allclose(r.astype(np.float64) ** 2 / aspect, at, rtol=1e-5)
    np.testing.assert_allclose(r.astype(np.float64) ** 2 * aspect, ab, rtol=1e-5)
    np.testing.assert_allclose(rot * math.pi, ex.tangent_angle, rtol=1e-6)  # spec: 1 = 180 deg
    assert (rot >= 0).all() and (rot < 1).all()
    r_o, a_o = openpbr_anisotropy(ex)
    a2 = r_o.astype(np.float64) ** 2  # OpenPBR: alpha_t = r^2 sqrt(2 / (1 + (1 - a)^2)), alpha_b = (1 - a) alpha_t
    t = np.minimum(1, a2 * np.sqrt(2 / (1 + (1 - a_o) ** 2)))
    np.testing.assert_allclose(t, np.minimum(at, 1), rtol=1e-4)
    np.testing.assert_allclose((1 - a_o) * t, np.minimum(ab, at), rtol=1e-4)


def test_transmission_splits_keep_the_energy():
    m = _maps(trans=True)
    ex = exchange(m)
    b, t = ex.base_color.astype(np.float64), ex.transmittance.astype(np.float64)
    g = gltf_transmission(ex)
    # glTF: (1 - T) base reflects -- ours exactly -- and T base transmits: ours in luminance where T was
    # not lowered to keep base below 1
    np.testing.assert_allclose(g.base_color * (1 - g.weight[..., None]), b, rtol=1e-4, atol=1e-6)
    free = g.weight < 1 - b.max(-1) - 1e-6
    assert free.any()
    np.testing.assert_allclose((luminance(g.base_color) * g.weight)[free], luminance(t)[free], rtol=1e-4)
    s = thin_walled_translucency(ex)
    ok = b.max(-1) + t.max(-1) <= 1  # a split exact per channel exists
    assert ok.any()
    np.testing.assert_allclose((s.base_color * (1 - s.weight[..., None]))[ok], b[ok], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose((s.color * s.weight[..., None])[ok], t[ok], rtol=1e-4, atol=1e-6)
    assert gltf_transmission(exchange(_maps())) is None


def test_specular_colour_carries_the_ior_variation_at_normal_incidence():
    ex = exchange(_maps())
    col, fac = specular_f0_color(ex)
    assert col.max() <= 1 + 1e-6 and fac >= 1
    np.testing.assert_allclose(f0_from_ior(ex.ior_scalar) * col * fac,
                               f0_from_ior(ex.ior)[..., None] * ex.specular_color, rtol=1e-4)


def _flat(h=4, w=4, albedo=0.4, rough=0.5) -> dict:
    return dict(base_color=np.full((h, w, 3), albedo), roughness=np.full((h, w), rough))


def test_gltf_model_without_specular_is_lambert():
    p = _flat()
    p["specular_color"] = np.zeros((4, 4, 3))
    l = np.array([[0, 0, 1.0], [0.6, 0, 0.8]])
    f = gltf_bsdf(p, l, np.array([0, 0, 1.0]))
    # F90 = 1 (KHR_materials_specular) keeps (1 - v.h)^5 = 3.5e-7 at v.h = 0.949
    np.testing.assert_allclose(f[:, 0, 0, 0], 0.4 / math.pi * np.array([1.0, 0.8]), rtol=1e-6)


def test_models_agree_with_ours_where_they_share_the_lobe():
    """The glTF and Standard Surface specular lobes are ours (GGX, height-correlated Smith);
    their differences are only the Fresnel and the diffuse, so with a black albedo and a mirror
    angle away from grazing they differ from ours by the Fresnel alone."""
    m = MaterialMaps(albedo=torch.zeros(3, 3, 3), roughness=torch.full((3, 3, 1), 0.4))
    ex = exchange(m)
    l = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, math.sqrt(0.75)]])
    v = torch.tensor([0.0, 0.0, 1.0])
    ours = evaluate(m, l, v).double().numpy()
    ss = standard_surface_bsdf(dict(base_color=ex.base_color, specular_roughness=ex.roughness,
                                    specular_IOR=1.5), l.numpy(), v.numpy())
    np.testing.assert_allclose(ss, ours, rtol=2e-3)  # exact Fresnel: identical lobe
    g = gltf_bsdf(dict(base_color=ex.base_color, roughness=ex.roughness, ior=1.5), l.numpy(), v.numpy())
    np.testing.assert_allclose(g[0], ours[0], rtol=2e-3)  # at normal incidence Schlick = exact F0
    assert relative_error(g, ours)[1] < 0.05


def test_directional_albedo_of_a_smooth_dielectric_is_its_f0():
    """Standard Surface's base attenuation 1 - E(v): for a near-mirror (r = 0.1, alpha = 0.01) at
    normal view, E equals the Fresnel F0 = 0.04 of eta 1.5 (and the diffuse is 0.96 b/pi)."""
    p = dict(base_color=np.full((2, 2, 3), 0.5), specular_roughness=np.full((2, 2), 0.1), specular_IOR=1.5)
    l = np.array([[0.6, 0.0, 0.8]])
    f = standard_surface_bsdf(p, l, np.array([0, 0, 1.0]))
    np.testing.assert_allclose(f[0, 0, 0, 0], 0.5 / math.pi * (1 - 0.04) * 0.8, rtol=0.02)


def test_shading_refuses_directions_below_the_horizon():
    with pytest.raises(GeometryError):
        gltf_bsdf(_flat(), np.array([[0.0, 0.6, -0.8]]), np.array([0, 0, 1.0]))
