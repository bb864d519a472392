"""Export benchmark: what each format's approximation costs, and how long each takes to write.
Prints the markdown tables of docs/EXPORT.md.

    PYTHONPATH=host python bench/bench_export.py [--size 96] [--materials twill satin denim leather sheer]
        [--maps DIR ...] [--threads 1] [--work /tmp/exportbench]

For each material (synthetic ``generate(name, size, 10 um)``, plus any ``--maps`` folder such as a
digitize run's ``fit/maps``): export every format, read each export back the way a tool would
(``dualscale.export.readback``: only the written files), render it with the format's own model
(``dualscale.export.shading``: glTF's for glTF/GLB, Standard Surface's for MaterialX and the EXR
set, Principled for U3M) under the dome's 127 LEDs seen from the zenith camera, and compare with
our model's render of the source maps: the mean relative L1 per LED elevation row.  The baseline
of the same run is our own maps read back from ``OUT/maps`` and rendered with our model (0 up to
float32 EXR: what a lossless export would score).  Machine, load average and date are printed.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import time
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "host"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

FORMATS = ("exr", "mtlx", "gltf", "glb", "u3m")
MODEL = {"exr": "Standard Surface", "mtlx": "Standard Surface", "gltf": "glTF 2.0", "glb": "glTF 2.0",
         "u3m": "Principled"}


def _params(fmt: str, out: Path, name: str):
    from dualscale.export import readback

    if fmt == "exr":
        return readback.read_exchange_exr(out / "exr")
    if fmt == "mtlx":
        return readback.read_mtlx(out / "mtlx" / f"{name}.mtlx")
    if fmt == "gltf":
        return readback.read_gltf(out / "gltf" / f"{name}.gltf")
    if fmt == "glb":
        return readback.read_gltf(out / "glb" / f"{name}.glb")
    return readback.read_u3ma(out / "u3m" / f"{name}.u3ma")


def _render(fmt: str, params, lights: np.ndarray, view: np.ndarray) -> np.ndarray:
    from dualscale.export import shading

    fn = {"exr": shading.standard_surface_bsdf, "mtlx": shading.standard_surface_bsdf,
          "gltf": shading.gltf_bsdf, "glb": shading.gltf_bsdf, "u3m": shading.principled_bsdf}[fmt]
    return fn(params, lights, view)


def measure(src: Path, work: Path, name: str) -> dict:
    from dualscale.bsdf.model import evaluate
    from dualscale.export.material import export_material
    from dualscale.export.shading import relative_error
    from dualscale.formats.maps import load_maps
    from dualscale.geometry.dome import led_directions, ring_layout

    maps, _ = load_maps(src)
    out = work / name
    shutil.rmtree(out, ignore_errors=True)
    times, sizes = {}, {}
    for fmt in FORMATS:
        t0 = time.perf_counter()
        doc = export_material(src, out, [fmt], name=name)
        times[fmt] = time.perf_counter() - t0
        sizes[fmt] = sum((out / f).stat().st_size for f in doc["formats"][fmt])
    lights = led_directions(torch.float64).numpy()
    view = np.array([0.0, 0.0, 1.0])
    ours = evaluate(maps, torch.as_tensor(lights, dtype=torch.float32), torch.tensor(view, dtype=torch.float32)
                    ).double().numpy()
    base_maps, _ = load_maps(out / "maps")
    errors = {"ours (baseline)": relative_error(
        evaluate(base_maps, torch.as_tensor(lights, dtype=torch.float32),
                 torch.tensor(view, dtype=torch.float32)).double().numpy(), ours)}
    for fmt in FORMATS:
        errors[fmt] = relative_error(_render(fmt, _params(fmt, out, name), lights, view), ours)
    rows = np.array([r for r, _, _ in ring_layout()])
    theta = {int(r): float(t) for r, t, _ in ring_layout()}
    per_row = {f: [float(e[rows == r].mean()) for r in sorted(theta)] for f, e in errors.items()}
    comps = [n for n, _ in maps.items()]
    return {"rows": [theta[r] for r in sorted(theta)], "errors": per_row, "times": times, "sizes": sizes,
            "maps": comps, "shape": maps.shape}


def materialx_glsl(src: Path, work: Path, name: str, size: int) -> None:
    """Print the relative L1 of MaterialX's own GLSL renderer (tests/export/mtlx_render.py:
    Xvfb, Mesa llvmpipe, one directional light, zenith orthographic view, a pixel per texel)
    against our model, per sun elevation (azimuth 0), both shaders, and the time per render
    (median after the first compile).  Skipped with the reason when no GL context can be made."""
    sys.path.insert(0, str(REPO))
    from tests.export import mtlx_render

    from dualscale.bsdf.model import evaluate
    from dualscale.export.material import export_material
    from dualscale.export.shading import relative_error
    from dualscale.formats.maps import load_maps

    why = mtlx_render.available()
    if why:
        print(f"\nMaterialX GLSL renderer: skipped ({why})")
        return
    maps, _ = load_maps(src)
    out = work / f"glsl_{name}"
    shutil.rmtree(out, ignore_errors=True)
    export_material(src, out, ["mtlx"], name=name)
    elevations = (90, 60, 35, 20)
    lights = np.stack([mtlx_render.sun(e) for e in elevations])
    ours = evaluate(maps, torch.as_tensor(lights, dtype=torch.float32),
                    torch.tensor([0.0, 0.0, 1.0], dtype=torch.float32)).double().numpy()
    rows, times = {}, []
    for shader in mtlx_render.SHADERS:
        r = mtlx_render.MtlxRenderer(out / "mtlx" / f"{name}.mtlx", (size, size))
        errs = []
        for i, _ in enumerate(elevations):
            t0 = time.perf_counter()
            img = r.render(shader, lights[i])
            times.append(time.perf_counter() - t0)
            errs.append(float(relative_error(img[None], ours[i:i + 1])[0]))
        rows[shader] = errs
    print(f"\n**MaterialX's GLSL renderer** ({name}, {size}×{size} px, materialx {mx_version()}, Mesa llvmpipe "
          f"under Xvfb): mean relative L1 against our renderer, sun at azimuth 0\n")
    print("| shader | " + " | ".join(f"{e}°" for e in elevations) + " |")
    print("|---|" + "---|" * len(elevations))
    for shader, errs in rows.items():
        print(f"| `{shader}` | " + " | ".join(f"{100 * e:.1f} %" for e in errs) + " |")
    print(f"\nfirst render (compile) {times[0]:.2f} s; then median {float(np.median(times[1:])):.3f} s per render")


def mx_version() -> str:
    import MaterialX

    return MaterialX.__version__


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--materials", nargs="*", default=["twill", "satin", "denim", "leather", "sheer"])
    ap.add_argument("--maps", nargs="*", default=[], type=Path, help="extra maps folders (e.g. RUN/fit/maps)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", type=Path, default=Path("/tmp/exportbench"))
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    from dualscale.formats.maps import save_maps
    from dualscale.sim.materials import generate

    a.work.mkdir(parents=True, exist_ok=True)
    sources = []
    for m in a.materials:
        mat = generate(m, size=a.size, texel_mm=0.01, seed=0)
        src = a.work / "src" / m
        save_maps(src, mat.maps, {"material": m}, texel_mm=0.01, previews=False)
        sources.append((m, src))
    sources += [(p.resolve().parent.name.replace(".", "_") or "maps", p) for p in a.maps]
    results = {name: measure(src, a.work / "out", name) for name, src in sources}

    print(f"machine: {platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"torch threads {a.threads}; load average {os.getloadavg()[0]:.2f}; {date.today().isoformat()}")
    first = next(iter(results.values()))
    head = " | ".join(f"{t:.0f}°" for t in first["rows"])
    for name, r in results.items():
        print(f"\n**{name}** ({r['shape'][1]}×{r['shape'][0]} texels; maps: {', '.join(r['maps'])}): mean relative "
              f"L1 of the format's render against ours, per LED elevation row\n")
        print(f"| format | model | {head} | all |")
        print("|---|---|" + "---|" * (len(first["rows"]) + 1))
        for fmt, errs in r["errors"].items():
            model = MODEL.get(fmt, "ours (dualscale-maps)")
            print(f"| {fmt} | {model} | " + " | ".join(f"{100 * e:.2f} %" for e in errs)
                  + f" | {100 * float(np.mean(errs)):.2f} % |")
    print("\nWrite time and size per format (median over the materials):\n")
    print("| format | time | size |")
    print("|---|---|---|")
    for fmt in FORMATS:
        t = float(np.median([r["times"][fmt] for r in results.values()]))
        s = float(np.median([r["sizes"][fmt] for r in results.values()]))
        print(f"| {fmt} | {t:.2f} s | {s / 1024:.0f} KiB |")
    twill = dict(sources).get("twill")
    if twill is not None:
        materialx_glsl(twill, a.work / "out", "twill", a.size)


if __name__ == "__main__":
    main()
