"""Fong elliptical grid mapping: both directions, rim/corner stability, gradients."""

import math

import torch
from hypothesis import given, settings, strategies as st
from torch.autograd import gradcheck

import dualscale.bsdf as B

D64 = torch.float64


def test_known_points():
    pts = torch.tensor([[1.0, 0.0], [0.0, -1.0], [1.0, 1.0], [0.0, 0.0], [-1.0, 1.0]], dtype=D64)
    disc = B.square_to_disc(pts)
    h = 1 / math.sqrt(2)
    exp = torch.tensor([[1.0, 0.0], [0.0, -1.0], [h, h], [0.0, 0.0], [-h, h]], dtype=D64)
    torch.testing.assert_close(disc, exp)
    torch.testing.assert_close(B.disc_to_square(exp), pts, atol=2e-6, rtol=0)


def test_round_trip_and_unit_normals():
    g = torch.Generator().manual_seed(0)
    sq = torch.rand(2000, 2, generator=g, dtype=D64) * 2 - 1
    torch.testing.assert_close(B.disc_to_square(B.square_to_disc(sq)), sq, atol=1e-6, rtol=0)
    n = B.normal_from_square(sq)
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(2000, dtype=D64))
    assert (n[:, 2] >= 0).all()
    torch.testing.assert_close(B.square_from_normal(n), sq, atol=1e-6, rtol=0)


def test_outside_disc_is_pulled_to_rim():
    sq = B.disc_to_square(torch.tensor([[2.0, 0.0], [3.0, 3.0]], dtype=D64))
    torch.testing.assert_close(sq, torch.tensor([[1.0, 0.0], [1.0, 1.0]], dtype=D64), atol=2e-6, rtol=0)


@settings(max_examples=60, deadline=None)
@given(st.floats(0, 2 * math.pi), st.sampled_from([1.0, 1 - 1e-9, 1 - 1e-6, 0.999, 1 + 1e-7]),
       st.sampled_from([torch.float32, torch.float64]))
def test_rim_gradients_finite(phi, r, dtype):
    uv = torch.tensor([[r * math.cos(phi), r * math.sin(phi)]], dtype=dtype, requires_grad=True)
    sq = B.disc_to_square(uv)
    (g,) = torch.autograd.grad(sq.sum(), uv)
    assert torch.isfinite(sq).all() and torch.isfinite(g).all()
    xy = sq.detach().requires_grad_()
    n = B.normal_from_square(xy)
    (g2,) = torch.autograd.grad(n.sum(), xy)
    assert torch.isfinite(n).all() and torch.isfinite(g2).all()


def test_gradcheck_mappings():
    g = torch.Generator().manual_seed(1)
    sq = (torch.rand(8, 2, generator=g, dtype=D64) * 1.8 - 0.9).requires_grad_()
    assert gradcheck(B.square_to_disc, (sq,))
    assert gradcheck(B.normal_from_square, (sq,))
    disc = B.square_to_disc(sq).detach().requires_grad_()
    assert gradcheck(B.disc_to_square, (disc,))


def test_tangent_frame_orthonormal_and_gradcheck():
    g = torch.Generator().manual_seed(2)
    n = B.normal_from_square(torch.rand(16, 2, generator=g, dtype=D64) * 1.6 - 0.8)
    ang = torch.rand(16, 1, generator=g, dtype=D64) * math.pi
    t, b = B.tangent_frame(n, ang)
    for a, c in ((t, n), (b, n), (t, b)):
        torch.testing.assert_close((a * c).sum(-1), torch.zeros(16, dtype=D64), atol=1e-9, rtol=0)
    torch.testing.assert_close(t.norm(dim=-1), torch.ones(16, dtype=D64))
    flat = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    t0, _ = B.tangent_frame(flat, torch.tensor([[math.pi / 2]], dtype=D64))
    torch.testing.assert_close(t0, torch.tensor([[0.0, 1.0, 0.0]], dtype=D64), atol=1e-12, rtol=0)
    assert gradcheck(lambda nn, a: B.tangent_frame(nn, a)[0], (n[:4].requires_grad_(), ang[:4].requires_grad_()))
