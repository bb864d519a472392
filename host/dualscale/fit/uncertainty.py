"""Per-pixel uncertainty of a fit (issue 26): :func:`.core.fit_observations`
computes it at its solution when asked (``uncertainty=True``, any preset: the covariance goes
through the fused kernel's Jacobian also for Adam), :func:`.io.save_fit` then writes it
(:func:`dualscale.formats.maps.save_uncertainty`) with :func:`summary` in ``fit.json``;
:func:`calibration` scores it against a ground truth.

With the joint step's free parameters, one kernel pass per pixel (:func:`.covariance.covariance_rows`,
the fused kernel's Jacobian) builds the matrices

* ``A = J^T C J``, ``B = J^T C^2 J`` and the noise-weighted ``N`` (below)

over the *kept* rows only (invalid samples and the rows :meth:`.lm.Loss.keep` sets aside as cast
shadows have zero weight), ``C`` the row weights of :class:`.lm.Loss` (1 per LED row,
``back_weight`` per back-lit row).  The fit minimises ``sum c rho(r)``; its asymptotic
(sandwich) covariance, for residuals of density ``f`` and scale ``sigma``, is

* ``loss='l2'`` (``rho = r^2``): ``Sigma = sigma^2 A^-1 B A^-1`` for one scale;
* ``loss='l1'`` (``rho = |r|``, the presets' default): the least-absolute-deviations
  covariance ``Sigma = 1 / (4 f(0)^2) A^-1 B A^-1`` for one density.  The IRLS matrix ``J^T W J``,
  ``W = 1/|r|``, that the optimiser solves with is *not* used: ``E[1/|r|]`` diverges, so it
  says nothing about the spread of the estimate.

**Noise model** (:func:`row_noise`): each row's residual is Gaussian with the per-pixel
variance ``s_i^2 = a u_i^2 + b u_i mu_i`` (read noise plus shot noise of the sensor's signal;
``mu_i`` the render; ``u_i`` the row's *signal scale*, the factor from the sensor's signal to
the image's radiance: ``1 / (exposure x intensity)`` times the calibration's gains, which the
dataset records per image, ``signal_scale`` in :mod:`dualscale.formats.dataset`, and
:attr:`.Observations.signal_scale` carries), ``a`` and ``b`` fitted to the pixel's own kept
residuals at the solution.  A rig that meters every image (the paper's "dynamically computed
exposure") gives its bright specular images short exposures, so in radiance their noise is
larger than one ``a + b mu`` across the images says: on the virtual sensor the one-scale model
put the z-scores' spread of roughness, anisotropy and IOR at 1.2-1.4, the recorded scales at
1.0-1.17 (docs/FITTING.md).  Without recorded scales (``u = 1``) it is the one-scale model.  The
sensor's gain and read noise themselves are not calibrated (no photon transfer curve yet), so
``a`` and ``b`` are always fitted; ``Uncertainty.noise`` says which model ran.  Then, with
``f_i(0) = 1 / (sqrt(2 pi) s_i)``:

* ``loss='l1'``: ``Sigma = (pi / 2) N^-1 B N^-1``, ``N = J^T C S^-1 J``, ``B = J^T C^2 J``;
* ``loss='l2'``: ``Sigma = A^-1 N A^-1``, ``N = J^T C^2 S^2 J``.

Homoscedastic rows (``s_i = s``) give back ``(pi / 2) s^2 A^-1 B A^-1`` and ``s^2 A^-1 B
A^-1``.  Under shot noise a single scale per pixel follows the many dark rows and understates
the highlights' noise, which carry the roughness and the normal: on a twill crop with the
virtual sensor's shot and read noise the z-scores' spread was 1.4-1.7 with it and 0.9-1.05 with
the model (``tests/fit/test_uncertainty.py``).

**The optimiser's own error.**  ``Sigma`` is the spread of the *optimum* under the noise; a fit
that stopped short of it (Adam's presets, a coarse start, few lights) is off by more.  The one
Gauss-Newton step the optimiser would take next from the solution, ``dx = -(J^T W J + prior)^-1
(J^T W r + prior gradient)`` with the fit's own reweighting ``W`` (:meth:`.fused.Problem.irls`),
estimates that distance, and ``Sigma + dx dx^T`` is reported: at a converged LM fit ``dx`` is
negligible beside ``Sigma``, after ``adam-fast`` it took the z-scores' spread from 3.5-7 to
1.25-1.6 (docs/FITTING.md).  The matrices (``J^T W J``, ``A``, ``B``, ``N``) come from one
evaluation of the Jacobian.

**Where the pass runs.**  The LM presets (fused kernel) make it in their joint step's last
iteration (:class:`Gather`): that iteration evaluates every pixel's Jacobian for its own ``J^T W
J`` anyway, which the pass returns to it bit for bit, so the maps do not change and the
covariance costs two more accumulations, the noise model and the small solves (docs/FITTING.md,
*Cost*).  The matrices are then taken one accepted step before the solution; the remaining step
from the solution is that iteration's Gauss-Newton step less the step it took (on a twill crop
sigma agreed with a pass at the solution to a median 0.01 %, ``tests/fit/test_uncertainty.py``).
A parameter at a bound at the solution is undetermined; the others keep the covariance
conditional on the set determined at the evaluation point.  The Adam presets, the eager
kernels and a fit resumed past its last iteration make a pass of their own at the solution.

A prior (:attr:`.lm.Loss.priors`, the presets' IOR prior) is added in information units: the
data give the information ``Sigma_data^-1`` (``(2 / pi) N B^-1 N`` or ``A N^-1 A``), the
Gaussian prior ``1 / sd^2`` on its channel (:meth:`.lm.Loss.prior_terms`' curvature divided by its likelihood scale ``k``: the LM cost is the negative log posterior
times ``k``), and ``Sigma = (Sigma_data^-1 + diag(1 / sd^2))^-1``, a Laplace approximation of
the posterior.

**Undetermined** (``determined`` False; the parameter's rows and columns of ``Sigma`` are NaN,
and the others' covariance is that of the determined sub-block, i.e. conditional on it):

* a parameter within :data:`BOUND_TOL` of its box (:data:`.params.BOX`; the tangent wraps and
  has none), or a roughness below the GGX alpha floor ``sqrt(1e-3)`` (``ggx.ggx_alphas``);
* a parameter the data do not see: ``A_jj <= DIAG_TOL * max_i A_ii``;
* a direction the data do not constrain: the smallest eigenvalue of the unit-diagonal
  (correlation-scaled) ``A`` below :data:`EIG_TOL`; the parameter with the largest share of
  that eigenvector is set aside and the test repeated;
* every parameter of a pixel with fewer kept rows than ``P + 1`` (a pixel with no valid
  sample among them), or whose solve fails.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components, normal_from_square
from dualscale.bsdf.maps import IOR_MAX, IOR_MIN

from . import fused, lm
from .covariance import covariance_rows, covariance_solve, noise_rows
from .loop import free_names, step_data
from .observations import Observations, stride_leds
from .params import PARAM_CHANNELS, pack
from .presets import Preset

#: a parameter this close to its box (normalised units) is pinned there
BOUND_TOL = 1e-3
#: GGX alphas floor at 1e-3 = r^2 (``ggx.ggx_alphas``): below, roughness only reaches the retro term
ROUGHNESS_FLOOR = math.sqrt(1e-3)
#: a parameter whose normal-matrix diagonal is below this fraction of the largest one is unseen
DIAG_TOL = 1e-10
#: smallest eigenvalue of the correlation-scaled normal matrix below which a direction is taken as
#: unconstrained: its variance is then inflated > 1e6 x (sigma > 1000 x) over an uncorrelated one
EIG_TOL = 1e-6
#: below this anisotropy the tangent is undetermined: the lobe's alphas differ by
#: ``1 - sqrt(1 - 0.9 a)`` < 2.3 %, so its axis is not an observable of the material
TANGENT_MIN_ANISOTROPY = 0.05


def _offsets(names: tuple[str, ...]) -> dict[str, slice]:
    out, c = {}, 0
    for n in names:
        out[n] = slice(c, c + PARAM_CHANNELS[n])
        c += PARAM_CHANNELS[n]
    return out


#: iterations of the per-pixel noise-model fit (:func:`row_noise`; with one signal scale 2
#: recovered the per-row sigmas as well as 4; with images' scales over a range of 55x, 3 are
#: needed and 6 do no better, ``tests/fit/test_uncertainty.py``)
NOISE_ITERATIONS = 3
#: rows whose residual exceeds this many of their model sigmas are left out of the next
#: iteration of the noise-model fit (cast-shadow edges, misfit, hot pixels)
NOISE_CLIP = 3.0
#: ``E[r^2 | |r| <= z sigma] / sigma^2`` for a Gaussian ``r``, ``z`` = :data:`NOISE_CLIP`: the
#: rejection's bias, divided out
_TRUNCATED_VARIANCE = 1.0 - 2.0 * NOISE_CLIP * math.exp(-0.5 * NOISE_CLIP ** 2) / math.sqrt(2.0 * math.pi) / math.erf(
    NOISE_CLIP / math.sqrt(2.0))


def _noise(r: Tensor, y: np.ndarray, u: np.ndarray, keep: Tensor) -> tuple[Tensor, Tensor]:
    """``(a (H, W), b (H, W))`` of :func:`.covariance.noise_rows`; ``r``, ``keep`` ``(H, W, K)``, ``y``
    ``(npix, K)``, ``u`` ``(K,)``."""
    shape = r.shape
    # float64 always: one compiled signature of the kernel
    r2 = np.ascontiguousarray(r.reshape(-1, shape[-1]).double().numpy())
    kp = np.ascontiguousarray(keep.reshape(-1, shape[-1]).double().numpy())
    a, b = np.empty(r2.shape[0]), np.empty(r2.shape[0])
    noise_rows(r2, np.ascontiguousarray(y, dtype=np.float64), np.ascontiguousarray(u, dtype=np.float64), kp,
                NOISE_ITERATIONS, NOISE_CLIP ** 2, _TRUNCATED_VARIANCE, a, b)
    t = torch.from_numpy
    return t(a).reshape(shape[:-1]), t(b).reshape(shape[:-1])


def row_scales(obs: Observations, rows: int) -> np.ndarray:
    """``(rows,)`` float64: each residual row's signal scale (:attr:`.Observations.signal_scale`,
    row ``3 k + c`` of image ``k``, then the back-lit image's three when ``rows`` has them,
    :class:`.fused.Problem`'s layout), relative to the largest; all 1 when the dataset records
    one scale for every image."""
    n = obs.images.shape[0]
    if obs.signal_scale is None:
        return np.ones(rows)
    u = obs.signal_scale.double().reshape(-1).numpy()
    if rows > 3 * n:
        back = obs.back_signal_scale
        u = np.concatenate([u, np.ones(3) * u.mean() if back is None else back.double().numpy()])
    return np.ascontiguousarray(u / u.max())


def row_noise(r: Tensor, mu: Tensor, keep: Tensor, u: np.ndarray | None = None) -> Tensor:
    """``(H, W, K)`` float64: each row's noise sigma under the per-pixel model ``var = a u^2 + b u
    mu`` (read noise plus shot noise of a signal that reached these values scaled by ``u (K,)``,
    the rows' signal scales, :func:`row_scales`, default 1; ``mu`` the rendered value, clamped at
    0), fitted to the pixel's kept residuals ``r`` (``keep`` > 0) by :data:`NOISE_ITERATIONS` of
    iteratively reweighted least squares on ``r^2`` (weights ``1 / var^2``, since ``Var(r^2) = 2
    var^2`` for a Gaussian ``r``; a row beyond :data:`NOISE_CLIP` sigmas of the previous iterate
    is left out, and the truncation's bias divided out), with ``a > 0`` and ``b >= 0``.  Starts
    from the read-noise-only mean square.  (The fit itself runs the same model inside
    :func:`.covariance.covariance_rows`.)"""
    u = np.ones(r.shape[-1]) if u is None else np.asarray(u, np.float64)
    y = (mu.double() - r.double()).reshape(-1, r.shape[-1]).numpy()
    a, b = _noise(r.double(), y, u, keep.double())
    ut = torch.from_numpy(u)
    var = a.unsqueeze(-1) * ut ** 2 + b.unsqueeze(-1) * ut * mu.double().clamp(min=0.0)
    return var.clamp(min=1e-30).sqrt()


def _candidates(x: Tensor, names: tuple[str, ...], a: Tensor, keep: Tensor) -> Tensor:
    """``(H, W, P)`` bool: not at a bound, seen by the data, in a pixel with enough kept rows."""
    ok = ~_bounded(x, names)
    diag = torch.diagonal(a, dim1=-2, dim2=-1)
    ok &= diag > DIAG_TOL * diag.amax(-1, keepdim=True).clamp(min=1e-300)
    ok &= (keep.sum(-1) > x.shape[-1]).unsqueeze(-1)
    return ok


def _block_matrices(prob, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], r: Tensor, keep: Tensor,
                    sw_fit: Tensor, loss: lm.Loss, u_rows: np.ndarray) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """One block's matrices from one pass of :func:`.covariance.covariance_rows` at ``x (h, w, P)`` with
    residuals ``r``, kept rows ``keep`` and the optimiser's row multipliers ``sw_fit`` (all
    ``(h, w, K)`` in the images' dtype, as :meth:`.fused.Problem.irls` gives them; other dtypes
    are cast to it): ``(J^T W J, J^T W r, {"A", "B", "N", "keep", "residuals", "noise"})``
    (module doc; ``noise`` ``(h, w, 2)``: the model's ``a``, ``b``).  ``J^T W J`` and ``J^T W
    r`` are bit for bit those of :meth:`.fused.Problem.normal_equations` with ``sw_fit``: the
    LM's last iteration takes them as its own (:class:`Gather`).  ``B = A + (c^2 - c) J_b^T K
    J_b``, the back-lit rows weighing ``c^2`` in it and ``c`` in ``A``."""
    fused._threads()
    full, cols = fused.full_vectors(x, names, fixed)
    npix, p = full.shape[0], cols.shape[0]
    dt = prob.rows.dtype
    has_back = prob.back.shape[0] == npix
    images = prob.rows if not has_back else prob.rows_and_back()
    rows = [np.ascontiguousarray(t.reshape(npix, -1).numpy(), dtype=dt) for t in (r, sw_fit, keep)]
    c_back = float(loss.back_weight)
    c_rows = prob.row_weights(c_back)
    jtjs, jtr, noise = np.empty((4, npix, p, p)), np.empty((npix, p)), np.empty((npix, 2))
    covariance_rows(full, cols, prob.view, prob.dirs, prob.w_s, prob.w_p, prob.w_d, prob.back, prob.back_wd,
                     prob.flags, prob.eta, *rows, images, c_rows, np.ascontiguousarray(u_rows[:images.shape[1]]),
                     loss.kind == "l1", NOISE_ITERATIONS, NOISE_CLIP ** 2, _TRUNCATED_VARIANCE, jtjs, jtr, noise)
    h_fit, a, nm, back = (torch.from_numpy(j).reshape(*x.shape[:2], p, p) for j in jtjs)
    b = a + (c_back * c_back - c_back) * back if has_back else a
    return (h_fit, torch.from_numpy(jtr).reshape(*x.shape[:2], p),
            {"A": a, "B": b, "N": nm, "keep": keep, "residuals": r, "noise": torch.from_numpy(noise).reshape(*x.shape[:2], 2)})


def _block_covariance(x: Tensor, names: tuple[str, ...], m: dict[str, Tensor], h_fit: Tensor, g_fit: Tensor,
                      scale: Tensor, loss: lm.Loss) -> dict[str, Tensor]:
    """A block's covariance at the evaluation point ``x (h, w, P)`` float64 from
    :func:`_block_matrices`' ``m``: ``{"x", "cov" (h, w, P, P), "determined" (h, w, P),
    "step" (h, w, P)}``, ``cov`` the noise's (with the prior, conditional on the determined
    block; anything on the others), ``step`` the optimiser's next Gauss-Newton step from ``x``
    (``-(J^T W J + prior)^-1 (J^T W r + prior gradient)``, undamped; 0 where the solve fails);
    the small solves per pixel in :func:`.covariance.covariance_solve`."""
    shape, p = x.shape[:-1], x.shape[-1]
    _, pg, ph = loss.prior_terms(x, names, scale.double())
    _, _, prior_info = loss.prior_terms(x, names, torch.ones(shape, dtype=x.dtype))  # k = 1: 1 / sd^2
    det = _candidates(x, names, m["A"], m["keep"]).reshape(-1, p).numpy().copy()

    def flat(t: Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.double().reshape(det.shape[0], *t.shape[len(shape):]).numpy())

    cov, step = np.empty((det.shape[0], p, p)), np.empty((det.shape[0], p))
    covariance_solve(flat(m["A"]), flat(m["B"]), flat(m["N"]), flat(h_fit), flat(-(g_fit + pg)), flat(ph),
                      flat(prior_info), det, loss.kind == "l1", EIG_TOL, cov, step)
    t = torch.from_numpy
    return {"x": x, "cov": t(cov).reshape(*shape, p, p), "determined": t(det).reshape(*shape, p),
            "step": t(step).reshape(*shape, p)}


def _bounded(x: Tensor, names: tuple[str, ...]) -> Tensor:
    """``(..., P)`` bool: within :data:`BOUND_TOL` of the box, or a roughness below the floor."""
    lo, hi = lm._lohi(names, {}, x)
    out = (x - lo <= BOUND_TOL) | (hi - x <= BOUND_TOL)
    if "roughness" in names:
        j = _offsets(names)["roughness"].start
        out[..., j] |= x[..., j] <= ROUGHNESS_FLOOR
    return out


def _gone(x: Tensor, x_eval: Tensor, names: tuple[str, ...]) -> Tensor:
    """``x - x_eval``, the tangent's wrapped to ``[-0.5, 0.5)`` (its period is 1)."""
    gone = x - x_eval
    if "tangent" in names:
        j = _offsets(names)["tangent"].start
        gone[..., j] = torch.remainder(gone[..., j] + 0.5, 1.0) - 0.5
    return gone


def _finish(x: Tensor, names: tuple[str, ...], point: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """``(cov, determined)`` at the solution ``x (h, w, P)`` float64 from a :func:`_block_covariance`
    taken at ``point["x"]`` (the solution itself, or the LM's last iterate before it): a
    parameter at a bound at ``x`` is undetermined too, and the optimiser's remaining step from
    ``x`` (the one from the evaluation point less the way already gone; the tangent's wrapped)
    is added, ``Sigma + dx dx^T`` (module doc).  Undetermined rows and columns are NaN."""
    det = point["determined"] & ~_bounded(x, names)
    dx = (point["step"] - _gone(x, point["x"], names)) * det
    cov = point["cov"] + dx.unsqueeze(-1) * dx.unsqueeze(-2)
    outer = det.unsqueeze(-1) & det.unsqueeze(-2)
    return torch.where(outer, cov, torch.full_like(cov, float("nan"))), det


def _separate_pass(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset
                   ) -> tuple[tuple[str, ...], list[tuple[dict[str, Tensor], dict[str, Tensor]]]]:
    """``(names, [(matrices, covariance)] per chunk)``: :func:`_block_matrices` and
    :func:`_block_covariance` at the fitted ``params`` themselves, by the LM's chunks of rows
    (``obs`` as given to ``fit_observations``: the preset's stride is applied)."""
    loss = lm.preset_loss(preset)
    names = free_names("joint", params)
    fixed = {k: v for k, v in params.items() if k not in names}
    strided = stride_leds(obs, preset.led_stride)
    d = step_data(strided, "joint", "fused")
    u_rows = row_scales(strided, 3 * strided.n + (3 if strided.backlight is not None else 0))
    x = pack(params, names)
    parts = []
    for y0, y1 in lm._chunks(*x.shape[:2]):
        xb = x[y0:y1]
        fx = {k: v[y0:y1] for k, v in fixed.items()}
        prob = lm.problem(lm._block(d, y0, y1), comps)
        r = prob.residuals(xb, names, fx)
        keep, sw_fit, _, scale = prob.irls(r, loss)  # kept rows: valid and not in a cast shadow
        h_fit, g_fit, m = _block_matrices(prob, xb, names, fx, r, keep, sw_fit, loss, u_rows)
        parts.append((m, _block_covariance(xb.double(), names, m, h_fit, g_fit, scale, loss)))
    return names, parts


def _cat(parts: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    return {k: torch.cat([p[k] for p in parts], 0) for k in parts[0]}


def normal_matrices(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset
                    ) -> dict[str, Tensor | tuple[str, ...]]:
    """The pieces of :func:`pixel_covariance` at ``params``: ``names`` (joint free parameters),
    ``x`` ``(H, W, P)``, ``A = J^T C J`` and ``B = J^T C^2 J`` ``(H, W, P, P)`` float64 over the
    kept rows, the noise-weighted ``N`` (``J^T C S^-1 J`` for ``loss='l1'``, ``J^T C^2 S^2 J`` for
    ``'l2'``; ``S`` the rows' noise sigmas, :func:`row_noise`), ``keep`` ``(H, W, K)``,
    ``residuals`` ``(H, W, K)``, ``noise`` ``(H, W, 2)`` (the noise model's ``a``, ``b``) and
    ``step`` ``(H, W, P)`` (the optimiser's next Gauss-Newton step, module doc).  ``obs``: as
    given to ``fit_observations`` (the preset's LED stride is applied)."""
    names, parts = _separate_pass(params, comps, obs, preset)
    out = _cat([{**m, "step": c["step"]} for m, c in parts])
    return {"names": names, "x": pack(params, names).double(), "kind": preset.loss, **out}


class Gather:
    """The covariance from the LM's last iteration of its joint step (:func:`.lm.run_lm`'s
    ``gather``): that iteration evaluates the Jacobian of every pixel anyway, so its kernel pass
    (:func:`_block_matrices`) builds ``A``, ``B`` and ``N`` beside the LM's own ``J^T W J``,
    which it returns to the LM unchanged (the maps are bit for bit those of a fit without it),
    and :func:`_block_covariance` reduces each chunk at once (memory: one ``(P, P)`` matrix per
    pixel).  The matrices are then one accepted step before the solution; :func:`_finish`
    takes the remaining step from there.  ``obs``: the fit's (strided) observations."""

    def __init__(self, obs: Observations, preset: Preset) -> None:
        self.loss = lm.preset_loss(preset)
        self.u_rows = row_scales(obs, 3 * obs.n + (3 if obs.backlight is not None else 0))
        self.height = obs.shape[0]
        self.parts: list[tuple[int, int, dict[str, Tensor]]] = []
        self.seconds = 0.0  # time spent in the gathering passes

    def __call__(self, prob, x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], r: Tensor, keep: Tensor,
                 sw: Tensor, scale: Tensor, y0: int, y1: int) -> tuple[Tensor, Tensor]:
        """One chunk of rows ``y0:y1`` of the LM's normal equations: ``(J^T W J, J^T W r)``."""
        t0 = time.perf_counter()
        if self.parts and self.parts[-1][1] != y0:  # a new iteration: keep the last one only
            self.parts, self.seconds = [], 0.0
        h_fit, g_fit, m = _block_matrices(prob, x, names, fixed, r, keep, sw, self.loss, self.u_rows)
        self.parts.append((y0, y1, _block_covariance(x.double(), names, m, h_fit, g_fit, scale, self.loss)))
        self.seconds += time.perf_counter() - t0
        return h_fit, g_fit

    def point(self) -> dict[str, Tensor] | None:
        """The gathered covariance over every row, or ``None`` when no whole iteration was gathered."""
        if not self.parts or self.parts[0][0] != 0 or self.parts[-1][1] != self.height:
            return None
        return {k: torch.cat([p[2][k] for p in self.parts], 0) for k in self.parts[0][2]}


def pixel_covariance(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset,
                     point: dict[str, Tensor] | None = None) -> tuple[Tensor, tuple[str, ...], Tensor]:
    """``(cov (H, W, P, P) float64, names, determined (H, W, P) bool)`` of the joint step's free
    parameters at the fitted ``params`` (normalised units, as the optimisers leave them), any
    preset (module doc: the formula, the noise scale, the undetermined rules); ``point``: a
    :class:`Gather`'s (the LM's last iteration), else a pass of its own at ``params``.
    Undetermined parameters have NaN rows and columns."""
    names = free_names("joint", params)
    if point is None:
        point = _cat([c for _, c in _separate_pass(params, comps, obs, preset)[1]])
    cov, det = _finish(pack(params, names).double(), names, point)
    return cov, names, det


def _normal_jacobian(s: Tensor) -> Tensor:
    """``d normal_from_square / d s``: ``(H, W, 3, 2)`` (pixels are independent)."""
    s = s.detach().double().clone().requires_grad_(True)
    with torch.enable_grad():
        n = normal_from_square(s)
        rows = [torch.autograd.grad(n[..., k].sum(), s, retain_graph=k < 2)[0] for k in range(3)]
    return torch.stack(rows, -2)


def map_sigmas(params: dict[str, Tensor], cov: Tensor, names: tuple[str, ...], determined: Tensor,
               comps: Components) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """``(sigma, undetermined)``: per map of ``names`` (the maps ``comps`` fits), the 1-sigma
    uncertainty ``(H, W, C)`` in the map's own units (NaN where undetermined) and its
    undetermined mask ``(H, W, C)`` bool, by the delta method through the parametrisation
    (:func:`.params.to_maps`):

    * albedo, transmittance (per channel), roughness, anisotropy, specular tint, opacity: the
      maps are the normalised parameters themselves, ``sigma = sqrt(Sigma_jj)``;
    * ior: in ``eta = 1 + 2 v`` (``bsdf.ior_from_map``), ``sigma_eta = 2 sigma_v``;
    * normal ``(H, W, 1)``, degrees: ``Sigma_n = J Sigma_s J^T`` through ``normal_from_square``
      (``J`` its 3x2 Jacobian at the square point ``s``), and ``sqrt(trace Sigma_n)``: the RMS
      angle between the estimated and the true normal (a 2-D error, so not a 1-D sigma: it covers
      ~63 % under an isotropic Gaussian, not 68 %);
    * tangent ``(H, W, 1)``, degrees of azimuth (``phi = pi v``): ``180 sigma_v``; undetermined
      also where the anisotropy is below :data:`TANGENT_MIN_ANISOTROPY` or below twice its own
      sigma (or undetermined), since the axis of a round lobe is not a property of the material.
    """
    off = _offsets(names)
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    sig, und = {}, {}
    for n in names:
        sl = off[n]
        d = determined[..., sl]
        if n == "normal":
            j = _normal_jacobian(params["normal"])
            cn = j @ cov[..., sl, sl] @ j.transpose(-1, -2)
            s = torch.diagonal(cn, dim1=-2, dim2=-1).sum(-1, keepdim=True).clamp(min=0).sqrt() * (180 / math.pi)
            u = ~d.all(-1, keepdim=True) | ~torch.isfinite(s)
        else:
            s = var[..., sl].clamp(min=0).sqrt()
            if n == "ior":
                s = s * (IOR_MAX - IOR_MIN)
            elif n == "tangent":
                s = s * 180.0
            u = ~d | ~torch.isfinite(s)
        sig[n], und[n] = s, u
    if "tangent" in und:
        if "anisotropy" in names:
            aniso = params["anisotropy"].double()
            round_lobe = (aniso < TANGENT_MIN_ANISOTROPY) | und["anisotropy"] | (aniso < 2 * sig["anisotropy"])
        else:
            round_lobe = torch.ones_like(und["tangent"])
        und["tangent"] = und["tangent"] | round_lobe
    for n in sig:
        sig[n] = torch.where(und[n], torch.full_like(sig[n], float("nan")), sig[n].double())
    return sig, und


#: pixels per block of :func:`pixel_uncertainty`: its ``(P, P)`` float64 matrices (a few per
#: pixel, P <= 16) then stay within ~50 MB whatever the map's size
BLOCK_PIXELS = 4096
#: how the noise scale was obtained (``Uncertainty.noise``; module doc)
NOISE_RESIDUAL = ("residual noise model: per pixel var = a + b * render (read + shot noise), fitted to its "
                  "kept residuals")
#: the same with the dataset's per-image signal scales (exposure, light, calibration gains)
NOISE_SCALED = ("residual noise model with the images' recorded signal scales u: per pixel var = a u^2 + b u "
                "render (read + shot noise of the sensor's signal), a and b fitted to its kept residuals")


@dataclass
class Uncertainty:
    """The uncertainty of a fit's maps: ``sigma`` ``{map: (H, W, C) float32}`` (1 sigma in the
    map's units, :data:`dualscale.formats.maps.SIGMA_UNITS`; NaN where undetermined),
    ``undetermined`` ``{map: (H, W, C) bool}``, ``noise`` (which noise scale), ``seconds``."""

    sigma: dict[str, Tensor]
    undetermined: dict[str, Tensor]
    noise: str
    seconds: float

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "Uncertainty":
        return Uncertainty({k: v[y0:y1, x0:x1] for k, v in self.sigma.items()},
                           {k: v[y0:y1, x0:x1] for k, v in self.undetermined.items()}, self.noise, self.seconds)

    def arrays(self) -> tuple[dict, dict]:
        """``(sigma, undetermined)`` as numpy arrays, for :func:`~dualscale.formats.maps.save_uncertainty`."""
        return ({k: v.numpy() for k, v in self.sigma.items()}, {k: v.numpy() for k, v in self.undetermined.items()})


#: a gathered pixel whose last LM step moved a determined parameter by more than this many of
#: its sigmas is evaluated again at the solution (:func:`_refresh`)
STALE_STEP = 1.0


def _refresh(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset,
             point: dict[str, Tensor]) -> dict[str, Tensor]:
    """A :class:`Gather`'s ``point`` with its stale pixels evaluated again at the solution: those
    whose last accepted step moved a determined parameter by more than :data:`STALE_STEP` of its
    sigma, where the matrices of one step before may no longer describe the solution (an LM
    stopped short: on ``coarse-to-fine``'s 6 iterations the roughness, anisotropy and IOR were
    1.1-1.6x more overconfident without it, ~5 % of its pixels are re-evaluated, < 1 % of a
    converged ``standard`` fit's; 0.3 sigma re-evaluated 18 % and 3 % for the same calibration)."""
    names = free_names("joint", params)
    x = pack(params, names).double()
    sd = torch.diagonal(point["cov"], dim1=-2, dim2=-1).clamp(min=1e-300).sqrt()
    moved = (_gone(x, point["x"], names).abs() > STALE_STEP * sd) & point["determined"]
    idx = moved.any(-1).reshape(-1).nonzero().squeeze(-1)
    if idx.numel() == 0:
        return point
    flat = {k: v.reshape(-1, v.shape[-1]) for k, v in params.items()}
    sub = {k: v[idx].unsqueeze(0) for k, v in flat.items()}
    again = _cat([c for _, c in _separate_pass(sub, comps, obs.pixels(idx), preset)[1]])
    out = {}
    for k, v in point.items():
        f = v.reshape(-1, *v.shape[2:]).clone()
        f[idx] = again[k][0].to(f.dtype)
        out[k] = f.reshape(v.shape)
    return out


def pixel_uncertainty(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset,
                      block_pixels: int = BLOCK_PIXELS, gathered: Gather | None = None) -> Uncertainty:
    """The :class:`Uncertainty` of the fitted ``params`` (normalised, ``(H, W, C)`` each, as the
    optimisers leave them) on ``obs`` (as given to the fit: the preset's LED stride is applied
    here), for any preset: :func:`pixel_covariance` then :func:`map_sigmas`.  From ``gathered``
    (the LM's last iteration) when it holds every row, else by a pass of its own, in blocks of
    rows of at most ``block_pixels`` pixels (pixels are independent, so blocks change nothing).
    ``seconds``: this call's time plus the gathering's (which includes the kernel pass the LM's
    last iteration makes anyway: the cost of the uncertainty is the fit's time with it less
    the fit's without, ``bench/bench_uncertainty.py``)."""
    t0 = time.perf_counter()
    h, w = next(iter(params.values())).shape[:2]
    point = None if gathered is None else gathered.point()
    if point is not None:
        point = _refresh(params, comps, obs, preset, point)
    rows = h if point is not None else max(1, block_pixels // max(1, w))
    sig_l: dict[str, list[Tensor]] = {}
    und_l: dict[str, list[Tensor]] = {}
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        pb = {k: v[y0:y1].detach() for k, v in params.items()}
        cov, names, det = pixel_covariance(pb, comps, obs.crop(y0, y1, 0, w), preset, point)
        sig, und = map_sigmas(pb, cov, names, det, comps)
        for n in sig:
            sig_l.setdefault(n, []).append(sig[n].float())
            und_l.setdefault(n, []).append(und[n])
    extra = gathered.seconds if point is not None else 0.0
    return Uncertainty({n: torch.cat(v, 0) for n, v in sig_l.items()}, {n: torch.cat(v, 0) for n, v in und_l.items()},
                       NOISE_RESIDUAL if obs.signal_scale is None else NOISE_SCALED,
                       time.perf_counter() - t0 + extra)


def summary(sigma: dict[str, "Tensor | object"], undetermined: dict[str, "Tensor | object"], noise: str,
            seconds: float) -> dict:
    """``fit.json``'s ``"uncertainty"`` record: ``{"noise", "seconds", "files": "uncertainty/",
    "maps": {map: {"units", "channels", "median", "p90", "undetermined_fraction"}}}``, per
    channel over the determined pixels (``None`` where none is); ``sigma``/``undetermined`` as
    in :class:`Uncertainty` (tensors or numpy arrays)."""
    import numpy as np

    from dualscale.formats.maps import SIGMA_UNITS, _sigma_names

    maps = {}
    for n, s in sigma.items():
        s = np.asarray(s, np.float64)
        u = np.asarray(undetermined[n], bool)
        med, p90, frac = [], [], []
        for c in range(s.shape[-1]):
            v = s[..., c][~u[..., c]]
            med.append(float(np.median(v)) if v.size else None)
            p90.append(float(np.percentile(v, 90)) if v.size else None)
            frac.append(float(u[..., c].mean()))
        maps[n] = {"units": SIGMA_UNITS[n], "channels": list(_sigma_names(n)), "median": med, "p90": p90,
                   "undetermined_fraction": frac}
    return {"noise": noise, "seconds": round(float(seconds), 3), "files": "uncertainty/", "maps": maps}


#: the radius, in units of the normal's RMS angle sigma, that holds 95 % of a 2-D isotropic
#: Gaussian error (``sqrt(-ln 0.05)``: the squared angle over ``sigma^2 / 2`` is chi-square 2)
Z95_NORMAL = math.sqrt(-math.log(0.05))
#: ``|z| <= 1.96``: 95 % of a 1-D Gaussian error
Z95 = 1.959963984540054


def map_error(name: str, fit, truth):
    """The signed error ``fit - truth`` of one map ``(H, W, C)`` (numpy or tensors) in its
    sigma's units (:data:`dualscale.formats.maps.SIGMA_UNITS`), as a float64 numpy array: the
    angle between the normals in degrees (``(H, W, 1)``, unsigned: a 2-D error), the tangents'
    axial azimuth difference in degrees, wrapped to ``[-90, 90)``, eta for the IOR (``eta = 1 +
    2 v``), the map's own value otherwise."""
    import numpy as np

    from .metrics import normal_angle_deg

    f, g = (np.asarray(t.detach().cpu().numpy() if isinstance(t, Tensor) else t, np.float64) for t in (fit, truth))
    if name == "normal":
        # atan2(|a x b|, a . b): exact near 0, where the arccos of the dot product loses the
        # small angles that a calibrated normal's sigma (a few hundredths of a degree) is made of
        return normal_angle_deg(torch.from_numpy(f), torch.from_numpy(g)).numpy()[..., None]
    if name == "tangent":
        return np.mod(180.0 * (f[..., :1] - g[..., :1]) + 90.0, 180.0) - 90.0
    if name == "ior":
        return (IOR_MAX - IOR_MIN) * (f[..., :1] - g[..., :1])
    return f - g


def calibration(maps, sigma: dict, undetermined: dict, truth) -> dict[str, dict]:
    """How well ``sigma`` predicts the error of ``maps`` against ``truth`` (both
    :class:`~dualscale.bsdf.maps.MaterialMaps` or ``{name: (H, W, C)}``), per map of ``sigma``
    present in both, over the determined texel channels: ``{"determined"`` (share),
    ``"z_sd"``, ``"z_mean"``, ``"coverage_95"``, ``"median_sigma"``, ``"n"}``.  ``z = (fit -
    truth) / sigma``; for the normal (a 2-D error whose sigma is the RMS angle) ``z_sd`` is
    ``sqrt(mean((angle / sigma)^2))``, ``z_mean`` is ``None`` and the 95 % radius is
    :data:`Z95_NORMAL` sigma; otherwise ``|z| <= 1.96``.  A calibrated sigma gives ``z_sd``
    near 1 and ``coverage_95`` near 0.95 (issue 26 asks 0.8-1.25 and 0.90-0.98)."""
    import numpy as np

    def get(m, n):
        return getattr(m, n, None) if not isinstance(m, dict) else m.get(n)

    out = {}
    for n, s in sigma.items():
        f, g = get(maps, n), get(truth, n)
        if f is None or g is None:
            continue
        s = np.asarray(s.numpy() if isinstance(s, Tensor) else s, np.float64)
        u = np.asarray(undetermined[n].numpy() if isinstance(undetermined[n], Tensor) else undetermined[n], bool)
        e = map_error(n, f, g)
        ok = ~u & np.isfinite(s) & (s > 0) & np.isfinite(e)
        rec: dict = {"determined": float(ok.mean()), "n": int(ok.sum())}
        if ok.any():
            z = e[ok] / s[ok]
            if n == "normal":
                rec.update(z_sd=float(np.sqrt(np.mean(z ** 2))), z_mean=None,
                           coverage_95=float(np.mean(z <= Z95_NORMAL)))
            else:
                rec.update(z_sd=float(np.std(z)), z_mean=float(np.mean(z)), coverage_95=float(np.mean(np.abs(z) <= Z95)))
            rec["median_sigma"] = float(np.median(s[ok]))
        out[n] = rec
    return out


def median_sigmas(unc: Uncertainty) -> dict[str, float | None]:
    """``{map: median sigma}`` over the determined texel channels of every channel together, in
    the map's sigma units (``None`` where none is determined): the one figure per map that the
    light-subset study and the preset table quote."""
    out: dict[str, float | None] = {}
    for n, s in unc.sigma.items():
        v = s[~unc.undetermined[n] & torch.isfinite(s)]
        out[n] = float(v.double().median()) if v.numel() else None
    return out


def posterior(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset
              ) -> dict[str, "Tensor | tuple[str, ...]"]:
    """What an experimental design needs of a fit at its solution (:mod:`dualscale.adaptive`), from
    a pass of its own at ``params``: ``names`` (the joint step's free parameters), ``x (H, W, P)``
    float64 (normalised units), ``determined (H, W, P)``, ``noise (H, W, 2)`` (each pixel's
    ``(a, b)``, ``var = a u^2 + b u mu``, module doc), and the sandwich's parts: ``bread`` and
    ``meat`` ``(H, W, P, P)`` with ``Sigma_data = c bread^-1 meat bread^-1`` (``l1``: ``N``, ``B``,
    ``c = pi / 2``; ``l2``: ``A``, ``N``, ``c = 1``), ``c`` and ``prior (H, W, P)``, the priors'
    information ``1 / sd^2`` per channel."""
    names, parts = _separate_pass(params, comps, obs, preset)
    point = _cat([c for _, c in parts])
    m = _cat([mm for mm, _ in parts])
    x = pack(params, names).double()
    _, det = _finish(x, names, point)
    loss = lm.preset_loss(preset)
    _, _, prior = loss.prior_terms(x, names, torch.ones(x.shape[:-1], dtype=x.dtype))
    l1 = loss.kind == "l1"
    return {"names": names, "x": x, "determined": det, "noise": m["noise"], "prior": prior,
            "bread": (m["N"] if l1 else m["A"]).double(), "meat": (m["B"] if l1 else m["N"]).double(),
            "c": math.pi / 2 if l1 else 1.0, "l1": l1}
