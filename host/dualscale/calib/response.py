"""Radiometric self-calibration of photographs: the camera response and the lights' relative
intensities, from the photographs themselves (``dualscale import --transfer auto``).

Model.  Each pixel-channel ``s`` of a photometric capture under distant lights ``l_k`` (known
unit directions, e.g. from a chrome sphere) records the code value

    c_sk = f( e_k max(0, b_s . l_k) )

with ``f`` the camera response (:mod:`dualscale.formats.response`, ``g = f^-1`` its inverse),
``e_k`` the light's relative intensity (geometric mean 1 over the lights) and ``b_s`` the
pixel-channel's albedo-scaled normal (Lambert).  Where the response is wrong, no ``b_s`` makes
the linearised values ``g(c_sk)`` linear in ``l_k`` across the lights: the photometric data are
inconsistent.  This is the consistency that radiometric calibration by rank minimisation (Lee,
Matsushita et al., TPAMI 2013: linearised Lambertian observations have rank 3) and
self-calibrating photometric stereo (Shi et al., CVPR 2010) exploit; with the light directions
known it is the stronger per-pixel constraint used here.  The intensities ``e_k`` are estimated
jointly, as semi-calibrated photometric stereo does (Cho et al., CVPR 2016 / TPAMI 2018).  With
a matte reference sphere (:func:`estimate_response` with ``normals``) the normals are known and
only ``|b_s|`` is free.

Estimation (:func:`estimate_response`):

* samples: pixel-channels inside the mask, code values in ``[lo, hi]`` (:func:`code_window`:
  away from the black level, where 8-bit codes are few and cast/attached shadows live, and
  from clipping), at least :data:`MIN_LIGHTS` lights per pixel-channel;
* residuals in **code values**, where the noise is (8-bit quantisation, sensor noise after the
  camera's curve), so responses are compared on the scale the data were measured on;
* ``e_k`` and ``b_s`` are solved in closed form (an eigenvector, then weighted least squares,
  in linear values with the weights ``1 / g'(c)^2`` that map code errors to linear ones), so the outer
  least squares (``scipy.optimize.least_squares``) runs only over the response's parameters;
* robust to shadows, highlights and non-Lambertian pixels by iteratively reweighted least
  squares (Cauchy weights at 2.5 robust standard deviations of the code residual);
* the family (:data:`~dualscale.formats.response.FAMILIES`) is chosen by the consistency: the
  mean Cauchy loss of the code residuals at one common scale (:func:`choose_family`: the
  simplest within :data:`FAMILY_MARGIN` of the best; a curve must earn :data:`CURVE_MARGIN`);
* uncertainty by a bootstrap over pixels (:data:`BOOTSTRAP` resamples): the power's standard
  deviation, the inverse curve's largest standard deviation in fractions of full scale, the
  intensities' standard deviations.

A stated transfer is checked with :func:`check_stated`: it is refused as contradicted when its
consistency is clearly worse than the estimate's *and* its curve is far from the estimate's.

Errors: :class:`~dualscale.errors.CalibrationError` when too few pixel-channels are lit enough
to estimate anything (:data:`MIN_SERIES`), naming what was found.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from dualscale.errors import CalibrationError
from dualscale.formats.response import CURVE_DEGREE, Response

#: lights a pixel-channel needs inside the code window to take part (3 unknowns + 3 checks)
MIN_LIGHTS = 6
#: pixel-channels needed for an estimate
MIN_SERIES = 150
#: the simplest of linear / srgb / gamma whose consistency loss is within this fraction of the
#: best of them is chosen
FAMILY_MARGIN = 0.05
#: the monotone curve (7 parameters) must lower the best simple family's loss by this fraction:
#: on real objects the Lambertian consistency is limited by their own non-Lambertian reflection
#: (robust residuals of 1.5-2.3 codes on the psm figurines, 0.5 on synthetic Lambertian data), part
#: of which a flexible curve absorbs (it gained 1-5 % there), while a real S-shaped response
#: gains 80-95 % (synthetic film curve; docs/RADIOMETRY.md)
CURVE_MARGIN = 0.15
#: bootstrap resamples for the uncertainty
BOOTSTRAP = 8
#: the curve family's Legendre coefficients carry a Gaussian prior of this standard deviation
#: (a ridge: a curve must be told by the data, not by the misfit of non-Lambertian pixels)
CURVE_PRIOR = 20.0
#: IRLS rounds
ROUNDS = 4
#: Cauchy weight scale, in robust standard deviations of the code residual
CAUCHY_K = 2.5


def code_window(bits: int) -> tuple[float, float]:
    """``(lo, hi)``: the normalised code values used, for ``bits``-bit images: ``lo`` = the
    larger of 3 % of full scale and 3 codes, ``hi`` = 1 less the larger of 2 % and 3 codes."""
    q = 1.0 / (2 ** min(bits, 16) - 1)
    return max(0.03, 3 * q), 1.0 - max(0.02, 3 * q)


@dataclass
class ResponseEstimate:
    """What :func:`estimate_response` found: the chosen ``response`` (``source`` ``"auto"`` or
    ``"target"``; its ``uncertainty`` and ``evidence`` filled), the relative ``intensities``
    ``(K,)`` (geometric mean 1; the given ones when they were given) and their standard
    deviations ``intensities_std``, ``fits`` per family tried (``{family: {params, score,
    rms_codes}}``), the noise ``scale`` (code values) the scores share, and counts and time."""

    response: Response
    intensities: np.ndarray
    intensities_std: np.ndarray
    intensities_source: str
    fits: dict[str, dict[str, Any]]
    scale: float
    series: int
    samples: int
    seconds: float
    code_range: tuple[float, float]
    notes: list[str] = field(default_factory=list)
    #: the pixel-channel sample the estimate was made on (reused by :func:`check_stated`)
    sample: _Data | None = field(default=None, repr=False, compare=False)

    def score(self, family: str) -> float:
        return float(self.fits[family]["score"])

    def record(self) -> dict[str, Any]:
        """The JSON block written into a dataset (``extra.import.radiometry``) or a light file."""
        return {"response": self.response.to_json(),
                "intensities": {"values": self.intensities.round(6).tolist(),
                                "std": self.intensities_std.round(6).tolist(),
                                "source": self.intensities_source, "normalisation": "geometric mean 1"},
                "seconds": round(self.seconds, 3), "notes": self.notes}


# -- the consistency of one response ------------------------------------------------------------

@dataclass
class _Data:
    c: np.ndarray          # (S, K) code values
    m: np.ndarray          # (S, K) bool, inside the code window and valid
    dirs: np.ndarray       # (K, 3)
    normals: np.ndarray | None  # (S, 3) known normals (matte target) or None
    q: float               # one code value
    scale: float = 0.0     # the current robust code-residual scale (the curve prior's weight), 0 = q


def _intensities(lin: np.ndarray, w: np.ndarray, d: _Data) -> np.ndarray:
    """The relative intensities ``e`` ``(K,)`` (geometric mean 1) that make the linearised
    values most consistent, in closed form.  With ``u_k = 1 / e_k``, ``u_k I_sk = b_s . l_k`` is
    linear in ``(u, b)``; eliminating each ``b_s`` by weighted least squares leaves
    ``r_s = (1 - P_s) D_s u`` (``D_s = diag(I_s)``, ``P_s`` the weighted projection on the
    columns of ``L``, or on the known cosines), so ``u`` is the eigenvector of the smallest
    eigenvalue of ``Q = sum_s (D_s (1 - P_s))^T W_s (1 - P_s) D_s`` (semi-calibrated photometric
    stereo, Cho et al. 2016, here weighted).  A light no sample sees keeps ``e = 1``."""
    S, K = lin.shape
    eye = np.eye(K)
    if d.normals is None:
        L = d.dirs
        A = np.einsum("sk,ki,kj->sij", w, L, L)
        Ainv = np.linalg.inv(A + (1e-9 * np.trace(A, axis1=1, axis2=2)[:, None, None] + 1e-30) * np.eye(3))
        P = (L @ Ainv @ L.T) * w[:, None, :]                         # (S, K, K): L A^-1 L^T W
    else:
        cos = np.clip(d.normals @ d.dirs.T, 0.0, None)
        den = np.maximum((w * cos * cos).sum(1), 1e-30)
        P = cos[:, :, None] * (cos * w)[:, None, :] / den[:, None, None]
    M = (eye[None] - P) * lin[:, None, :]                            # (1 - P_s) D_s
    Mw = M * w[:, :, None]
    Q = np.einsum("sak,sal->kl", Mw, M, optimize=True)
    seen = w.sum(0) > 0
    if seen.sum() < 2:
        return np.ones(K)
    Qs = Q[np.ix_(seen, seen)]
    vals, vecs = np.linalg.eigh(Qs / max(np.trace(Qs), 1e-300))
    u = vecs[:, 0] * np.sign(vecs[:, 0].sum())
    e = np.ones(K)
    e[seen] = 1.0 / np.clip(u, 1e-6 * np.abs(u).max(), None)
    return e / math.exp(float(np.mean(np.log(e[seen]))))


def _solve(resp: Response, d: _Data, W: np.ndarray, e0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(residual (S, K) in code values, b (S, 3), e (K,))`` for ``resp`` with the sample
    weights ``W`` (0 outside the window); ``e`` estimated (:func:`_intensities`) when ``e0``
    is None, else fixed."""
    lin = resp.inverse(d.c)
    w = W / resp.slope(d.c) ** 2  # code error -> linear error
    L = d.dirs
    e = _intensities(lin, w, d) if e0 is None else e0
    if d.normals is None:
        we = w * e * e
        A = np.einsum("sk,ki,kj->sij", we, L, L)
        A = A + (1e-9 * np.trace(A, axis1=1, axis2=2)[:, None, None] + 1e-30) * np.eye(3)
        r = np.einsum("sk,sk,ki->si", w * e, lin, L)
        b = np.linalg.solve(A, r[..., None])[..., 0]
    else:
        cos = np.clip(d.normals @ L.T, 0.0, None)
        rho = (w * e * cos * lin).sum(1) / np.maximum((w * e * e * cos * cos).sum(1), 1e-30)
        b = rho[:, None] * d.normals
    pred = resp.forward(np.clip(e * (b @ L.T), 0.0, None))
    return np.where(d.m, d.c - pred, 0.0), b, e


def _robust_scale(r: np.ndarray, m: np.ndarray, q: float) -> float:
    v = np.abs(r[m])
    return max(1.4826 * float(np.median(v)) if v.size else q, 0.5 * q)


def _cauchy_w(r: np.ndarray, m: np.ndarray, s: float) -> np.ndarray:
    return np.where(m, 1.0 / (1.0 + (r / (CAUCHY_K * s)) ** 2), 0.0)


def _make(family: str, x: np.ndarray, source: str) -> Response:
    return Response(family, tuple(x), source)


def _fit_family(family: str, d: _Data, W: np.ndarray, x0: np.ndarray, e_fixed: np.ndarray | None,
                source: str, rounds: int = ROUNDS, max_nfev: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """IRLS over the family's parameters ``x``; returns ``(x, e, W, scale)``."""
    from scipy.optimize import least_squares

    x = np.asarray(x0, np.float64)
    lb = np.array([0.3] + [-4.0] * (x.size - 1))
    ub = np.array([4.5] + [4.0] * (x.size - 1))
    e = e_fixed
    s = d.q
    for _ in range(rounds):
        if x.size:
            sw = np.sqrt(W)

            ridge = math.sqrt(max(float(W.sum()), 1.0)) * max(d.scale, d.q) / CURVE_PRIOR

            def fun(p: np.ndarray) -> np.ndarray:
                r = (sw * _solve(_make(family, p, source), d, W, e_fixed)[0]).ravel()
                return np.concatenate([r, ridge * p[1:]]) if p.size > 1 else r

            x = least_squares(fun, np.clip(x, lb, ub), bounds=(lb, ub), x_scale="jac", diff_step=1e-4,
                              max_nfev=max_nfev).x
        r, _, e = _solve(_make(family, x, source), d, W, e_fixed)
        s = _robust_scale(r, d.m, d.q)
        W = _cauchy_w(r, d.m, s)
        d.scale = s
    return x, e, W, s


def _consistency(r: np.ndarray, m: np.ndarray, s0: float) -> float:
    """Mean Cauchy loss ``log(1 + (r / (k s0))^2)`` of the code residuals at the common scale."""
    return float(np.mean(np.log1p((r[m] / (CAUCHY_K * s0)) ** 2)))


# -- the estimate ---------------------------------------------------------------------------------

def choose_family(scores: dict[str, float]) -> str:
    """The family the consistency ``scores`` (lower is better) choose: the ``curve`` only when
    it beats every other family's best by :data:`CURVE_MARGIN`, else the simplest of
    ``linear``, ``srgb``, ``gamma`` within :data:`FAMILY_MARGIN` of their best."""
    simple = [f for f in ("linear", "srgb", "gamma") if f in scores]
    best = min(scores[f] for f in simple)
    if "curve" in scores and scores["curve"] < best * (1.0 - CURVE_MARGIN):
        return "curve"
    return next(f for f in simple if scores[f] <= best * (1.0 + FAMILY_MARGIN) + 1e-12)


def _series(codes: np.ndarray, valid: np.ndarray | None, bits: int, max_pixels: int, seed: int,
            normals: np.ndarray | None) -> tuple[_Data, int]:
    K, P, C = codes.shape
    lo, hi = code_window(bits)
    ok = (codes >= lo) & (codes <= hi)
    if valid is not None:
        ok &= valid[..., None]
    enough = ok.sum(0) >= MIN_LIGHTS  # (P, C)
    pix = np.flatnonzero(enough.any(1))
    rng = np.random.default_rng(seed)
    if pix.size > max_pixels:
        pix = np.sort(rng.choice(pix, max_pixels, replace=False))
    sel_p, sel_c = np.nonzero(enough[pix])
    pp = pix[sel_p]
    c = codes[:, pp, sel_c].T.astype(np.float64)       # (S, K)
    m = ok[:, pp, sel_c].T
    nrm = None if normals is None else np.asarray(normals, np.float64)[pp]
    return _Data(c, m, None, nrm, 1.0 / (2 ** min(bits, 16) - 1)), int(pix.size)  # type: ignore[arg-type]


def estimate_response(codes: np.ndarray, dirs: np.ndarray, valid: np.ndarray | None = None, *, bits: int = 8,
                      normals: np.ndarray | None = None, intensities: np.ndarray | None = None,
                      families: tuple[str, ...] = ("linear", "srgb", "gamma", "curve"),
                      max_pixels: int = 1000, bootstrap: int = BOOTSTRAP, seed: int = 0) -> ResponseEstimate:
    """Estimate the camera response (and the lights' relative intensities) from photographs.

    ``codes`` ``(K, P, C)``: normalised code values in [0, 1] of ``P`` sample pixels (e.g. the
    mask's) under ``K`` lights, ``C`` channels (the response is shared by the channels, each
    pixel-channel has its own ``b``); ``dirs`` ``(K, 3)`` unit light directions (camera frame,
    towards the light); ``valid`` ``(K, P)`` bool (False: clipped or otherwise unusable);
    ``bits``: the images' bit depth (the code window and the quantum); ``normals`` ``(P, 3)``:
    known unit normals (a matte reference sphere) or None; ``intensities`` ``(K,)``: known
    relative intensities (then only the response is estimated) or None; ``families``: the
    candidates (``gamma`` is always fitted: it starts the curve).  Module doc for the method.

    Raises :class:`CalibrationError` when fewer than :data:`MIN_SERIES` pixel-channels have
    :data:`MIN_LIGHTS` lights inside the code window.
    """
    t0 = time.perf_counter()
    codes = np.asarray(codes)
    dirs = np.asarray(dirs, np.float64)
    if codes.ndim != 3 or codes.shape[0] != dirs.shape[0]:
        raise ValueError(f"codes {codes.shape} must be (K, P, C) with K = {dirs.shape[0]} lights")
    d, npix = _series(codes, valid, bits, max_pixels, seed, normals)
    d.dirs = dirs
    lo, hi = code_window(bits)
    S = d.c.shape[0]
    if dirs.shape[0] < MIN_LIGHTS:
        raise CalibrationError(
            f"{dirs.shape[0]} photograph(s): a camera response is estimated from the shading of at least "
            f"{MIN_LIGHTS} photographs under different lights; state it with --transfer srgb|linear|gamma:G")
    if S < MIN_SERIES:
        raise CalibrationError(
            f"too few lit pixels to estimate a camera response: {S} pixel-channels have {MIN_LIGHTS} or more "
            f"lights with code values in [{lo:.3f}, {hi:.3f}] (need {MIN_SERIES}): the photographs are too dark, "
            f"too bright or too small" + ("" if normals is not None else "; state the response with "
                                          "--transfer srgb|linear|gamma:G, or photograph a matte reference sphere"))
    e_fixed = None if intensities is None else np.asarray(intensities, np.float64) / math.exp(
        float(np.mean(np.log(np.asarray(intensities, np.float64)))))
    src = "auto" if normals is None else "target"
    W0 = d.m.astype(np.float64)
    fits: dict[str, dict[str, Any]] = {}
    # gamma first: a coarse scan of the power, then IRLS
    scan = np.arange(0.6, 3.21, 0.2)
    sc = [_consistency(_solve(Response("gamma", (g,)), d, W0, e_fixed)[0], d.m, 0.02) for g in scan]
    xg, eg, Wg, sg = _fit_family("gamma", d, W0, np.array([scan[int(np.argmin(sc))]]), e_fixed, src)
    results = {"gamma": (xg, eg, Wg, sg)}
    if "curve" in families:
        x0 = np.concatenate([xg, np.zeros(CURVE_DEGREE)])
        results["curve"] = _fit_family("curve", d, Wg, x0, e_fixed, src, rounds=3, max_nfev=80)
    for fam in ("linear", "srgb"):
        if fam in families:
            results[fam] = _fit_family(fam, d, W0, np.zeros(0), e_fixed, src)
    s0 = min(v[3] for v in results.values())
    for fam, (x, e, W, s) in results.items():
        r = _solve(_make(fam, x, src), d, W, e_fixed if e_fixed is not None else e)[0]
        fits[fam] = {"params": [round(float(v), 6) for v in x], "score": _consistency(r, d.m, s0),
                     "rms_codes": float(np.sqrt(np.mean(r[d.m] ** 2)) / d.q), "robust_sd_codes": s / d.q,
                     "inliers": float((W[d.m] > 0.5).mean())}
    chosen = choose_family({f: v["score"] for f, v in fits.items()})
    x, e, W, s = results[chosen]
    signal = float(np.median(d.c[d.m]))
    if s > 0.25 * signal or not np.all(np.isfinite(e)) or float(np.max(e) / np.min(e)) > 50.0:
        raise CalibrationError(
            f"the photographs' shading is not consistent with any camera response under the given light directions "
            f"(robust residual {s / d.q:.1f} codes for a median code of {signal / d.q:.0f}; intensities "
            f"{float(np.min(e)):.3g}..{float(np.max(e)):.3g}): are these one object's photographs under the light "
            "file's lights, in its order? State the response with --transfer srgb|linear|gamma:G to import anyway")
    # bootstrap over pixel-channels
    rng = np.random.default_rng(seed + 1)
    boot_x, boot_e, boot_g = [], [], []
    cgrid = np.linspace(0.0, 1.0, 33)
    for _ in range(bootstrap if x.size or e_fixed is None else 0):
        idx = rng.integers(0, S, S)
        db = _Data(d.c[idx], d.m[idx], dirs, None if d.normals is None else d.normals[idx], d.q, d.scale)
        xb, eb, _, _ = _fit_family(chosen, db, W[idx], x, e_fixed, src, rounds=1, max_nfev=15)
        boot_x.append(xb)
        boot_e.append(eb)
        boot_g.append(_make(chosen, xb, src).inverse(cgrid))
    unc: dict[str, Any] = {"method": f"bootstrap over pixel-channels ({len(boot_x)} resamples)"}
    if boot_x and x.size:
        unc["params_std"] = np.std(boot_x, axis=0).round(6).tolist()
        unc["gamma_std"] = float(np.std([b[0] for b in boot_x]))
        unc["curve_std_max"] = float(np.max(np.std(boot_g, axis=0)))
    e_std = np.std(boot_e, axis=0) if boot_e and e_fixed is None else np.zeros(dirs.shape[0])
    cr = (float(d.c[d.m].min()), float(d.c[d.m].max()))
    evidence = {"criterion": "mean Cauchy loss of the code residuals of a per-pixel Lambertian fit under the "
                             "known light directions, at one common scale (lower = more consistent)",
                "fits": fits, "chosen": chosen, "family_margin": FAMILY_MARGIN, "curve_margin": CURVE_MARGIN,
                "common_scale_codes": s0 / d.q, "pixels": npix, "pixel_channels": S,
                "samples": int(d.m.sum()), "code_window": [round(lo, 4), round(hi, 4)],
                "code_range_used": [round(cr[0], 4), round(cr[1], 4)], "lights": int(dirs.shape[0]),
                "normals": "known (matte sphere)" if d.normals is not None else "unknown (fitted per pixel)",
                "intensities": "given" if e_fixed is not None else "estimated jointly"}
    resp = Response(chosen, tuple(float(v) for v in x), src, unc, evidence)
    notes = []
    if cr[1] < 0.6:
        notes.append(f"the sample's code values reach only {cr[1]:.2f} of full scale: the response above is "
                     "extrapolated by its family")
    return ResponseEstimate(resp, np.asarray(e if e_fixed is None else e_fixed), np.asarray(e_std),
                            "given" if e_fixed is not None else ("target" if normals is not None else "estimated"),
                            fits, s0, S, int(d.m.sum()), time.perf_counter() - t0, cr, notes, d)


# -- checking a stated response -------------------------------------------------------------------

#: a stated response contradicts the data when its consistency loss exceeds the estimate's by
#: this factor *and* its inverse curve is this far (fraction of full scale) from the estimate's.
#: On real objects the loss has a floor set by their non-Lambertian reflection, which compresses
#: the ratios: sRGB on the psm figurines (28 % of full scale from the estimate, 10-24 % worse at
#: predicting held-out photographs) scores 1.21-1.33; a stated gamma 1.2 there 1.02-1.03
CONTRADICTION_LOSS = 1.10
CONTRADICTION_CURVE = 0.03


def curve_distance(a: Response, b: Response, code_range: tuple[float, float] = (0.0, 1.0), *,
                   scale_free: bool = False) -> float:
    """Largest ``|g_a(c) - g_b(c)|`` over codes in ``code_range`` (fractions of full scale).

    ``scale_free``: the smallest such distance over a common scale ``s`` of ``g_a``
    (``max |s g_a - g_b|``, ``s`` in [0.5, 2]).  The photographs fix an inverse response only up
    to that scale: ``s g`` with the albedos (or the exposure) divided by ``s`` explains every
    photograph equally well, so the convention ``g(1) = 1`` places the scale by the family's
    extrapolation from the highest code the sample holds to full scale, not by data.  On an
    S-shaped film curve the last 2 % of codes (above the code window) span 17 % of the linear
    range, and that extrapolation moves the whole curve by 2-3 % (docs/RADIOMETRY.md).  This is
    the distance that what the data determine is judged by."""
    c = np.linspace(code_range[0], code_range[1], 257)
    ga, gb = a.inverse(c), b.inverse(c)
    if not scale_free:
        return float(np.max(np.abs(ga - gb)))
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(lambda s: float(np.max(np.abs(s * ga - gb))), bounds=(0.5, 2.0), method="bounded",
                          options={"xatol": 1e-7})
    return float(min(res.fun, np.max(np.abs(ga - gb))))


def check_stated(est: ResponseEstimate, stated: Response, codes: np.ndarray, dirs: np.ndarray,
                 valid: np.ndarray | None, bits: int) -> tuple[bool, str, dict[str, Any]]:
    """Does the data contradict the ``stated`` response?  ``(contradicted, message, record)``.

    The stated curve's consistency (the same sample and common scale as ``est``; the
    intensities re-estimated for it, or the given ones) against the estimate's: contradicted
    when the loss is :data:`CONTRADICTION_LOSS` times the estimate's or more *and* the two
    inverse curves differ by :data:`CONTRADICTION_CURVE` of full scale or more over the code
    range the sample uses (and by more than 3 bootstrap standard deviations), up to a common
    scale (:func:`curve_distance` ``scale_free``: a stated curve that differs from the estimate
    by a scale alone is contradicted by no photograph)."""
    if est.sample is not None and est.sample.normals is None:  # the estimate's own sample
        d = replace(est.sample)
    else:
        d, _ = _series(np.asarray(codes), valid, bits, 1000, 0, None)
        d.dirs = np.asarray(dirs, np.float64)
    e_fixed = est.intensities if est.intensities_source == "given" else None
    W = d.m.astype(np.float64)
    for _ in range(ROUNDS):  # IRLS with the stated curve fixed (a stated gamma's power is not refitted)
        r, _, e = _solve(stated, d, W, e_fixed)
        d.scale = _robust_scale(r, d.m, d.q)
        W = _cauchy_w(r, d.m, d.scale)
    r = _solve(stated, d, W, e_fixed if e_fixed is not None else e)[0]
    loss = _consistency(r, d.m, est.scale)
    best = est.score(est.response.family)
    dist = curve_distance(stated, est.response, est.code_range, scale_free=True)
    sd = float(est.response.uncertainty.get("curve_std_max", 0.0))
    bad = loss >= CONTRADICTION_LOSS * best and dist >= max(CONTRADICTION_CURVE, 3 * sd)
    rec = {"stated": stated.transfer, "stated_score": loss, "estimate": est.response.transfer,
           "estimate_score": best, "curve_distance": dist, "contradicted": bool(bad)}
    msg = (f"the photographs contradict --transfer {stated.transfer}: its photometric consistency loss is "
           f"{loss:.3f} against {best:.3f} for the estimate, {est.response.describe()}, and the curves differ by "
           f"up to {100 * dist:.1f} % of full scale at their best common scale; use --transfer auto (or --transfer {est.response.transfer}"
           ")")
    return bool(bad), msg, rec


def estimate_intensities(resp: Response, codes: np.ndarray, dirs: np.ndarray, valid: np.ndarray | None,
                         bits: int, normals: np.ndarray | None = None) -> np.ndarray:
    """The lights' relative intensities ``(K,)`` (geometric mean 1) under a *given* response
    (semi-calibrated photometric stereo on the decoded values, the same robust IRLS and
    intensity prior as :func:`estimate_response`); ``codes`` ``(K, P, C)`` as there.  Raises
    :class:`CalibrationError` when too few pixel-channels are lit."""
    d, _ = _series(np.asarray(codes), valid, bits, 1000, 0, normals)
    d.dirs = np.asarray(dirs, np.float64)
    if d.c.shape[0] < MIN_SERIES:
        raise CalibrationError(f"too few lit pixels to estimate the lights' intensities: {d.c.shape[0]} "
                               f"pixel-channels with {MIN_LIGHTS} lights in the code window (need {MIN_SERIES})")
    W = d.m.astype(np.float64)
    for _ in range(ROUNDS):  # IRLS with the response fixed
        r, _, e = _solve(resp, d, W, None)
        d.scale = _robust_scale(r, d.m, d.q)
        W = _cauchy_w(r, d.m, d.scale)
    return np.asarray(e)


# -- a matte reference sphere ---------------------------------------------------------------------

#: the part of the matte sphere's disc used (fraction of the radius): the limb is left out,
#: where the outline's error moves the normals most and the lights graze
MATTE_RADIUS = 0.92


def matte_sphere_normals(mask: np.ndarray, max_rms_px: float = 1.0, source: str = "matte sphere mask"
                         ) -> tuple[np.ndarray, np.ndarray, Any]:
    """``(inside (H, W) bool, normals (H, W, 3), sphere)``: the matte sphere's disc fitted to
    its ``mask`` (:func:`dualscale.calib.lightsphere.sphere_from_mask`), the pixels within
    :data:`MATTE_RADIUS` of its radius and their unit normals (orthographic camera, the
    camera frame of :mod:`dualscale.calib.lightsphere`).  Raises :class:`CalibrationError`
    when the mask does not fit a circle (outline RMS above ``max_rms_px``)."""
    from dualscale.calib.lightsphere import LightSphereError, sphere_from_mask

    try:
        sph = sphere_from_mask(mask, source, max_rms_px=max_rms_px)
    except LightSphereError as e:
        raise CalibrationError(f"{e}: a matte reference sphere's mask must be its disc") from e
    h, w = np.asarray(mask).shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    nx, ny = (xx - sph.cx) / sph.r, (sph.cy - yy) / sph.r
    rho2 = nx * nx + ny * ny
    inside = (rho2 < MATTE_RADIUS ** 2) & (np.asarray(mask) > 0)
    n = np.stack([nx, ny, np.sqrt(np.clip(1.0 - rho2, 0.0, 1.0))], -1)
    return inside, n, sph


def estimate_from_matte_sphere(codes: np.ndarray, mask: np.ndarray, dirs: np.ndarray, bits: int,
                               clipped: np.ndarray | None = None, **kw: Any) -> tuple[ResponseEstimate, Any]:
    """The response and the lights' relative intensities from photographs of a **matte
    reference sphere** under the same lights: ``codes`` ``(K, H, W, 3)`` normalised code
    values, ``mask`` ``(H, W)`` the sphere's mask (:func:`matte_sphere_normals`), ``dirs``
    ``(K, 3)`` the lights (e.g. from the chrome sphere), ``clipped`` ``(K, H, W)``.  The
    normals are known, so only each pixel's albedo is free (:func:`estimate_response` with
    ``normals``).  Returns ``(estimate, sphere)``; the estimate's source is ``"target"``."""
    inside, n, sph = matte_sphere_normals(mask)
    c = np.asarray(codes)[:, inside].astype(np.float64)
    valid = None if clipped is None else ~np.asarray(clipped)[:, inside]
    return estimate_response(c, dirs, valid, bits=bits, normals=n[inside], **kw), sph
