"""What the optimisers share: per-step data, free/frozen split, progress and checkpoints."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

from torch import Tensor
from tqdm import tqdm

from dualscale.bsdf import Components

from .checkpoint import Checkpointer, FitInterrupted
from .init import diffuse_images
from .observations import Observations
from .params import bounds_at, project
from .presets import STEP_DATA, STEP_FITS, STEP_NAMES, Preset
from .render import clamp_images


@dataclass
class StepData:
    """Observations of one step with their images clamped at 2 (LED and back-lit); ``kernel``:
    how LM renders them (:data:`.presets.KERNELS`); ``cache`` holds the fused kernel's per-block
    layouts (:class:`.fused.Problem`)."""

    obs: Observations
    images: Tensor
    back: Tensor | None
    kernel: str = "eager"
    cache: dict = field(default_factory=dict)

    @property
    def compiled(self) -> bool:
        return self.kernel == "compiled"


def step_data(obs: Observations, step: str, kernel: str = "eager") -> StepData:
    o = diffuse_images(obs) if STEP_DATA[step] == "diffuse" else obs
    back = None if o.backlight is None else clamp_images(o.backlight)
    return StepData(o, clamp_images(o.images), back, kernel)


def free_names(step: str, params: dict[str, Tensor]) -> tuple[str, ...]:
    return tuple(n for n in params if n in STEP_FITS[step])


@dataclass
class Loop:
    """Global iteration bookkeeping for a preset: progress bar, checkpoints, early stop."""

    preset: Preset
    comps: Components
    checkpointer: Checkpointer
    progress: bool = False
    stop_after: int | None = None
    history: list[tuple[int, str, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.bar = tqdm(total=self.preset.total, desc=f"fit[{self.preset.name}]", disable=not self.progress,
                        leave=False)

    def global_index(self, step: int, it: int) -> int:
        return int(sum(self.preset.iterations[:step])) + it

    def fraction(self, step: int, it: int) -> float:
        return self.global_index(step, it) / max(1, self.preset.total)

    def steps(self):
        return list(enumerate(STEP_NAMES))

    def bounds(self, step: int, it: int) -> dict[str, tuple[float, float]]:
        """The bounds in force before iteration ``it`` of ``step``."""
        return bounds_at(self.fraction(step, it), self.preset.bounds)

    def after(self, step: int, it: int) -> tuple[int, int]:
        """``(step, iteration)`` that follows iteration ``it`` of ``step``."""
        return (step, it + 1) if it + 1 < self.preset.iterations[step] else (step + 1, 0)

    def plan(self, params: dict[str, Tensor], obs: Observations,
             resume: dict | None) -> Iterator[tuple[int, str, StepData, tuple[str, ...], int]]:
        """Restore ``params`` from ``resume`` (projected onto the bounds in force there), then
        yield ``(step index, step, data, free names, first iteration)`` for every step left
        to run; steps with no iterations or nothing to fit are skipped."""
        start_step, start_it = (resume["step"], resume["iteration"]) if resume is not None else (0, 0)
        if resume is not None:
            for k, v in resume["params"].items():
                params[k].data.copy_(v)
        project(params, self.bounds(start_step, start_it))
        for s, step in self.steps():
            if s < start_step or self.preset.iterations[s] == 0:
                continue
            free = free_names(step, params)
            if free:
                yield s, step, step_data(obs, step, self.preset.kernel), free, start_it if s == start_step else 0

    def after_iteration(self, step: int, it: int, loss: float, state: Callable[[], dict]) -> None:
        """Call after iteration ``it`` of ``step`` finished; ``state()`` resumes at the next one."""
        done = self.global_index(step, it) + 1
        self.history.append((done, STEP_NAMES[step], float(loss)))
        self.bar.update(1)
        self.bar.set_postfix(step=STEP_NAMES[step], loss=f"{loss:.4g}")
        stop = self.stop_after is not None and done >= self.stop_after
        if self.checkpointer.due(done) or stop:
            self.checkpointer.save({**state(), "history": list(self.history)})
        if stop and done < self.preset.total:
            self.close()
            raise FitInterrupted(f"stopped after {done} of {self.preset.total} iterations "
                                 f"(checkpoint {self.checkpointer.path})")

    def close(self) -> None:
        self.bar.close()
