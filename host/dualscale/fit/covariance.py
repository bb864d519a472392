"""The numba kernels of the per-pixel covariance (:mod:`.uncertainty`, issue 26): one pass
per pixel that fits the noise model and builds, from the fused kernel's Jacobian
(:mod:`.fused`), the LM's own normal equations and the covariance's matrices
(:func:`covariance_rows`), and the small per-pixel solves (:func:`covariance_solve`).  The
formulas are :mod:`.uncertainty`'s module doc; this module holds only their loops."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .fused import CLAMP, JIT, LIGHT_BLOCK, _back_derivative, _basis_lights, _block_weights, _flush, _pixel_start

#: the per-row loops of the covariance (reductions over one pixel's rows, which LLVM vectorises
#: only when it may reassociate them; the results agree with the ordered sums to ~1e-8)
FAST = dict(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})


@njit(**FAST)
def _gram(blk, q, a):  # pragma: no cover - numba
    """``a += B B^T`` (upper triangle) over the first ``q`` columns of ``B = blk``, two rows by
    two columns of ``a`` at a time (half the loads of :func:`.fused._flush`'s dot products; each
    entry's sum is the same)."""
    n = blk.shape[0]
    for i in range(0, n - 1, 2):
        b0, b1 = blk[i], blk[i + 1]
        s00 = s01 = s11 = 0.0
        for t in range(q):
            s00 += b0[t] * b0[t]
            s01 += b0[t] * b1[t]
            s11 += b1[t] * b1[t]
        a[i, i] += s00
        a[i, i + 1] += s01
        a[i + 1, i + 1] += s11
        for j in range(i + 2, n - 1, 2):
            c0, c1 = blk[j], blk[j + 1]
            s00 = s01 = s10 = s11 = 0.0
            for t in range(q):
                s00 += b0[t] * c0[t]
                s01 += b0[t] * c1[t]
                s10 += b1[t] * c0[t]
                s11 += b1[t] * c1[t]
            a[i, j] += s00
            a[i, j + 1] += s01
            a[i + 1, j] += s10
            a[i + 1, j + 1] += s11
        if n % 2 == 1:
            c0 = blk[n - 1]
            s00 = s10 = 0.0
            for t in range(q):
                s00 += b0[t] * c0[t]
                s10 += b1[t] * c0[t]
            a[i, n - 1] += s00
            a[i + 1, n - 1] += s10
    if n % 2 == 1:
        c0 = blk[n - 1]
        s00 = 0.0
        for t in range(q):
            s00 += c0[t] * c0[t]
        a[n - 1, n - 1] += s00


@njit(**FAST)
def _noise_pixel(r, y, u, keep, iterations, clip2, trunc):  # pragma: no cover - numba
    """``(a, b)`` of one pixel's ``var = a u^2 + b u mu`` (:func:`row_noise`) from its rows:
    residuals ``r``, images ``y``, kept ``keep > 0`` (``(K,)`` each) and signal scales ``u``."""
    k = r.shape[0]
    n, ss, su = 0.0, 0.0, 0.0
    for i in range(k):
        m = 1.0 if keep[i] > 0 else 0.0
        n += m
        ss += m * float(r[i]) ** 2
        su += m * u[i] * u[i]
    a = max(ss / max(su, 1e-300), 1e-30)
    b = 0.0
    tiny = 1e-12 * a
    flat = max(ss / max(n, 1.0), 1e-30)  # the first iteration weighs every row alike
    for it in range(iterations):
        s0 = s1 = s2 = t0 = t1 = 0.0
        for i in range(k):  # branch-free, so that it vectorises
            f0 = u[i] * u[i]
            f1 = u[i] * max(float(y[i]) + float(r[i]), 0.0)
            v = flat if it == 0 else max(a * f0 + b * f1, 1e-30)
            r2 = float(r[i]) ** 2
            w = 1.0 / (v * v) if (keep[i] > 0 and r2 <= clip2 * v) else 0.0
            q = r2 / trunc
            s0 += w * f0 * f0
            s1 += w * f0 * f1
            s2 += w * f1 * f1
            t0 += w * f0 * q
            t1 += w * f1 * q
        if s0 <= 0.0:
            break
        det = s0 * s2 - s1 * s1
        if det > 1e-300:
            a_new, b_new = (s2 * t0 - s1 * t1) / det, (s0 * t1 - s1 * t0) / det
        else:
            a_new, b_new = t0 / s0, 0.0
        if b_new < 0.0:  # no shot term: a alone
            a_new, b_new = t0 / s0, 0.0
        if a_new <= tiny:  # no read term: b alone
            a_new, b_new = tiny, max(t1 / max(s2, 1e-300), 0.0)
        a, b = a_new, b_new
    return a, b


@njit(**FAST)
def _row_multipliers(r, y, keep, c, u, a, b, l1, out):  # pragma: no cover - numba
    """One pixel's row multipliers into ``out (3, 1, K)``: ``A``'s ``sqrt(c) keep``, ``N``'s
    (``sqrt(c keep / s)`` for ``l1``, ``c sqrt(keep) s`` for ``l2``, ``s = sqrt(a u^2 + b u
    mu)``, ``mu = max(y + r, 0)``) and the back-lit rows' own ``keep``."""
    for i in range(r.shape[0]):
        kp = max(float(keep[i]), 0.0)
        sd = np.sqrt(max(a * u[i] * u[i] + b * u[i] * max(float(y[i]) + float(r[i]), 0.0), 1e-30))
        out[0, 0, i] = np.sqrt(c[i]) * kp
        out[1, 0, i] = np.sqrt(c[i] * kp / sd) if l1 else c[i] * np.sqrt(kp) * sd
        out[2, 0, i] = kp


@njit(parallel=True, **JIT)
def noise_rows(r, y, u, keep, iterations, clip2, trunc, a_out, b_out):  # pragma: no cover - numba
    """:func:`_noise_pixel` of every pixel: rows ``(npix, K)``."""
    for p in prange(r.shape[0]):
        a_out[p], b_out[p] = _noise_pixel(r[p], y[p], u, keep[p], iterations, clip2, trunc)


@njit(parallel=True, **JIT)
def covariance_rows(x, cols, view, L, w_s, w_p, w_d, back, back_wd, flags, eta_const, r, sw_fit, keep, images,
                     c_rows, u, l1, iterations, clip2, trunc, jtjs, jtr, noise):  # pragma: no cover - numba
    """One pass per pixel (rows ``(npix, K)``: residuals ``r``, the optimiser's row multipliers
    ``sw_fit``, kept ``keep``, the images ``images`` (the LED rows, then the back-lit ones; the
    render is ``images + r``), any one float dtype; ``c_rows``, ``u`` ``(K,)`` float64): the
    noise model's ``a``, ``b`` (:func:`_noise_pixel`, into ``noise (npix, 2)``), then from one
    evaluation of the Jacobian (as :func:`.fused.normal_equations`, ``LIGHT_BLOCK`` lights at a
    time) ``jtjs (4, npix, P, P)``: ``J^T W J`` and ``jtr = J^T W r`` with ``sw_fit`` (bit for
    bit the LM's own), ``A = J^T C K J``, the noise-weighted ``N`` (row multipliers ``sqrt(c
    keep / s)`` for ``l1``, ``c sqrt(keep) s`` for ``l2``, ``s = sqrt(a u^2 + b u mu)``) and
    the back-lit rows' own ``J_b^T K J_b``.  The weights are made per pixel: no ``(npix, K)``
    array is written."""
    npix, n, P = x.shape[0], L.shape[1], cols.shape[0]
    iso, opaque, lam = flags[0] != 0, flags[2] != 0, flags[5] != 0
    has_back = back.shape[0] == npix
    kk = r.shape[1]
    for p in prange(npix):
        a_n, b_n = _noise_pixel(r[p], images[p], u, keep[p], iterations, clip2, trunc)
        noise[p, 0], noise[p, 1] = a_n, b_n
        wrow = np.empty((3, 1, kk))  # A's and N's row multipliers, then the back-lit rows' own
        _row_multipliers(r[p], images[p], keep[p], c_rows, u, a_n, b_n, l1, wrow)
        geo, kc, al, xp, op, rows, coef = _pixel_start(x, p, view, flags, eta_const, cols)
        bas, wv = np.empty((12, LIGHT_BLOCK)), np.empty((3, LIGHT_BLOCK))
        jraw, jw, wr = np.empty((P, 3 * LIGHT_BLOCK)), np.empty((P, 3 * LIGHT_BLOCK)), np.empty(3 * LIGHT_BLOCK)
        row = np.empty(P)
        acc, g = np.zeros((4, P, P)), np.zeros(P)
        for k0 in range(0, n, LIGHT_BLOCK):
            k1 = min(n, k0 + LIGHT_BLOCK)
            b = k1 - k0
            _basis_lights(xp, geo, al, kc, L, view[p, 2], w_s, w_p, w_d, iso, opaque, lam, k0, k1, bas)
            for i in range(P):
                for c in range(3):
                    r0, r1, r2 = rows[i, c, 0], rows[i, c, 1], rows[i, c, 2]
                    w0, w1, w2 = coef[i, c, 0], coef[i, c, 1], coef[i, c, 2]
                    for q in range(b):
                        jraw[i, c * b + q] = w0 * bas[r0, q] + w1 * bas[r1, q] + w2 * bas[r2, q]
            for e in range(3):
                if e == 0:
                    _block_weights(xp, kc, bas, opaque, op, sw_fit, p, k0, b, wv)
                else:
                    _block_weights(xp, kc, bas, opaque, op, wrow[e - 1], 0, k0, b, wv)
                if e == 0:
                    for c in range(3):
                        for q in range(b):
                            wr[c * b + q] = r[p, 3 * (k0 + q) + c] * wv[c, q]
                for i in range(P):  # contiguous rows, which vectorise
                    for c in range(3):
                        for q in range(b):
                            jw[i, c * b + q] = jraw[i, c * b + q] * wv[c, q]
                if e == 0:
                    _flush(jw, wr, 3 * b, acc[0], g)
                else:
                    _gram(jw, 3 * b, acc[e])
        if has_back and not opaque:
            for c in range(3):
                bk = back_wd * (xp[10 + c] * xp[13] + 1.0 - xp[13])
                if bk > CLAMP:
                    continue
                for e in range(4):
                    w = sw_fit[p, 3 * n + c] if e == 0 else wrow[e - 1, 0, 3 * n + c]
                    if w == 0.0:
                        continue
                    for i in range(P):
                        row[i] = _back_derivative(xp, back_wd, cols[i], c) * w
                    # in the rows' dtype, as normal_equations forms it (the LM's bits)
                    wrb = r[p, 3 * n + c] * sw_fit[p, 3 * n + c]
                    for i in range(P):
                        if e == 0:
                            g[i] += row[i] * wrb
                        for j in range(i, P):
                            acc[e, i, j] += row[i] * row[j]
        for i in range(P):
            jtr[p, i] = g[i]
            for e in range(4):
                for j in range(i, P):
                    jtjs[e, p, i, j] = acc[e, i, j]
                    jtjs[e, p, j, i] = acc[e, i, j]


@njit(**JIT)
def _lu_solve(a, b, n, m):  # pragma: no cover - numba
    """Solve ``a[:n, :n] X = b[:n, :m]`` in place (``b`` becomes ``X``, ``a`` its LU) by Gaussian
    elimination with partial pivoting; False when a pivot is zero or not finite (singular)."""
    for k in range(n):
        piv, big = k, abs(a[k, k])
        for i in range(k + 1, n):
            if abs(a[i, k]) > big:
                piv, big = i, abs(a[i, k])
        if not (big > 0.0) or not np.isfinite(big):
            return False
        if piv != k:
            for j in range(n):
                a[k, j], a[piv, j] = a[piv, j], a[k, j]
            for j in range(m):
                b[k, j], b[piv, j] = b[piv, j], b[k, j]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            if f != 0.0:
                for j in range(k + 1, n):
                    a[i, j] -= f * a[k, j]
                for j in range(m):
                    b[i, j] -= f * b[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(m):
            s = b[k, j]
            for t in range(k + 1, n):
                s -= a[k, t] * b[t, j]
            b[k, j] = s / a[k, k]
    return True


@njit(**JIT)
def _positive_definite(a, n, shift, work):  # pragma: no cover - numba
    """Whether ``a[:n, :n] - shift I`` is positive definite (a Cholesky factorisation in ``work``)."""
    for j in range(n):
        s = a[j, j] - shift
        for t in range(j):
            s -= work[j, t] * work[j, t]
        if not (s > 0.0):
            return False
        d = np.sqrt(s)
        work[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for t in range(j):
                s -= work[i, t] * work[j, t]
            work[i, j] = s / d
    return True


@njit(**JIT)
def _mask(m, det, out):  # pragma: no cover - numba
    """``out``: ``m`` on the determined block, 1 on the other diagonal entries, 0 elsewhere."""
    p = m.shape[0]
    for i in range(p):
        for j in range(p):
            out[i, j] = m[i, j] if (det[i] and det[j]) else (1.0 if i == j else 0.0)


@njit(parallel=True, **JIT)
def covariance_solve(a, b, n, h_fit, rhs, ph, prior_info, det, l1, eig_tol, cov, step):  # pragma: no cover
    """Per pixel (``(npix, P, P)`` ``a``, ``b``, ``n``, ``h_fit``; ``(npix, P)`` ``rhs = -(J^T W
    r + prior gradient)``, ``ph`` the prior's curvature, ``prior_info`` its ``1 / sd^2``, ``det``
    the candidates, updated in place): ``step`` = the undamped Gauss-Newton step (0 where the
    solve fails), the unconstrained directions set aside one parameter at a time (unit-diagonal
    ``A``'s smallest eigenvalue below ``eig_tol``, the parameter with the largest share of its
    eigenvector dropped), then ``cov`` = the inverse of the information ``(2 / pi) N B^-1 N``
    (``l1``) or ``A N^-1 A``, plus the prior's, over the determined block; a pixel whose solves
    fail, or that gives a non-positive variance, has nothing determined."""
    npix, p = a.shape[0], a.shape[1]
    for q in prange(npix):
        m1, m2, m3, work = np.empty((p, p)), np.empty((p, p)), np.empty((p, p)), np.empty((p, p))
        v = np.empty((p, 1))
        for i in range(p):
            for j in range(p):
                m1[i, j] = h_fit[q, i, j]
            m1[i, i] += ph[q, i] + 1e-12 * h_fit[q, i, i]
            v[i, 0] = rhs[q, i]
        ok = _lu_solve(m1, v, p, 1)
        for i in range(p):
            step[q, i] = v[i, 0] if (ok and np.isfinite(v[i, 0])) else 0.0
        d = det[q]
        for _ in range(p):  # set aside unconstrained directions one parameter at a time
            anyd = False
            for i in range(p):
                anyd = anyd or d[i]
            if not anyd:
                break
            _mask(a[q], d, m1)
            for i in range(p):
                for j in range(p):
                    m2[i, j] = m1[i, j] / np.sqrt(max(m1[i, i], 1e-300) * max(m1[j, j], 1e-300))
            if _positive_definite(m2, p, eig_tol, work):  # smallest eigenvalue above eig_tol
                break
            ev, vec = np.linalg.eigh(m2)
            if ev[0] >= eig_tol:
                break
            best, share = -1, -1.0
            for i in range(p):
                if d[i] and abs(vec[i, 0]) > share:
                    best, share = i, abs(vec[i, 0])
            d[best] = False
        _mask(a[q], d, m1)
        if l1:  # (2/pi) N B^-1 N
            _mask(b[q], d, m2)
            _mask(n[q], d, m3)
            ok = _lu_solve(m2, m3, p, p)  # m3 = B^-1 N
            _mask(n[q], d, m2)
            f = 2.0 / math.pi
        else:  # A N^-1 A
            _mask(n[q], d, m2)
            for i in range(p):
                for j in range(p):
                    m3[i, j] = m1[i, j]
            ok = _lu_solve(m2, m3, p, p)  # m3 = N^-1 A
            f = 1.0
            for i in range(p):
                for j in range(p):
                    m2[i, j] = m1[i, j]
        for i in range(p):  # info = f m2 m3 (+ prior), into work; masked again below
            for j in range(p):
                s = 0.0
                for t in range(p):
                    s += m2[i, t] * m3[t, j]
                work[i, j] = f * s
            if d[i]:
                work[i, i] += prior_info[q, i]
        _mask(work, d, m1)
        for i in range(p):
            for j in range(p):
                m2[i, j] = 1.0 if i == j else 0.0
        ok = ok and _lu_solve(m1, m2, p, p)
        for i in range(p):
            for j in range(p):
                cov[q, i, j] = m2[i, j]
                if not np.isfinite(m2[i, j]):
                    ok = False
            if d[i] and not (m2[i, i] > 0.0):
                ok = False
        if not ok:
            for i in range(p):
                d[i] = False
