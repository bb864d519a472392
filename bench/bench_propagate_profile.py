"""Where a propagation training step spends its time (issue 29 §1): prints markdown tables.

    PYTHONPATH=host python bench/bench_propagate_profile.py [--work /tmp/propbench] [--presets fast,balanced]
        [--steps 6] [--warmup 2] [--threads 1] [--variants base,...]

Trains on the twill micro dataset of bench/bench_propagate.py (``prep`` stage, made here when
missing: 256^2 at 6 um, 127 LEDs P0/P90 + the synthesised diffuse image) with the real training
step (:func:`dualscale.propagate.train.train_step`, the model of :func:`~dualscale.propagate.train.build`).

Three tables per preset (the step depends on the preset's batch and crop only: ``fast`` and
``balanced`` are both 8 x 128^2 and differ in their iteration count):

* **phases**: wall time per step of the data pipeline (``data.crops``: random crops out of the
  float16 images; ``data.augment``: blur and colour gains), forward, loss, backward, optimiser;
  median over ``--steps`` timed steps after ``--warmup``, no profiler attached.
* **operators**: torch.profiler self CPU time per ATen operator over ``--steps`` steps.
* **network parts**: forward (module pre/post hooks) and backward (module full backward
  pre/post hooks) wall time of every encoder level, the bottleneck, each decoder level summed over
  the decoders (level 1 = full resolution) and the heads; measured in a third pass (the hooks add a
  little overhead; the shares are what matters).

``--accuracy N`` trains each of ``--variants`` for ``N`` iterations of the preset and scores it on
the benchmark's twill guidance (every map's L1 and SSIM), old and new in the same run.

``--variants`` (comma list, each a ``+``-joined set of ``base`` (bf16 autocast, contiguous, eager:
the default before issue 29), ``fp32`` (no autocast), ``cl`` (channels-last: today's default),
``compile``) times several settings of the step, alternated step by step.  The profile tables
use today's defaults (:class:`~dualscale.propagate.train.TrainOptions`).

With ``--accuracy`` more flags choose the recipe (issue 29 §2, "Schedule and warm start"). A
variant starts from the named preset as it is today (:data:`~dualscale.propagate.train.PRESETS`),
or as it was before issue 29 with ``legacy`` (:data:`~dualscale.propagate.train.LEGACY_PRESETS`:
constant lr 0.002, random weights, every light alike); the other flags change it:
``warm`` (warm start from the packaged ``warmstart_w16.dsp``, or ``--warm``), ``cold`` (random
weights), ``ocN`` (one-cycle learning rate, peak ``N / 1000``: ``oc8`` peaks at 0.008), ``dfN``
(``N`` % of the crops under the diffuse light), ``stN`` (``N`` style triplets per step, ``st0``
no style term), ``cropN`` (``N`` px crops), ``bN`` (batch ``N`` with the iteration count scaled
so that the samples stay ``N_iterations x preset batch``: ``b16`` on ``fast`` at 300 is 150 x 16)
and ``itsN`` (``N`` iterations, whatever ``--accuracy`` says), e.g.
``--variants cl+legacy,cl+warm+oc8,cl+warm+oc8+b16``.  The step timings (``--variants`` without
``--accuracy``) take every flag; those that change only the run's length or start (``warm``,
``ocN``, ``itsN``) leave the step as it is.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from dualscale.propagate.train import PHASES  # noqa: E402



REPO = Path(__file__).resolve().parent.parent
from dualscale.propagate.train import WARM_START as WARM  # noqa: E402
STEP_FLAGS = {"base", "fp32", "cl", "compile"}
WARM_FILE = [WARM]  # the ``warm`` flag's model; ``--warm`` replaces it


def recipe(variant: str, preset_name: str, iterations: int):
    """``(TrainOptions, Preset)`` of an ``--accuracy`` variant (the flags of the module docstring)."""
    import re

    from dualscale.propagate.train import LEGACY_PRESETS, TrainOptions, preset_with

    flags = set(variant.split("+"))
    base = LEGACY_PRESETS[preset_name] if "legacy" in flags else preset_with(preset_name)
    over: dict = {"iterations": iterations}
    schedule = None  # the preset's
    over_opts: dict = {}
    for f in flags - STEP_FLAGS - {"warm", "cold", "legacy"}:
        if m := re.fullmatch(r"oc(\d+)", f):
            schedule, over["lr"] = "onecycle", int(m[1]) / 1000
        elif m := re.fullmatch(r"st(\d+)", f):
            over_opts["style_triplets"] = int(m[1])
            if not int(m[1]):
                over_opts["style_weight"] = 0.0
        elif m := re.fullmatch(r"df(\d+)", f):
            over_opts["diffuse_fraction"] = int(m[1]) / 100
        elif m := re.fullmatch(r"crop(\d+)", f):
            over["crop"] = int(m[1])
        elif m := re.fullmatch(r"b(\d+)", f):
            over["batch"] = int(m[1])
            over["iterations"] = max(1, round(iterations * base.batch / int(m[1])))
        elif not re.fullmatch(r"its(\d+)", f):
            raise SystemExit(f"unknown variant flag {f!r}")
    for f in flags:  # after bN: an explicit iteration count wins
        if m := re.fullmatch(r"its(\d+)", f):
            over["iterations"] = int(m[1])
    opts = TrainOptions(amp="fp32" not in flags, channels_last="cl" in flags, compile="compile" in flags,
                        progress=False, checkpoint_every=10 ** 9, schedule=schedule,
                        init=str(WARM_FILE[0]) if "warm" in flags else ("none" if flags & {"cold", "legacy"} else None),
                        **over_opts)
    return opts, replace(base, **over)


def load() -> str:
    return open("/proc/loadavg").read().split()[0]


def source(work: Path):
    from bench_propagate import EVAL, prep

    from dualscale.propagate.data import load_source

    if not (work / EVAL / "micro" / "manifest.json").is_file():
        prep(work)
    return load_source(work / EVAL)


def make_step(src, preset_name: str, variant: str, seed: int = 0):
    """``(step(phase) -> loss, model, preset)`` for one variant of the training step (any flags of
    :func:`recipe`; those that change only the run's length or start, ``warm``, ``ocN``, ``itsN``,
    leave the step as it is)."""
    from dualscale.propagate.train import build, effective_preset, train_step

    opts, preset = recipe(variant, preset_name, 1)
    opts = replace(opts, seed=seed, init="none", schedule="constant")
    preset = effective_preset(preset, opts)
    model, optim, scaler, loss_fn = build([src], preset, opts)
    gen = torch.Generator().manual_seed(seed)
    model.train()
    it = [0]

    def step(phase=None):
        kw = {"phase": phase} if phase else {}
        loss, _ = train_step(model, optim, scaler, loss_fn, [src], preset, gen, opts, it[0], **kw)
        it[0] += 1
        return loss

    return step, model, preset


def phase_times(step, steps: int) -> dict[str, list[float]]:
    out: dict[str, list[float]] = defaultdict(list)
    for _ in range(steps):
        acc: dict[str, float] = {}

        @contextmanager
        def phase(name):
            t = time.perf_counter()
            yield
            acc[name] = time.perf_counter() - t

        t0 = time.perf_counter()
        step(phase)
        out["step"].append(time.perf_counter() - t0)
        for k, v in acc.items():
            out[k].append(v)
    return out


def operator_table(step, steps: int, top: int) -> list[tuple[str, float, int]]:
    from torch.profiler import ProfilerActivity, profile, record_function

    @contextmanager
    def phase(name):
        with record_function(name):
            yield

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            step(phase)
    rows = [(e.key, e.self_cpu_time_total / steps / 1e3, e.count // steps) for e in prof.key_averages()
            if not e.key.startswith("data.") and e.key not in PHASES and not e.key.startswith("ProfilerStep")]
    rows.sort(key=lambda r: -r[1])
    return rows[:top], sum(r[1] for r in rows)


def part_names(model) -> dict[str, str]:
    """module path -> part of the network."""
    parts = {}
    for i in range(len(model.enc)):
        parts[f"enc.{i}"] = f"encoder level {i + 1}"
    parts["bottleneck"] = "bottleneck (1/16)"
    for m in model.config.maps:
        n = len(model.decoders[m].ups)
        for j in range(n):
            level = n - j  # ups[0] is the coarsest step; level 1 = full resolution
            parts[f"decoders.{m}.ups.{j}"] = f"decoders, level {level}"
            parts[f"decoders.{m}.blocks.{j}"] = f"decoders, level {level}"
        parts[f"decoders.{m}.head"] = "decoder heads (1x1)"
    return parts


def part_times(step, model, steps: int) -> tuple[dict[str, float], dict[str, float], float, float]:
    """Forward and backward seconds per step of each part, plus the whole forward and backward."""
    names = part_names(model)
    fwd: dict[str, float] = defaultdict(float)
    bwd: dict[str, float] = defaultdict(float)
    starts: dict[str, float] = {}
    handles = []
    mods = dict(model.named_modules())
    for path, part in names.items():
        mod = mods[path]

        def pre(m, inp, path=path):
            starts["f" + path] = time.perf_counter()

        def post(m, inp, out, path=path, part=part):
            fwd[part] += time.perf_counter() - starts["f" + path]

        def bpre(m, gout, path=path):
            starts["b" + path] = time.perf_counter()

        def bpost(m, gin, gout, path=path, part=part):
            bwd[part] += time.perf_counter() - starts["b" + path]

        handles += [mod.register_forward_pre_hook(pre), mod.register_forward_hook(post),
                    mod.register_full_backward_pre_hook(bpre), mod.register_full_backward_hook(bpost)]
    tot: dict[str, float] = defaultdict(float)

    @contextmanager
    def phase(name):
        t = time.perf_counter()
        yield
        tot[name] += time.perf_counter() - t

    try:
        for _ in range(steps):
            step(phase)
    finally:
        for h in handles:
            h.remove()
    return ({k: v / steps for k, v in fwd.items()}, {k: v / steps for k, v in bwd.items()},
            tot["forward"] / steps, tot["backward"] / steps)


def profile_preset(src, preset: str, steps: int, warmup: int, top: int) -> None:
    step, model, p = make_step(src, preset, "cl")
    for _ in range(warmup):
        step()
    l0 = load()
    ph = phase_times(step, steps)
    med = {k: statistics.median(v) for k, v in ph.items()}
    print(f"\n### `{preset}`: {p.iterations} iterations x batch {p.batch}, crop {p.crop}, bf16 autocast, "
          f"channels-last, {torch.get_num_threads()} thread(s); load {l0} -> {load()}\n")
    print(f"Phases, median of {steps} steps (no profiler):\n")
    print("| phase | s / step | share |\n|---|---:|---:|")
    for k in PHASES:
        print(f"| {k} | {med[k]:.3f} | {100 * med[k] / med['step']:.1f} % |")
    print(f"| **step** | **{med['step']:.3f}** | |")
    print(f"\nAt this rate the preset's {p.iterations} steps take ~{med['step'] * p.iterations:.0f} s.")
    rows, total = operator_table(step, steps, top)
    print(f"\nOperators (torch.profiler self CPU time, mean per step over {steps} steps; all operators "
          f"{total:.0f} ms):\n")
    print("| operator | ms / step | share | calls / step |\n|---|---:|---:|---:|")
    for k, ms, n in rows:
        print(f"| `{k}` | {ms:.1f} | {100 * ms / total:.1f} % | {n} |")
    fwd, bwd, ft, bt = part_times(step, model, steps)
    print(f"\nNetwork parts (module hooks, mean per step over {steps} steps; forward {ft:.3f} s, backward "
          f"{bt:.3f} s; the rest of each is the output activations, the concatenations and autograd "
          "bookkeeping):\n")
    print("| part | forward [s] | share of forward | backward [s] | share of backward |\n|---|---:|---:|---:|---:|")
    order = sorted(set(fwd) | set(bwd), key=lambda k: (not k.startswith("enc"), not k.startswith("bott"),
                                                        k.startswith("decoder heads"), k))
    for k in order:
        print(f"| {k} | {fwd.get(k, 0):.3f} | {100 * fwd.get(k, 0) / ft:.1f} % | {bwd.get(k, 0):.3f} | "
              f"{100 * bwd.get(k, 0) / bt:.1f} % |")


def compare_variants(src, preset: str, variants: list[str], steps: int, warmup: int) -> None:
    built = {}
    for v in variants:
        t = time.perf_counter()
        step, _, _ = make_step(src, preset, v)
        first = time.perf_counter()
        step()  # the first step compiles, when compiling
        built[v] = (step, time.perf_counter() - first, first - t)
        for _ in range(warmup):
            step()
    times: dict[str, list[float]] = defaultdict(list)
    l0 = load()
    for _ in range(steps):  # alternated, so that a changing load hits every variant alike
        for v in variants:
            t = time.perf_counter()
            built[v][0]()
            times[v].append(time.perf_counter() - t)
    ref = statistics.median(times[variants[0]])
    print(f"\nVariants of the `{preset}` step, {torch.get_num_threads()} thread(s), median of {steps} alternated "
          f"steps after {warmup} warm-up; load {l0} -> {load()}:\n")
    print(f"| variant | s / step (min-max) | {variants[0]} / variant | first step [s] |\n|---|---:|---:|---:|")
    for v in variants:
        t = times[v]
        print(f"| {v} | {statistics.median(t):.3f} ({min(t):.3f}-{max(t):.3f}) | "
              f"{ref / statistics.median(t):.2f} | {built[v][1]:.1f} |")


def accuracy(work: Path, preset: str, variants: list[str], iterations: int, json_out: str | None = None) -> None:
    """Train ``iterations`` steps of ``preset`` per variant (same seed, one after the other) and
    score each on the benchmark's guidance (bench_propagate.scores: ORT fp32, 256 px tiles)."""
    from bench_propagate import EVAL, score_pairs, scores, write_rows

    from dualscale.propagate.data import load_source
    from dualscale.propagate.train import train

    src = load_source(work / EVAL)
    rows = []
    start = load()
    for v in variants:
        opts, p = recipe(v, preset, iterations)
        tag = f"{v.replace('+', '_')}_{p.iterations}" + (f"_{WARM_FILE[0].stem}" if opts.init else "")
        model = work / f"variant_{tag}.dsp"  # one file per run: several benches may share the work folder
        for f in (model, Path(str(model) + ".ckpt")):
            f.unlink(missing_ok=True)
        l0 = load()
        t = time.perf_counter()
        train([src], p, model, opts)
        sec = time.perf_counter() - t
        rows.append((f"{v} ({p.iterations} x {p.batch}, lr {p.lr:g} {opts.schedule or p.schedule})", sec, l0, load(),
                     scores(work, model, work / f"pred_variant_{tag}"), v))
        sc = rows[-1][4]
        print(f"{rows[-1][0]}: {sec:.0f} s, load {l0}-{rows[-1][3]}, {time.strftime('%H:%M')}; "
              + ", ".join(f"{m} {sc[m]['l1']:.4f}/{sc[m]['ssim']:.3f}" for m in sc), file=sys.stderr, flush=True)
    maps = list(rows[0][4])
    print(f"\nAccuracy of the variants: `{preset}` at {iterations} iterations' samples, same seed, trained one after "
          f"the other; L1 / SSIM on the twill guidance:\n")
    print("| variant | train [s] (load) | " + " | ".join(maps) + " |\n|---|---:|" + "---:|" * len(maps))
    for v, sec, l0, l1, sc, _ in rows:
        print(f"| {v} | {sec:.0f} ({l0}-{l1}) | " + " | ".join(f"{sc[m]['l1']:.4f} / {sc[m]['ssim']:.3f}" for m in maps)
              + " |")
    if json_out:  # the variants share a preset: a figure of their own, not the trade data (one point per preset)
        points = []
        for _, sec, l0, l1, sc, v in rows:
            opts, p = recipe(v, preset, iterations)
            legacy = "legacy" in v.split("+")
            warm = opts.init not in (None, "none") or (opts.init is None and p.warm_start)
            points.append({"label": f"{'legacy-' if legacy else ''}{preset} {p.iterations} its, {v}", "kind": "preset",
                           "preset": f"legacy-{preset}" if legacy else preset, "variant": v, "warm_start": bool(warm),
                           "iterations": p.iterations, "batch": p.batch, "seconds": float(f"{sec:.4g}"),
                           "load": float(l0), "maps": score_pairs(sc)})
        write_rows(json_out, f"variants of {preset} at {iterations} iterations", points, start)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="/tmp/propbench")
    ap.add_argument("--presets", default="fast,balanced")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--top", type=int, default=15, help="operators listed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--variants", help="compare these step variants instead of profiling, e.g. base,fp32,cl")
    ap.add_argument("--accuracy", type=int, metavar="ITERATIONS",
                    help="with --variants: train each variant this many iterations and score it on the guidance")
    ap.add_argument("--warm", help=f"model file of the 'warm' flag (default: {WARM.name}, packaged)")
    ap.add_argument("--json", help="with --accuracy: also write the rows as JSON to this file (one preset)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.warm:
        WARM_FILE[0] = Path(a.warm)
    import platform

    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {os.cpu_count()} cores "
          f"({platform.processor() or platform.machine()}), load {load()}, {time.strftime('%Y-%m-%d %H:%M')}")
    src = source(Path(a.work))
    if a.accuracy:
        if not (Path(a.work) / "guide" / "guidance.exr").is_file():
            from bench_propagate import prep

            prep(Path(a.work))
        for preset in a.presets.split(","):
            accuracy(Path(a.work), preset, (a.variants or "base").split(","), a.accuracy, a.json)
        return 0
    for preset in a.presets.split(","):
        if a.variants:
            compare_variants(src, preset, a.variants.split(","), a.steps, a.warmup)
        else:
            profile_preset(src, preset, a.steps, a.warmup, a.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
