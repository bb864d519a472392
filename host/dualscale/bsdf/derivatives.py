"""Analytic partial derivatives of the BSDF terms, as scalar numba functions.

Each function mirrors one tensor term of :mod:`.terms`, :mod:`.ggx` and :mod:`.fresnel`
(supplementary Section 5) for one sample, in float64, and returns the value followed by its
partial derivatives with respect to the term's own inputs, in the order of the arguments
named in its docstring.  The fit's fused kernel (:mod:`dualscale.fit.fused`) chains them to
the normalised map parameters; ``tests/appearance/test_bsdf_derivatives.py`` checks every partial against
torch autograd in float64.

Clamp conventions follow the tensor terms: where an input is clamped (``cos`` to [0, 1], the
GGX alpha floor, the D-bracket floor) the derivative through the clamped branch is 0; the guards
``TINY`` and the floors are the tensor code's, so values agree to rounding.
"""

from __future__ import annotations

import math

from numba import njit

from .ggx import ALPHA_MIN
from .vec import TINY

INV_PI = 1.0 / math.pi
CHROMA_EPS = 1e-6  # terms.chromaticity: a max channel at or below this is black (white chromaticity)
#: inlined into the fit's kernels (numba IR inlining), where LLVM vectorises them over the lights
#: and drops the partials a caller does not use
JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy", inline="always")


@njit(**JIT)
def schlick_weight_d(c):
    """``F = (1 - clamp(c, 0, 1))^5`` -> ``(F, dF/dc)``."""
    if c <= 0.0:
        return 1.0, 0.0
    if c >= 1.0:
        return 0.0, 0.0
    t = 1.0 - c
    t2 = t * t
    return t2 * t2 * t, -5.0 * t2 * t2


@njit(**JIT)
def diffuse_d(cl, cv, clv, rough):
    """Burley diffuse plus retro-reflection per unit albedo (``terms.diffuse`` / albedo):
    ``G = [(1 - F_l/2)(1 - F_v/2) + R_R (F_l + F_v + F_l F_v (R_R - 1))] / pi`` with
    ``R_R = rough (1 + clamp(l.v, -1, 1))`` -> ``(G, dG/dcl, dG/dcv, dG/drough)``."""
    fl, dfl = schlick_weight_d(cl)
    fv, dfv = schlick_weight_d(cv)
    k = 1.0 + min(max(clv, -1.0), 1.0)
    rr = rough * k
    g = INV_PI * ((1.0 - 0.5 * fl) * (1.0 - 0.5 * fv) + rr * (fl + fv + fl * fv * (rr - 1.0)))
    dg_fl = INV_PI * (-0.5 * (1.0 - 0.5 * fv) + rr * (1.0 + fv * (rr - 1.0)))
    dg_fv = INV_PI * (-0.5 * (1.0 - 0.5 * fl) + rr * (1.0 + fl * (rr - 1.0)))
    dg_rr = INV_PI * (fl + fv + fl * fv * (2.0 * rr - 1.0))
    return g, dg_fl * dfl, dg_fv * dfv, dg_rr * k


@njit(**JIT)
def alphas_iso_d(rough):
    """``ggx.ggx_alphas`` without anisotropy: ``a = max(1e-3, r^2)`` -> ``(a, da/dr)``."""
    a = rough * rough
    if a < ALPHA_MIN:
        return ALPHA_MIN, 0.0
    return a, 2.0 * rough


@njit(**JIT)
def alphas_aniso_d(rough, aniso):
    """``ggx.ggx_alphas``: ``aspect = sqrt(1 - 0.9 clamp(an, 0, 1))``, ``ax = max(1e-3, r^2/aspect)``,
    ``ay = max(1e-3, r^2 aspect)`` -> ``(ax, ay, dax/dr, dax/dan, day/dr, day/dan)``."""
    an = min(max(aniso, 0.0), 1.0)
    aspect = math.sqrt(1.0 - 0.9 * an)
    dasp = -0.45 / aspect if 0.0 < aniso < 1.0 else 0.0
    r2 = rough * rough
    ax, ay = r2 / aspect, r2 * aspect
    dax_r, dax_an, day_r, day_an = 2.0 * rough / aspect, -r2 / (aspect * aspect) * dasp, 2.0 * rough * aspect, r2 * dasp
    if ax < ALPHA_MIN:
        ax, dax_r, dax_an = ALPHA_MIN, 0.0, 0.0
    if ay < ALPHA_MIN:
        ay, day_r, day_an = ALPHA_MIN, 0.0, 0.0
    return ax, ay, dax_r, dax_an, day_r, day_an


@njit(**JIT)
def ggx_d_iso_d(hz, a):
    """``ggx.ggx_d_iso``: ``a^2 / (pi max(s, min(a^2, 1))^2)``, ``s = hz^2 (a^2 - 1) + 1``, 0 for
    ``hz <= 0`` -> ``(D, dD/dhz, dD/da)``."""
    if hz <= 0.0:
        return 0.0, 0.0, 0.0
    a2 = a * a
    s = hz * hz * (a2 - 1.0) + 1.0
    floor = min(a2, 1.0)
    if s >= floor:
        m, dm_hz, dm_a2 = s, 2.0 * hz * (a2 - 1.0), hz * hz
    else:
        m, dm_hz, dm_a2 = floor, 0.0, 1.0 if a2 < 1.0 else 0.0
    d = a2 * INV_PI / (m * m)
    dd_m = -2.0 * d / m
    return d, dd_m * dm_hz, (INV_PI / (m * m) + dd_m * dm_a2) * 2.0 * a


@njit(**JIT)
def ggx_d_aniso_d(hx, hy, hz, ax, ay):
    """``ggx.ggx_d_aniso``: ``1 / (pi ax ay max(s, floor)^2)``, ``s = (hx/ax)^2 + (hy/ay)^2 + hz^2``,
    ``floor = min(1, 1/max(ax, ay)^2)``, 0 for ``hz <= 0`` ->
    ``(D, dD/dhx, dD/dhy, dD/dhz, dD/dax, dD/day)``."""
    if hz <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    s = (hx / ax) ** 2 + (hy / ay) ** 2 + hz * hz
    amax = max(ax, ay)
    floor = min(1.0 / (amax * amax), 1.0)
    if s >= floor:
        m = s
        dm_hx, dm_hy, dm_hz = 2.0 * hx / (ax * ax), 2.0 * hy / (ay * ay), 2.0 * hz
        dm_ax, dm_ay = -2.0 * hx * hx / (ax * ax * ax), -2.0 * hy * hy / (ay * ay * ay)
    else:
        m = floor
        dm_hx = dm_hy = dm_hz = dm_ax = dm_ay = 0.0
        if 1.0 / (amax * amax) < 1.0:
            if ax >= ay:
                dm_ax = -2.0 / (ax * ax * ax)
            else:
                dm_ay = -2.0 / (ay * ay * ay)
    d = INV_PI / (ax * ay * m * m)
    dd_m = -2.0 * d / m
    return d, dd_m * dm_hx, dd_m * dm_hy, dd_m * dm_hz, -d / ax + dd_m * dm_ax, -d / ay + dd_m * dm_ay


@njit(**JIT)
def smith_visibility_d(lz, a2l, vz, a2v):
    """``ggx.smith_visibility``: ``1 / ((zl + sl)(zv + sv))``, ``z = max(cos, 0)``,
    ``s = sqrt(z^2 + max(a2, 0) + TINY)`` -> ``(V, dV/dlz, dV/da2l, dV/dvz, dV/da2v)``."""
    zl, zv = max(lz, 0.0), max(vz, 0.0)
    al, av = max(a2l, 0.0), max(a2v, 0.0)
    sl = math.sqrt(zl * zl + al + TINY)
    sv = math.sqrt(zv * zv + av + TINY)
    pl, pv = zl + sl, zv + sv
    v = 1.0 / (pl * pv)
    dl, dv = -v / pl, -v / pv
    return (v, dl * (1.0 + zl / sl) if lz > 0.0 else 0.0, dl * 0.5 / sl if a2l > 0.0 else 0.0,
            dv * (1.0 + zv / sv) if vz > 0.0 else 0.0, dv * 0.5 / sv if a2v > 0.0 else 0.0)


@njit(**JIT)
def fresnel_weighted_d(cos_i, eta, w_s, w_p):
    """``fresnel.fresnel_weighted``: ``w_s R_s + w_p R_p`` of a real IOR ``eta`` at ``cos_i`` ->
    ``(F, dF/deta)`` (``cos_i`` is a constant of the light and view, so its partial is not
    needed); total internal reflection gives ``w_s + w_p`` and 0."""
    c = min(max(cos_i, 0.0), 1.0)
    g2 = eta * eta - 1.0 + c * c
    if g2 <= 0.0:
        return w_s + w_p, 0.0
    if g2 > TINY:
        g = math.sqrt(g2)
        dg = eta / g
    else:
        g, dg = math.sqrt(TINY), 0.0
    c = max(c, TINY)
    rs = (c - g) / (c + g)
    drs = -2.0 * c / ((c + g) * (c + g)) * dg
    e = eta * eta * c
    rp = (e - g) / (e + g)
    drp = (2.0 * g * (2.0 * eta * c) - 2.0 * e * dg) / ((e + g) * (e + g))
    return w_s * rs * rs + w_p * rp * rp, 2.0 * w_s * rs * drs + 2.0 * w_p * rp * drp
