"""Mesoscale propagation benchmark: prints markdown tables for docs/PROPAGATION.md.

    PYTHONPATH=host python bench/bench_propagate.py [--work /tmp/propbench] [--stages ...]

Stages: ``prep`` (synthetic data: twill micro dataset 256^2 at 6 um/texel, all 127 LEDs,
P0/P90; guidance = twill, another seed, 768^2 at the same texel size, diffuse group, no
analyser), ``warm`` (train the generic warm-start model on plain/satin/denim), ``presets``
(cold and warm-started training, scores on the guidance), ``parity`` (ONNX fp32/fp16),
``seams`` (border vs interior error), ``big`` (4072^2 inference time and peak memory in a
child process).  Everything is cached under ``--work``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

TEXEL_UM = 6.0
MICRO = 256
GUIDE = 768
EVAL = "twill"
WARM_MATERIALS = ("plain", "satin", "denim")
THREADS = 1  # training threads; set by --threads


def sh(*args: str) -> None:
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    subprocess.run([sys.executable, "-m", "dualscale.cli", *args], check=True, stdout=subprocess.DEVNULL, env=env)


def load() -> str:
    return open("/proc/loadavg").read().split()[0]


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


def stage_warm(work: Path, repo: Path, iterations: int, batch: int) -> None:
    out = repo / "models" / "warmstart_w16.dsp"
    if out.is_file():
        return
    from dualscale.propagate.data import load_source
    from dualscale.propagate.train import TrainOptions, preset_with, train

    srcs = [load_source(work / m) for m in WARM_MATERIALS]
    t = time.perf_counter()
    r = train(srcs, preset_with("fast", iterations=iterations, batch=batch), work / "warm_full.dsp",
              TrainOptions(width=16, progress=False), half_file=False)
    from dualscale.propagate.model import save_model
    from dualscale.propagate.train import input_reference

    save_model(out, r.model, input_reference(srcs), {"materials": list(WARM_MATERIALS), "iterations": iterations,
                                                      "batch": batch, "seconds": time.perf_counter() - t,
                                                      "load": load(), "texel_um": TEXEL_UM, "size": MICRO},
               half=True)
    print(f"warm-start model: {iterations} its x batch {batch}, {time.perf_counter() - t:.0f} s, load {load()}")


def stage_presets(work: Path, repo: Path, runs: list[str]) -> None:
    rows = []
    for run in runs:  # e.g. quick, fast, quick+warm
        preset, _, warm = run.partition("+")
        extra = ["--init", str(repo / "models" / "warmstart_w16.dsp")] if warm else []
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


def stage_big(work: Path, size: int = 4072) -> None:
    from dualscale.formats.exr import read_exr, write_exr
    from dualscale.propagate.export import onnx_paths

    big = work / f"guidance_{size}.exr"
    if not big.is_file():
        g = read_exr(work / "guide" / "guidance.exr")
        reps = -(-size // GUIDE)
        write_exr(big, np.tile(g, (reps, reps, 1))[:size, :size])
    model = sorted(work.glob("model_*.dsp"))[0]
    print(f"\n4072x4072 inference ({model.name}, onnxruntime CPU, 2 threads):\n")
    print("| precision | ORT threads | wall time [s] | peak RSS [GB] | load before |\n|---|---:|---:|---:|---:|")
    for prec, th in (("fp32", 2), ("fp32", 1), ("fp16", 2)):
        onnx = onnx_paths(model)[0 if prec == "fp32" else 1]
        code = ("import resource,sys,time;from dualscale.propagate.infer import OnnxModel,run_tiled;"
                "t=time.perf_counter();"
                f"run_tiled(OnnxModel.open('{onnx}',{th}),'{big}','{work / 'big_out'}',512,64,progress=False);"
                "print(time.perf_counter()-t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
        l0 = load()
        res = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
        sec, rss = res.stdout.split()[-2:]
        print(f"| {prec} | {th} | {float(sec):.1f} | {int(rss) / 1024 ** 2:.2f} | {l0} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--work", default="/tmp/propbench")
    ap.add_argument("--stages", default="prep,warm,presets,parity,seams,big")
    ap.add_argument("--runs", default="quick,quick+warm,fast,fast+warm")
    ap.add_argument("--warm-iterations", type=int, default=300)
    ap.add_argument("--warm-batch", type=int, default=8)
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
        stage_warm(work, repo, a.warm_iterations, a.warm_batch)
    if "presets" in st:
        stage_presets(work, repo, a.runs.split(","))
    if "parity" in st:
        stage_parity(work)
    if "seams" in st:
        stage_seams(work)
    if "big" in st:
        stage_big(work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
