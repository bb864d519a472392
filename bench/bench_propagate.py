"""Mesoscale propagation benchmark: prints markdown tables for docs/PROPAGATION.md.

    PYTHONPATH=host python bench/bench_propagate.py [--work /tmp/propbench] [--stages ...]

Stages: ``prep`` (synthetic data: twill micro dataset 256^2 at 6 um/texel, all 127 LEDs,
P0/P90; guidance = twill, another seed, 768^2 at the same texel size, diffuse group, no
analyser), ``warm`` (train the generic warm-start model on plain/satin/denim), ``presets``
(cold and warm-started training, scores on the guidance), ``parity`` (ONNX fp32/fp16),
``seams`` (border vs interior error), ``big`` (4072^2 inference: the runs of ``--big-configs``,
before and after issue 15 side by side, each in a child process, interleaved ``--big-repeats`` times;
time, peak memory, int8's accuracy), ``profile`` (onnxruntime per op type and network part,
optimisation levels, precisions, tile size against overlap), ``bridge-reg`` (locating the micro
field in the guidance: error against the truth from shifted priors) and ``bridge`` (propagation accuracy with the micro data resampled to the
guidance texel vs trained at the micro texel on an enlarged guidance) and ``real`` (the warm-start
model on the real fabric photos of ../shared/data/fabric-rt); the last three are not in the default
list.
Everything is cached under ``--work``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dualscale.propagate.train import WARM_START

TEXEL_UM = 6.0
MICRO = 256
GUIDE = 768
EVAL = "twill"
WARM_MATERIALS = ("plain", "satin", "denim")
THREADS = 1  # training threads; set by --threads



def constant_maps(train_maps: dict[str, np.ndarray], shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """The per-map constant predictor: each map's mean over the training maps (the normal's
    renormalised, the axial tangent's circular mean), broadcast to ``shape`` (H, W)."""
    out = {}
    for m, v in train_maps.items():
        if m == "normal":
            mean = v.mean((0, 1))
            mean = mean / np.linalg.norm(mean)
        elif m == "tangent":
            a = 2 * np.pi * v[..., 0]
            mean = np.array([np.mod(np.arctan2(np.sin(a).mean(), np.cos(a).mean()), 2 * np.pi) / (2 * np.pi)])
        else:
            mean = v.mean((0, 1))
        out[m] = np.broadcast_to(mean, tuple(shape) + (v.shape[-1],)).astype(np.float32)
    return out


def sh(*args: str) -> None:
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    subprocess.run([sys.executable, "-m", "dualscale.cli", *args], check=True, stdout=subprocess.DEVNULL, env=env)


def load() -> str:
    return open("/proc/loadavg").read().split()[0]


def machine() -> str:
    """The machine, in words, for the JSON rows (cores, CPU, torch, training threads)."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{os.cpu_count()}-core {cpu}, torch {torch.__version__}, {THREADS} torch thread(s)"


def write_rows(path: str | Path, name: str, points: list[dict], load0: str) -> None:
    """Write one run's points (the layout of ``dualscale.report.trade``'s points) as JSON to
    ``path`` through a temp file and a rename: ``{"name", "date", "machine", "load", "points"}``
    (``load``: the 1-min load average at the start and the end).  ``bench_propagate_trade.py``
    collects these files into the package's trade data."""
    from dualscale.formats.atomic import write_json

    write_json(path, {"name": name, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "machine": machine(),
                      "load": f"{load0}-{load()}", "points": points})


def score_pairs(sc: dict) -> dict[str, list[float]]:
    """``compare``'s ``{map: {"l1", "ssim"}}`` as the trade data's ``{map: [l1, ssim]}``."""
    return {m: [round(float(v["l1"]), 5), round(float(v["ssim"]), 4)] for m, v in sc.items()}


def prep(work: Path) -> None:
    from dualscale.geometry.cameras import micro_camera
    from dualscale.formats.exr import write_exr
    from dualscale.sim.render import LightState, render
    from dualscale.sim.materials import generate
    from dualscale.formats.maps import save_maps

    for m in (EVAL, *WARM_MATERIALS):
        if not (work / m / "micro" / "manifest.json").is_file():
            sh("synth", m, "-o", str(work / m), "--size", str(MICRO), "--texel-um", str(TEXEL_UM), "--dataset",
               "--no-previews")
    g = work / "guide"
    if not (g / "guidance.exr").is_file():
        mat = generate(EVAL, GUIDE, TEXEL_UM / 1000, seed=1)
        img = render(mat.maps, micro_camera(GUIDE, TEXEL_UM), LightState.diffuse_group())
        save_maps(g / "gt", mat.maps, mat.meta, previews=False)
        write_exr(g / "guidance.exr", img.numpy())


def scores(work: Path, model: Path, out: Path, tile: int = 256, overlap: int = 64) -> dict:
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.export import export_model, onnx_paths
    from dualscale.propagate.infer import OnnxModel, run_tiled
    from dualscale.propagate.metrics import compare

    export_model(model, check=False)
    run_tiled(OnnxModel.open(onnx_paths(model)[0]), work / "guide" / "guidance.exr", out, tile, overlap,
              progress=False)
    pred, _ = load_maps(out)
    gt, _ = load_maps(work / "guide" / "gt")
    return compare({k: v.numpy() for k, v in pred.items()}, {k: v.numpy() for k, v in gt.items()})


def train_cmd(work: Path, sources: list[str], out: Path, preset: str, extra: list[str]) -> float:
    t = time.perf_counter()
    sh("propagate", "train", *sources, "-o", str(out), "--preset", preset, "--no-progress", "--threads",
       str(THREADS), *extra)
    return time.perf_counter() - t


def stage_warm(work: Path, repo: Path, iterations: int, batch: int, seeds: tuple[int, ...] = (0,),
               out: Path | None = None, schedule: str = "constant", lr: float = 0.002) -> None:
    """Train the generic warm-start model on ``WARM_MATERIALS`` (never ``EVAL``), one dataset per
    material and seed (seed 0 is the prep stage's, others are made here), and save it as float16 at
    ``out`` (default ``WARM_START``, the packaged model); does nothing when ``out`` exists."""
    out = out or WARM_START
    if out.is_file():
        return
    from dualscale.propagate.data import load_source
    from dualscale.propagate.train import TrainOptions, preset_with, train

    names = []
    for m in WARM_MATERIALS:
        for seed in seeds:
            name = m if seed == 0 else f"{m}_s{seed}"
            if not (work / name / "micro" / "manifest.json").is_file():
                sh("synth", m, "-o", str(work / name), "--size", str(MICRO), "--texel-um", str(TEXEL_UM),
                   "--seed", str(seed), "--dataset", "--no-previews")
            names.append(name)
    srcs = [load_source(work / n) for n in names]
    t, l0 = time.perf_counter(), load()
    r = train(srcs, preset_with("fast", iterations=iterations, batch=batch, lr=lr), work / f"{out.stem}_full.dsp",
              TrainOptions(width=16, progress=False, schedule=schedule, checkpoint_every=100, resume=True),
              half_file=False)
    from dualscale.propagate.model import save_model
    from dualscale.propagate.train import input_reference

    save_model(out, r.model, input_reference(srcs), {"materials": list(WARM_MATERIALS), "seeds": list(seeds),
                                                      "iterations": iterations, "batch": batch, "lr": lr,
                                                      "schedule": schedule, "seconds": time.perf_counter() - t,
                                                      "load": [l0, load()], "texel_um": TEXEL_UM, "size": MICRO},
               half=True)
    print(f"warm-start model {out}: {len(srcs)} datasets, {iterations} its x batch {batch}, lr {lr:g} {schedule}, "
          f"{time.perf_counter() - t:.0f} s, load {l0}-{load()}")


def stage_presets(work: Path, repo: Path, runs: list[str], json_out: str | None = None) -> None:
    from dualscale.propagate.train import PRESETS

    rows = []
    start = load()
    for run in runs:  # e.g. quick, fast, quick+warm
        preset, _, warm = run.partition("+")
        extra = ["--init", str(WARM_START)] if warm else []
        model = work / f"model_{preset}{'_warm' if warm else ''}.dsp"
        for f in (model, Path(str(model) + ".ckpt")):
            f.unlink(missing_ok=True)
        load0 = load()
        sec = train_cmd(work, [str(work / EVAL)], model, preset, extra)
        sc = scores(work, model, work / f"pred_{model.stem}")
        rows.append((run, sec, load0, sc))
        print(f"{run}: {sec:.0f} s, load {load0}", file=sys.stderr)
    maps = list(rows[0][3])
    print("\n| run | train time [s] (load) | " + " | ".join(f"{m} L1 / SSIM" for m in maps) + " |")
    print("|---|---:|" + "---:|" * len(maps))
    for run, sec, l0, sc in rows:
        print(f"| {run} | {sec:.0f} ({l0}) | " + " | ".join(f"{sc[m]['l1']:.3f} / {sc[m]['ssim']:.2f}" for m in maps)
              + " |")
    if json_out:
        write_rows(json_out, "presets", [
            {"label": run.replace("+warm", " + warm start"), "kind": "preset", "preset": run.partition("+")[0],
             "warm_start": bool(run.partition("+")[2]), "iterations": PRESETS[run.partition("+")[0]].iterations,
             "batch": PRESETS[run.partition("+")[0]].batch, "seconds": float(f"{sec:.4g}"), "load": float(l0),
             "maps": score_pairs(sc)} for run, sec, l0, sc in rows], start)


def stage_parity(work: Path) -> None:
    from dualscale.propagate.export import export_model

    model = sorted(work.glob("model_*.dsp"))[0]
    out = export_model(model)
    print(f"\nONNX parity ({model.name}, random 2x3x64x64 radiance):\n")
    print("| map | fp32 max abs diff | fp16 max abs diff |\n|---|---:|---:|")
    for m in out["parity_fp32"]:
        print(f"| {m} | {out['parity_fp32'][m]:.2e} | {out['parity_fp16'][m]:.2e} |")


def stage_seams(work: Path, tile: int = 128) -> None:
    """Error within 4 px of inner tile borders vs elsewhere, blended vs naive (no overlap)."""
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.export import onnx_paths
    from dualscale.propagate.infer import OnnxModel, run_tiled, tile_positions

    model = sorted(work.glob("model_*.dsp"))[0]
    gt, _ = load_maps(work / "guide" / "gt")
    print(f"\nSeams ({model.name}, tile {tile}; border = within 4 px of an inner tile edge):\n")
    print("| tiling | map | border L1 | interior L1 | ratio |\n|---|---|---:|---:|---:|")
    for overlap in (0, 32):
        out = work / f"seams_{overlap}"
        run_tiled(OnnxModel.open(onnx_paths(model)[0]), work / "guide" / "guidance.exr", out, tile, overlap,
                  progress=False)
        pred, _ = load_maps(out)
        edges = [p for p in tile_positions(GUIDE, tile, tile - overlap)[1:]]
        if overlap:  # blended: the seam would be where weights switch, anywhere in the overlap
            edges = sorted({p + d for p in edges for d in range(0, overlap, 8)})
        band = np.zeros(GUIDE, bool)
        for p in edges:
            band[max(0, p - 4):p + 4] = True
        mask = band[:, None] | band[None, :]
        for m in ("albedo", "normal", "roughness"):
            err = np.abs(pred.__dict__[m].numpy() - gt.__dict__[m].numpy()).mean(-1)
            b, i = err[mask].mean(), err[~mask].mean()
            print(f"| {'raised-cosine, overlap ' + str(overlap) if overlap else 'naive, no overlap'} | {m} | "
                  f"{b:.4f} | {i:.4f} | {b / i:.3f} |")


def _big_inputs(work: Path, repo: Path, model: str | None, size: int = 4072) -> tuple[Path, Path]:
    """The model (``--big-model``; else the first ``model_*.dsp``, else ``bridge_rig_A/model.dsp``,
    else the shipped warm-start model: all are W=16, 7 maps) with its fp32 and int8 exports,
    and the guidance tiled to ``size``^2 (from ``guide/``, else the rig test bed's guidance)."""
    import shutil

    from dualscale.formats.exr import write_exr
    from dualscale.propagate.export import export_model, onnx_path
    from dualscale.propagate.guidance import read_guidance

    big = work / f"guidance_{size}.exr"
    if not big.is_file():
        src = work / "guide" / "guidance.exr"
        if not src.is_file():
            src, _ = bridge_testbed(work, "rig")
            src = src / "mid"
        g = read_guidance(src).rgb
        reps = -(-size // g.shape[0])
        write_exr(big, np.tile(g, (reps, reps, 1))[:size, :size])
    if model is None:
        found = sorted(work.glob("model_*.dsp")) or [p for p in [work / "bridge_rig_A" / "model.dsp"] if p.is_file()]
        if found:
            m = found[0]
        else:
            m = work / "warmstart_w16.dsp"
            shutil.copy(WARM_START, m)
    else:
        m = Path(model)
    if not onnx_path(m, "int8").is_file() or onnx_path(m, "int8").stat().st_mtime < m.stat().st_mtime:
        export_model(m, check=False, int8=True)
    return m, big


# the runs of the 4072^2 table: run_tiled keywords, and the precision
BIG_CONFIGS = {
    "before": {"stream": False, "tile": 512, "optimization": "all", "precision": "fp32"},  # issue 15 start
    "after": {"stream": True, "tile": 512, "optimization": "all", "precision": "fp32"},
    "after-640": {"stream": True, "tile": 640, "optimization": "all", "precision": "fp32"},
    "after-768": {"stream": True, "tile": 768, "optimization": "all", "precision": "fp32"},
    "extended": {"stream": True, "tile": 512, "optimization": "extended", "precision": "fp32"},
    "int8": {"stream": True, "tile": 512, "optimization": "all", "precision": "int8"},
}

_BIG_CHILD = """
import json, resource, sys, time
from dualscale.propagate.infer import OnnxModel, run_tiled
c = json.loads(sys.argv[1])
t = time.perf_counter(); cpu = time.process_time()
om = OnnxModel.open(c["model"], c["threads"], precision=c["precision"], optimization=c["optimization"])
run_tiled(om, c["guidance"], c["out"], c["tile"], 64, progress=False, stream=c["stream"])
print(json.dumps({"wall": time.perf_counter() - t, "cpu": time.process_time() - cpu,
                  "rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2}))
"""


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _wait_quiet(below: float, most_s: float = 1800) -> None:
    """Wait (at most ``most_s``) until the 1-min load average is under ``below`` (a shared machine)."""
    t = time.time()
    while float(load()) >= below and time.time() - t < most_s:
        time.sleep(10)


def stage_big(work: Path, repo: Path, model: str | None, configs: list[str], repeats: int, threads: int = 2,
              quiet_below: float | None = None) -> None:
    """4072^2 fp32 (and int8): each configuration in a child process (``run_tiled`` from reading the
    guidance to the last file, ``ru_maxrss``), the configurations interleaved ``repeats`` times so
    that a changing load hits them alike; medians, and every run's 1-min load.  ``quiet_below``:
    before each run, wait until the 1-min load is under it (at most 30 min)."""
    import platform
    import statistics

    m, big = _big_inputs(work, repo, model)
    runs: dict[str, list[dict]] = {c: [] for c in configs}
    print(f"\n4072x4072 inference ({m.name}, onnxruntime CPU, {threads} threads, overlap 64; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores):")
    print(f"start: {_uptime()}")
    for r in range(repeats):
        for name in configs:
            c = {**BIG_CONFIGS[name], "model": str(m), "guidance": str(big), "out": str(work / f"big_{name}"),
                 "threads": threads}
            if quiet_below:
                _wait_quiet(quiet_below)
            l0 = load()
            res = subprocess.run([sys.executable, "-c", _BIG_CHILD, json.dumps(c)], check=True, capture_output=True,
                                 text=True, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
            d = json.loads(res.stdout.splitlines()[-1])
            d["load"] = float(l0)
            runs[name].append(d)
            print(f"  run {r + 1} {name}: {d['wall']:.1f} s, cpu {d['cpu']:.1f} s, {d['rss_gb']:.2f} GB, "
                  f"load {l0} -> {load()} ({time.strftime('%H:%M:%S')})", file=sys.stderr)
    print(f"end: {_uptime()}\n")
    med = {n: statistics.median(d["wall"] for d in v) for n, v in runs.items()}
    ref = med.get("before")
    print("| run | stream | tile (fitted) | graph opt. | precision | wall median [s] (min-max) | CPU median [s] | "
          "peak RSS [GB] | before / run | 1-min load at the starts |")
    print("|---|---|---|---|---|---:|---:|---:|---:|---|")
    from dualscale.propagate.infer import TilePlan

    for n, v in runs.items():
        c = BIG_CONFIGS[n]
        plan = TilePlan.make(4072, 4072, c["tile"], 64)
        walls = [d["wall"] for d in v]
        print(f"| {n} | {'yes' if c['stream'] else 'no (held whole)'} | {c['tile']} ({plan.th}, {plan.tiles} tiles) | "
              f"{c['optimization']} | {c['precision']} | {med[n]:.1f} ({min(walls):.1f}-{max(walls):.1f}) | "
              f"{statistics.median(d['cpu'] for d in v):.1f} | {max(d['rss_gb'] for d in v):.2f} | "
              f"{(ref / med[n]) if ref else float('nan'):.2f} | "
              f"{min(d['load'] for d in v):.2f}-{max(d['load'] for d in v):.2f} |")
    if "int8" in runs:
        ref32 = "after" if "after" in runs else "before"
        _int8_accuracy(work, m, work / f"big_{ref32}", work / "big_int8")


def _map_diffs(a: dict, b: dict) -> dict[str, tuple[float, float, float]]:
    """Per map: mean, 99th percentile and max of |a - b| (normals: angle in degrees; the tangent
    axially, min(d, 1 - d))."""
    out = {}
    for k in a:
        x, y = np.asarray(a[k], np.float64), np.asarray(b[k], np.float64)
        if k == "normal":
            d = np.degrees(np.arccos(np.clip((x * y).sum(-1), -1, 1)))
        elif k == "tangent":
            d = np.abs(x - y)[..., 0]
            d = np.minimum(d, 1 - d)
        else:
            d = np.abs(x - y).max(-1)
        out[k] = (float(d.mean()), float(np.percentile(d, 99)), float(d.max()))
    return out


def _int8_accuracy(work: Path, model: Path, fp32_dir: Path, int8_dir: Path) -> None:
    """int8 against fp32 on the 4072^2 run, and both against the ground truth of the rig test
    bed's guidance (when ``model`` is the one trained there, ``bridge_rig_A``)."""
    from dualscale.formats.maps import load_maps

    a, _ = load_maps(fp32_dir)
    b, _ = load_maps(int8_dir)
    d = _map_diffs({k: v.numpy() for k, v in a.items()}, {k: v.numpy() for k, v in b.items()})
    del a, b
    print("\nint8 against fp32, 4072^2 (per texel; normal: angle in degrees, tangent: axial):\n")
    print("| map | mean abs diff | 99th percentile | max |\n|---|---:|---:|---:|")
    for k, (mean, p99, mx) in d.items():
        print(f"| {k} | {mean:.4f} | {p99:.4f} | {mx:.4f} |")
    if model.parent.name != "bridge_rig_A":
        return
    from dualscale.propagate.guidance import read_guidance
    from dualscale.propagate.infer import OnnxModel, exposure_gain, propagate_image
    from dualscale.propagate.metrics import compare
    from dualscale.sim.materials import generate

    bed, tex = bridge_testbed(work, "rig")
    g = read_guidance(bed / "mid")
    gt = {k: v.numpy() for k, v in generate(EVAL, BRIDGE_CONFIGS["rig"][2], tex, 0).maps.items()}
    scores = {}
    for prec in ("fp32", "int8"):
        om = OnnxModel.open(model, 2, precision=prec)
        maps, _ = propagate_image(om, g.rgb, 512, 64, exposure_gain(om, g.luminance()), progress=False)
        scores[prec] = compare(maps, gt)
    print(f"\nAccuracy against the ground truth of the rig test bed's guidance ({g.shape[0]}^2, the data this model "
          "was trained for; L1 / SSIM):\n")
    print("| map | fp32 | int8 | L1 change |\n|---|---:|---:|---:|")
    for k in scores["fp32"]:
        f, q = scores["fp32"][k], scores["int8"][k]
        print(f"| {k} | {f['l1']:.4f} / {f['ssim']:.3f} | {q['l1']:.4f} / {q['ssim']:.3f} | "
              f"{100 * (q['l1'] / f['l1'] - 1):+.1f} % |")


_PROFILE_CHILD = """
import json, resource, statistics, sys, time
import numpy as np
from dualscale.propagate.infer import OnnxModel
c = json.loads(sys.argv[1])
om = OnnxModel.open(c["path"], c["threads"], optimization=c["optimization"])
x = (0.1 + 0.3 * np.random.default_rng(0).random((1, 3, c["tile"], c["tile"]))).astype(np.float32)
r0 = int(open("/proc/self/statm").read().split()[1]) * resource.getpagesize() / 1024  # resident now, KiB
om(x)
walls, cpus = [], []
for _ in range(c["n"]):
    t, cpu = time.perf_counter(), time.process_time()
    om(x)
    walls.append(time.perf_counter() - t); cpus.append(time.process_time() - cpu)
r1 = int(open("/proc/self/statm").read().split()[1]) * resource.getpagesize() / 1024  # the arena stays resident
print(json.dumps({"wall": statistics.median(walls), "cpu": statistics.median(cpus), "rss_mb": (r1 - r0) / 1024}))
"""


def _tile_child(path: Path, tile: int, optimization: str = "all", threads: int = 2, n: int = 3) -> dict:
    res = subprocess.run([sys.executable, "-c", _PROFILE_CHILD, json.dumps(
        {"path": str(path), "tile": tile, "optimization": optimization, "threads": threads, "n": n})],
        check=True, capture_output=True, text=True)
    return json.loads(res.stdout.splitlines()[-1])


def stage_profile(work: Path, repo: Path, model: str | None, rounds: int = 2, threads: int = 2) -> None:
    """Where onnxruntime spends a 512^2 tile (per op type, per network part), what the graph
    optimisation level and the precision change, and the cost per output pixel of a 4072^2
    image against the tile size (the overlap's share)."""
    import collections
    import re
    import statistics

    from dualscale.propagate.export import onnx_path, session
    from dualscale.propagate.infer import TilePlan

    m, _ = _big_inputs(work, repo, model)
    p32 = onnx_path(m, "fp32")
    print(f"\nonnxruntime profile ({m.name}, {threads} threads, {_uptime()}):")
    x = (0.1 + 0.3 * np.random.default_rng(0).random((1, 3, 512, 512))).astype(np.float32)
    for level in ("all", "extended"):
        s = session(p32, threads, level, profile=str(work / f"ortprofile_{level}"))
        for _ in range(4):
            s.run(None, {"image": x})
        f = Path(s.end_profiling())
        ev = json.loads(f.read_text())
        f.unlink()
        ops, parts = collections.Counter(), collections.Counter()
        for e in ev:
            if e.get("cat") != "Node" or not e["name"].endswith("_kernel_time"):
                continue
            name, op = e["name"], e["args"]["op_name"]
            if re.search(r"/norm\d/", name) and op != "Conv":
                op = "GroupNorm (Reshape, InstanceNormalization, Mul, Add)"
            ops[op] += e["dur"]
            mm = re.match(r"/(enc\.\d|bottleneck)", name) or re.match(r"/\w+/(ups|blocks)\.(\d)", name)
            if mm is None:
                part = ("decoder heads (1x1 conv) and activations" if "/head/" in name or op in (
                    "Sigmoid", "Tanh", "Sqrt", "Div", "ReduceSum", "Slice") else
                    "layout reorders, skip concats, other")
            elif mm.group(1) == "bottleneck":
                part = "bottleneck (1/16 resolution)"
            elif mm.group(1).startswith("enc"):
                part = f"encoder, level {int(mm.group(1)[-1]) + 1}"
            else:
                part = f"decoders, level {4 - int(mm.group(2))} {'up-convolution' if mm.group(1) == 'ups' else 'block'}"
            parts[part] += e["dur"]
        tot = sum(ops.values())
        per = tot / 5 / 1e3  # ms per run (1 warm-up + 4 runs are in the profile)
        print(f"\nGraph optimisation `{level}`, tile 512^2: {per:.0f} ms of kernels per tile.\n")
        print("| op type | share | ms per tile |\n|---|---:|---:|")
        for op, v in ops.most_common(10):
            print(f"| {op} | {100 * v / tot:.1f} % | {v / 5 / 1e3:.1f} |")
        if level == "all":
            print("\n| part of the network (decoder level 1 = full resolution) | share |\n|---|---:|")
            for part, v in sorted(parts.items()):
                print(f"| {part} | {100 * v / tot:.1f} % |")
    # optimisation levels and precisions, per tile (children, interleaved)
    cases = [("all", p32), ("extended", p32), ("basic", p32), ("none", p32), ("all", onnx_path(m, "fp16")),
             ("all", onnx_path(m, "int8"))]
    res: dict[int, list[dict]] = {i: [] for i in range(len(cases))}
    for _ in range(rounds):
        for i, (level, path) in enumerate(cases):
            res[i].append(_tile_child(path, 512, level, threads))
    print(f"\nPer 512^2 tile, {threads} threads, median of {rounds} x 3 runs (child processes, interleaved; "
          f"{_uptime()}):\n")
    print("| model | graph optimisation | wall [s] | CPU [s] |\n|---|---|---:|---:|")
    for i, (level, path) in enumerate(cases):
        prec = "fp16" if ".fp16." in path.name else "int8" if ".int8." in path.name else "fp32"
        print(f"| {prec} | {level} | {statistics.median(d['wall'] for d in res[i]):.3f} | "
              f"{statistics.median(d['cpu'] for d in res[i]):.3f} |")
    # tile size against overlap
    tiles = (256, 384, 512, 640, 768, 1024)
    tres: dict[int, list[dict]] = {t: [] for t in tiles}
    for _ in range(rounds):
        for t in tiles:
            tres[t].append(_tile_child(p32, t, "all", threads))
    print(f"\nTile size against the overlap (64 px) on a 4072^2 image, fp32, {threads} threads; per-tile times "
          f"measured as above ({_uptime()}):\n")
    print("| --tile | fitted tile | tiles | computed / output pixels | wall per computed px [ns] | CPU per "
          "computed px [ns] | ORT wall for 4072^2 [s] | ORT memory [MB] |\n|---:|---:|---:|---:|---:|---:|---:|---:|")
    for t in tiles:
        plan = TilePlan.make(4072, 4072, t, 64)
        w = statistics.median(d["wall"] for d in tres[t])
        c = statistics.median(d["cpu"] for d in tres[t])
        px = plan.th * plan.tw
        rss = max(d["rss_mb"] for d in tres[t])
        print(f"| {t} | {plan.th} | {plan.tiles} | {plan.tiles * px / 4072 ** 2:.2f} | {1e9 * w / px:.0f} | "
              f"{1e9 * c / px:.0f} | {plan.tiles * w:.1f} | {rss:.0f} |")


# bridging the two scales: (name, micro size, micro texel um, guidance size, guidance texel um)
BRIDGE_CONFIGS = {
    "rig": (512, 1.8, 256, 100000 / 4072),  # the rig's scales: 1.8 um micro, 4072 px over 100 mm
    "6um": (256, 6.0, 256, 24.0),  # the training set-up of the tables above, against a 24 um guidance
}
BRIDGE_OFFSETS_MM = ((0.0, 0.0), (0.3, -0.2), (0.6, 0.45))


def bridge_testbed(work: Path, name: str, material: str = EVAL, lights: str = "all") -> tuple[Path, float]:
    """``synth MATERIAL --dataset --mid`` at the configuration's scales; returns (folder, guidance texel mm)."""
    ms, mt, gs, gt = BRIDGE_CONFIGS[name]
    d = work / f"bridge_{name}_{material}"
    if not (d / "mid" / "manifest.json").is_file():
        sh("synth", material, "-o", str(d), "--size", str(ms), "--texel-um", str(mt), "--dataset", "--lights", lights,
           "--mid", "--mid-size", str(gs), "--mid-field-mm", repr(gs * gt / 1000), "--no-previews")
    return d, gt / 1000


def stage_bridge_registration(work: Path) -> None:
    """Registered micro box against the truth (the micro field is centred on the origin), from priors
    shifted by BRIDGE_OFFSETS_MM."""
    from dualscale.propagate.bridge import prior_box, register_micro
    from dualscale.propagate.data import load_source
    from dualscale.propagate.guidance import LUMA, read_guidance

    print("\nRegistration of the micro field in the guidance (truth: centred; prior shifted by dx, dy):\n")
    print("| test bed | micro at guidance scale [px] | prior shift [mm] | method | NCC | best other peak | "
          "candidates | ECC | error [px] |\n|---|---:|---|---|---:|---:|---:|---:|---:|")
    beds = [("rig", EVAL, "all"), ("6um", EVAL, "all"), ("6um", "leather", "mod8")]
    for name, material, lights in beds:
        d, tex = bridge_testbed(work, name, material, lights)
        g = read_guidance(d / "mid")
        src = load_source(d)
        scale = src.texel_mm / tex
        h, w = src.size
        truth = prior_box(g.shape, tex, (w * src.texel_mm, h * src.texel_mm), g.camera)
        lum = np.einsum("chw,c->hw", src.diffuse_image().numpy(), LUMA)
        for dx, dy in BRIDGE_OFFSETS_MM:
            prior = (truth[0] + dx / tex, truth[1] - dy / tex, truth[2], truth[3])
            r = register_micro(g.luminance(), lum, scale, prior, tex)
            err = float(np.hypot(r.box_px[0] - truth[0], r.box_px[1] - truth[1]))
            f = (lambda v: "-" if v is None else f"{v:.2f}")
            print(f"| {name} {material} | {w * scale:.1f} | {dx:+.2f}, {dy:+.2f} | {r.method} | {f(r.score)} | "
                  f"{f(r.second)} | {r.candidates} | {f(r.ecc)} | {err:.2f} |")


def _micro_texel_run(d: Path, out: Path, preset: str, tex: float) -> tuple[dict, float, float]:
    """Train at the micro texel, run on the guidance enlarged to it, area-average the maps back."""
    from dualscale.propagate.data import load_source
    from dualscale.propagate.export import export_model, onnx_paths
    from dualscale.propagate.guidance import read_guidance
    from dualscale.propagate.infer import OnnxModel, exposure_gain, propagate_image
    from dualscale.propagate.resample import resize, resize_maps
    from dualscale.propagate.train import TrainOptions, preset_with, train

    src = load_source(d)
    p = preset_with(preset, crop=min(128, min(src.size) // 16 * 16))
    model = out / "model.dsp"
    t = time.perf_counter()
    if not model.is_file():
        train([src], p, model, TrainOptions(progress=False, resume=True))
    t_train = time.perf_counter() - t
    export_model(model, check=False)
    t = time.perf_counter()
    g = read_guidance(d / "mid")
    up = 1 / (src.texel_mm / tex)
    H, W = g.shape
    big = resize(g.rgb, (int(round(H * up)), int(round(W * up))))
    om = OnnxModel.open(onnx_paths(model)[0])
    cx, cy, bw, bh = W * up / 2, H * up / 2, src.size[1], src.size[0]
    gain = exposure_gain(om, big @ np.array([0.2126, 0.7152, 0.0722], np.float32), "auto",
                         (cx - bw / 2, cy - bh / 2, bw, bh))
    maps, _ = propagate_image(om, big, 512, 64, gain, progress=False)
    del big
    small = resize_maps(maps, (H, W))
    return small, t_train, time.perf_counter() - t


def stage_bridge(work: Path, preset: str, configs: list[str], inits: tuple[str, ...] = ("",),
                 micro: bool = True) -> None:
    """Propagation accuracy on the guidance grid: micro data resampled to the guidance texel
    (``run_propagation``, once per warm start of ``inits``: ``""`` the preset's, ``"none"`` random
    weights, or a model file) against training at the micro texel on an enlarged guidance
    (``micro``)."""
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.metrics import compare
    from dualscale.propagate.stage import run_propagation
    from dualscale.sim.materials import generate

    maps = ("albedo", "roughness", "anisotropy", "tangent", "normal", "ior", "specular_tint")
    print(f"\nBridging ({EVAL}, preset {preset}, {THREADS} torch thread(s); L1 / SSIM against the mid-scale "
          "ground truth generate(material, mid_size, mid_texel)):\n")
    print("| test bed | training texel | train [s] (load) | run [s] | " + " | ".join(maps) + " |\n|---|---|---:|---:|"
          + "---:|" * len(maps))
    for name in configs:
        d, tex = bridge_testbed(work, name)
        gs = BRIDGE_CONFIGS[name][2]
        gt = {k: v.numpy() for k, v in generate(EVAL, gs, tex, 0).maps.items()}
        train_maps, _ = load_maps(d / "maps")
        base = constant_maps({m: getattr(train_maps, m).numpy() for m in maps}, gt[maps[0]].shape[:2])
        sb = compare(base, gt)
        print(f"| {name} | constant (mean of the micro maps) | - | - | "
              + " | ".join(f"{sb[m]['l1']:.3f} / {sb[m]['ssim']:.2f}" for m in maps) + " |")
        for init in inits:
            l0 = load()
            out = work / (f"bridge_{name}_A_{preset}" + (f"_{Path(init).stem}" if init else ""))
            s = run_propagation(d / "micro", d / "maps", d / "mid", out, preset=preset, threads=THREADS,
                                init=init or None)
            pred, _ = load_maps(out / "maps")
            sa = compare({k: v.numpy() for k, v in pred.items()}, gt)
            start = f"; init {init}" if init else ""
            print(f"| {name} | guidance ({tex * 1000:.1f} um; micro resampled to {s['training_size_px'][0]} px, crop "
                  f"{s['crop']}{start}) | {s['train_seconds']:.0f} ({l0}) | {s['run_seconds']:.0f} | "
                  + " | ".join(f"{sa[m]['l1']:.3f} / {sa[m]['ssim']:.2f}" for m in maps) + " |", flush=True)
        if not micro:
            continue
        l0 = load()
        (work / f"bridge_{name}_B").mkdir(exist_ok=True)
        mb, t_train, t_run = _micro_texel_run(d, work / f"bridge_{name}_B", preset, tex)
        sbm = compare(mb, gt)
        ms, mt = BRIDGE_CONFIGS[name][:2]
        print(f"| {name} | micro ({mt:g} um, crop {min(128, ms // 16 * 16)}; guidance enlarged x{tex * 1000 / mt:.2f}) | "
              f"{t_train:.0f} ({l0}) | {t_run:.0f} | "
              + " | ".join(f"{sbm[m]['l1']:.3f} / {sbm[m]['ssim']:.2f}" for m in maps) + " |")


def stage_real(work: Path, repo: Path) -> None:
    """The warm-start model on the real fabric photos (../shared/data/fabric-rt, sRGB): the
    plausibility measures of tests/propagate/test_real_guidance.py, per photo."""
    from dualscale.propagate.export import export_model, onnx_paths
    from dualscale.propagate.guidance import LUMA, read_guidance
    from dualscale.propagate.infer import OnnxModel, exposure_gain, propagate_image
    from dualscale.propagate.metrics import seam_score

    data = repo / ".." / "shared" / "data" / "fabric-rt"
    if not data.is_dir():
        print(f"\n(real photos: {data} absent, skipped)")
        return
    model = work / "warm_real.dsp"
    model.write_bytes(WARM_START.read_bytes())
    export_model(model, check=False)
    om = OnnxModel.open(onnx_paths(model)[0], THREADS)

    def spectrum(x):
        n = x.shape[0]
        w = np.hanning(n)[:, None] * np.hanning(n)[None]
        return np.abs(np.fft.fftshift(np.fft.fft2((x - x.mean()) * w))) ** 2

    print(f"\nReal guidance photos, warm-start model (load {load()}): albedo-luminance correlation, weave peak "
          "(guidance period; albedo power at it over the ring median), tile seams (largest step near a tile edge "
          "over the median step; 256 px tiles: blended with 64 px overlap / naive), tile dependence (mean "
          "|tiled - whole| albedo):\n")
    print("| photo | clipped | r(albedo, luminance) | weave period [px] | peak / ring | seams albedo | seams "
          "roughness | seams normal | tiled vs whole |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for f in sorted(data.glob("*.png")):
        g = read_guidance(f, "srgb")
        lum = g.luminance()
        gain = exposure_gain(om, lum)
        whole, _ = propagate_image(om, g.rgb, 512, 64, gain, progress=False)
        blend, _ = propagate_image(om, g.rgb, 256, 64, gain, progress=False)
        naive, _ = propagate_image(om, g.rgb, 256, 0, gain, progress=False)
        alb = whole["albedo"] @ LUMA
        pg, pa = spectrum(lum), spectrum(alb)
        n = lum.shape[0]
        fy, fx = np.mgrid[-n // 2:n // 2, -n // 2:n // 2]
        r = np.hypot(fx, fy)
        pg[r < 8] = 0
        y, x = np.unravel_index(np.argmax(pg), pg.shape)
        ring = np.abs(r - r[y, x]) < 2
        ratio = pa[y - 1:y + 2, x - 1:x + 2].max() / np.median(pa[ring])
        sm = {k: f"{seam_score(blend[k], 256, 64):.1f} / {seam_score(naive[k], 256, 0):.1f}" for k in ("albedo", "roughness",
                                                                                               "normal")}
        print(f"| {f.name} | {100 * g.clipped:.2f} % | {np.corrcoef(lum.ravel(), alb.ravel())[0, 1]:.2f} | "
              f"{n / r[y, x]:.1f} | {ratio:.0f} | {sm['albedo']} | {sm['roughness']} | {sm['normal']} | "
              f"{np.abs(blend['albedo'] - whole['albedo']).mean():.3f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--work", default="/tmp/propbench")
    ap.add_argument("--stages", default="prep,warm,presets,parity,seams,profile,big")
    ap.add_argument("--runs", default="quick,quick+warm,fast,fast+warm")
    ap.add_argument("--bridge-preset", default="fast", help="training preset of the bridge stage")
    ap.add_argument("--bridge-inits", default="", help="bridge stage: comma list of warm starts for the "
                    "guidance-texel rows ('' the preset's, 'none', or a model file; default: the preset's)")
    ap.add_argument("--bridge-no-micro", action="store_true", help="bridge stage: skip the micro-texel rows")
    ap.add_argument("--bridge-configs", default=",".join(BRIDGE_CONFIGS), help="test beds of the bridge stage")
    ap.add_argument("--big-model", help="model of the big/profile stages (default: see _big_inputs)")
    ap.add_argument("--big-configs", default="before,after,int8", help=f"runs of the big stage, of {list(BIG_CONFIGS)}")
    ap.add_argument("--big-repeats", type=int, default=3, help="rounds of the big stage (medians)")
    ap.add_argument("--quiet-below", type=float, help="big stage: wait before each run until the 1-min load is "
                    "under this (a shared machine)")
    ap.add_argument("--profile-rounds", type=int, default=2, help="rounds of the profile stage's per-tile timings")
    ap.add_argument("--warm-iterations", type=int, default=1000)
    ap.add_argument("--warm-batch", type=int, default=8)
    ap.add_argument("--warm-seeds", default="0,1", help="warm stage: material seeds, comma list (default: 0,1)")
    ap.add_argument("--warm-out", help="warm stage: model file to write (default: the packaged dualscale/propagate/models/warmstart_w16.dsp)")
    ap.add_argument("--warm-schedule", default="constant", help="warm stage: learning-rate schedule")
    ap.add_argument("--warm-lr", type=float, default=0.002, help="warm stage: (peak) learning rate")
    ap.add_argument("--json", help="presets stage: also write its rows as JSON to this file (for "
                    "bench_propagate_trade.py)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads for training (1: the shared cores "
                    "are busy, and 2 spinning OpenMP threads ran ~2-10x slower)")
    a = ap.parse_args()
    work, repo = Path(a.work), Path(__file__).resolve().parents[1]
    work.mkdir(parents=True, exist_ok=True)
    global THREADS
    THREADS = a.threads
    torch.set_num_threads(a.threads)
    print(f"torch threads {torch.get_num_threads()}, cores {os.cpu_count()}, load {load()}")
    st = a.stages.split(",")
    if "prep" in st:
        prep(work)
    if "warm" in st:
        stage_warm(work, repo, a.warm_iterations, a.warm_batch, tuple(int(x) for x in a.warm_seeds.split(",")),
                   Path(a.warm_out) if a.warm_out else None, a.warm_schedule, a.warm_lr)
    if "presets" in st:
        stage_presets(work, repo, a.runs.split(","), a.json)
    if "parity" in st:
        stage_parity(work)
    if "seams" in st:
        stage_seams(work)
    if "profile" in st:
        stage_profile(work, repo, a.big_model, a.profile_rounds)
    if "big" in st:
        stage_big(work, repo, a.big_model, a.big_configs.split(","), a.big_repeats, quiet_below=a.quiet_below)
    if "bridge-reg" in st:
        stage_bridge_registration(work)
    if "real" in st:
        stage_real(work, repo)
    if "bridge" in st:
        from dataclasses import replace as _replace

        from dualscale.propagate.train import LEGACY_PRESETS, PRESETS

        for k, v in LEGACY_PRESETS.items():  # "legacy-fast" etc.: the presets before issue 29, for old-vs-new rows
            PRESETS.setdefault(f"legacy-{k}", _replace(v, name=f"legacy-{k}"))
        stage_bridge(work, a.bridge_preset, a.bridge_configs.split(","), tuple(a.bridge_inits.split(",")),
                     not a.bridge_no_micro)
    return 0


if __name__ == "__main__":
    sys.exit(main())
