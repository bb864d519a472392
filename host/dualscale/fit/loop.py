"""What the optimisers share: per-step data, free/frozen split, progress and checkpoints."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from torch import Tensor
from tqdm import tqdm

from dualscale.bsdf import Components

from .checkpoint import Checkpointer, FitInterrupted
from .init import diffuse_images
from .observations import Observations
from .presets import STEP_DATA, STEP_FITS, STEP_NAMES, Preset
from .render import clamp_images


@dataclass
class StepData:
    """Observations of one step with their images clamped at 2 (LED and back-lit)."""

    obs: Observations
    images: Tensor
    back: Tensor | None


def step_data(obs: Observations, step: str) -> StepData:
    o = diffuse_images(obs) if STEP_DATA[step] == "diffuse" else obs
    back = None if o.backlight is None else clamp_images(o.backlight)
    return StepData(o, clamp_images(o.images), back)


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
