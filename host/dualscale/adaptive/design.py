"""Optimal experimental design for the micro capture: which LEDs would teach the fit the most
(issue 27; the light subsets of supplementary Sec. 6, chosen per sample instead of fixed).

From a fit of the lights taken so far, on a sample of pixels, every pixel has the parts of its
covariance (:func:`dualscale.fit.uncertainty.posterior`): the fit minimises an unweighted
least-absolute-deviations cost, so its data covariance is the sandwich ``Sigma = c H^-1 G
H^-1`` (``H = J^T S^-1 J``, ``G = J^T J``, ``c = pi / 2``, with ``S`` the rows' noise sigmas of
the pixel's noise model ``var = a u^2 + b u mu``; for ``l2``: ``H = J^T J``, ``G = J^T S^2 J``,
``c = 1``), and the posterior's information is ``F = H G^-1 H / c + P`` with the priors' ``P``.
A candidate LED ``l``, taken at P0 and P90, adds six rows (two analyser modes x RGB) whose
Jacobian ``J_l (6, P)`` at the current maps and predicted noise ``S_l`` add ``H_l`` and ``G_l``
(the same weightings) to ``H`` and ``G``: the estimator's own covariance after the light, not
the Gaussian optimum's (an L1 fit does not weigh a row by its noise, so a low-noise light
helps it less than ``J^T S^-2 J`` says).  The criteria, per pixel then summed over the sample
(the pixels are independent, so the sum is the criterion of the whole map's joint posterior,
and the worst-determined pixels, whose gains are largest, weigh most):

* ``D``: ``log det F' - log det F`` -- the log of the factor by which the posterior ellipsoid's
  volume shrinks;
* ``A``: ``sum_j (1 - Sigma'_jj / Sigma_jj)``, ``Sigma = F^-1`` -- the parameters' variance
  reductions, each on its own scale (the maps' units differ, so a plain trace would weigh them
  arbitrarily).

A parameter the fit leaves undetermined (at a bound, unseen, the tangent of an isotropic
pixel) is held at its value: it is left out (its rows and columns of every ``H``, ``G`` are
those of the identity, of every ``H_l``, ``G_l`` zero), so it adds no gain.  (Letting such a
parameter count made the tangent of near-isotropic pixels, which no light determines, dominate
the choice.)  A batch is chosen greedily (:func:`choose_batch`), each pick adding its ``H_l``,
``G_l`` to every pixel's before the next is scored (the standard greedy for batch
D-optimality), by gain per second of device time.

The predicted noise of a candidate: ``mu`` its render at the current maps, ``u`` (the image's
signal scale, which metering sets) ``kappa x peak(mu)``: metering exposes every image so that
its brightest sample sits at the same fraction of full scale, so the scale goes as the image's
peak radiance; ``kappa`` is the median over the images taken (per channel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components
from dualscale.fit import lm
from dualscale.fit.loop import step_data
from dualscale.fit.observations import Observations, analyzer_weights
from dualscale.fit.presets import Preset
from dualscale.fit.uncertainty import Uncertainty, map_sigmas, median_sigmas, posterior

from .options import CRITERIA  # noqa: F401  (the criteria, module doc)


@dataclass
class DesignState:
    """A fit's posterior on a pixel sample (module doc): ``names`` of the free parameters, ``x (n,
    P)``, the sandwich's ``bread`` and ``meat`` ``(n, P, P)`` float64 (undetermined parameters
    replaced by the identity's rows, module doc), ``c``, ``prior (n, P)``, ``determined (n, P)``,
    ``noise (n, 2)`` ``(a, b)``, ``l1`` (the loss), ``kappa (3,)`` the signal scale per unit peak
    radiance (module doc; ``None``: one scale for every image) and ``u_max`` the largest signal
    scale, which the noise model's ``u`` is relative to."""

    names: tuple[str, ...]
    x: Tensor
    bread: Tensor
    meat: Tensor
    c: float
    prior: Tensor
    determined: Tensor
    noise: Tensor
    l1: bool
    kappa: np.ndarray | None
    u_max: float


def _held(m: Tensor, det: Tensor) -> Tensor:
    """``m (n, P, P)`` with the rows and columns of the undetermined parameters those of the identity."""
    both = det.unsqueeze(-1) & det.unsqueeze(-2)
    eye = torch.eye(m.shape[-1], dtype=m.dtype).expand_as(m)
    return torch.where(both, m, eye)


def design_state(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset) -> DesignState:
    """The :class:`DesignState` of ``params`` fitted to ``obs`` (a ``1 x n`` pixel sample, as
    :meth:`~dualscale.fit.observations.Observations.pixels` lays it out) with ``preset``."""
    post = posterior(params, comps, obs, preset)
    x = post["x"]
    n, p = x.shape[0] * x.shape[1], x.shape[-1]
    det = post["determined"].reshape(n, p)
    kappa, u_max = None, 1.0
    if obs.signal_scale is not None:
        u = obs.signal_scale.double().numpy()  # (K, 3)
        peak = obs.images.double().reshape(obs.n, -1).quantile(0.99, dim=1).clamp(min=1e-12).numpy()
        kappa = np.median(u / peak[:, None], axis=0)
        u_max = float(max(u.max(), 0.0 if obs.back_signal_scale is None else float(obs.back_signal_scale.max())))
    return DesignState(post["names"], x.reshape(n, p), _held(post["bread"].reshape(n, p, p), det),
                       _held(post["meat"].reshape(n, p, p), det), float(post["c"]),
                       post["prior"].reshape(n, p).double() * det, det, post["noise"].reshape(n, 2).double(),
                       bool(post["l1"]), kappa, u_max)


def candidate_observations(sample: Observations, dirs: np.ndarray, ids: list[int]) -> Observations:
    """The sample's pixels under candidate LEDs ``ids`` with directions ``dirs (C, 3)``, each at
    P0 then P90 (relative analyser angles; image ``2 c`` and ``2 c + 1``), images zero (only
    their renders are wanted), no back light."""
    ws, wd = [], []
    for d in dirs:
        for an in (0.0, 90.0):
            s, _, w = analyzer_weights(an, True, np.asarray(d))
            ws.append(s)
            wd.append(w)
    k = 2 * len(ids)
    f = dict(dtype=sample.images.dtype)
    return Observations(images=torch.zeros((k, *sample.images.shape[1:]), **f),
                        dirs=torch.tensor(np.repeat(np.asarray(dirs, np.float64), 2, axis=0), **f),
                        w_s=torch.tensor(ws, **f), w_p=torch.zeros(k, **f), w_d=torch.tensor(wd, **f),
                        led_ids=torch.tensor([i for i in ids for _ in (0, 1)], dtype=torch.long),
                        pixel_mm=sample.pixel_mm, view=sample.view)


def candidate_information(state: DesignState, params: dict[str, Tensor], comps: Components,
                          cand: Observations) -> Tensor:
    """``(n, C, 2, P, P)`` float64: each sample pixel's ``(H_l, G_l)`` from each candidate LED
    (module doc) of :func:`candidate_observations`' ``cand``; zero on undetermined parameters."""
    d = step_data(cand, "joint", "fused")
    prob = lm.problem(d, comps)
    fixed = {k: v for k, v in params.items() if k not in state.names}
    xb = state.x.reshape(*cand.shape, -1).to(cand.images.dtype)
    mu = prob.residuals(xb, state.names, fixed).double().clamp(min=0.0)  # (1, n, 3 K): render - 0
    n, k3 = mu.shape[1], mu.shape[2]
    c = k3 // 6
    if state.kappa is None:
        u = torch.ones(n, k3, dtype=torch.float64)
    else:  # metering: the image's scale goes with its peak radiance (module doc)
        peak = mu.reshape(n, 2 * c, 3).permute(1, 0, 2).reshape(2 * c, -1).quantile(0.99, dim=1).clamp(min=1e-12)
        u = (peak[:, None] * torch.from_numpy(state.kappa)[None, :]).reshape(1, k3) / state.u_max
        u = u.expand(n, k3)
    a, b = state.noise[:, :1], state.noise[:, 1:]
    s2 = (a * u ** 2 + b * u * mu[0]).clamp(min=1e-30)
    # sqrt of the rows' weights in H and in G (module doc)
    w_h, w_g = (s2 ** -0.25, torch.ones_like(s2)) if state.l1 else (torch.ones_like(s2), s2.sqrt())
    p = state.x.shape[-1]
    out = torch.empty(n, c, 2, p, p, dtype=torch.float64)
    r = torch.zeros_like(mu).to(xb.dtype)
    for j in range(c):  # one candidate's six rows at a time
        mask = torch.zeros(k3, dtype=torch.float64)
        mask[6 * j:6 * j + 6] = 1.0
        for q, w in enumerate((w_h, w_g)):
            jtj, _ = prob.normal_equations(xb, state.names, fixed, r, (w * mask).reshape(1, n, k3).to(xb.dtype))
            out[:, j, q] = jtj.reshape(n, p, p)
    both = (state.determined.unsqueeze(-1) & state.determined.unsqueeze(-2))[:, None, None]
    return torch.where(both, out, torch.zeros((), dtype=out.dtype))  # undetermined: held (module doc)


#: the smallest eigenvalue of an information matrix, relative to its largest, that
#: :func:`_cholesky` keeps (a matrix that rounding left indefinite is lifted to it)
EIG_FLOOR = 1e-12


def _cholesky(f: Tensor) -> Tensor:
    """The Cholesky factor of symmetric ``f (..., P, P)``; where rounding made a matrix
    indefinite (``H G^-1 H`` of a badly determined pixel: a poor early fit of a sheer sample),
    the factor of the matrix with its eigenvalues raised to :data:`EIG_FLOOR` times the largest."""
    chol, info = torch.linalg.cholesky_ex(f)
    bad = info > 0
    if bad.any():
        w, v = torch.linalg.eigh(f[bad])
        w = w.clamp(min=EIG_FLOOR * w.abs().amax(-1, keepdim=True).clamp(min=1e-300))
        chol = chol.clone()
        chol[bad] = torch.linalg.cholesky((v * w.unsqueeze(-2)) @ v.transpose(-1, -2)
                                          + torch.diag_embed(EIG_FLOOR * w.amax(-1, keepdim=True).expand_as(w)))
    return chol


def _information(bread: Tensor, meat: Tensor, c: float, prior: Tensor) -> Tensor:
    """``F = H G^-1 H / c + diag(prior)`` for ``(..., P, P)`` bread ``H`` and meat ``G``."""
    f = bread @ torch.linalg.solve(meat, bread) / c
    f = 0.5 * (f + f.transpose(-1, -2))
    return f + torch.diag_embed(prior.expand(f.shape[:-1]))


def predicted_sigmas(state: DesignState, params: dict[str, Tensor], comps: Components,
                     info: Tensor | None = None) -> dict[str, float]:
    """``{map: median sigma}`` (the maps' sigma units, as :func:`dualscale.fit.uncertainty.median_sigmas`:
    the normal in degrees) of the posterior ``F^-1`` (module doc) of the sample's pixels, after
    the lights whose summed ``(H_l, G_l)`` are ``info (n, 2, P, P)`` (``None``: the lights taken
    so far; ``params`` the sample's ``(1, n, C)`` parameters), by the fit's own delta method (:func:`dualscale.fit.uncertainty.map_sigmas`);
    undetermined parameters are left out.  With ``info`` the sum over every candidate it is the
    prediction, at the current maps, of what the whole candidate plan would give: the
    ``--target full+N%`` rule (:mod:`.loop`).  Maps with no determined texel are absent."""
    h, g = state.bread, state.meat
    if info is not None:
        h, g = h + info[:, 0], g + info[:, 1]
    f = _information(h, g, state.c, state.prior)
    cov = torch.cholesky_inverse(_cholesky(f))
    n, p = state.x.shape
    det = state.determined.reshape(1, n, p)
    sig, und = map_sigmas(params, cov.reshape(1, n, p, p), state.names, det, comps)
    medians = median_sigmas(Uncertainty(sig, und, "predicted by the design", 0.0))
    return {k: v for k, v in medians.items() if v is not None}


def gains(state_h: Tensor, state_g: Tensor, c: float, prior: Tensor, info: Tensor, criterion: str = "D",
          chunk: int = 16) -> Tensor:
    """``(n, C)``: each pixel's gain from each candidate (module doc) for the current bread
    ``state_h`` and meat ``state_g`` ``(n, P, P)``, ``prior (n, P)`` and the candidates' ``info
    (n, C, 2, P, P)`` (:func:`candidate_information`), ``chunk`` candidates at a time."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion {criterion!r}: one of {', '.join(CRITERIA)}")
    f0 = _information(state_h, state_g, c, prior)
    l0 = _cholesky(f0)
    out = []
    for j0 in range(0, info.shape[1], chunk):
        blk = info[:, j0:j0 + chunk]
        f1 = _information(state_h.unsqueeze(1) + blk[:, :, 0], state_g.unsqueeze(1) + blk[:, :, 1], c,
                          prior.unsqueeze(1))
        if criterion == "D":
            ld1 = _cholesky(f1).diagonal(dim1=-2, dim2=-1).log().sum(-1)
            out.append(2.0 * (ld1 - l0.diagonal(dim1=-2, dim2=-1).log().sum(-1).unsqueeze(1)))
        else:
            v0 = torch.cholesky_inverse(l0).diagonal(dim1=-2, dim2=-1).unsqueeze(1)
            v1 = torch.cholesky_inverse(_cholesky(f1)).diagonal(dim1=-2, dim2=-1)
            out.append((1.0 - v1 / v0).sum(-1))
    return torch.cat(out, 1)


def choose_batch(state: DesignState, info: Tensor, cost_s: np.ndarray, size: int, criterion: str = "D"
                 ) -> tuple[list[int], list[float], np.ndarray]:
    """Greedy batch (module doc): ``(picked candidate indices, their gains when picked (summed
    over pixels), every candidate's first-pick gain (C,))``.  ``cost_s (C,)``: each candidate's
    device time; the pick maximises gain per second.  Ties go to the lower index (deterministic)."""
    h, g = state.bread.clone(), state.meat.clone()
    first = gains(h, g, state.c, state.prior, info, criterion).sum(0).numpy()
    picked: list[int] = []
    got: list[float] = []
    gsum = first.copy()
    for _ in range(min(size, info.shape[1])):
        score = gsum / np.asarray(cost_s, np.float64)
        score[picked] = -np.inf
        j = int(np.argmax(score))
        picked.append(j)
        got.append(float(gsum[j]))
        h, g = h + info[:, j, 0], g + info[:, j, 1]
        if len(picked) < size:
            gsum = gains(h, g, state.c, state.prior, info, criterion).sum(0).numpy()
    return picked, got, first
