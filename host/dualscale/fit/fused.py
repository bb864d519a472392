"""The fit's fused kernel: renders, residuals and analytic Jacobians per pixel in one pass.

The per-pixel Levenberg-Marquardt (:mod:`.lm`) needs, every iteration, the residuals of every
pixel and its weighted normal equations ``J^T W J`` and ``J^T W r``.  The eager reference
renders the whole stack with torch once per parameter channel (forward differences).  This
module computes the same quantities with numba, pixel by pixel and light by light:

* the model is the one of :func:`dualscale.bsdf.evaluate` on fit maps (supplementary Sec. 5:
  Burley diffuse plus retro-reflection, or Lambert's ``b / pi`` for ``Components(diffuse=
  "lambert")``, anisotropic GGX with Heitz's Smith term, exact
  Fresnel ``w_s R_s + w_p R_p``, specular tint, diffuse transmittance and opacity), over the
  normalised parameters of :mod:`.params` (the normal as a Fong square point, the tangent as
  ``phi / pi``, ``eta = 1 + 2 ior``), clamped at 2 like :func:`.render.render_leds`;
* its derivatives are analytic: :mod:`dualscale.bsdf.derivatives` gives each term's partials,
  chained here through the normal, the tangent frame (Gram-Schmidt about the normal), the GGX
  alphas and the chromaticity of the tint; the per-pixel geometry derivatives are computed once
  per pixel, not per light;
* ``J^T W J`` and ``J^T W r`` are accumulated in place in float64, row by row; a row of zero
  weight (invalid, set aside as a cast shadow) costs nothing.

Layout: pixels are flattened (``npix = H W``); the residual rows of a pixel are the LED images
in :func:`.render.pixel_rows` order (image-major, then RGB), followed by the 3 back-lit rows
when the step has a back-lit image.  Full parameter vector per pixel, :data:`FULL`::

    0-2 albedo, 3 roughness, 4 anisotropy, 5 tangent, 6-7 normal (square), 8 ior,
    9 specular_tint, 10-12 transmittance, 13 opacity

Threads: numba's pool, set on every call to the command's count (:func:`dualscale.threads.sync_numba`).
"""

from __future__ import annotations

import math
import sys

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from dualscale.bsdf import Components
from dualscale.bsdf.derivatives import (CHROMA_EPS, INV_PI, alphas_aniso_d, alphas_iso_d, diffuse_d,
                                        fresnel_weighted_d, ggx_d_aniso_d, ggx_d_iso_d,
                                        smith_visibility_d)
from dualscale.bsdf.vec import TINY
from dualscale.threads import sync_numba

from .params import PARAM_CHANNELS
from .render import CLAMP, valid_rows

#: the shadow test's constants (:meth:`.lm.Loss.keep`, which imports them from here)
SHADOW_FLOOR = 1e-3  # renders below this (normalised radiance) are too dark to call a shadow
SHADOW_ANCHOR_COS = math.cos(math.radians(15.0))  # LEDs this close to the camera's axis light what it sees

#: parameter name -> its slots in the full per-pixel vector
FULL: dict[str, tuple[int, ...]] = {"albedo": (0, 1, 2), "roughness": (3,), "anisotropy": (4,), "tangent": (5,),
                                    "normal": (6, 7), "ior": (8,), "specular_tint": (9,),
                                    "transmittance": (10, 11, 12), "opacity": (13,)}
NFULL = 14
#: below this ``n_z`` (the rim of the hemisphere, where the square's border maps) ``dn_z/ds`` is
#: the secant over an inward step of ``RIM_STEP``: the exact derivative is infinite on the rim and
#: 0 through the square root's guard, which would pin a normal that reached the box's edge there
RIM_W, RIM_STEP = 1e-3, 3e-4
LIGHT_BLOCK = 256  # lights whose weighted Jacobian rows are gathered per pixel before they are folded into J^T W J
NCONST = 42  # size of a pixel's light-independent scratch (_pixel_consts)
DEFAULTS = np.array([0.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.25, 0.0, 0.0, 0.0, 0.0, 1.0])
JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")


@njit(**JIT)
def _fong_z(sx, sy):
    """``n_z`` of the square point ``(sx, sy)`` (``bsdf.mapping.normal_from_square``)."""
    u, v = sx * math.sqrt(1.0 - 0.5 * sy * sy), sy * math.sqrt(1.0 - 0.5 * sx * sx)
    return math.sqrt(max(1.0 - u * u - v * v, TINY))


@njit(**JIT)
def _pixel_setup(xp, iso, normal_mapped, ior_mapped, eta_const, geo):
    """Per-pixel, light-independent quantities into ``geo`` (a scratch vector, layout below);
    returns ``(ax, ay, dax_r, dax_an, day_r, day_an, eta)``.

    ``geo``: 0-2 n, 3-5 dn/dsx, 6-8 dn/dsy, 9-11 t, 12-14 b, 15-32 dt/d(sx, sy, tau) (3 x 3),
    33-50 db/d(sx, sy, tau)."""
    for i in range(51):
        geo[i] = 0.0
    if normal_mapped:
        sx, sy = xp[6], xp[7]
        inx, iny = 1.0 if -1.0 <= sx <= 1.0 else 0.0, 1.0 if -1.0 <= sy <= 1.0 else 0.0
        sx, sy = min(max(sx, -1.0), 1.0), min(max(sy, -1.0), 1.0)
        qy, qx = math.sqrt(1.0 - 0.5 * sy * sy), math.sqrt(1.0 - 0.5 * sx * sx)
        u, v = sx * qy, sy * qx
        du_sx, du_sy = qy, -0.5 * sx * sy / qy
        dv_sx, dv_sy = -0.5 * sx * sy / qx, qx
        w2 = 1.0 - u * u - v * v
        w = math.sqrt(max(w2, TINY))
        geo[0], geo[1], geo[2] = u, v, w
        if w > RIM_W:
            dw_sx = -(u * du_sx + v * dv_sx) / w
            dw_sy = -(u * du_sy + v * dv_sy) / w
        else:  # on the rim dn_z/ds is infinite (0 through the guard): the inward secant instead
            dw_sx = (_fong_z(sx - math.copysign(RIM_STEP, sx), sy) - w) / -math.copysign(RIM_STEP, sx)
            dw_sy = (_fong_z(sx, sy - math.copysign(RIM_STEP, sy)) - w) / -math.copysign(RIM_STEP, sy)
        geo[3], geo[4], geo[5] = du_sx * inx, dv_sx * inx, dw_sx * inx
        geo[6], geo[7], geo[8] = du_sy * iny, dv_sy * iny, dw_sy * iny
    else:
        geo[2] = 1.0
    if iso:
        a, da = alphas_iso_d(xp[3])
        ax, ay, dax_r, dax_an, day_r, day_an = a, a, da, 0.0, da, 0.0
    else:
        ax, ay, dax_r, dax_an, day_r, day_an = alphas_aniso_d(xp[3], xp[4])
        phi = math.pi * xp[5]
        c, s = math.cos(phi), math.sin(phi)
        nx, ny, nz = geo[0], geo[1], geo[2]
        if normal_mapped:
            t0n = c * nx + s * ny
            qx_, qy_, qz_ = c - t0n * nx, s - t0n * ny, -t0n * nz
            r = 1.0 / math.sqrt(qx_ * qx_ + qy_ * qy_ + qz_ * qz_ + TINY)
            tx, ty, tz = qx_ * r, qy_ * r, qz_ * r
            for k in range(3):  # theta = sx, sy, tau
                if k < 2:
                    dnx, dny, dnz = geo[3 + 3 * k], geo[4 + 3 * k], geo[5 + 3 * k]
                    d0x, d0y = 0.0, 0.0
                else:
                    dnx = dny = dnz = 0.0
                    d0x, d0y = -math.pi * s, math.pi * c
                dt0n = d0x * nx + d0y * ny + c * dnx + s * dny
                dqx = d0x - dt0n * nx - t0n * dnx
                dqy = d0y - dt0n * ny - t0n * dny
                dqz = -dt0n * nz - t0n * dnz
                qdq = qx_ * dqx + qy_ * dqy + qz_ * dqz
                r3 = r * r * r * qdq
                dtx, dty, dtz = dqx * r - qx_ * r3, dqy * r - qy_ * r3, dqz * r - qz_ * r3
                geo[15 + 3 * k], geo[16 + 3 * k], geo[17 + 3 * k] = dtx, dty, dtz
                # b = n x t: db = dn x t + n x dt
                geo[33 + 3 * k] = dny * tz - dnz * ty + ny * dtz - nz * dty
                geo[34 + 3 * k] = dnz * tx - dnx * tz + nz * dtx - nx * dtz
                geo[35 + 3 * k] = dnx * ty - dny * tx + nx * dty - ny * dtx
            geo[9], geo[10], geo[11] = tx, ty, tz
            geo[12], geo[13], geo[14] = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
        else:  # flat: the frame is the image plane
            geo[9], geo[10], geo[11] = c, s, 0.0
            geo[12], geo[13], geo[14] = -s, c, 0.0
            geo[21], geo[22] = -math.pi * s, math.pi * c
            geo[39], geo[40] = -math.pi * c, -math.pi * s
    eta = 1.0 + 2.0 * xp[8] if ior_mapped else eta_const
    return ax, ay, dax_r, dax_an, day_r, day_an, eta


@njit(**JIT)
def _pixel_consts(xp, geo, al, eta, vx, vy, vz, iso, tinted, k):
    """Light-independent terms of one pixel into ``k`` (a scratch vector, layout in the body)."""
    ax, ay, dax_r, dax_an, day_r, day_an = al
    nx, ny, nz = geo[0], geo[1], geo[2]
    cv = vx * nx + vy * ny + vz * nz
    vvx = vx * geo[9] + vy * geo[10] + vz * geo[11]
    vvy = vx * geo[12] + vy * geo[13] + vz * geo[14]
    a2v = ax * ax * (1.0 - cv * cv) if iso else (ax * vvx) ** 2 + (ay * vvy) ** 2
    k[0], k[3], k[4], k[5] = cv, vvx, vvy, a2v  # (slots 1, 2, 6-9 unused)
    for j in range(3):  # d(v.n)/d(sx, sy); d(v.t), d(v.b) / d(sx, sy, tau)
        k[10 + j] = vx * geo[3 + 3 * j] + vy * geo[4 + 3 * j] + vz * geo[5 + 3 * j] if j < 2 else 0.0
        k[13 + j] = vx * geo[15 + 3 * j] + vy * geo[16 + 3 * j] + vz * geo[17 + 3 * j]
        k[16 + j] = vx * geo[33 + 3 * j] + vy * geo[34 + 3 * j] + vz * geo[35 + 3 * j]
    m, im = xp[0], 0
    for c in range(1, 3):
        if xp[c] > m:
            m, im = xp[c], c
    rho = xp[9] if tinted else 0.0
    for c in range(3):  # tint, chr, d tint / d albedo_j (3 x 3)
        chr_c = xp[c] / m if m > CHROMA_EPS else 1.0
        k[20 + c] = chr_c * rho + 1.0 - rho if tinted else 1.0
        k[23 + c] = chr_c
        for j in range(3):
            dchr = (1.0 / m if j == c else 0.0) - (xp[c] / (m * m) if j == im else 0.0)
            k[26 + 3 * c + j] = rho * dchr if (tinted and m > CHROMA_EPS) else 0.0
    k[35] = dax_r
    k[36] = dax_an
    k[37] = day_r
    k[38] = day_an
    k[39] = eta


@njit(**JIT)
def _render_lights(xp, geo, al, kc, L, vz, ws, wp, wd, iso, opaque, lam, k0, k1, out):
    """Renders of lights ``k0:k1`` (``L (3, N)``) at one pixel into ``out[c, k - k0]`` (before the
    clamp at 2); ``lam``: Lambert's diffuse instead of Burley's.  One branch-free loop over the
    lights: LLVM vectorises it."""
    ax, ay = al[0], al[1]
    nx, ny, nz = geo[0], geo[1], geo[2]
    tx, ty, tz, bx, by, bz = geo[9], geo[10], geo[11], geo[12], geo[13], geo[14]
    cv, vvx, vvy, a2v = kc[0], kc[3], kc[4], kc[5]
    vx, vy = kc[40], kc[41]
    t0, t1, t2 = kc[20], kc[21], kc[22]
    a0, a1, a2_, rough, eta = xp[0], xp[1], xp[2], xp[3], kc[39]
    a2 = ax * ax
    vok = cv > 0.0 and vz > 0.0
    op = 1.0 if opaque else xp[13]
    for k in range(k0, k1):
        lx, ly, lz = L[0, k], L[1, k], L[2, k]
        cl = lx * nx + ly * ny + lz * nz
        clv = lx * vx + ly * vy + lz * vz
        len2 = max(2.0 + 2.0 * clv, 1e-12)
        inv_len = 1.0 / math.sqrt(len2)
        cos_d = 0.5 * len2 * inv_len
        g = INV_PI if lam else diffuse_d(cl, cv, clv, rough)[0]
        f = fresnel_weighted_d(cos_d, eta, ws[k], wp[k])[0]
        hz = (cl + cv) * inv_len
        if iso:
            d = ggx_d_iso_d(hz, ax)[0]
            a2l = a2 * (1.0 - cl * cl)
        else:
            llx = lx * tx + ly * ty + lz * tz
            lly = lx * bx + ly * by + lz * bz
            d = ggx_d_aniso_d((llx + vvx) * inv_len, (lly + vvy) * inv_len, hz, ax, ay)[0]
            a2l = (ax * llx) ** 2 + (ay * lly) ** 2
        spec = d * f * smith_visibility_d(cl, a2l, cv, a2v)[0]
        front = cl > 0.0 and lz > 0.0 and vok
        w = wd[k] * g
        o0 = cl * (w * a0 + spec * t0) if front else 0.0
        o1 = cl * (w * a1 + spec * t1) if front else 0.0
        o2 = cl * (w * a2_ + spec * t2) if front else 0.0
        if not opaque:
            tr = wd[k] * abs(lz) * INV_PI if lz * vz < 0.0 else 0.0
            o0 = (o0 + xp[10] * tr) * op
            o1 = (o1 + xp[11] * tr) * op
            o2 = (o2 + xp[12] * tr) * op
        out[0, k - k0] = o0
        out[1, k - k0] = o1
        out[2, k - k0] = o2


@njit(inline="always", **JIT)
def _light_basis(k, L, ws, wp, wd, pc, iso, opaque, lam):
    """The 12 shared rows of light ``k``'s Jacobian at one pixel (``pc``: the pixel's
    constants, :func:`_jacobian_lights`): ``clf wd G``, ``clf S``, ``clf wd dG/dr``, ``clf dS/dr``,
    ``clf dS/dan``, ``clf dS/dtau``, the normal's two (diffuse, specular) pairs, ``clf dS/deta``
    and the transmission factor, where ``clf`` is ``n.l`` on the lit front and 0 elsewhere;
    ``lam``: Lambert's diffuse ``G = 1/pi`` (no derivative) instead of Burley's."""
    (ax, ay, nx, ny, nz, tx, ty, tz, bx, by, bz, cv, vvx, vvy, a2v, dcv0,
     dcv1, dvx0, dvx1, dvx2, dvy0, dvy1, dvy2, dax_r, dax_an, day_r, day_an, eta, vx, vy, vz, rough, dn0x,
     dn0y, dn0z, dn1x, dn1y, dn1z, t0x, t0y, t0z, t1x, t1y, t1z, t2x, t2y, t2z, b0x, b0y, b0z, b1x, b1y,
     b1z, b2x, b2y, b2z) = pc
    a2 = ax * ax
    vok = cv > 0.0 and vz > 0.0
    lx, ly, lz = L[0, k], L[1, k], L[2, k]
    wsk, wpk, wdk = ws[k], wp[k], wd[k]
    cl = lx * nx + ly * ny + lz * nz
    clv = lx * vx + ly * vy + lz * vz
    len2 = max(2.0 + 2.0 * clv, 1e-12)
    inv_len = 1.0 / math.sqrt(len2)
    cos_d = 0.5 * len2 * inv_len
    if lam:
        g, dg_cl, dg_cv, dg_r = INV_PI, 0.0, 0.0, 0.0
    else:
        g, dg_cl, dg_cv, dg_r = diffuse_d(cl, cv, clv, rough)
    f, df = fresnel_weighted_d(cos_d, eta, wsk, wpk)
    hz = (cl + cv) * inv_len
    # D, the Smith visibility V and S = D V F with their partials
    if iso:
        d, dd_hz, dd_ax = ggx_d_iso_d(hz, ax)
        dd_hx = dd_hy = dd_ay = 0.0
        a2l = a2 * (1.0 - cl * cl)
        llx = lly = 0.0
    else:
        llx = lx * tx + ly * ty + lz * tz
        lly = lx * bx + ly * by + lz * bz
        d, dd_hx, dd_hy, dd_hz, dd_ax, dd_ay = ggx_d_aniso_d((llx + vvx) * inv_len, (lly + vvy) * inv_len, hz, ax, ay)
        a2l = (ax * llx) ** 2 + (ay * lly) ** 2
    vis, dv_zl, dv_a2l, dv_zv, dv_a2v = smith_visibility_d(cl, a2l, cv, a2v)
    dvis_h = inv_len * vis
    if iso:
        ds_cl = f * (dd_hz * dvis_h + d * (dv_zl + dv_a2l * (-2.0 * a2 * cl)))
        ds_cv = f * (dd_hz * dvis_h + d * (dv_zv + dv_a2v * (-2.0 * a2 * cv)))
        ds_ax = f * (dd_ax * vis + d * (dv_a2l * 2.0 * ax * (1.0 - cl * cl) + dv_a2v * 2.0 * ax * (1.0 - cv * cv)))
        ds_ay = ds_lx = ds_ly = ds_vx = ds_vy = 0.0
    else:
        ds_cl = f * (dd_hz * dvis_h + d * dv_zl)
        ds_cv = f * (dd_hz * dvis_h + d * dv_zv)
        ds_lx = f * (dd_hx * dvis_h + d * dv_a2l * 2.0 * ax * ax * llx)
        ds_ly = f * (dd_hy * dvis_h + d * dv_a2l * 2.0 * ay * ay * lly)
        ds_vx = f * (dd_hx * dvis_h + d * dv_a2v * 2.0 * ax * ax * vvx)
        ds_vy = f * (dd_hy * dvis_h + d * dv_a2v * 2.0 * ay * ay * vvy)
        ds_ax = f * (dd_ax * vis + d * (dv_a2l * 2.0 * ax * llx * llx + dv_a2v * 2.0 * ax * vvx * vvx))
        ds_ay = f * (dd_ay * vis + d * (dv_a2l * 2.0 * ay * lly * lly + dv_a2v * 2.0 * ay * vvy * vvy))
    sp = d * vis * f
    ds_r = ds_ax * dax_r + ds_ay * day_r
    ds_an = ds_ax * dax_an + ds_ay * day_an
    ds_eta = d * vis * df * 2.0
    dcl0 = lx * dn0x + ly * dn0y + lz * dn0z
    dcl1 = lx * dn1x + ly * dn1y + lz * dn1z
    ds0 = ds_cl * dcl0 + ds_cv * dcv0
    ds1 = ds_cl * dcl1 + ds_cv * dcv1
    ds2 = 0.0
    if not iso:  # the tangent frame's derivatives w.r.t. sx, sy, tau
        ds0 += (ds_lx * (lx * t0x + ly * t0y + lz * t0z) + ds_ly * (lx * b0x + ly * b0y + lz * b0z)
                + ds_vx * dvx0 + ds_vy * dvy0)
        ds1 += (ds_lx * (lx * t1x + ly * t1y + lz * t1z) + ds_ly * (lx * b1x + ly * b1y + lz * b1z)
                + ds_vx * dvx1 + ds_vy * dvy1)
        ds2 = (ds_lx * (lx * t2x + ly * t2y + lz * t2z) + ds_ly * (lx * b2x + ly * b2y + lz * b2z)
               + ds_vx * dvx2 + ds_vy * dvy2)
    dg0 = dg_cl * dcl0 + dg_cv * dcv0
    dg1 = dg_cl * dcl1 + dg_cv * dcv1
    front = cl > 0.0 and lz > 0.0 and vok
    fr = 1.0 if front else 0.0
    clf = cl * fr
    tr = (wdk * abs(lz) * INV_PI if lz * vz < 0.0 else 0.0) if not opaque else 0.0
    return (clf * wdk * g, clf * sp, clf * wdk * dg_r, clf * ds_r, clf * ds_an, clf * ds2,
            fr * wdk * (dcl0 * g + cl * dg0), fr * (dcl0 * sp + cl * ds0), fr * wdk * (dcl1 * g + cl * dg1),
            fr * (dcl1 * sp + cl * ds1), clf * ds_eta, tr)

@njit(inline="always", **JIT)
def _basis_lights(xp, geo, al, kc, L, vz, ws, wp, wd, iso, opaque, lam, k0, k1, bas):
    """The shared Jacobian rows ``bas[r, k - k0]`` (:func:`_light_basis`) of lights ``k0:k1`` at
    one pixel; every channel's render and Jacobian row is a combination of them
    (:func:`_coefficients`).  The light loops are branch-free and write 6 arrays each, so that
    LLVM vectorises them (at 12 its runtime alias checks exceed their limit and the loop stays
    scalar)."""
    ax, ay = al[0], al[1]
    pc = (ax, ay, geo[0], geo[1], geo[2], geo[9], geo[10], geo[11], geo[12], geo[13], geo[14], kc[0],
          kc[3], kc[4], kc[5], kc[10], kc[11], kc[13], kc[14], kc[15], kc[16], kc[17],
          kc[18], kc[35], kc[36], kc[37], kc[38], kc[39], kc[40], kc[41], vz, xp[3], geo[3], geo[4], geo[5], geo[6],
          geo[7], geo[8], geo[15], geo[16], geo[17], geo[18], geo[19], geo[20], geo[21], geo[22], geo[23], geo[33],
          geo[34], geo[35], geo[36], geo[37], geo[38], geo[39], geo[40], geo[41])
    for q in range(k1 - k0):
        b = _light_basis(k0 + q, L, ws, wp, wd, pc, iso, opaque, lam)
        bas[0, q], bas[1, q], bas[2, q], bas[3, q], bas[4, q], bas[5, q] = b[0], b[1], b[2], b[3], b[4], b[5]
    for q in range(k1 - k0):
        b = _light_basis(k0 + q, L, ws, wp, wd, pc, iso, opaque, lam)
        bas[6, q], bas[7, q], bas[8, q], bas[9, q], bas[10, q], bas[11, q] = b[6], b[7], b[8], b[9], b[10], b[11]


@njit(**JIT)
def _coefficients(xp, kc, cols, opaque, rows, coef):
    """How each free column ``i`` and channel ``c`` of the Jacobian combines the shared rows:
    ``J[c, i] = sum_j coef[i, c, j] bas[rows[i, c, j]]`` (3 terms; the opacity folded in).  Per
    channel, ``render = (A_c bas0 + tint_c bas1 + T_c bas11) op``."""
    op = 1.0 if opaque else xp[13]
    for i in range(cols.shape[0]):
        s = cols[i]
        for c in range(3):
            ac, tc, tt = xp[c], kc[20 + c], (0.0 if opaque else xp[10 + c])
            r0, w0, r1, w1, r2, w2 = 0, 0.0, 1, 0.0, 11, 0.0
            if s < 3:  # albedo: its own channel's diffuse, and every channel's tint through chr(b)
                w0, w1 = (op if c == s else 0.0), op * kc[26 + 3 * c + s]
            elif s == 3:
                r0, w0, r1, w1 = 2, op * ac, 3, op * tc
            elif s == 4 or s == 5:
                r1, w1 = s, op * tc
            elif s == 6:
                r0, w0, r1, w1 = 6, op * ac, 7, op * tc
            elif s == 7:
                r0, w0, r1, w1 = 8, op * ac, 9, op * tc
            elif s == 8:
                r1, w1 = 10, op * tc
            elif s == 9:
                w1 = op * (kc[23 + c] - 1.0)
            elif s < 13:
                w2 = op if c == s - 10 else 0.0
            else:  # opacity: the render before it
                w0, w1, w2 = ac, tc, tt
            rows[i, c, 0], rows[i, c, 1], rows[i, c, 2] = r0, r1, r2
            coef[i, c, 0], coef[i, c, 1], coef[i, c, 2] = w0, w1, w2


@njit(**JIT)
def _setup(x, p, view, flags, eta_const, geo, kc):
    """Per-pixel setup of the kernels: geometry, alphas and the light-independent terms."""
    iso, tinted, nmap, imap = flags[0] != 0, flags[1] != 0, flags[3] != 0, flags[4] != 0
    al7 = _pixel_setup(x[p], iso, nmap, imap, eta_const, geo)
    al = (al7[0], al7[1], al7[2], al7[3], al7[4], al7[5])
    _pixel_consts(x[p], geo, al, al7[6], view[p, 0], view[p, 1], view[p, 2], iso, tinted, kc)
    kc[40], kc[41] = view[p, 0], view[p, 1]
    return al


@njit(**JIT)
def _pixel_residuals(p, x, view, L, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row, geo, kc, o):
    """Residuals of pixel ``p`` (render clamped at 2 - image) into ``row (K,)``."""
    n = L.shape[1]
    iso, opaque, lam = flags[0] != 0, flags[2] != 0, flags[5] != 0
    al = _setup(x, p, view, flags, eta_const, geo, kc)
    _render_lights(x[p], geo, al, kc, L, view[p, 2], w_s, w_p, w_d, iso, opaque, lam, 0, n, o)
    for k in range(n):
        for c in range(3):
            row[3 * k + c] = min(o[c, k], CLAMP) - images[p, 3 * k + c]
    if back.shape[0] == x.shape[0]:
        xp = x[p]
        for c in range(3):
            b = 0.0 if opaque else back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
            row[3 * n + c] = min(b, CLAMP) - back[p, c]


@njit(parallel=True, **JIT)
def residual_rows(x, view, L, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, out):
    """``out (npix, K)`` = render clamped at 2 - image, for every pixel (``x (npix, 14)`` full
    vectors, ``view (npix, 3)``, light directions ``L (3, N)``, weights ``(N,)``, ``images
    (npix, 3N)``, ``back (npix, 3)`` or empty; ``flags`` = (iso, tinted, opaque, normal_mapped,
    ior_mapped, lambert))."""
    for p in prange(x.shape[0]):
        row = np.empty(out.shape[1])
        geo, kc, o = np.empty(51), np.empty(NCONST), np.empty((3, L.shape[1]))
        _pixel_residuals(p, x, view, L, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row, geo, kc, o)
        for i in range(out.shape[1]):
            out[p, i] = row[i]


@njit(parallel=True, **JIT)
def weighted_cost(x, view, L, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, sel, c_rows, l1, out,
                  rows_out):
    """``out (npix,)`` = ``sum c sel |r|`` (``l1``) or ``sum c sel r^2`` over the residual rows, with
    the row weights ``c_rows (K,)`` and the row selection ``sel (npix, K)`` (1/0; empty = all);
    the residuals go to ``rows_out (npix, K)`` unless it is empty."""
    kk = c_rows.shape[0]
    has_sel, keep_rows = sel.shape[0] == x.shape[0], rows_out.shape[0] == x.shape[0]
    for p in prange(x.shape[0]):
        row = np.empty(kk)
        geo, kc, o = np.empty(51), np.empty(NCONST), np.empty((3, L.shape[1]))
        _pixel_residuals(p, x, view, L, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row, geo, kc, o)
        acc = 0.0
        for i in range(kk):
            w = c_rows[i] * sel[p, i] if has_sel else c_rows[i]
            acc += w * (abs(row[i]) if l1 else row[i] * row[i])
            if keep_rows:
                rows_out[p, i] = row[i]
        out[p] = acc


@njit(parallel=True, **JIT)
def irls_rows(r, c_rows, valid, lum, partner_ptr, partner_idx, near, shadow_ratio, floor, l1, eps,
              keep, sw, cost, scale):
    """The reweighting of one LM iteration (:class:`.lm.Loss`, the eager reference) from the
    residuals ``r (npix, K)``: kept rows ``keep`` (invalid rows and, with ``shadow_ratio`` > 0,
    the captures of an LED taken for a cast shadow, tested on its diffuse-only partners
    ``partner_idx[partner_ptr[i]:partner_ptr[i + 1]]`` when it has any; not where more than half
    of the ``near`` LEDs are dark), row multipliers ``sw = sqrt(W)``, the data cost and the
    likelihood scale (lower median of ``|r|`` over the valid rows) per pixel.  ``valid
    (npix, K)`` 1/0 or empty (all valid), ``lum (npix, N)`` the images' mean over RGB."""
    npix, kk = r.shape
    n = lum.shape[1]
    n_near = 0
    for i in range(n):
        if near[i]:
            n_near += 1
    has_valid = valid.shape[0] == npix
    for p in prange(npix):
        dark = np.zeros(n, dtype=np.bool_)
        buf, tmp = np.empty(kk), np.empty(kk)
        if has_valid:
            for i in range(kk):
                keep[p, i] = valid[p, i]
        else:
            for i in range(kk):
                keep[p, i] = 1.0
        if shadow_ratio > 0.0:
            dark_near = 0
            for i in range(n):
                rl = (r[p, 3 * i] + r[p, 3 * i + 1] + r[p, 3 * i + 2]) / 3.0 + lum[p, i]
                dark[i] = lum[p, i] < shadow_ratio * rl and rl > floor and keep[p, 3 * i] > 0.0
                if dark[i] and near[i]:
                    dark_near += 1
            if not (n_near > 0 and dark_near > 0.5 * n_near):
                for i in range(n):
                    a, b = partner_ptr[i], partner_ptr[i + 1]
                    drop = dark[i]
                    if b > a:
                        drop = False
                        for q in range(a, b):
                            if dark[partner_idx[q]]:
                                drop = True
                    if drop:
                        keep[p, 3 * i] = keep[p, 3 * i + 1] = keep[p, 3 * i + 2] = 0.0
        kp, rp, sp = keep[p], r[p], sw[p]
        if l1:  # branch-free loops over the rows (vectorised)
            for i in range(kk):
                sp[i] = math.sqrt(c_rows[i] * kp[i] / max(abs(rp[i]), eps))
        else:
            for i in range(kk):
                sp[i] = math.sqrt(c_rows[i] * kp[i])
        acc = _row_cost(c_rows, kp, rp, l1)
        if has_valid:
            m = 0
            for i in range(kk):
                if valid[p, i] > 0.0:
                    buf[m] = abs(rp[i])
                    m += 1
        else:
            m = kk
            for i in range(kk):
                buf[i] = abs(rp[i])
        cost[p] = acc
        med = eps
        if m > 0:
            med = max(_select(buf, m, (m - 1) // 2, tmp), eps)
        scale[p] = med / math.log(2.0) if l1 else (1.4826 * med) ** 2


@njit(**JIT)
def _select(a, m, kth, tmp):
    """The ``kth`` smallest of ``a[:m]`` (0-based; the lower median at ``(m - 1) // 2``).

    A quickselect whose partition has no data-dependent branch: every value is written to both
    ends of the other buffer (``tmp``, at least ``m`` long; both are scratch) and the ends
    advance by the comparisons.  On the fit's residual rows it took 3.2 us per pixel against
    6.8 for the classic in-place one (whose branches mispredict on these rows)."""
    src, dst = a, tmp
    lo, n = 0, m
    while n > 24:
        x, y, z = src[lo], src[lo + n // 2], src[lo + n - 1]
        pivot = max(min(x, y), min(max(x, y), z))  # median of three
        nl, ng = 0, n - 1
        for i in range(lo, lo + n):
            v = src[i]
            dst[nl] = v
            dst[ng] = v
            nl += 1 if v < pivot else 0
            ng -= 1 if v > pivot else 0
        neq = ng + 1 - nl
        if kth < nl:
            lo, n = 0, nl
        elif kth < nl + neq:
            return pivot
        else:
            kth -= nl + neq
            lo, n = ng + 1, n - ng - 1
        src, dst = dst, src
    for i in range(lo + 1, lo + n):  # insertion sort of the last few
        v = src[i]
        j = i - 1
        while j >= lo and src[j] > v:
            src[j + 1] = src[j]
            j -= 1
        src[j + 1] = v
    return src[lo + kth]


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _row_cost(c_rows, keep, r, l1):
    """``sum c keep |r|`` (``l1``) or ``sum c keep r^2`` over one pixel's rows."""
    acc = 0.0
    if l1:
        for i in range(r.shape[0]):
            acc += c_rows[i] * keep[i] * abs(r[i])
    else:
        for i in range(r.shape[0]):
            acc += c_rows[i] * keep[i] * r[i] * r[i]
    return acc


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _flush(blk, wrb, q, a, g):
    """``a += B B^T`` (upper triangle), ``g += B wr`` over the first ``q`` columns of ``B = blk``:
    contiguous dot products, which LLVM vectorises."""
    n = blk.shape[0]
    for i in range(n):
        bi = blk[i]
        s = 0.0
        for t in range(q):
            s += bi[t] * wrb[t]
        g[i] += s
        for j in range(i, n):
            bj = blk[j]
            s = 0.0
            for t in range(q):
                s += bi[t] * bj[t]
            a[i, j] += s


@njit(inline="always", **JIT)
def _pixel_start(x, p, view, flags, eta_const, cols):
    """A pixel's setup for the Jacobian kernels: scratch, geometry, alphas and the coefficients."""
    opaque = flags[2] != 0
    geo, kc = np.empty(51), np.empty(NCONST)
    rows, coef = np.empty((cols.shape[0], 3, 3), dtype=np.int64), np.empty((cols.shape[0], 3, 3))
    al = _setup(x, p, view, flags, eta_const, geo, kc)
    xp = x[p]
    _coefficients(xp, kc, cols, opaque, rows, coef)
    return geo, kc, al, xp, (1.0 if opaque else xp[13]), rows, coef


@njit(inline="always", **JIT)
def _block_weights(xp, kc, bas, opaque, op, src, p, k0, b, wv):
    """``wv[c, q]`` = ``src[p, 3 (k0 + q) + c]`` (a row weight or an upstream gradient), 0 where
    the render is clamped (> 2: no derivative, as torch's ``clamp``)."""
    for c in range(3):
        ac, tc, tt = xp[c], kc[20 + c], (0.0 if opaque else xp[10 + c])
        for q in range(b):
            o = (ac * bas[0, q] + tc * bas[1, q] + tt * bas[11, q]) * op
            w = src[p, 3 * (k0 + q) + c]
            wv[c, q] = w if o <= CLAMP else 0.0


@njit(inline="always", **JIT)
def _back_derivative(xp, back_wd, s, c):
    """d(back-lit render, channel ``c``) / d(full slot ``s``): ``B = back_wd (T_c o + 1 - o)``."""
    return back_wd * xp[13] if s == 10 + c else (back_wd * (xp[10 + c] - 1.0) if s == 13 else 0.0)


@njit(parallel=True, **JIT)
def normal_equations(x, cols, view, L, w_s, w_p, w_d, back, back_wd, flags, eta_const, r, sw, jtj, jtr):
    """Accumulate ``J^T W J (npix, P, P)`` and ``J^T W r (npix, P)`` (overwritten) from the
    residuals ``r (npix, K)`` and row multipliers ``sw = sqrt(W) (npix, K)``; ``cols (P,)`` are
    the full-vector slots of the free parameters, in their order.  The lights are taken
    ``LIGHT_BLOCK`` at a time: their weighted Jacobian rows (a few kB) are folded into the
    normal equations at once.  Rows with ``sw == 0`` and rows whose render is clamped (> 2)
    contribute nothing (zero derivative)."""
    npix, n, P = x.shape[0], L.shape[1], cols.shape[0]
    iso, opaque, lam = flags[0] != 0, flags[2] != 0, flags[5] != 0
    has_back = back.shape[0] == npix
    for p in prange(npix):
        geo, kc, al, xp, op, rows, coef = _pixel_start(x, p, view, flags, eta_const, cols)
        bas, wv = np.empty((12, LIGHT_BLOCK)), np.empty((3, LIGHT_BLOCK))
        jw, wr = np.empty((P, 3 * LIGHT_BLOCK)), np.empty(3 * LIGHT_BLOCK)
        row = np.empty(P)
        a, g = np.zeros((P, P)), np.zeros(P)
        for k0 in range(0, n, LIGHT_BLOCK):
            k1 = min(n, k0 + LIGHT_BLOCK)
            b = k1 - k0
            _basis_lights(xp, geo, al, kc, L, view[p, 2], w_s, w_p, w_d, iso, opaque, lam, k0, k1, bas)
            _block_weights(xp, kc, bas, opaque, op, sw, p, k0, b, wv)
            for c in range(3):
                for q in range(b):
                    wr[c * b + q] = r[p, 3 * (k0 + q) + c] * wv[c, q]
            for i in range(P):
                for c in range(3):
                    r0, r1, r2 = rows[i, c, 0], rows[i, c, 1], rows[i, c, 2]
                    w0, w1, w2 = coef[i, c, 0], coef[i, c, 1], coef[i, c, 2]
                    for q in range(b):
                        jw[i, c * b + q] = (w0 * bas[r0, q] + w1 * bas[r1, q] + w2 * bas[r2, q]) * wv[c, q]
            _flush(jw, wr, 3 * b, a, g)
        if has_back and not opaque:
            for c in range(3):
                w = sw[p, 3 * n + c]
                bk = back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
                if w == 0.0 or bk > CLAMP:
                    continue
                for i in range(P):
                    row[i] = _back_derivative(xp, back_wd, cols[i], c) * w
                wrb = r[p, 3 * n + c] * w
                for i in range(P):
                    g[i] += row[i] * wrb
                    for j in range(i, P):
                        a[i, j] += row[i] * row[j]
        for i in range(P):
            jtr[p, i] = g[i]
            for j in range(i, P):
                jtj[p, i, j] = a[i, j]
                jtj[p, j, i] = a[i, j]


@njit(parallel=True, **JIT)
def vector_jacobian(x, cols, view, L, w_s, w_p, w_d, back, back_wd, flags, eta_const, grad, out):
    """``out (npix, P)`` = ``J^T grad``: the gradient of a loss whose derivative with respect to
    the residuals is ``grad (npix, K)`` (reverse mode for Adam, :class:`Residuals`); clamped
    renders (> 2) pass no gradient, as in torch's ``clamp``."""
    npix, n, P = x.shape[0], L.shape[1], cols.shape[0]
    iso, opaque, lam = flags[0] != 0, flags[2] != 0, flags[5] != 0
    has_back = back.shape[0] == npix
    for p in prange(npix):
        geo, kc, al, xp, op, rows, coef = _pixel_start(x, p, view, flags, eta_const, cols)
        bas, wv = np.empty((12, LIGHT_BLOCK)), np.empty((3, LIGHT_BLOCK))
        g = np.zeros(P)
        for k0 in range(0, n, LIGHT_BLOCK):
            k1 = min(n, k0 + LIGHT_BLOCK)
            b = k1 - k0
            _basis_lights(xp, geo, al, kc, L, view[p, 2], w_s, w_p, w_d, iso, opaque, lam, k0, k1, bas)
            _block_weights(xp, kc, bas, opaque, op, grad, p, k0, b, wv)
            for i in range(P):
                for c in range(3):
                    r0, r1, r2 = rows[i, c, 0], rows[i, c, 1], rows[i, c, 2]
                    w0, w1, w2 = coef[i, c, 0], coef[i, c, 1], coef[i, c, 2]
                    g[i] += _combine(bas, r0, w0, r1, w1, r2, w2, wv[c], b)
        if has_back and not opaque:
            for c in range(3):
                bk = back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
                if bk > CLAMP:
                    continue
                for i in range(P):
                    g[i] += _back_derivative(xp, back_wd, cols[i], c) * grad[p, 3 * n + c]
        for i in range(P):
            out[p, i] = g[i]


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _combine(bas, r0, w0, r1, w1, r2, w2, wv, b):
    """``sum_q (w0 bas[r0] + w1 bas[r1] + w2 bas[r2])[q] wv[q]`` over the first ``b`` lights."""
    acc = 0.0
    for q in range(b):
        acc += (w0 * bas[r0, q] + w1 * bas[r1, q] + w2 * bas[r2, q]) * wv[q]
    return acc


class Residuals(torch.autograd.Function):
    """Residuals ``(H, W, K)`` of :meth:`Problem.residuals` as a differentiable function of the
    packed free parameters ``x (H, W, P)``: its backward is :func:`vector_jacobian` (the
    analytic derivatives), so Adam's presets fit through the fused kernel too."""

    @staticmethod
    def forward(ctx, x: Tensor, prob: "Problem", names: tuple[str, ...], fixed: dict[str, Tensor]) -> Tensor:
        ctx.save_for_backward(x.detach().clone())
        ctx.prob, ctx.names, ctx.fixed = prob, names, fixed
        return prob.residuals(x.detach(), names, fixed)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (x,) = ctx.saved_tensors
        return ctx.prob.vjp(x, ctx.names, ctx.fixed, grad), None, None, None


_ANNOUNCED: list[bool] = []


def _announce_compile() -> None:
    """Say once per process, on stderr, when the kernels are about to be compiled (no numba cache
    for this version of the module yet): the first fit otherwise pauses for half a minute in
    silence.  The compiled kernels are cached in this package's ``__pycache__``."""
    if _ANNOUNCED:
        return
    _ANNOUNCED.append(True)
    from pathlib import Path

    here = Path(__file__)
    line = normal_equations.py_func.__code__.co_firstlineno
    index = here.parent / "__pycache__" / f"{here.stem}.normal_equations-{line}.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
    if not index.is_file() or index.stat().st_mtime < here.stat().st_mtime:
        print("dualscale: compiling the fit's kernels (first run of this version only, about 30-60 s; numba caches "
              f"them in {index.parent})", file=sys.stderr, flush=True)


def _threads() -> None:
    """numba's pool at the command's thread count (``--threads``; else torch's), leaving torch's
    count as it is (starting numba's OpenMP pool would reset it)."""
    sync_numba()


def full_vectors(x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor]) -> tuple[np.ndarray, np.ndarray]:
    """``(X (npix, 14) float64, cols (P,) int64)``: the full per-pixel vectors from the free
    parameters ``x (H, W, P)`` (channels in ``names`` order) and the frozen maps ``fixed``
    (normalised units, :mod:`.params`); absent parameters get their defaults (unused)."""
    h, w = x.shape[:2]
    full = np.empty((h * w, NFULL))
    full[:] = DEFAULTS
    cols, c = [], 0
    for name in names:
        k = PARAM_CHANNELS[name]
        full[:, list(FULL[name])] = x[..., c:c + k].reshape(-1, k).double().numpy()
        cols += list(FULL[name])
        c += k
    for name, t in fixed.items():
        if name not in names:
            full[:, list(FULL[name])] = t.reshape(h * w, -1).double().numpy()
    return full, np.asarray(cols, dtype=np.int64)


def flags_of(comps: Components) -> np.ndarray:
    """Kernel flags ``(iso, tinted, opaque, normal_mapped, ior_mapped, lambert)``."""
    return np.array([comps.isotropic, comps.tinted, comps.opaque, comps.normal_mapped, comps.ior_mapped,
                     comps.lambertian], dtype=np.int64)


class Problem:
    """One pixel block of a fit step, laid out for the kernels: lights, weights, per-pixel view,
    image rows ``(npix, 3N)`` and back-lit rows (built once per block and reused)."""

    def __init__(self, obs, images: Tensor, back: Tensor | None, comps: Components) -> None:
        _announce_compile()
        h, w = obs.shape
        self.shape = (h, w)
        self.comps = comps
        self.flags = flags_of(comps)
        self.eta = float(comps.ior)
        self.dirs = np.ascontiguousarray(obs.dirs.double().numpy().T)  # (3, N): a light loop reads it contiguously
        self.w_s, self.w_p, self.w_d = (np.ascontiguousarray(t.double().numpy()) for t in (obs.w_s, obs.w_p, obs.w_d))
        view = obs.view.double()
        self.view = np.ascontiguousarray((view.expand(h, w, 3) if view.ndim == 1 else view).reshape(-1, 3).numpy())
        self.rows = np.ascontiguousarray(images.permute(1, 2, 0, 3).reshape(h * w, -1).numpy())
        self.back = (np.ascontiguousarray(back.reshape(h * w, 3).numpy()) if back is not None
                     else np.empty((0, 3), dtype=self.rows.dtype))
        self.back_wd = float(obs.back_wd)
        self.k = self.rows.shape[1] + (3 if back is not None else 0)
        self._rows_and_back: np.ndarray | None = None
        valid = valid_rows(obs, back is not None, images.dtype)
        self.valid = (np.ascontiguousarray(valid.reshape(h * w, -1).numpy()) if valid is not None
                      else np.empty((0, self.k), dtype=self.rows.dtype))
        self.lum = np.ascontiguousarray(images.mean(-1).permute(1, 2, 0).reshape(h * w, -1).numpy())
        # the shadow test's partners: image i is judged on the diffuse-only images j of its LED
        diffuse = (obs.w_s < 1e-6) & (obs.w_p < 1e-6)
        same = (obs.led_ids.reshape(-1, 1) == obs.led_ids.reshape(1, -1)) & diffuse.reshape(1, -1)
        self.partner_ptr = np.concatenate([[0], np.cumsum(same.sum(1).numpy())]).astype(np.int64)
        self.partner_idx = np.ascontiguousarray(same.nonzero()[:, 1].numpy().astype(np.int64))
        self.near = np.ascontiguousarray((obs.dirs[:, 2] >= SHADOW_ANCHOR_COS).numpy())

    def row_weights(self, back_weight: float) -> np.ndarray:
        """``c`` per residual row: 1 per LED row, ``back_weight`` per back-lit row."""
        c = np.ones(self.k)
        c[self.rows.shape[1]:] = back_weight
        return c

    def irls(self, r: Tensor, loss) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(keep, sqrt(W), data cost, likelihood scale)`` of :class:`.lm.Loss` at the residuals
        ``r (H, W, K)``: ``(H, W, K)``, ``(H, W, K)``, ``(H, W)``, ``(H, W)`` (:func:`irls_rows`)."""
        _threads()
        npix = r.shape[0] * r.shape[1]
        r2 = np.ascontiguousarray(r.reshape(npix, -1).numpy())
        keep, sw = np.empty_like(r2), np.empty_like(r2)
        cost, scale = np.empty(npix, dtype=r2.dtype), np.empty(npix, dtype=r2.dtype)
        irls_rows(r2, self.row_weights(loss.back_weight), self.valid, self.lum, self.partner_ptr, self.partner_idx, self.near,
                  float(loss.shadow_ratio), SHADOW_FLOOR, loss.kind == "l1", float(loss.eps), keep, sw, cost, scale)
        t = torch.from_numpy
        return (t(keep).reshape(r.shape), t(sw).reshape(r.shape), t(cost).reshape(self.shape),
                t(scale).reshape(self.shape))

    def cost(self, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], loss,
             keep: Tensor | None, residuals: bool = False) -> tuple[Tensor, Tensor | None]:
        """``(cost (H, W), residuals (H, W, K) or None)``: the per-pixel data cost of
        :class:`.lm.Loss` at ``x`` over the rows ``keep`` (``(H, W, K)``), else over the valid
        rows, and with ``residuals`` the residuals it rendered (:func:`weighted_cost`)."""
        _threads()
        full, _ = full_vectors(x, names, fixed)
        npix = full.shape[0]
        sel = (np.ascontiguousarray(keep.reshape(npix, -1).numpy()) if keep is not None else self.valid)
        out = np.empty(npix)
        rows = np.empty((npix if residuals else 0, self.k), dtype=np.float32 if x.dtype == torch.float32 else np.float64)
        weighted_cost(full, self.view, self.dirs, self.w_s, self.w_p, self.w_d, self.rows, self.back, self.back_wd,
                      self.flags, self.eta, sel, self.row_weights(loss.back_weight), loss.kind == "l1", out, rows)
        return (torch.from_numpy(out).to(x.dtype).reshape(self.shape),
                torch.from_numpy(rows).reshape(*self.shape, self.k) if residuals else None)

    def residuals(self, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor]) -> Tensor:
        """``(H, W, K)`` residuals ``render - image`` in ``x``'s dtype (:func:`residual_rows`)."""
        _threads()
        full, _ = full_vectors(x, names, fixed)
        out = np.empty((full.shape[0], self.k), dtype=np.float32 if x.dtype == torch.float32 else np.float64)
        residual_rows(full, self.view, self.dirs, self.w_s, self.w_p, self.w_d, self.rows, self.back, self.back_wd,
                      self.flags, self.eta, out)
        return torch.from_numpy(out).reshape(*self.shape, self.k)

    def vjp(self, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], grad: Tensor) -> Tensor:
        """``J^T grad``, ``(H, W, P)`` in ``x``'s dtype, for ``grad (H, W, K)`` (:func:`vector_jacobian`)."""
        _threads()
        full, cols = full_vectors(x, names, fixed)
        npix = full.shape[0]
        out = np.empty((npix, cols.shape[0]))
        g = np.ascontiguousarray(grad.reshape(npix, -1).double().numpy())
        vector_jacobian(full, cols, self.view, self.dirs, self.w_s, self.w_p, self.w_d, self.back, self.back_wd,
                        self.flags, self.eta, g, out)
        return torch.from_numpy(out).to(x.dtype).reshape(*self.shape, -1)

    def rows_and_back(self) -> np.ndarray:
        """``(npix, K)``: the images' LED rows, then the back-lit image's three (made once)."""
        if self._rows_and_back is None:
            self._rows_and_back = np.ascontiguousarray(np.concatenate([self.rows, self.back], 1))
        return self._rows_and_back

    def normal_equations(self, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], r: Tensor,
                         sw: Tensor) -> tuple[Tensor, Tensor]:
        """``(J^T W J (H, W, P, P), J^T W r (H, W, P))`` in float64 at ``x`` from the residuals
        ``r`` and row multipliers ``sw = sqrt(W)``, both ``(H, W, K)``."""
        _threads()
        full, cols = full_vectors(x, names, fixed)
        npix, p = full.shape[0], cols.shape[0]
        jtj = np.empty((npix, p, p))
        jtr = np.empty((npix, p))
        r2 = np.ascontiguousarray(r.reshape(npix, -1).numpy())
        sw2 = np.ascontiguousarray(sw.reshape(npix, -1).to(r.dtype).numpy())
        normal_equations(full, cols, self.view, self.dirs, self.w_s, self.w_p, self.w_d, self.back, self.back_wd,
                         self.flags, self.eta, r2, sw2, jtj, jtr)
        return torch.from_numpy(jtj).reshape(*self.shape, p, p), torch.from_numpy(jtr).reshape(*self.shape, p)
