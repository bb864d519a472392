"""Learning-rate schedules of propagation training (issue 29 §2): a ``method=``-style registry.

:data:`SCHEDULES` maps a name (``TrainOptions.schedule``, ``propagate train --schedule``) to a
factory ``(optimiser, iterations, lr) -> scheduler | None``; the training loop calls the
scheduler's ``step()`` once after every optimiser step, and its ``state_dict()`` goes into the
checkpoint, so a resumed run takes the same learning rates as an uninterrupted one.

* ``"constant"`` (default): the preset's ``lr`` at every step (no scheduler; Adam as in the
  paper, Section 7.4).
* ``"onecycle"``: :class:`torch.optim.lr_scheduler.OneCycleLR` (Smith & Topin 2019, "Super-
  convergence") over the run's ``iterations`` with the preset's ``lr`` as the *peak*: warm-up
  from ``lr / 25`` to ``lr`` over the first 30 % of the steps, then cosine annealing to
  ``lr / 25e4``; Adam's ``beta1`` cycles inversely, 0.95 -> 0.85 -> 0.95.  PyTorch's defaults.
  The schedule is tied to its length: a checkpoint cannot be continued to a larger iteration
  count (:func:`check_extend` says so).  Pair it with a higher ``lr`` than the constant 0.002
  (docs/PROPAGATION.md, "Schedule and warm start").
"""

from __future__ import annotations

from typing import Callable

import torch


def _constant(optim: torch.optim.Optimizer, iterations: int, lr: float):
    return None


def _onecycle(optim: torch.optim.Optimizer, iterations: int, lr: float):
    return torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=lr, total_steps=iterations)


SCHEDULES: dict[str, Callable] = {"constant": _constant, "onecycle": _onecycle}
"""Schedule name -> factory ``(optimiser, iterations, lr) -> LRScheduler | None``."""

#: schedules whose learning rates depend on the run's total iteration count
LENGTH_BOUND = frozenset({"onecycle"})


def make_schedule(name: str, optim: torch.optim.Optimizer, iterations: int, lr: float):
    """The scheduler of schedule ``name`` for a run of ``iterations`` steps with (peak) ``lr``;
    ``None`` for ``"constant"``.  An unknown name is a :class:`ValueError` listing the choices."""
    if name not in SCHEDULES:
        raise ValueError(f"learning-rate schedule must be one of {sorted(SCHEDULES)}, got {name!r}")
    if iterations < 1:
        raise ValueError(f"a training run needs at least 1 iteration, got {iterations}")
    return SCHEDULES[name](optim, iterations, lr)


def check_extend(name: str, ckpt, target: int | None, iterations: int) -> None:
    """Refuse to continue a checkpoint of a length-bound schedule (``onecycle``) whose run was
    ``target`` iterations long with ``iterations`` (a :class:`ValueError` saying what to pass)."""
    if name in LENGTH_BOUND and target is not None and target != iterations:
        raise ValueError(f"checkpoint {ckpt} is a {target}-iteration {name} schedule; its learning rates depend on "
                         f"that length, so it cannot continue as a {iterations}-iteration run: pass --iterations "
                         f"{target}, or delete it (training restarts)")
