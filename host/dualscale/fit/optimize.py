"""The paper's optimiser: Adam on whole maps through the differentiable renderer.

Loss: mean absolute error between renders and images, both clamped at 2, over the step's LED
images, plus the back-lit image weighted as ``preset.back_weight`` LED images; samples that are
clipped or outside the sample mask (``Observations.valid``) have zero weight, and the mean is
taken over the valid ones.  After every
update the parameters are projected onto their box and the bounds in force (``params``).
``light_batch`` draws that many LED images per iteration (seeded, resumable).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dualscale.bsdf import Components

from . import fused
from .loop import Loop
from .observations import Observations, WholeMap
from .params import project, to_maps
from .render import render_back, render_leds


def l1_loss(params: dict[str, Tensor], fixed: dict[str, Tensor], comps: Components, obs: Observations,
            images: Tensor, back: Tensor | None, back_weight: float) -> Tensor:
    """Mean absolute residual over the valid samples (module doc), a scalar."""
    maps = to_maps(params, fixed)
    r = (render_leds(maps, comps, obs) - images).abs()
    h, w = obs.shape
    whole = obs.whole
    if obs.valid is None and obs.back_valid is None:
        err = r.sum()
        if back is not None:
            err = err + back_weight * (render_back(maps, comps, obs) - back).abs().sum()
        hw = h * w if whole is None else whole.pixels
        return err / (hw * 3 * (obs.n + (back_weight if back is not None else 0.0)))
    v = obs.valid.to(r.dtype) if obs.valid is not None else torch.ones(r.shape[:3], dtype=r.dtype)
    vs = v.sum() if whole is None else torch.tensor(whole.led_samples(obs.n), dtype=r.dtype)
    err, count = (r * v.unsqueeze(-1)).sum(), 3.0 * vs
    if back is not None:
        bv = (obs.back_valid if obs.back_valid is not None else torch.ones((h, w), dtype=torch.bool)).to(r.dtype)
        err = err + back_weight * ((render_back(maps, comps, obs) - back).abs() * bv.unsqueeze(-1)).sum()
        bs = bv.sum() if whole is None else torch.tensor(whole.back_samples(), dtype=r.dtype)
        count = count + back_weight * 3.0 * bs
    return err / count.clamp(min=1.0)


def fused_l1_loss(params: dict[str, Tensor], fixed: dict[str, Tensor], prob: fused.Problem,
                  back_weight: float, whole: WholeMap | None = None) -> Tensor:
    """:func:`l1_loss` through the fused kernel (:class:`.fused.Residuals`: numba renders, the
    gradient by its analytic derivatives); ``prob`` holds the step's (or batch's) images;
    ``whole``: the whole map's counts when ``prob`` is a tile's (its ``n`` images)."""
    names = tuple(params)
    r = fused.Residuals.apply(torch.cat([params[k] for k in names], -1), prob, names, fixed)
    c = torch.from_numpy(prob.row_weights(back_weight)).to(r.dtype).expand_as(r)
    if prob.valid.shape[0]:
        c = c * torch.from_numpy(prob.valid).to(r.dtype).reshape(r.shape)
    if whole is None:
        den = c.sum()
    else:  # the sum of c over the whole map: 1 per valid LED row, back_weight per valid back-lit row
        n_led = prob.rows.shape[1] // 3
        back = back_weight * 3.0 * whole.back_samples() if prob.k > prob.rows.shape[1] else 0.0
        den = torch.tensor(3.0 * whole.led_samples(n_led) + back, dtype=r.dtype)
    return (r.abs() * c).sum() / den.clamp(min=1.0)


def _problem(data, o: Observations, imgs: Tensor, comps: Components, full: bool) -> fused.Problem:
    if not full:
        return fused.Problem(o, imgs, data.back, comps)
    if "adam" not in data.cache:
        data.cache["adam"] = fused.Problem(o, imgs, data.back, comps)
    return data.cache["adam"]


def run_adam(params: dict[str, Tensor], comps: Components, obs: Observations, loop: Loop,
             resume: dict | None = None, seed: int = 0) -> dict[str, Tensor]:
    """Optimise ``params`` in place through the preset's three steps; returns them."""
    preset = loop.preset
    gen = torch.Generator().manual_seed(seed)
    if resume is not None:
        gen.set_state(resume["generator"])
    for s, step, data, free, it0 in loop.plan(params, obs, resume):
        fixed = {k: v.detach() for k, v in params.items() if k not in free}
        leaves = [params[k].requires_grad_(True) for k in free]
        opt = torch.optim.Adam(leaves, lr=preset.lr)
        if resume is not None and it0 > 0 and resume.get("adam") is not None:
            opt.load_state_dict(resume["adam"])
        for it in range(it0, preset.iterations[s]):
            o, imgs = data.obs, data.images
            if preset.light_batch is not None and preset.light_batch < o.n:
                idx = torch.randperm(o.n, generator=gen)[:preset.light_batch]
                o, imgs = o.select(idx), imgs[idx]
            opt.zero_grad(set_to_none=True)
            if preset.kernel == "fused":
                prob = _problem(data, o, imgs, comps, o is data.obs)
                loss = fused_l1_loss({k: params[k] for k in free}, fixed, prob, preset.back_weight, o.whole)
            else:
                loss = l1_loss({k: params[k] for k in free}, fixed, comps, o, imgs, data.back, preset.back_weight)
            loss.backward()
            for p in leaves:  # a non-finite gradient (never expected) must not poison the maps
                if p.grad is not None:
                    torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            opt.step()
            project(params, loop.bounds(s, it + 1))
            nxt = loop.after(s, it)
            loop.after_iteration(s, it, float(loss.detach()), lambda: {
                "step": nxt[0], "iteration": nxt[1], "params": {k: v.detach().clone() for k, v in params.items()},
                "adam": opt.state_dict() if nxt[0] == s else None, "generator": gen.get_state()})
        for p in leaves:
            p.requires_grad_(False)
    return params
