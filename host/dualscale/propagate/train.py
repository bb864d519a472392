"""Training loop: presets, mixed precision, progress bar, resumable checkpoints, warm start.

Presets (``PRESETS``): ``paper`` is Section 7.4 (Adam, lr 0.002, batch 40, 5,000 iterations,
no weight decay, random weights; ~15 min on a 1080Ti, ~8 h on one busy CPU core).  ``balanced``,
``fast`` and ``quick`` cut the samples seen for CPU use and, since issue 29, start from the
packaged warm start :data:`WARM_START` (:func:`resolve_init`), run one cycle peaking at 0.01 and
take half their crops under the diffuse light; :data:`LEGACY_PRESETS` are the ones before.
docs/PROPAGATION.md ("Presets re-based") has their measured trade.

Mixed precision: bfloat16 autocast on the CPU, float16 autocast with gradient scaling on CUDA.

Speed (issue 29, docs/PROPAGATION.md "Training speed"): the model and its inputs are
channels-last (``TrainOptions.channels_last``, measured 1.05-1.08x per step on the CPU, same
accuracy); bf16 autocast stays on (float32 steps took 1.4-1.6x as long); ``TrainOptions.compile``
(``torch.compile`` of the U-Net, in place) is off: ~1.1x per step after a 250-270 s compile on
2 busy cores, which the ``fast`` and ``balanced`` presets do not win back.

Learning-rate schedule (``TrainOptions.schedule``, :mod:`.schedule`): ``"constant"`` (the
preset's ``lr``) or ``"onecycle"`` (``OneCycleLR`` peaking at the preset's ``lr``), stepped after
every optimiser step; its state is checkpointed.

Checkpoints: ``<model>.ckpt`` every ``checkpoint_every`` iterations and at the last one (model,
optimiser, scaler, scheduler, sampler RNG, iteration, the run's target iteration count); ``resume=True``
continues from it when it matches the run.  Checkpoints and the model file are written
atomically (:mod:`dualscale.formats.torchfile`), and the last checkpoint is written before the
model: a run killed while saving the model resumes by writing the model from it (no training),
also when the rerun's iteration count is lower than that finished run's.  A damaged checkpoint
or model file is a one-line :class:`~dualscale.errors.FormatError` naming it.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch

from dualscale.errors import FormatError, InputError
from dualscale.formats.torchfile import load_torch, save_torch

from .augment import BLUR_SIGMA, augment
from .data import DiskSource, Source, check_sources, sample_batch
from .model import load_model, save_model
from .losses import STYLE_WEIGHT, PropagationLoss
from .schedule import check_extend, make_schedule
from .unet import PropagationUNet, UNetConfig


@dataclass(frozen=True)
class Preset:
    """Optimisation settings; ``crop`` in pixels; ``schedule`` a key of
    :data:`~dualscale.propagate.schedule.SCHEDULES` (``lr`` is its peak for ``"onecycle"``);
    ``diffuse_fraction`` the share of crops under the diffuse light (:func:`~.data.sample_batch`);
    ``warm_start``: start from the packaged generic model :data:`WARM_START` where it fits
    (:func:`resolve_init`)."""

    name: str
    iterations: int
    batch: int
    lr: float = 0.002
    weight_decay: float = 0.0
    crop: int = 128
    schedule: str = "constant"
    diffuse_fraction: float = 0.0
    warm_start: bool = False

    def __post_init__(self) -> None:
        bad = []
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            bad.append(f"iterations must be at least 1, got {self.iterations}")
        if not (isinstance(self.batch, int) and self.batch >= 1):
            bad.append(f"batch must be at least 1, got {self.batch}")
        if not (isinstance(self.crop, int) and self.crop >= 16 and self.crop % 16 == 0):
            bad.append(f"crop must be a positive multiple of 16 px, got {self.crop}")
        if not self.lr > 0:
            bad.append(f"lr must be positive, got {self.lr}")
        if not 0 <= self.diffuse_fraction <= 1:
            bad.append(f"diffuse_fraction must be in [0, 1], got {self.diffuse_fraction}")
        if bad:
            raise ValueError(f"training preset {self.name!r}: " + "; ".join(bad))


PRESETS: dict[str, Preset] = {
    # Section 7.4 as printed: Adam at a constant 0.002, random weights, every light alike
    "paper": Preset("paper", 5000, 40),
    # issue 29 (docs/PROPAGATION.md "Presets re-based"): the packaged warm start, one cycle peaking
    # at 0.01, half the crops under the diffuse light; fast is a quarter of balanced's steps
    "balanced": Preset("balanced", 1000, 8, lr=0.01, schedule="onecycle", diffuse_fraction=0.5, warm_start=True),
    "fast": Preset("fast", 240, 8, lr=0.01, schedule="onecycle", diffuse_fraction=0.5, warm_start=True),
    "quick": Preset("quick", 100, 4, lr=0.01, schedule="onecycle", diffuse_fraction=0.5, warm_start=True),
}
LEGACY_PRESETS: dict[str, Preset] = {
    "balanced": Preset("balanced", 1000, 8), "fast": Preset("fast", 300, 8), "quick": Preset("quick", 100, 4),
}
"""The presets before issue 29 (constant lr 0.002, random weights, every light alike), for the
benchmark's old-against-new rows (``bench/bench_propagate_profile.py`` flag ``legacy``)."""


WARM_START = Path(__file__).resolve().parent / "models" / "warmstart_w16.dsp"
"""The packaged generic warm-start model (W = 16, decoder ratio 1/2, the woven-fabric maps;
``README.md`` next to it says how it was trained)."""


@dataclass
class TrainOptions:
    """Everything besides the preset; ``width=None`` picks 16 for one dataset, 32 for several.

    ``schedule``: the learning-rate schedule, a key of :data:`dualscale.propagate.schedule.SCHEDULES`
    (``"constant"``: the preset's ``lr``; ``"onecycle"``: one cycle peaking at the preset's ``lr``);
    ``None``: the preset's.

    ``style_weight``, ``style_triplets``: the style term's weight in the loss (``0`` drops it) and
    the random channel triplets it scores per step (:class:`~dualscale.propagate.losses.PropagationLoss`).

    ``diffuse_fraction``: the share of crops taken from the diffuse light, the guidance's lighting
    (:func:`~dualscale.propagate.data.sample_batch`); ``None``: the preset's.

    ``init``: a warm-start model file; ``"none"``: random weights; ``None``: the preset's
    (:func:`resolve_init`)."""

    width: int | None = None
    decoder_ratio: float = 0.5
    perceptual: str = "gram"
    amp: bool = True
    blur_sigma: tuple[float, float] = BLUR_SIGMA
    seed: int = 0
    checkpoint_every: int = 50
    resume: bool = False
    init: str | None = None
    progress: bool = True
    device: str = "cpu"
    channels_last: bool = True
    compile: bool = False
    schedule: str | None = None
    style_weight: float = STYLE_WEIGHT
    style_triplets: int = 2
    diffuse_fraction: float | None = None


@dataclass
class TrainResult:
    model: PropagationUNet
    iterations: int
    seconds: float
    resumed_from: int
    history: list[dict[str, float]]


def checkpoint_path(model_path: str | Path) -> Path:
    return Path(str(model_path) + ".ckpt")


def warm_start(model: PropagationUNet, path: str | Path) -> list[str]:
    """Copy every parameter of the model file at ``path`` whose name and shape match; returns them."""
    if not Path(path).is_file():
        raise InputError(f"warm-start model (--init) {path}: no such file; pass a dualscale propagation model "
                         "(.dsp), or --init none for random weights")
    try:
        src, _ = load_model(path)
    except (FormatError, InputError) as e:
        raise InputError(f"warm-start model (--init) {path} cannot be used: {str(e).split('; train it again')[0]}; pass a dualscale "
                         "propagation model (.dsp), or --init none for random weights") from None
    if src.config.width != model.config.width or src.config.decoder_ratio != model.config.decoder_ratio:
        raise InputError(f"warm-start model (--init) {path} has width {src.config.width}/decoder ratio "
                         f"{src.config.decoder_ratio}, this run needs {model.config.width}/"
                         f"{model.config.decoder_ratio}: pass --width {src.config.width}, or --init none")
    own = model.state_dict()
    copied = [k for k, v in src.state_dict().items() if k in own and own[k].shape == v.shape]
    model.load_state_dict({**own, **{k: src.state_dict()[k] for k in copied}})
    return copied


def input_reference(sources: list[Source | DiskSource]) -> list[float]:
    """Mean RGB of the training diffuse images (mean of all images when there is none)."""
    refs = []
    for s in sources:
        refs.append(s.diffuse_mean() if "diffuse" in s.light_names else s.mean_rgb())
    return [sum(r[c] for r in refs) / len(refs) for c in range(3)]


def _autocast(device: str, enabled: bool):
    dtype = torch.float16 if device.startswith("cuda") else torch.bfloat16
    return torch.autocast(device.split(":")[0], dtype=dtype, enabled=enabled)


def resolve_init(preset: Preset, opts: TrainOptions, config: UNetConfig) -> str | None:
    """The warm-start model of a run, or ``None`` (random weights): ``opts.init`` when given
    (``"none"``: random weights), else :data:`WARM_START` when ``preset.warm_start`` and the
    network is the packaged model's (width 16, decoder ratio 1/2; a wider network, e.g. W = 32 for
    several datasets, starts from random weights)."""
    if opts.init is not None:
        if not str(opts.init).strip():
            raise ValueError("init must name a warm-start model file, or be 'none' for random weights; got ''")
        return None if str(opts.init).lower() == "none" else str(opts.init)
    if preset.warm_start and (config.width, config.decoder_ratio) == (16, 0.5):
        return str(WARM_START)
    return None


def build(sources: list[Source | DiskSource], preset: Preset, opts: TrainOptions):
    """``(model, optimiser, gradient scaler, loss)`` of a training run, seeded by ``opts.seed``
    (the warm start of :func:`resolve_init` applied)."""
    maps = check_sources(sources)
    width = opts.width or (16 if len(sources) == 1 else 32)
    config = UNetConfig(tuple(maps), width, opts.decoder_ratio)
    torch.manual_seed(opts.seed)
    model = PropagationUNet(config).to(opts.device)
    init = resolve_init(preset, opts, config)
    if init:
        warm_start(model, init)
    if opts.channels_last:
        model = model.to(memory_format=torch.channels_last)
    if opts.compile:
        model.compile()  # in place: the state dict keeps its names
    optim = torch.optim.Adam(model.parameters(), lr=preset.lr, weight_decay=preset.weight_decay)
    cuda = opts.device.startswith("cuda")
    scaler = torch.amp.GradScaler("cuda", enabled=cuda and opts.amp)
    loss_fn = PropagationLoss(maps, opts.perceptual, opts.style_weight, opts.style_triplets).to(opts.device)
    return model, optim, scaler, loss_fn


def train(sources: list[Source | DiskSource], preset: Preset, out: str | Path, opts: TrainOptions = TrainOptions(),
          half_file: bool = False) -> TrainResult:
    """Train on ``sources`` and write the model file ``out`` (+ ``out.ckpt`` checkpoints)."""
    from tqdm import tqdm

    preset = asked = effective_preset(preset, opts)
    if opts.checkpoint_every < 1:
        raise ValueError(f"checkpoint_every must be at least 1 iteration, got {opts.checkpoint_every}")
    model, optim, scaler, loss_fn = build(sources, preset, opts)
    config = model.config
    # before the optimiser state is loaded: the scheduler sets the optimiser's lr when it is made
    sched = make_schedule(preset.schedule, optim, max(preset.iterations, 1), preset.lr)
    gen = torch.Generator().manual_seed(opts.seed)
    start, history = 0, []
    ckpt = checkpoint_path(out)
    # the run's identity; the iteration count may grow between resumes
    run_id = {"preset": {k: v for k, v in asdict(preset).items() if k != "iterations"},
              "config": config.to_json(), "sources": [s.name for s in sources]}
    if (opts.style_weight, opts.style_triplets) != (STYLE_WEIGHT, 2):  # keeps the default loss's identity
        run_id["style"] = [opts.style_weight, opts.style_triplets]
    init = resolve_init(preset, opts, config)
    if init is not None:  # a warm start is part of the run (cold runs keep their identity of before)
        run_id["init"] = Path(init).name
    elif preset.warm_start and opts.init is None:
        warnings.warn(f"preset {preset.name!r} warm-starts from {WARM_START.name}, a W = 16 network, but this one is "
                      f"W = {config.width}, decoder ratio {config.decoder_ratio:g}: training from random weights "
                      "(one cycle at the preset's peak lr; compare with --schedule constant --lr 0.002)", stacklevel=2)
    if preset.diffuse_fraction and not any("diffuse" in s.light_names for s in sources):
        warnings.warn(f"diffuse_fraction {preset.diffuse_fraction:g} has no effect: no training source has a diffuse "
                      "light (it needs every dome LED); every crop draws a light uniformly", stacklevel=2)
        preset = replace(preset, diffuse_fraction=0.0)  # what is used; the record keeps the preset as asked
    if opts.resume and ckpt.is_file():
        st = load_torch(ckpt, "training checkpoint", "delete it (training restarts) or drop --resume",
                        map_location=opts.device)
        if not isinstance(st, dict) or st.get("run") != run_id:
            raise ValueError(f"checkpoint {ckpt} belongs to a different run (preset, maps or datasets differ); "
                             "delete it or drop --resume")
        try:
            model.load_state_dict(st["model"])
            optim.load_state_dict(st["optim"])
            scaler.load_state_dict(st["scaler"])
            gen.set_state(st["gen"])
            start, history = int(st["iteration"]), list(st["history"])
            if sched is not None:
                sched.load_state_dict(st["sched"])
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise FormatError(f"{ckpt}: damaged training checkpoint ({type(e).__name__}: "
                              f"{(str(e).splitlines() or [''])[0][:160]}); delete it (training restarts) or drop "
                              "--resume") from None
        if start > preset.iterations:
            if st.get("target") != start:
                raise ValueError(f"checkpoint {ckpt} is at iteration {start}, beyond this run's {preset.iterations}; "
                                 f"pass --iterations {start} or more to continue it, or delete it")
            # a finished run whose model was not written (killed while saving it): write it now
            preset, asked = replace(preset, iterations=start), replace(asked, iterations=start)
        # start == iterations: a run stopped after its last checkpoint; the loop is empty, the model is written
        check_extend(preset.schedule, ckpt, st.get("target"), preset.iterations)
    t0 = time.perf_counter()
    model.train()
    bar = tqdm(range(start, preset.iterations), initial=start, total=preset.iterations, disable=not opts.progress,
               desc=f"propagate train ({preset.name})", unit="it")
    for it in bar:
        lr = optim.param_groups[0]["lr"]
        loss, parts = train_step(model, optim, scaler, loss_fn, sources, preset, gen, opts, it)
        if sched is not None:
            sched.step()
        history.append({"it": it + 1, "loss": loss, "lr": lr, **parts})
        bar.set_postfix(loss=f"{history[-1]['loss']:.4f}")
        done = it + 1
        if done % opts.checkpoint_every == 0 or done == preset.iterations:
            _save_checkpoint(ckpt, model, optim, scaler, gen, done, history, run_id, preset.iterations, sched)
    seconds = time.perf_counter() - t0
    model.eval().cpu()
    info: dict[str, Any] = {"preset": asdict(asked), "iterations": preset.iterations, "seconds_this_run": seconds,
                            "resumed_from": start, "datasets": [s.name for s in sources],
                            "perceptual": opts.perceptual, "amp": opts.amp,
                            "init": init,
                            "schedule": preset.schedule, "style": [opts.style_weight, opts.style_triplets],
                            "diffuse_fraction": preset.diffuse_fraction,
                            "blur_sigma": list(opts.blur_sigma), "final": history[-1] if history else {}}
    save_model(out, model, input_reference(sources), info, half=half_file)
    return TrainResult(model, preset.iterations, seconds, start, history)


PHASES = ("data.crops", "data.augment", "forward", "loss", "backward", "optimiser")
"""The parts of :func:`train_step`, in order."""


def _phase(name: str):
    return contextlib.nullcontext()


def train_step(model: PropagationUNet, optim, scaler, loss_fn: PropagationLoss, sources: list[Source | DiskSource],
               preset: Preset, gen: torch.Generator, opts: TrainOptions, it: int = 0,
               phase=_phase) -> tuple[float, dict]:
    """One optimisation step on a fresh random batch; returns ``(loss, {part: value})``.

    ``phase(name)``: a context manager around each part of the step (``data.crops``,
    ``data.augment``, ``forward``, ``loss``, ``backward``, ``optimiser``), for the profiler
    (bench/bench_propagate_profile.py); a no-op by default.  A non-finite loss is a
    :class:`FloatingPointError` naming iteration ``it + 1``."""
    with phase("data.crops"):
        x, y = sample_batch(sources, preset.batch, preset.crop, gen, preset.diffuse_fraction)
    with phase("data.augment"):
        x = augment(x, gen, len(sources), opts.blur_sigma).to(opts.device)
        if opts.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        y = {k: v.to(opts.device) for k, v in y.items()}
    with phase("forward"):
        with _autocast(opts.device, opts.amp):
            pred = model.split(model(x))
    with phase("loss"):
        loss, parts = loss_fn(pred, y, gen)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss became {float(loss.detach())} at iteration {it + 1}")
    with phase("backward"):
        optim.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
    with phase("optimiser"):
        scaler.step(optim)
        scaler.update()
    return float(loss.detach()), parts


def _save_checkpoint(path: Path, model, optim, scaler, gen, iteration: int, history, run_id, target: int,
                     sched=None) -> None:
    """Write the checkpoint atomically; ``target``: the iteration count of this run (a checkpoint
    with ``iteration == target`` is a finished run); ``sched``: the learning-rate scheduler, if any."""
    st = {"model": model.state_dict(), "optim": optim.state_dict(), "scaler": scaler.state_dict(),
          "gen": gen.get_state(), "iteration": iteration, "history": history, "run": run_id, "target": target}
    if sched is not None:
        st["sched"] = sched.state_dict()
    save_torch(path, st)


def effective_preset(preset: Preset, opts: TrainOptions) -> Preset:
    """``preset`` with the options' ``schedule`` and ``diffuse_fraction`` where they are set."""
    over = {"schedule": opts.schedule, "diffuse_fraction": opts.diffuse_fraction}
    return replace(preset, **{k: v for k, v in over.items() if v is not None})


def preset_with(name: str, **overrides: Any) -> Preset:
    """A named preset with some fields replaced (``None`` values are ignored)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return replace(PRESETS[name], **{k: v for k, v in overrides.items() if v is not None})
