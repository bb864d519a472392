"""Optimal experimental design for the micro capture: which LEDs would teach the fit the most
(issue 27; the light subsets of supplementary Sec. 6, chosen per sample instead of fixed).

From a fit of the lights taken so far, on a sample of pixels, every pixel has a posterior
covariance ``Sigma`` of its free parameters (normalised units, :func:`dualscale.fit.uncertainty.posterior`)
and a noise model ``var = a u^2 + b u mu``.  A candidate LED ``l``, taken at P0 and P90, adds six
rows (two analyser modes x RGB) whose Jacobian ``J_l (6, P)`` at the current maps and predicted
noise ``S_l = diag(s)`` give the information

    ``M_l = e J_l^T S_l^-2 J_l``,

``e = 2 / pi`` for the fit's least-absolute-deviations loss (its efficiency under Gaussian
noise; 1 for ``l2``).  The posterior after it is ``(Sigma^-1 + M_l)^-1`` (Laplace, the noise
model and the maps held at their current values).  The criteria, per pixel then summed over the
sample (the pixels are independent, so the sum is the criterion of the whole map's joint
posterior, and the worst-determined pixels, whose gains are largest, weigh most):

* ``D``: ``log det(I + L^T M_l L)``, ``Sigma = L L^T`` -- the log of the factor by which the
  posterior ellipsoid's volume shrinks (the determinant lemma);
* ``A``: ``sum_j (1 - Sigma'_jj / Sigma_jj)`` -- the parameters' variance reductions, each on its
  own scale (the maps' units differ, so a plain trace would weigh them arbitrarily).

A parameter the fit leaves undetermined (at a bound, unseen) enters with the prior variance of
a uniform over its box, ``(hi - lo)^2 / 12``, uncorrelated: a light that would determine it has
a large gain.  A batch is chosen greedily (:func:`choose_batch`), each pick updating every
pixel's ``Sigma`` before the next is scored (the standard greedy for batch D-optimality, within
``1 - 1/e`` of the best batch for this submodular criterion), by gain per second of device time.

The predicted noise of a candidate: ``mu`` its render at the current maps, ``u`` (the image's
signal scale, which metering sets) ``kappa x peak(mu)``: metering exposes every image so that
its brightest sample sits at the same fraction of full scale, so the scale goes as the image's
peak radiance; ``kappa`` is the median over the images taken (per channel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import Components
from dualscale.fit import lm
from dualscale.fit.loop import step_data
from dualscale.fit.observations import Observations, analyzer_weights
from dualscale.fit.params import BOX
from dualscale.fit.presets import Preset
from dualscale.fit.uncertainty import posterior

CRITERIA = ("D", "A")
"""The optimal-design criteria (module doc)."""


@dataclass
class DesignState:
    """A fit's posterior on a pixel sample: ``names`` of the free parameters, ``x (n, P)``,
    ``cov (n, P, P)`` float64 with undetermined parameters at their box's uniform prior
    (module doc), ``noise (n, 2)`` ``(a, b)``, ``kappa (3,)`` the signal scale per unit peak
    radiance (module doc; ``None``: one scale for every image), ``u_max`` the largest signal
    scale the noise model's ``u`` is relative to, and ``efficiency`` (``2 / pi`` or 1)."""

    names: tuple[str, ...]
    x: Tensor
    cov: Tensor
    noise: Tensor
    kappa: np.ndarray | None
    u_max: float
    efficiency: float


def _box_variance(names: tuple[str, ...], params: dict[str, Tensor]) -> Tensor:
    """``(P,)``: the variance of a uniform over each free parameter's box (the tangent: its period)."""
    out = []
    for n in names:
        lo, hi = BOX.get(n, (0.0, 1.0))
        out.extend([(hi - lo) ** 2 / 12.0] * params[n].shape[-1])
    return torch.tensor(out, dtype=torch.float64)


def design_state(params: dict[str, Tensor], comps: Components, obs: Observations, preset: Preset) -> DesignState:
    """The :class:`DesignState` of ``params`` fitted to ``obs`` (a ``1 x n`` pixel sample, as
    :meth:`~dualscale.fit.observations.Observations.pixels` lays it out) with ``preset``."""
    names, x, cov, det, noise = posterior(params, comps, obs, preset)
    n, p = x.shape[0] * x.shape[1], x.shape[-1]
    cov, det = cov.reshape(n, p, p), det.reshape(n, p)
    prior = torch.diag_embed(_box_variance(names, params).expand(n, p))
    both = det.unsqueeze(-1) & det.unsqueeze(-2)
    cov = torch.where(both, torch.nan_to_num(cov), prior)
    kappa, u_max = None, 1.0
    if obs.signal_scale is not None:
        u = obs.signal_scale.double().numpy()  # (K, 3)
        peak = obs.images.double().reshape(obs.n, -1).quantile(0.99, dim=1).clamp(min=1e-12).numpy()
        kappa = np.median(u / peak[:, None], axis=0)
        u_max = float(max(u.max(), 0.0 if obs.back_signal_scale is None else float(obs.back_signal_scale.max())))
    eff = 2.0 / math.pi if lm.preset_loss(preset).kind == "l1" else 1.0
    return DesignState(names, x.reshape(n, p), cov, noise.reshape(n, 2), kappa, u_max, eff)


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
    """``(n, C, P, P)`` float64: each sample pixel's information ``M_l`` from each candidate LED
    (module doc) of :func:`candidate_observations`' ``cand``."""
    d = step_data(cand, "joint", "fused")
    prob = lm._problem(d, comps)
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
    var = (a * u ** 2 + b * u * mu[0]).clamp(min=1e-30)
    sw = var.rsqrt().reshape(1, n, k3)
    out = torch.empty(n, c, state.x.shape[-1], state.x.shape[-1], dtype=torch.float64)
    r = torch.zeros_like(mu)
    for j in range(c):  # one candidate's six rows at a time: its own J^T S^-2 J
        mask = torch.zeros(k3, dtype=torch.float64)
        mask[6 * j:6 * j + 6] = 1.0
        jtj, _ = prob.normal_equations(xb, state.names, fixed, r.to(xb.dtype), (sw * mask).to(xb.dtype))
        out[:, j] = state.efficiency * jtj.reshape(n, *jtj.shape[-2:])
    return out


def gains(cov: Tensor, info: Tensor, criterion: str = "D") -> Tensor:
    """``(n, C)``: each pixel's gain from each candidate (module doc) for ``cov (n, P, P)`` and
    ``info (n, C, P, P)``."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion {criterion!r}: one of {', '.join(CRITERIA)}")
    p = cov.shape[-1]
    L = torch.linalg.cholesky(cov + 1e-15 * torch.eye(p, dtype=cov.dtype))
    inner = L.transpose(-1, -2).unsqueeze(1) @ info @ L.unsqueeze(1)  # (n, C, P, P)
    eye = torch.eye(p, dtype=cov.dtype)
    if criterion == "D":
        return torch.linalg.cholesky(eye + inner).diagonal(dim1=-2, dim2=-1).log().sum(-1) * 2.0
    post = L.unsqueeze(1) @ torch.linalg.solve(eye + inner, L.transpose(-1, -2).unsqueeze(1).expand_as(inner))
    var0 = cov.diagonal(dim1=-2, dim2=-1).unsqueeze(1)
    return (1.0 - post.diagonal(dim1=-2, dim2=-1) / var0).sum(-1)


def update(cov: Tensor, info: Tensor) -> Tensor:
    """``(n, P, P)``: the posterior covariance after information ``info (n, P, P)``:
    ``L (I + L^T M L)^-1 L^T``."""
    p = cov.shape[-1]
    L = torch.linalg.cholesky(cov + 1e-15 * torch.eye(p, dtype=cov.dtype))
    inner = torch.eye(p, dtype=cov.dtype) + L.transpose(-1, -2) @ info @ L
    out = L @ torch.linalg.solve(inner, L.transpose(-1, -2))
    return 0.5 * (out + out.transpose(-1, -2))


def choose_batch(cov: Tensor, info: Tensor, cost_s: np.ndarray, size: int, criterion: str = "D"
                 ) -> tuple[list[int], list[float], np.ndarray]:
    """Greedy batch (module doc): ``(picked candidate indices, their gains when picked (summed
    over pixels), every candidate's first-pick gain (C,))``.  ``cost_s (C,)``: each candidate's
    device time; the pick maximises gain per second.  Ties go to the lower index (deterministic)."""
    first = gains(cov, info, criterion).sum(0).numpy()
    picked: list[int] = []
    got: list[float] = []
    cov = cov.clone()
    g = first.copy()
    for _ in range(min(size, info.shape[1])):
        score = g / np.asarray(cost_s, np.float64)
        score[picked] = -np.inf
        j = int(np.argmax(score))
        picked.append(j)
        got.append(float(g[j]))
        cov = update(cov, info[:, j])
        if len(picked) < size:
            g = gains(cov, info, criterion).sum(0).numpy()
    return picked, got, first
