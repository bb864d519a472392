"""Our exports in the users' own renderers (issue 28 "Measure"; docs/EXPORT.md): every format in
the real renderer that opens it, per sun elevation, opaque (twill) and sheer, with the time each
renderer takes.

* **Blender Cycles** (PyPI ``bpy`` 5.0.1 in ``make blender``'s ``.venv-blender``, CPU, 64 px, 8
  samples, nearest-texel lookups; tests/export/blender_render.py in a subprocess): the GLB as
  Blender's glTF importer reads it, and the ``.blend`` of ``--format blend``;
* **MaterialX's GLSL renderer** (``PyMaterialXRenderGlsl``, Mesa llvmpipe under Xvfb;
  tests/export/mtlx_render.py): the ``.mtlx`` export, ``standard_surface`` and ``open_pbr_surface``.

Each against our renderer (``bsdf.model.evaluate``) by the relative L1 of
:func:`dualscale.export.shading.relative_error`; synthetic 64 x 64 texel materials at 10 um
(seed 2, the tests' own), suns at 90 deg and at 60/35/20 deg elevation, azimuth 30 deg (off the
weave's axes).  A renderer that cannot run here is reported as skipped with the reason.  Prints
markdown tables with the machine, the load and the date.  Usage:
``.venv/bin/python bench/bench_renderers.py``.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dualscale.errors import ToolError  # noqa: E402
from dualscale.export.shading import relative_error  # noqa: E402
from tests.export import test_blender as tb  # noqa: E402  (its materials, suns and Cycles runner)


def _materials() -> dict:
    return tb.materials.__wrapped__() if hasattr(tb.materials, "__wrapped__") else tb.materials()


def cycles_rows(mats: dict, work: Path) -> dict[str, tuple[list[float], float]]:
    """``{row: (errors per elevation, seconds for the four suns)}`` of the GLB and the .blend."""
    from dualscale.export.blend import blender_python, write
    from dualscale.export.gltf import write_glb

    py = blender_python()
    out: dict[str, tuple[list[float], float]] = {}
    for kind in ("twill", "sheer"):
        _, ex, ctx, ours = mats[kind]
        for fmt in ("glb", "blend"):
            d = work / f"{kind}_{fmt}"
            src = (write_glb if fmt == "glb" else write)(ex, ctx, d)[0]
            t0 = time.perf_counter()
            img = tb.cycles(py, src, d / "render", ctx.swatch())
            out[f"Cycles, {'GLB as imported' if fmt == 'glb' else '.blend'} | {kind}"] = (
                relative_error(img, ours).tolist(), time.perf_counter() - t0)
    return out


def glsl_rows(mats: dict, work: Path) -> dict[str, tuple[list[float], float]]:
    """The same for MaterialX's GLSL renderer, both shaders; raises RuntimeError when no GL."""
    from tests.export import mtlx_render

    from dualscale.export.mtlx import write as write_mtlx

    why = mtlx_render.available()
    if why:
        raise RuntimeError(why)
    out: dict[str, tuple[list[float], float]] = {}
    for kind in ("twill", "sheer"):
        _, ex, ctx, ours = mats[kind]
        path = write_mtlx(ex, ctx, work / f"{kind}_mtlx")[0]
        for shader in mtlx_render.SHADERS:
            r = mtlx_render.MtlxRenderer(path, (tb.SIZE, tb.SIZE))
            t0 = time.perf_counter()
            imgs = np.stack([r.render(shader, d) for d in tb._dirs()])
            out[f"MaterialX GLSL, `{shader}` | {kind}"] = (relative_error(imgs, ours).tolist(),
                                                          time.perf_counter() - t0)
    return out


def main() -> None:
    import torch

    torch.set_num_threads(1)
    mats = _materials()
    rows: dict[str, tuple[list[float], float]] = {}
    skipped = []
    with tempfile.TemporaryDirectory(prefix="bench-renderers-") as td:
        try:
            rows.update(cycles_rows(mats, Path(td)))
        except ToolError as e:
            skipped.append(f"Blender Cycles: {e}")
        try:
            rows.update(glsl_rows(mats, Path(td)))
        except (RuntimeError, ImportError) as e:
            skipped.append(f"MaterialX GLSL: {e}")
    load = os.getloadavg()
    print(f"machine: {platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}; load "
          f"{load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f}; {date.today().isoformat()}\n")
    print("| renderer, format | material | " + " | ".join(f"{e}°" for e in tb.ELEVATIONS) + " | time (4 suns) |")
    print("|---|---|" + "---:|" * (len(tb.ELEVATIONS) + 1))
    for name, (errs, secs) in rows.items():
        print(f"| {name} | " + " | ".join(f"{100 * e:.1f} %" for e in errs) + f" | {secs:.1f} s |")
    for s in skipped:
        print(f"\nskipped: {s}")


if __name__ == "__main__":
    main()
