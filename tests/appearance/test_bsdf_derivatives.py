"""The per-term analytic partials (``bsdf.derivatives``, which the fit's fused kernel inlines)
against torch autograd of the tensor terms, in float64, over random points that include the
extremes of each term (grazing cosines, the alpha floor, the D-bracket floor, eta near 1)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualscale.bsdf import derivatives as dv
from dualscale.bsdf import fresnel_weighted, ggx_alphas, ggx_d_aniso, ggx_d_iso, smith_visibility
from dualscale.bsdf.terms import diffuse, schlick_weight

RNG = np.random.default_rng(7)


def _check(fn_d, fn_t, points, rtol=1e-9, atol=1e-12, wrt=None):
    """``fn_d(*p)`` = (value, partials...) against ``fn_t`` (tensors -> tensor) and its autograd;
    ``wrt`` names the inputs the partials are taken for (default: all, in order)."""
    for p in points:
        got = fn_d(*p)
        xs = [torch.tensor(float(v), dtype=torch.float64, requires_grad=True) for v in p]
        val = fn_t(*xs)
        grads = torch.autograd.grad(val, xs, allow_unused=True)
        grads = grads if wrt is None else [grads[i] for i in wrt]
        assert got[0] == pytest.approx(float(val.detach()), rel=rtol, abs=atol), p
        assert len(got) - 1 == len(grads)
        for i, (a, g) in enumerate(zip(got[1:], grads)):
            want = 0.0 if g is None else float(g)
            assert a == pytest.approx(want, rel=1e-7, abs=1e-9 * max(1.0, abs(want))), (p, i, a, want)


def test_schlick_and_diffuse():
    cos = [-0.2, 0.0001, 0.3, 0.9999, 1.2] + list(RNG.uniform(0.01, 0.99, 6))
    _check(lambda c: dv.schlick_weight_d(c), lambda c: schlick_weight(c), [(c,) for c in cos])
    pts = [(cl, cv, clv, r) for cl, cv, clv, r in zip(RNG.uniform(0.01, 0.99, 20), RNG.uniform(0.01, 0.99, 20),
                                                        RNG.uniform(-0.95, 0.95, 20), RNG.uniform(0, 1, 20))]
    _check(lambda cl, cv, clv, r: dv.diffuse_d(cl, cv, clv, r),
           lambda cl, cv, clv, r: diffuse(torch.ones(1, dtype=torch.float64), r, cl, cv, clv)[0], pts, wrt=(0, 1, 3))


def test_alphas():
    # the two partials of each alpha, one alpha at a time
    for r, an in [(0.02, 0.5), (0.04, 0.995), (0.5, 0.0001), (0.7, 0.6), (0.9, 0.3)]:
        got = dv.alphas_aniso_d(r, an)
        rt = torch.tensor(r, dtype=torch.float64, requires_grad=True)
        at = torch.tensor(an, dtype=torch.float64, requires_grad=True)
        ax, ay = ggx_alphas(rt, at)
        gx = torch.autograd.grad(ax, [rt, at], retain_graph=True)
        gy = torch.autograd.grad(ay, [rt, at])
        assert got[0:2] == pytest.approx((float(ax.detach()), float(ay.detach())), rel=1e-12)
        assert got[2:] == pytest.approx((float(gx[0]), float(gx[1]), float(gy[0]), float(gy[1])), rel=1e-9, abs=1e-12)
    _check(lambda r: dv.alphas_iso_d(r), lambda r: ggx_alphas(r)[0], [(0.02,), (0.04,), (0.5,), (1.0,)])


def test_ggx_distributions():
    iso = [(hz, a) for hz, a in zip(RNG.uniform(-0.1, 1.0, 20), RNG.uniform(0.001, 1.0, 20))] + [(0.99999, 0.05)]
    _check(lambda hz, a: dv.ggx_d_iso_d(hz, a), lambda hz, a: ggx_d_iso(hz, a), iso)
    pts = []
    for _ in range(30):
        h = RNG.normal(size=3)
        h[2] = abs(h[2]) if RNG.random() > 0.1 else -abs(h[2])
        h /= np.linalg.norm(h)
        pts.append((*h, *RNG.uniform(0.001, 1.0, 2)))
    pts.append((0.0, 0.0, 0.5, 0.3, 0.2))  # a degenerate (short) h: the bracket at its floor
    _check(lambda hx, hy, hz, ax, ay: dv.ggx_d_aniso_d(hx, hy, hz, ax, ay),
           lambda hx, hy, hz, ax, ay: ggx_d_aniso(hx, hy, hz, ax, ay), pts)


def test_smith_visibility_and_fresnel():
    pts = [(lz, a2l, vz, a2v) for lz, a2l, vz, a2v in zip(RNG.uniform(-0.1, 1, 20), RNG.uniform(-0.01, 1, 20),
                                                          RNG.uniform(0.001, 1, 20), RNG.uniform(0, 1, 20))]
    _check(lambda *p: dv.smith_visibility_d(*p), lambda *p: smith_visibility(*p), pts)
    fr = [(c, eta, ws, wp) for c, eta, ws, wp in zip(RNG.uniform(0, 1, 20), RNG.uniform(1.0005, 3.0, 20),
                                                     RNG.uniform(0, 1, 20), RNG.uniform(0, 1, 20))]
    fr += [(0.999, 1.004, 1.0, 0.0), (0.02, 2.9, 0.5, 0.5)]
    _check(lambda c, eta, ws, wp: dv.fresnel_weighted_d(c, eta, ws, wp),
           lambda c, eta, ws, wp: fresnel_weighted(c, eta, ws, wp), fr, wrt=(1,))
