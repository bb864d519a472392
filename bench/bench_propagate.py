"""Mesoscale propagation benchmark: prints markdown tables for docs/PROPAGATION.md.

    PYTHONPATH=host python bench/bench_propagate.py [--work /tmp/propbench] [--stages ...]

Stages: ``prep`` (synthetic data: twill micro dataset 256^2 at 6 um/texel, all 127 LEDs,
P0/P90; guidance = twill, another seed, 768^2 at the same texel size, diffuse group, no
analyser), ``warm`` (train the generic warm-start model on plain/satin/denim), ``presets``
(cold and warm-started training, scores on the guidance), ``parity`` (ONNX fp32/fp16),
``seams`` (border vs interior error), ``big`` (4072^2 inference time and peak memory in a
child process), ``bridge-reg`` (locating the micro field in the guidance: error against the truth
from shifted priors) and ``bridge`` (propagation accuracy with the micro data resampled to the
guidance texel vs trained at the micro texel on an enlarged guidance) and ``real`` (the warm-start
model on the real fabric photos of ../shared/data/fabric-rt); the last three are not in the default
list.
Everything is cached under ``--work``.
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


def stage_bridge(work: Path, preset: str, configs: list[str]) -> None:
    """Propagation accuracy on the guidance grid: micro data resampled to the guidance texel
    (``run_propagation``) against training at the micro texel on an enlarged guidance."""
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
        base = {}
        for m in maps:
            v = getattr(train_maps, m).numpy()
            if m == "normal":
                mean = v.mean((0, 1))
                mean = mean / np.linalg.norm(mean)
            elif m == "tangent":
                a = 2 * np.pi * v[..., 0]
                mean = np.array([np.mod(np.arctan2(np.sin(a).mean(), np.cos(a).mean()), 2 * np.pi) / (2 * np.pi)])
            else:
                mean = v.mean((0, 1))
            base[m] = np.broadcast_to(mean, gt[m].shape).astype(np.float32)
        sb = compare(base, gt)
        print(f"| {name} | constant (mean of the micro maps) | - | - | "
              + " | ".join(f"{sb[m]['l1']:.3f} / {sb[m]['ssim']:.2f}" for m in maps) + " |")
        l0 = load()
        s = run_propagation(d / "micro", d / "maps", d / "mid", work / f"bridge_{name}_A", preset=preset,
                            threads=THREADS)
        pred, _ = load_maps(work / f"bridge_{name}_A" / "maps")
        sa = compare({k: v.numpy() for k, v in pred.items()}, gt)
        print(f"| {name} | guidance ({tex * 1000:.1f} um; micro resampled to {s['training_size_px'][0]} px, crop "
              f"{s['crop']}) | {s['train_seconds']:.0f} ({l0}) | {s['run_seconds']:.0f} | "
              + " | ".join(f"{sa[m]['l1']:.3f} / {sa[m]['ssim']:.2f}" for m in maps) + " |")
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
    model.write_bytes((repo / "models" / "warmstart_w16.dsp").read_bytes())
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
    ap.add_argument("--stages", default="prep,warm,presets,parity,seams,big")
    ap.add_argument("--runs", default="quick,quick+warm,fast,fast+warm")
    ap.add_argument("--bridge-preset", default="fast", help="training preset of the bridge stage")
    ap.add_argument("--bridge-configs", default=",".join(BRIDGE_CONFIGS), help="test beds of the bridge stage")
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
    if "bridge-reg" in st:
        stage_bridge_registration(work)
    if "real" in st:
        stage_real(work, repo)
    if "bridge" in st:
        stage_bridge(work, a.bridge_preset, a.bridge_configs.split(","))
    return 0


if __name__ == "__main__":
    sys.exit(main())
