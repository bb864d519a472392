"""Forward+backward throughput of the SVBSDF on CPU (a benchmark, not a test).

Usage: PYTHONPATH=host python bench/bench_bsdf.py [--size 256] [--lights 127] [--repeats 3]

Prints a markdown table of BSDF evaluations/s (one evaluation = one pixel under one light,
all three colour channels, value + gradients w.r.t. every map) for the straightforward
unfused implementation (``evaluate_reference``) and the optimised paths of ``evaluate``,
plus the memory-bandwidth bound measured on this machine.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "host"))

from dualscale import bsdf as B  # noqa: E402
from dualscale.geometry.dome import led_directions  # noqa: E402


def make_leaves(size: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)

    def r(c, lo=0.05, hi=0.95):
        return (lo + (hi - lo) * torch.rand(size, size, c, generator=g, dtype=dtype)).requires_grad_()

    return dict(albedo=r(3), roughness=r(1, 0.2, 0.9), anisotropy=r(1), tangent=r(1), ior=r(1),
                specular_tint=r(1), square=r(2, -0.6, 0.6))


def _old_diffuse(albedo, roughness, cos_l, cos_v, cos_lv):
    """The diffuse term as it was before 2026-11-30 (the baseline of issue 15's profile): the
    Schlick weights by ``pow``, four times, on three-channel products."""
    def w(c):
        return (1.0 - torch.clamp(c, 0.0, 1.0)) ** 5

    rr = roughness * (1.0 + torch.clamp(cos_lv, -1.0, 1.0))
    base = albedo * (1.0 / math.pi) * (1.0 - 0.5 * w(cos_l)) * (1.0 - 0.5 * w(cos_v))
    fl, fv = w(cos_l), w(cos_v)
    return base + albedo * (1.0 / math.pi) * rr * (fl + fv + fl * fv * (rr - 1.0))


def _with_old_diffuse(*args, **kw):
    from dualscale.bsdf import model

    new, model.diffuse = model.diffuse, _old_diffuse
    try:
        return B.evaluate(*args, **kw)
    finally:
        model.diffuse = new


def step(fn, leaves, lights, view, **kw) -> float:
    for t in leaves.values():
        t.grad = None
    t0 = time.perf_counter()
    maps = B.MaterialMaps(normal=B.normal_from_square(leaves["square"]),
                          **{k: v for k, v in leaves.items() if k != "square"})
    out = fn(maps, lights, view, **kw)
    out.sum().backward()
    return time.perf_counter() - t0


def bandwidth_gbs(nbytes: int = 256 * 2**20, reps: int = 5) -> float:
    """Measured copy bandwidth (read + write) in GB/s."""
    a = torch.empty(nbytes // 4, dtype=torch.float32).fill_(1.0)
    b = torch.empty_like(a)
    b.copy_(a)
    best = math.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        b.copy_(a)
        best = min(best, time.perf_counter() - t0)
    return 2 * nbytes / best / 1e9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--lights", type=int, default=127)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile variant")
    args = ap.parse_args()
    dtype = getattr(torch, args.dtype)
    leaves = make_leaves(args.size, dtype)
    lights = led_directions(dtype=dtype)[: args.lights]
    view = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    n_eval = args.size * args.size * lights.shape[0]

    variants = [("straightforward (unfused reference)", B.evaluate_reference, {}),
                ("evaluate, eager, all lights at once, the diffuse term before 2026-11-30", _with_old_diffuse, {}),
                ("evaluate, eager, all lights at once", B.evaluate, {}),
                (f"evaluate, eager, chunks of {args.chunk} lights", B.evaluate, dict(light_chunk=args.chunk))]
    if not args.no_compile:
        variants.append((f"evaluate, torch.compile, chunks of {args.chunk} lights", B.evaluate,
                         dict(light_chunk=args.chunk, compiled=True)))
    rows = []
    for name, fn, kw in variants:
        t_first = step(fn, leaves, lights, view, **kw)  # warm-up (compiles when compiled=True)
        best = min(step(fn, leaves, lights, view, **kw) for _ in range(args.repeats))
        rows.append((name, best, t_first))
    base = rows[0][1]
    bw = bandwidth_gbs()
    bytes_per_eval = 2 * 3 * torch.finfo(dtype).bits // 8  # write f (3 ch) forward, read df (3 ch) backward
    print(f"CPU: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {os.cpu_count()} cores; {args.size}x{args.size} map, "
          f"{lights.shape[0]} lights, {args.dtype}, anisotropic + normal map + tint + IOR map\n")
    print("| variant | fwd+bwd time [s] | evaluations/s | speed-up vs straightforward | first call [s] |")
    print("|---|---:|---:|---:|---:|")
    for name, t, t_first in rows:
        print(f"| {name} | {t:.3f} | {n_eval / t:.3e} | {base / t:.2f}x | {t_first:.1f} |")
    print(f"\nMeasured copy bandwidth: {bw:.1f} GB/s. A fully fused forward+backward must at least "
          f"write the output and read its gradient ({bytes_per_eval} B/evaluation), so the "
          f"memory-bandwidth bound is {bw * 1e9 / bytes_per_eval:.3e} evaluations/s.")


if __name__ == "__main__":
    main()
