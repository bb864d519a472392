"""The fit's fused kernel: renders, residuals and analytic Jacobians per pixel in one pass.

The per-pixel Levenberg-Marquardt (:mod:`.lm`) needs, every iteration, the residuals of every
pixel and its weighted normal equations ``J^T W J`` and ``J^T W r``.  The eager reference
renders the whole stack with torch once per parameter channel (forward differences).  This
module computes the same quantities with numba, pixel by pixel and light by light:

* the model is the one of :func:`dualscale.bsdf.evaluate` on fit maps (supplementary Sec. 5:
  Burley diffuse plus retro-reflection, anisotropic GGX with Heitz's Smith term, exact
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

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from dualscale.bsdf import Components
from dualscale.bsdf.derivatives import (CHROMA_EPS, INV_PI, alphas_aniso_d, alphas_iso_d, diffuse_d,
                                        fresnel_weighted_d, ggx_d_aniso_d, ggx_d_iso_d, schlick_weight_d,
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
BLOCK_ROWS = 48  # Jacobian rows gathered per pixel before they are folded into J^T W J (16 lights)
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
def _sample(xp, geo, al, ex, lx_, ly_, lz_, vx_, vy_, vz_, ws, wp, wd, iso, tinted, opaque, normal_mapped,
            want_jac, out, jac):
    """Render of one light at one pixel into ``out`` (3) and, when ``want_jac``, its Jacobian
    over the full vector into ``jac`` (3 x 14); values before the clamp at 2 (the caller clamps).
    ``al`` = the alphas tuple of :func:`_pixel_setup`, ``ex`` = eta."""
    ax, ay, dax_r, dax_an, day_r, day_an = al
    for c in range(3):
        out[c] = 0.0
        if want_jac:
            for i in range(14):
                jac[c, i] = 0.0
    nx, ny, nz = geo[0], geo[1], geo[2]
    if normal_mapped:
        cl = lx_ * nx + ly_ * ny + lz_ * nz
        cv = vx_ * nx + vy_ * ny + vz_ * nz
    else:
        cl, cv = lz_, vz_
    if cl > 0.0 and cv > 0.0 and lz_ > 0.0 and vz_ > 0.0:
        clv = lx_ * vx_ + ly_ * vy_ + lz_ * vz_
        len2 = max(2.0 + 2.0 * clv, 1e-12)
        inv_len = 1.0 / math.sqrt(len2)
        cos_d = 0.5 * len2 * inv_len
        g, dg_cl, dg_cv, dg_r = diffuse_d(cl, cv, clv, xp[3])
        f, df_eta = fresnel_weighted_d(cos_d, ex, ws, wp)
        hz = (cl + cv) * inv_len
        # spec S = D V F and its partials over (cl, cv, lx, ly, vx, vy, ax, ay)
        ds_lx = ds_ly = ds_vx = ds_vy = 0.0
        if iso:
            a = ax
            d, dd_hz, dd_a = ggx_d_iso_d(hz, a)
            a2 = a * a
            a2l, a2v = a2 * (1.0 - cl * cl), a2 * (1.0 - cv * cv)
            vis, dv_zl, dv_a2l, dv_zv, dv_a2v = smith_visibility_d(cl, a2l, cv, a2v)
            ds_cl = f * (dd_hz * inv_len * vis + d * (dv_zl + dv_a2l * (-2.0 * a2 * cl)))
            ds_cv = f * (dd_hz * inv_len * vis + d * (dv_zv + dv_a2v * (-2.0 * a2 * cv)))
            ds_a = f * (dd_a * vis + d * (dv_a2l * 2.0 * a * (1.0 - cl * cl) + dv_a2v * 2.0 * a * (1.0 - cv * cv)))
            ds_ax, ds_ay = ds_a, 0.0
        else:
            tx, ty, tz, bx, by, bz = geo[9], geo[10], geo[11], geo[12], geo[13], geo[14]
            llx, lly = lx_ * tx + ly_ * ty + lz_ * tz, lx_ * bx + ly_ * by + lz_ * bz
            vvx, vvy = vx_ * tx + vy_ * ty + vz_ * tz, vx_ * bx + vy_ * by + vz_ * bz
            d, dd_hx, dd_hy, dd_hz, dd_ax, dd_ay = ggx_d_aniso_d((llx + vvx) * inv_len, (lly + vvy) * inv_len, hz,
                                                                 ax, ay)
            a2l = (ax * llx) ** 2 + (ay * lly) ** 2
            a2v = (ax * vvx) ** 2 + (ay * vvy) ** 2
            vis, dv_zl, dv_a2l, dv_zv, dv_a2v = smith_visibility_d(cl, a2l, cv, a2v)
            ds_cl = f * (dd_hz * inv_len * vis + d * dv_zl)
            ds_cv = f * (dd_hz * inv_len * vis + d * dv_zv)
            ds_lx = f * (dd_hx * inv_len * vis + d * dv_a2l * 2.0 * ax * ax * llx)
            ds_ly = f * (dd_hy * inv_len * vis + d * dv_a2l * 2.0 * ay * ay * lly)
            ds_vx = f * (dd_hx * inv_len * vis + d * dv_a2v * 2.0 * ax * ax * vvx)
            ds_vy = f * (dd_hy * inv_len * vis + d * dv_a2v * 2.0 * ay * ay * vvy)
            ds_ax = f * (dd_ax * vis + d * (dv_a2l * 2.0 * ax * llx * llx + dv_a2v * 2.0 * ax * vvx * vvx))
            ds_ay = f * (dd_ay * vis + d * (dv_a2l * 2.0 * ay * lly * lly + dv_a2v * 2.0 * ay * vvy * vvy))
        s = d * vis * f
        # chromaticity of the tint
        m, im = xp[0], 0
        for c in range(1, 3):
            if xp[c] > m:
                m, im = xp[c], c
        rho = xp[9] if tinted else 0.0
        if want_jac:  # what the three channels share: the geometric derivatives of cl, cv, G and S
            ds_r = ds_ax * dax_r + ds_ay * day_r
            ds_an = ds_ax * dax_an + ds_ay * day_an
            ds_eta = d * vis * df_eta * 2.0
            dcl0 = dcv0 = ds0 = dcl1 = dcv1 = ds1 = ds2 = 0.0
            if normal_mapped:
                dcl0 = lx_ * geo[3] + ly_ * geo[4] + lz_ * geo[5]
                dcv0 = vx_ * geo[3] + vy_ * geo[4] + vz_ * geo[5]
                dcl1 = lx_ * geo[6] + ly_ * geo[7] + lz_ * geo[8]
                dcv1 = vx_ * geo[6] + vy_ * geo[7] + vz_ * geo[8]
                ds0 = ds_cl * dcl0 + ds_cv * dcv0
                ds1 = ds_cl * dcl1 + ds_cv * dcv1
            if not iso:
                for k in range(3):  # sx, sy, tau through the tangent frame
                    dtx, dty, dtz = geo[15 + 3 * k], geo[16 + 3 * k], geo[17 + 3 * k]
                    dbx, dby, dbz = geo[33 + 3 * k], geo[34 + 3 * k], geo[35 + 3 * k]
                    e = (ds_lx * (lx_ * dtx + ly_ * dty + lz_ * dtz) + ds_ly * (lx_ * dbx + ly_ * dby + lz_ * dbz)
                         + ds_vx * (vx_ * dtx + vy_ * dty + vz_ * dtz) + ds_vy * (vx_ * dbx + vy_ * dby + vz_ * dbz))
                    if k == 0:
                        ds0 += e
                    elif k == 1:
                        ds1 += e
                    else:
                        ds2 = e
            dg0 = dg_cl * dcl0 + dg_cv * dcv0
            dg1 = dg_cl * dcl1 + dg_cv * dcv1
        for c in range(3):
            chr_c = xp[c] / m if m > CHROMA_EPS else 1.0
            tint = chr_c * rho + 1.0 - rho if tinted else 1.0
            q = wd * xp[c] * g + s * tint
            out[c] = cl * q
            if not want_jac:
                continue
            # albedo: diffuse in its own channel; through chr(b) when tinted
            jac[c, c] = cl * wd * g
            if tinted and m > CHROMA_EPS:
                for j in range(3):
                    dchr = (1.0 / m if j == c else 0.0) - (xp[c] / (m * m) if j == im else 0.0)
                    jac[c, j] += cl * s * rho * dchr
                jac[c, 9] = cl * s * (chr_c - 1.0)
            wa = wd * xp[c]
            jac[c, 3] = cl * (wa * dg_r + tint * ds_r)
            jac[c, 4] = cl * tint * ds_an
            jac[c, 8] = cl * tint * ds_eta
            jac[c, 6] = dcl0 * q + cl * (wa * dg0 + tint * ds0)
            jac[c, 7] = dcl1 * q + cl * (wa * dg1 + tint * ds1)
            jac[c, 5] = cl * tint * ds2
    if not opaque:  # transmission, then the opacity scales the whole response
        op = xp[13]
        tr = wd * abs(lz_) * INV_PI if lz_ * vz_ < 0.0 else 0.0
        for c in range(3):
            out[c] += xp[10 + c] * tr
            if want_jac:
                jac[c, 10 + c] = tr
                for i in range(13):
                    jac[c, i] *= op
                jac[c, 13] = out[c]
            out[c] *= op
    return 0


@njit(**JIT)
def _pixel_residuals(p, x, view, dirs, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row):
    """Residuals of pixel ``p`` (render clamped at 2 - image) into ``row (K,)``."""
    n = dirs.shape[0]
    iso, tinted, opaque, nmap, imap = flags[0] != 0, flags[1] != 0, flags[2] != 0, flags[3] != 0, flags[4] != 0
    xp = x[p]
    geo = np.empty(51)
    o3 = np.empty(3)
    jac = np.empty((3, 14))
    al6 = _pixel_setup(xp, iso, nmap, imap, eta_const, geo)
    al = (al6[0], al6[1], al6[2], al6[3], al6[4], al6[5])
    for k in range(n):
        _sample(xp, geo, al, al6[6], dirs[k, 0], dirs[k, 1], dirs[k, 2], view[p, 0], view[p, 1], view[p, 2],
                w_s[k], w_p[k], w_d[k], iso, tinted, opaque, nmap, False, o3, jac)
        for c in range(3):
            row[3 * k + c] = min(o3[c], CLAMP) - images[p, 3 * k + c]
    if back.shape[0] == x.shape[0]:
        for c in range(3):
            b = 0.0 if opaque else back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
            row[3 * n + c] = min(b, CLAMP) - back[p, c]


@njit(parallel=True, **JIT)
def residual_rows(x, view, dirs, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, out):
    """``out (npix, K)`` = render clamped at 2 - image, for every pixel (``x (npix, 14)`` full
    vectors, ``view (npix, 3)``, ``dirs (N, 3)``, weights ``(N,)``, ``images (npix, 3N)``,
    ``back (npix, 3)`` or empty; ``flags`` = (iso, tinted, opaque, normal_mapped, ior_mapped))."""
    for p in prange(x.shape[0]):
        row = np.empty(out.shape[1])
        _pixel_residuals(p, x, view, dirs, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row)
        for i in range(out.shape[1]):
            out[p, i] = row[i]


@njit(parallel=True, **JIT)
def weighted_cost(x, view, dirs, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, sel, c_rows, l1, out,
                  rows_out):
    """``out (npix,)`` = ``sum c sel |r|`` (``l1``) or ``sum c sel r^2`` over the residual rows, with
    the row weights ``c_rows (K,)`` and the row selection ``sel (npix, K)`` (1/0; empty = all);
    the residuals go to ``rows_out (npix, K)`` unless it is empty."""
    kk = c_rows.shape[0]
    has_sel, keep_rows = sel.shape[0] == x.shape[0], rows_out.shape[0] == x.shape[0]
    for p in prange(x.shape[0]):
        row = np.empty(kk)
        _pixel_residuals(p, x, view, dirs, w_s, w_p, w_d, images, back, back_wd, flags, eta_const, row)
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
        buf = np.empty(kk)
        for i in range(kk):
            keep[p, i] = valid[p, i] if has_valid else 1.0
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
        acc, m = 0.0, 0
        for i in range(kk):
            w = c_rows[i] * keep[p, i]
            a = abs(r[p, i])
            acc += w * (a if l1 else a * a)
            if l1:
                sw[p, i] = math.sqrt(w / max(a, eps))
            else:
                sw[p, i] = math.sqrt(w)
            if not has_valid or valid[p, i] > 0.0:
                buf[m] = a
                m += 1
        cost[p] = acc
        med = eps
        if m > 0:
            med = max(np.partition(buf[:m], (m - 1) // 2)[(m - 1) // 2], eps)
        scale[p] = med / math.log(2.0) if l1 else (1.4826 * med) ** 2


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


@njit(parallel=True, **JIT)
def normal_equations(x, cols, view, dirs, w_s, w_p, w_d, back, back_wd, flags, eta_const, r, sw, jtj, jtr):
    """Accumulate ``J^T W J (npix, P, P)`` and ``J^T W r (npix, P)`` (overwritten) from the
    residuals ``r (npix, K)`` and row multipliers ``sw = sqrt(W) (npix, K)``; ``cols (P,)`` are
    the full-vector slots of the free parameters, in their order.  Rows with ``sw == 0`` and
    rows whose render is clamped (> 2) contribute nothing (zero derivative)."""
    npix, n, P = x.shape[0], dirs.shape[0], cols.shape[0]
    iso, tinted, opaque, nmap, imap = flags[0] != 0, flags[1] != 0, flags[2] != 0, flags[3] != 0, flags[4] != 0
    has_back = back.shape[0] == npix
    for p in prange(npix):
        xp = x[p]
        geo = np.empty(51)
        o3 = np.empty(3)
        jac = np.empty((3, 14))
        row = np.empty(P)
        a = np.zeros((P, P))
        g = np.zeros(P)
        blk = np.empty((P, BLOCK_ROWS))  # weighted Jacobian rows, transposed, flushed into a and g
        wrb = np.empty(BLOCK_ROWS)
        q = 0
        al6 = _pixel_setup(xp, iso, nmap, imap, eta_const, geo)
        al = (al6[0], al6[1], al6[2], al6[3], al6[4], al6[5])
        for k in range(n):
            if sw[p, 3 * k] == 0.0 and sw[p, 3 * k + 1] == 0.0 and sw[p, 3 * k + 2] == 0.0:
                continue
            _sample(xp, geo, al, al6[6], dirs[k, 0], dirs[k, 1], dirs[k, 2], view[p, 0], view[p, 1], view[p, 2],
                    w_s[k], w_p[k], w_d[k], iso, tinted, opaque, nmap, True, o3, jac)
            for c in range(3):
                w = sw[p, 3 * k + c]
                if w == 0.0 or o3[c] > 2.0:
                    continue
                for i in range(P):
                    blk[i, q] = jac[c, cols[i]] * w
                wrb[q] = r[p, 3 * k + c] * w
                q += 1
                if q == BLOCK_ROWS:
                    _flush(blk, wrb, q, a, g)
                    q = 0
        _flush(blk, wrb, q, a, g)
        if has_back and not opaque:
            for c in range(3):
                w = sw[p, 3 * n + c]
                b = back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
                if w == 0.0 or b > 2.0:
                    continue
                for i in range(P):
                    s = cols[i]
                    row[i] = (back_wd * xp[13] if s == 10 + c else (back_wd * (xp[10 + c] - 1.0) if s == 13 else 0.0)) * w
                wr = r[p, 3 * n + c] * w
                for i in range(P):
                    g[i] += row[i] * wr
                    for j in range(i, P):
                        a[i, j] += row[i] * row[j]
        for i in range(P):
            jtr[p, i] = g[i]
            for j in range(i, P):
                jtj[p, i, j] = a[i, j]
                jtj[p, j, i] = a[i, j]


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
    """Kernel flags ``(iso, tinted, opaque, normal_mapped, ior_mapped)``."""
    return np.array([comps.isotropic, comps.tinted, comps.opaque, comps.normal_mapped, comps.ior_mapped],
                    dtype=np.int64)


class Problem:
    """One pixel block of a fit step, laid out for the kernels: lights, weights, per-pixel view,
    image rows ``(npix, 3N)`` and back-lit rows (built once per block and reused)."""

    def __init__(self, obs, images: Tensor, back: Tensor | None, comps: Components) -> None:
        h, w = obs.shape
        self.shape = (h, w)
        self.comps = comps
        self.flags = flags_of(comps)
        self.eta = float(comps.ior)
        self.dirs = np.ascontiguousarray(obs.dirs.double().numpy())
        self.w_s, self.w_p, self.w_d = (np.ascontiguousarray(t.double().numpy()) for t in (obs.w_s, obs.w_p, obs.w_d))
        view = obs.view.double()
        self.view = np.ascontiguousarray((view.expand(h, w, 3) if view.ndim == 1 else view).reshape(-1, 3).numpy())
        self.rows = np.ascontiguousarray(images.permute(1, 2, 0, 3).reshape(h * w, -1).numpy())
        self.back = (np.ascontiguousarray(back.reshape(h * w, 3).numpy()) if back is not None
                     else np.empty((0, 3), dtype=self.rows.dtype))
        self.back_wd = float(obs.back_wd)
        self.k = self.rows.shape[1] + (3 if back is not None else 0)
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

    def row_weights(self, loss) -> np.ndarray:
        """``c`` per residual row: 1 per LED row, ``loss.back_weight`` per back-lit row."""
        c = np.ones(self.k)
        c[self.rows.shape[1]:] = loss.back_weight
        return c

    def irls(self, r: Tensor, loss) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(keep, sqrt(W), data cost, likelihood scale)`` of :class:`.lm.Loss` at the residuals
        ``r (H, W, K)``: ``(H, W, K)``, ``(H, W, K)``, ``(H, W)``, ``(H, W)`` (:func:`irls_rows`)."""
        _threads()
        npix = r.shape[0] * r.shape[1]
        r2 = np.ascontiguousarray(r.reshape(npix, -1).numpy())
        keep, sw = np.empty_like(r2), np.empty_like(r2)
        cost, scale = np.empty(npix, dtype=r2.dtype), np.empty(npix, dtype=r2.dtype)
        irls_rows(r2, self.row_weights(loss), self.valid, self.lum, self.partner_ptr, self.partner_idx, self.near,
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
                      self.flags, self.eta, sel, self.row_weights(loss), loss.kind == "l1", out, rows)
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

    def jacobian(self, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor]) -> Tensor:
        """The dense Jacobian ``(H, W, K, P)`` (tests and diagnostics only: it is what
        :meth:`normal_equations` never stores), column by column through unit weights."""
        r = self.residuals(x, names, fixed).double()
        p = x.shape[-1]
        h, w = self.shape
        out = torch.zeros(h, w, self.k, p, dtype=torch.float64)
        for k in range(self.k):  # J^T W J with W = e_k e_k^T is J_k^T J_k; J^T W r with r = 1 gives J_k
            sw = torch.zeros(h, w, self.k, dtype=torch.float64)
            sw[..., k] = 1.0
            _, jtr = self.normal_equations(x, names, fixed, torch.ones_like(r), sw)
            out[..., k, :] = jtr
        return out
