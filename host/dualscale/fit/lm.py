"""Per-pixel Levenberg-Marquardt: the fast optimiser.

The model has no spatial coupling, so every pixel is an independent problem in at most 14
unknowns over ``3 N`` residuals ``r = render - image`` (both clamped at 2), plus the back-lit
residuals weighted as ``back_weight`` LED images.  Per pixel, the cost is

* ``loss='l2'``: ``sum c r^2``;
* ``loss='l1'``: ``sum c |r|``, the paper's loss, minimised by iteratively reweighted least
  squares: every iteration weights each residual row by ``1 / max(|r|, eps)`` at the current
  residuals, so the weighted squared cost equals ``sum c |r|`` there (``c`` = 1 for LED
  residuals, ``back_weight`` for back-lit ones, as in the Adam loss).

Each iteration builds every pixel's weighted normal equations: with ``kernel='fused'`` (the
presets' default) in one numba pass per pixel with analytic derivatives, accumulated in place
(:mod:`.fused`); with the eager reference by forward differences (one torch render per parameter
channel, all pixels at once, in row chunks to bound memory).  It then solves the damped weighted normal
equations ``(J^T W J + lambda diag(J^T W J)) d = -J^T W r`` per pixel, projects onto the bounds
in force, and accepts the step per pixel only where the true cost (L1 or L2) drops (``lambda``
shrinks 3x on success, grows 4x on failure), so the cost never rises.  A pixel whose solve fails
keeps its value.

A :class:`Prior` makes the fit a MAP estimate: a Gaussian on one scalar map, in the same units
as the data cost.  The data term is a likelihood whose scale ``k`` is estimated per pixel and
per iteration from the median absolute residual (L1, Laplace: ``k = median|r| / ln 2``; L2,
Gaussian: ``k = s^2``, ``s = 1.4826 median|r|``), so the prior weighs ``k (x - m)^2 / (2 sd^2)``
against ``sum c |r|`` (L1) or ``k (x - m)^2 / sd^2`` against ``sum c r^2`` (L2).  A pixel whose
data pin the map down barely feels it; one whose data do not (a fly-out fibre seen by few LEDs,
a dark or clipped pixel) stays near ``m`` instead of following the noise.

Invalid samples: a capture sample that is clipped or outside the sample mask
(``Observations.valid``, :func:`.render.valid_rows`) has zero weight in every cost, step,
accept test and likelihood scale; a pixel with no valid sample keeps its start values.

Cast shadows: the model is local, so a texel in the shadow of its neighbours under a grazing
LED is an outlier that no parameter can fit.  With ``Loss.shadow_ratio``, each iteration sets
aside (zero weight, in the step and in its accept test alike) the captures of every LED whose
diffuse-only capture is below that fraction of its render at the current parameters
(:meth:`Loss.keep`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dualscale.bsdf import DEFAULT_IOR, Components, map_from_ior

from . import fused
from .fused import SHADOW_ANCHOR_COS, SHADOW_FLOOR
from .loop import Loop, StepData
from .observations import Observations
from .params import BOX, PARAM_CHANNELS, pack, project, to_maps, unpack
from .presets import Preset
from .render import pixel_rows, render_back, render_leds, valid_rows

FD_STEP = 3e-4
ROW_PIXELS = 4096  # pixels per Jacobian chunk
LOSSES = ("l1", "l2")


@dataclass(frozen=True)
class Prior:
    """Gaussian prior on the scalar map ``name``: ``mean`` and ``sd`` in normalised units."""

    name: str
    mean: float
    sd: float


@dataclass(frozen=True)
class Loss:
    """Per-pixel cost of the residuals: ``kind`` 'l1' or 'l2'; ``eps`` (normalised image units)
    floors ``|r|`` in the L1 reweighting so that zero residuals get a finite weight; the
    back-lit residuals count ``back_weight`` times; ``priors`` turn the fit into a MAP estimate
    (module doc); ``shadow_ratio`` sets cast shadows aside (:meth:`keep`)."""

    kind: str = "l2"
    eps: float = 1e-4
    back_weight: float = 16.0
    priors: tuple[Prior, ...] = ()
    shadow_ratio: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in LOSSES:
            raise ValueError(f"unknown loss {self.kind!r}; choose from {LOSSES}")

    def row_weights(self, k_led: int, has_back: bool, like: Tensor) -> Tensor:
        """``c``: 1 per LED residual, ``back_weight`` per back-lit residual ``(K,)``."""
        c = torch.ones(k_led + (3 if has_back else 0), dtype=like.dtype)
        if has_back:
            c[k_led:] = self.back_weight
        return c

    def cost(self, r: Tensor, c: Tensor) -> Tensor:
        """Per-pixel ``sum c |r|`` or ``sum c r^2`` over the last axis."""
        return (c * (r.abs() if self.kind == "l1" else r * r)).sum(-1)

    def sqrt_weights(self, r: Tensor, c: Tensor) -> Tensor:
        """Row multipliers ``sqrt(W)`` for the normal equations at residuals ``r``: the weighted
        squared residuals ``W r^2`` sum to :meth:`cost` (exactly for L1 where ``|r| >= eps``)."""
        if self.kind == "l2":
            return c.sqrt().expand_as(r)
        return (c / r.abs().clamp(min=self.eps)).sqrt()

    def keep(self, r: Tensor, d: "StepData") -> Tensor | None:
        """``(h, w, K)`` 1/0 row mask: the rows of invalid samples (clipped, outside the mask:
        :func:`.render.valid_rows`) are always dropped; with ``shadow_ratio`` > 0, so are the
        rows of an LED whose capture is below ``shadow_ratio`` x its render (a cast shadow,
        which the model cannot produce) for this iteration; ``None`` keeps every row.

        A shadow darkens the diffuse reflection, so where the LED has a diffuse-only capture
        (the crossed analyser, P90) the test is made on it, in luminance, and applies to all the
        LED's captures; a model that merely predicts a specular highlight the data lack (over an
        open gap, say) is then never mistaken for a shadow.  Without one, each capture is tested
        on its own."""
        o = d.obs
        n = o.n
        base = valid_rows(o, r.shape[-1] > 3 * n, r.dtype)
        if self.shadow_ratio <= 0:
            return base
        img = d.images.mean(-1).permute(1, 2, 0)  # (h, w, n) luminance
        render = r[..., :3 * n].reshape(*r.shape[:2], n, 3).mean(-1) + img
        dark = (img < self.shadow_ratio * render) & (render > SHADOW_FLOOR)  # (h, w, n)
        if o.valid is not None:
            dark = dark & o.valid.permute(1, 2, 0)  # an invalid sample tells nothing
        diffuse = (o.w_s < 1e-6) & (o.w_p < 1e-6)
        same = (o.led_ids.reshape(-1, 1) == o.led_ids.reshape(1, -1)) & diffuse.reshape(1, -1)  # image i <- P90 j
        via_p90 = torch.einsum("hwj,ij->hwi", dark.to(r.dtype), same.to(r.dtype)) > 0
        drop = torch.where(same.any(1), via_p90, dark)
        # the camera looks down the dome's axis, so a texel it sees is lit by the LEDs next to
        # it: a pixel also dark against its render under those is a model still far off, not a
        # shadow, and setting its data aside would freeze it there; it keeps every capture
        near = o.dirs[:, 2] >= SHADOW_ANCHOR_COS
        if bool(near.any()):
            off = (dark & near).to(r.dtype).sum(-1, keepdim=True) > 0.5 * float(near.sum())
            drop = drop & ~off
        out = torch.ones_like(r) if base is None else base
        out[..., :3 * n] = out[..., :3 * n] * (~drop).to(r.dtype).repeat_interleave(3, -1)
        return out

    def scale(self, r: Tensor, keep: Tensor | None = None) -> Tensor:
        """Per-pixel likelihood scale ``k`` of residuals ``r (..., K)`` (module doc), over the
        rows ``keep`` > 0 when given (``eps`` where none is kept)."""
        a = r.abs()
        if keep is None:
            m = a.median(-1).values
        else:
            m = torch.nan_to_num(a.masked_fill(keep <= 0, float("nan")).nanmedian(-1).values, nan=self.eps)
        m = m.clamp(min=self.eps)
        return m / math.log(2.0) if self.kind == "l1" else (1.4826 * m) ** 2

    def prior_terms(self, x: Tensor, names: tuple[str, ...], k: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(cost (...), gradient (..., P), curvature (..., P))`` of the priors at ``x`` with
        scale ``k``; the last two enter the (reweighted) normal equations."""
        cost = torch.zeros_like(k)
        grad, curv = torch.zeros_like(x), torch.zeros_like(x)
        for p in self.priors:
            if p.name not in names:
                continue
            j = sum(PARAM_CHANNELS[n] for n in names[:names.index(p.name)])
            z = (x[..., j] - p.mean) / p.sd
            cost = cost + k * z * z * (0.5 if self.kind == "l1" else 1.0)
            grad[..., j] = k * z / p.sd
            curv[..., j] = k / p.sd ** 2
        return cost, grad, curv


def preset_loss(preset: Preset) -> Loss:
    """The :class:`Loss` a :class:`~.presets.Preset` asks for (its IOR prior is centred on
    the default eta of an unmapped IOR)."""
    priors = (Prior("ior", float(map_from_ior(DEFAULT_IOR)), preset.ior_prior_sd),) if preset.ior_prior_sd > 0 else ()
    return Loss(preset.loss, preset.l1_eps, preset.back_weight, priors, preset.shadow_ratio)


def _lohi(names: tuple[str, ...], bounds: dict[str, tuple[float, float]], like: Tensor) -> tuple[Tensor, Tensor]:
    lo, hi = [], []
    for n in names:
        a, b = BOX.get(n, (0.0, 1.0))
        if n == "tangent":
            a, b = -1e9, 1e9
        else:
            a, b = max(a, bounds.get(n, (a, b))[0]), min(b, bounds.get(n, (a, b))[1])
        lo += [a] * PARAM_CHANNELS[n]
        hi += [b] * PARAM_CHANNELS[n]
    return torch.tensor(lo, dtype=like.dtype), torch.tensor(hi, dtype=like.dtype)


def problem(d: StepData, comps: Components) -> fused.Problem:
    """The fused kernel's layout (:class:`dualscale.fit.fused.Problem`) of a step's data ``d``
    (:func:`dualscale.fit.loop.step_data`) for ``comps``, built once per step and block and
    cached on ``d``: its ``residuals`` render the observations at given parameters and its
    ``normal_equations`` give each pixel's weighted ``J^T W J``.  Public for the experimental
    design of the adaptive capture (:mod:`dualscale.adaptive.design`), which renders candidate
    lights that are not in the data."""
    key = ("fused", comps)
    if key not in d.cache:
        d.cache[key] = fused.Problem(d.obs, d.images, d.back, comps)
    return d.cache[key]


def _residual(x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], comps: Components,
              d: StepData) -> Tensor:
    """Unweighted residuals ``(h, w, K)`` of a pixel block: LED images, then the back-lit image."""
    if d.kernel == "fused":
        return problem(d, comps).residuals(x, names, fixed)
    maps = to_maps(unpack(x, names), fixed)
    r = pixel_rows(render_leds(maps, comps, d.obs, compiled=d.compiled) - d.images)
    if d.back is not None:
        r = torch.cat([r, render_back(maps, comps, d.obs) - d.back], -1)
    return r


def _row_weights(d: StepData, loss: Loss, like: Tensor) -> Tensor:
    return loss.row_weights(3 * d.obs.n, d.back is not None, like)


def _block(d: StepData, y0: int, y1: int) -> StepData:
    """Rows ``y0:y1`` of a step's data (cached, with their fused layouts, for the whole step)."""
    if (y0, y1) == (0, d.obs.shape[0]):
        return d
    key = ("block", y0, y1)
    if key not in d.cache:
        o = d.obs.crop(y0, y1, 0, d.obs.shape[1])
        d.cache[key] = StepData(o, d.images[:, y0:y1], None if d.back is None else d.back[y0:y1], d.kernel)
    return d.cache[key]


def _chunks(h: int, w: int) -> list[tuple[int, int]]:
    rows = max(1, ROW_PIXELS // max(1, w))
    return [(y, min(h, y + rows)) for y in range(0, h, rows)]


def cost(x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], comps: Components, d: StepData,
         loss: Loss, scale: Tensor | None = None, keep: Tensor | None = None, remember: bool = False) -> Tensor:
    """Per-pixel cost ``(H, W)`` (see :class:`Loss`); with the likelihood ``scale`` ``(H, W)``,
    plus the priors; with ``keep`` ``(H, W, K)``, over the kept rows only, else over the valid
    samples.  ``remember`` (fused kernel): keep the residuals for :func:`_carry`."""
    out = []
    for y0, y1 in _chunks(*x.shape[:2]):
        fx = {k: v[y0:y1] for k, v in fixed.items()}
        db = _block(d, y0, y1)
        if d.kernel == "fused":
            cb, rows = problem(db, comps).cost(x[y0:y1], names, fx, loss, None if keep is None else keep[y0:y1],
                                                residuals=remember)
            if remember:
                db.cache["trial rows"] = rows
            out.append(cb)
            continue
        r = _residual(x[y0:y1], names, fx, comps, db)
        cw = _row_weights(d, loss, r)
        kb = keep[y0:y1] if keep is not None else valid_rows(db.obs, db.back is not None, r.dtype)
        out.append(loss.cost(r, cw if kb is None else cw * kb))
    c = torch.cat(out, 0)
    return c if scale is None else c + loss.prior_terms(x, names, scale)[0]


def _carry(d: StepData, x: Tensor, fixed: dict[str, Tensor], better: Tensor) -> None:
    """Fused kernel: the residuals at the new ``x`` are the trial's where the step was taken and
    the old ones elsewhere; keep them, keyed by ``x`` and the frozen maps, for the next
    iteration (:func:`_carried`), which then renders once instead of twice."""
    for y0, y1 in _chunks(*x.shape[:2]):
        db = _block(d, y0, y1)
        rows, r0 = db.cache.pop("trial rows"), db.cache.pop("rows")
        rows[~better[y0:y1]] = r0[~better[y0:y1]]
        db.cache["carried"] = (x[y0:y1].clone(), {k: v[y0:y1].clone() for k, v in fixed.items()}, rows)


def _carried(db: StepData, x: Tensor, fixed: dict[str, Tensor]) -> Tensor | None:
    """The residuals :func:`_carry` kept, if they belong to exactly this ``x`` and frozen maps (a
    projection onto new bounds, or a new step, renders afresh)."""
    hit = db.cache.pop("carried", None)
    if hit is None or not torch.equal(hit[0], x) or hit[1].keys() != fixed.keys():
        return None
    if not all(torch.equal(hit[1][k], v) for k, v in fixed.items()):
        return None
    return hit[2]


def _normal_equations(x: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], comps: Components, d: StepData,
                      loss: Loss, hi: Tensor, gather=None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """``(J^T W J (H, W, P, P), J^T W r (H, W, P), data cost (H, W), likelihood scale (H, W),
    kept rows (H, W, K) or None)`` (fused kernel, or forward differences), with the weights ``W`` and the kept
    rows taken at the current residuals (IRLS for L1).  ``gather`` (fused kernel): a
    :class:`.uncertainty.Gather`, called for each chunk in place of the kernel's
    ``normal_equations``; it returns the same two matrices, bit for bit."""
    jtj, jtr, c, k, kept = [], [], [], [], []
    p = x.shape[-1]
    for y0, y1 in _chunks(*x.shape[:2]):
        xb = x[y0:y1]
        fx = {k: v[y0:y1] for k, v in fixed.items()}
        db = _block(d, y0, y1)
        if d.kernel == "fused":
            r0 = _carried(db, xb, fx)
            if r0 is None:
                r0 = _residual(xb, names, fx, comps, db)
            db.cache["rows"] = r0
            prob = problem(db, comps)
            keep, sw, cst, scl = prob.irls(r0, loss)
            if gather is None:
                a, b = prob.normal_equations(xb, names, fx, r0, sw)
            else:
                a, b = gather(prob, xb, names, fx, r0, keep, sw, scl, y0, y1)
            jtj.append(a)
            jtr.append(b)
            c.append(cst)
            k.append(scl)
            kept.append(keep)
            continue
        r0 = _residual(xb, names, fx, comps, db)
        cw = _row_weights(d, loss, r0)
        keep = loss.keep(r0, db)
        if keep is not None:
            cw = cw * keep
            kept.append(keep)
        sw = loss.sqrt_weights(r0, cw)  # (h, w, K)
        c.append(loss.cost(r0, cw))
        k.append(loss.scale(r0, valid_rows(db.obs, db.back is not None, r0.dtype)))
        cols = []
        for j in range(p):
            step = torch.where(xb[..., j] + FD_STEP > hi[j], -FD_STEP, FD_STEP)
            xp = xb.clone()
            xp[..., j] = xp[..., j] + step
            cols.append((_residual(xp, names, fx, comps, db) - r0) * (sw / step.unsqueeze(-1)))
        jac = torch.stack(cols, -1)  # weighted rows sqrt(W) J: (h, w, K, P)
        jtj.append(torch.einsum("hwkp,hwkq->hwpq", jac, jac))
        jtr.append(torch.einsum("hwkp,hwk->hwp", jac, r0 * sw))
    return (torch.cat(jtj, 0), torch.cat(jtr, 0), torch.cat(c, 0), torch.cat(k, 0),
            torch.cat(kept, 0) if kept else None)


def lm_iteration(x: Tensor, lam: Tensor, names: tuple[str, ...], fixed: dict[str, Tensor], comps: Components,
                 d: StepData, loss: Loss, bounds: dict[str, tuple[float, float]], gather=None
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """One damped (reweighted) Gauss-Newton step for every pixel: ``(x, lambda, cost)`` after it;
    a pixel's step is kept only where its true cost drops.  ``gather``: see :func:`_normal_equations`."""
    lo, hi = _lohi(names, bounds, x)
    jtj, jtr, c0, k, keep = _normal_equations(x, names, fixed, comps, d, loss, hi, gather)
    pc, pg, ph = loss.prior_terms(x, names, k)
    c0, jtr, jtj = c0 + pc, jtr + pg, jtj + torch.diag_embed(ph)
    diag = torch.diagonal(jtj, dim1=-2, dim2=-1)
    a = jtj + torch.diag_embed(lam.unsqueeze(-1) * (diag + 1e-9))
    a64, b64 = a.to(torch.float64), (-jtr).to(torch.float64).unsqueeze(-1)
    sol, info = torch.linalg.solve_ex(a64, b64)
    delta = sol.squeeze(-1).to(x.dtype)
    ok = (info == 0) & torch.isfinite(delta).all(-1)
    delta = torch.where(ok.unsqueeze(-1), delta, torch.zeros_like(delta))
    trial = torch.maximum(torch.minimum(x + delta, hi), lo)
    if "tangent" in names:  # wrapped now as params.project will: the render is the same, the trial's bits too
        j = sum(PARAM_CHANNELS[n] for n in names[:names.index("tangent")])
        trial[..., j] = torch.remainder(torch.remainder(trial[..., j], 1.0), 1.0)  # -1e-9 % 1 rounds to 1.0
    c1 = cost(trial, names, fixed, comps, d, loss, k, keep, remember=d.kernel == "fused")
    better = ok & torch.isfinite(c1) & (c1 < c0)
    x = torch.where(better.unsqueeze(-1), trial, x)
    if d.kernel == "fused":
        _carry(d, x, fixed, better)
    lam = torch.where(better, lam / 3.0, lam * 4.0).clamp(1e-7, 1e7)
    return x, lam, torch.where(better, c1, c0)


def grid_init(params: dict[str, Tensor], comps: Components, d: StepData, loss: Loss) -> None:
    """Per pixel, start roughness (and tangent, when anisotropic) at the best of a small grid:
    roughness {0.3, 0.5, 0.7} x tangent {0, 1/4, 1/2, 3/4} (anisotropy 0.5 while searching)."""
    names = tuple(params)
    x = pack(params, names)
    sl = {n: i for i, n in enumerate(names)}
    off = {n: sum(PARAM_CHANNELS[m] for m in names[:sl[n]]) for n in names}
    tangents = [0.0, 0.25, 0.5, 0.75] if "tangent" in params else [None]
    best_x, best_c = x.clone(), None
    for rough in (0.3, 0.5, 0.7):
        for tan in tangents:
            xt = x.clone()
            xt[..., off["roughness"]] = rough
            if tan is not None:
                xt[..., off["tangent"]] = tan
                xt[..., off["anisotropy"]] = 0.5
            c = cost(xt, names, {}, comps, d, loss)
            if best_c is None:
                best_x, best_c = xt, c
            else:
                take = c < best_c
                best_x = torch.where(take.unsqueeze(-1), xt, best_x)
                best_c = torch.where(take, c, best_c)
    for n, t in unpack(best_x, names).items():
        params[n].copy_(t)


def run_lm(params: dict[str, Tensor], comps: Components, obs: Observations, loop: Loop,
           resume: dict | None = None, gather=None) -> dict[str, Tensor]:
    """Optimise ``params`` in place through the preset's three steps; returns them.  ``gather``
    (a :class:`.uncertainty.Gather`; fused kernel): the joint step's last iteration also builds
    the matrices of the fit's covariance, in the same kernel pass (the maps do not change)."""
    preset = loop.preset
    loss = preset_loss(preset)
    lam_resume = resume.get("lambda") if resume is not None else None
    h, w = obs.shape
    for s, step, data, free, it0 in loop.plan(params, obs, resume):
        if step == "specular" and preset.grid_init and it0 == 0:
            grid_init(params, comps, data, loss)
        fixed = {k: v for k, v in params.items() if k not in free}
        x = pack(params, free)
        lam = lam_resume if (it0 > 0 and lam_resume is not None) else torch.full((h, w), 1e-2, dtype=x.dtype)
        last = gather if (step == "joint" and data.kernel == "fused") else None
        for it in range(it0, preset.iterations[s]):
            x, lam, c = lm_iteration(x, lam, free, fixed, comps, data, loss, loop.bounds(s, it),
                                     last if it == preset.iterations[s] - 1 else None)
            for k, v in unpack(x, free).items():
                params[k].copy_(v)
            project(params, loop.bounds(s, it + 1))
            x = pack(params, free)
            nxt = loop.after(s, it)
            loop.after_iteration(s, it, float(c.mean()), lambda: {
                "step": nxt[0], "iteration": nxt[1], "params": {k: v.clone() for k, v in params.items()},
                "lambda": lam.clone() if nxt[0] == s else None})
    return params
