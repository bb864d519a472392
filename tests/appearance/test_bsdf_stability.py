"""Property tests: no NaN/Inf in values or gradients at the extremes, in float32 and float64."""

import math

import torch
from hypothesis import given, settings, strategies as st

import dualscale.bsdf as B

EXT01 = st.one_of(st.sampled_from([0.0, 1e-7, 1e-4, 0.5, 1 - 1e-6, 1.0]), st.floats(0, 1))
EXT_IOR = st.one_of(st.sampled_from([0.0, 1e-7, 1e-3, 0.25, 1.0]), st.floats(0, 1))
THETA = st.one_of(st.sampled_from([0.0, 89.0, 89.99, 90.0, 90.001, 120.0, 180.0]), st.floats(0, 180))
PHI = st.floats(0, 360)
SQ = st.one_of(st.sampled_from([-1.0, -0.999999, 0.0, 0.999999, 1.0]), st.floats(-1, 1))
RGB = st.one_of(st.sampled_from([(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1.0, 0.0, 0.0), (1e-8, 0.0, 1e-8)]),
                st.tuples(st.floats(0, 1), st.floats(0, 1), st.floats(0, 1)))
DTYPE = st.sampled_from([torch.float32, torch.float64])


def sph(theta_deg, phi_deg, dtype):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=dtype)


@settings(max_examples=150, deadline=None)
@given(rough=EXT01, aniso=EXT01, tang=EXT01, ior=EXT_IOR, tint=EXT01, opac=EXT01, albedo=RGB, trans=RGB,
       sx=SQ, sy=SQ, tl=THETA, pl=PHI, tv=THETA, pv=PHI, dtype=DTYPE, pol=st.sampled_from([(0.5, 0.5), (1.0, 0.0)]))
def test_model_finite_values_and_gradients(rough, aniso, tang, ior, tint, opac, albedo, trans, sx, sy,
                                           tl, pl, tv, pv, dtype, pol):
    def p(x, c=1):
        return torch.tensor(x, dtype=dtype).reshape(1, 1, c).requires_grad_()

    leaves = dict(albedo=p(albedo, 3), roughness=p(rough), anisotropy=p(aniso), tangent=p(tang), ior=p(ior),
                  specular_tint=p(tint), transmittance=p(trans, 3), opacity=p(opac))
    sq = torch.tensor([[[sx, sy]]], dtype=dtype, requires_grad=True)
    l = sph(tl, pl, dtype).reshape(1, 3).requires_grad_()
    v = sph(tv, pv, dtype).requires_grad_()
    maps = B.MaterialMaps(normal=B.normal_from_square(sq), **leaves)
    out = B.evaluate(maps, l, v, w_s=pol[0], w_p=pol[1])
    assert torch.isfinite(out).all(), out
    assert (out >= 0).all()
    grads = torch.autograd.grad(out.sum(), [*leaves.values(), sq, l, v])
    for g in grads:
        assert torch.isfinite(g).all()
    # flat, isotropic, untinted, opaque path too
    m2 = B.MaterialMaps(albedo=leaves["albedo"], roughness=leaves["roughness"])
    out2 = B.evaluate(m2, l, v)
    g2 = torch.autograd.grad(out2.sum(), [leaves["albedo"], leaves["roughness"], l, v])
    assert torch.isfinite(out2).all() and all(torch.isfinite(g).all() for g in g2)


@settings(max_examples=100, deadline=None)
@given(c=st.one_of(st.sampled_from([0.0, 1e-9, 1e-4, 1.0]), st.floats(0, 1)),
       eta=st.one_of(st.sampled_from([1.0, 1.0 + 1e-7, 3.0, 0.5, 1 / 1.5]), st.floats(0.3, 3.0)),
       dtype=DTYPE)
def test_fresnel_finite_in_range(c, eta, dtype):
    ct = torch.tensor([c], dtype=dtype, requires_grad=True)
    et = torch.tensor([eta], dtype=dtype, requires_grad=True)
    for fn in (B.fresnel_s, B.fresnel_p, B.fresnel_dielectric):
        v = fn(ct, et)
        assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1 + 1e-6).all()
        g = torch.autograd.grad(v.sum(), [ct, et])
        assert all(torch.isfinite(x).all() for x in g)


def test_float32_agrees_with_float64():
    """Relative agreement on a random full material and lights that avoid the grazing 1%."""
    from helpers import hemisphere_dirs, random_maps
    maps64 = random_maps(16, 16, seed=3)
    l = hemisphere_dirs(32, seed=4, zmin=0.1)
    v = torch.tensor([0.05, 0.1, 1.0], dtype=torch.float64)
    v = v / v.norm()
    ref = B.evaluate(maps64, l, v)
    out = B.evaluate(maps64.to(torch.float32), l.float(), v.float()).double()
    rel = ((out - ref).abs() / (ref.abs() + 1e-3)).max().item()
    assert rel < 1e-4, rel
