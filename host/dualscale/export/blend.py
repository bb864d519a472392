"""Blender export (issue 28): ``<name>.blend``, a swatch at real size with a Cycles material
whose parameters are converted for Blender's own Principled BSDF (docs/EXPORT.md, "Blender").

Written through Blender's Python module (PyPI ``bpy`` 5.0.1) in a subprocess: bpy 5.0 needs
numpy < 2, so it lives in its own venv (``make blender`` makes ``.venv-blender``).  The Python
that runs it is, first found: ``$DUALSCALE_BLENDER_PYTHON``; ``.venv-blender/bin/python`` in the
source tree of this package (an editable install); this Python, if it imports ``bpy``.  None:
:class:`~dualscale.errors.ToolError`, before any file is written.

What the file holds (:mod:`.blend_build` builds it; frame X = image right, Y = image up, Z out;
metres, so 1 texel = ``texel_mm`` mm):

* the swatch plane of ``ctx.swatch()`` (``ExportContext``), UVs repeating the texture
  ``ctx.repeats()`` times (``REPEAT`` images for a tile, else ``EXTEND``);
* a Principled BSDF (``GGX``, single scattering): Base Color = our ``b``; Roughness = our
  ``r``; Anisotropic = our ``a``; Anisotropic Rotation = ``phi / 2 pi`` on the UV tangent
  (Tangent node).  Cycles (``svm/closure.h``) takes ``alpha = r^2`` and the aspect
  ``sqrt(1 - 0.9 Anisotropic)`` with ``alpha_x = alpha / aspect`` along the tangent -- Burley's,
  ours -- so writing our ``r`` and ``a`` unchanged gives our ``alpha_t``, ``alpha_b`` exactly
  (Blender's glTF importer instead takes glTF's base roughness and strength, which it then
  misreads: docs/EXPORT.md).  IOR = our per-texel eta (or :attr:`Exchange.ior_scalar`),
  Specular IOR Level 0.5, Specular Tint = our tint; Normal Map node (tangent space, OpenGL +Y);
* our diffuse transmittance ``t`` as a *Translucent* BSDF of colour ``t`` added to the
  Principled (our model adds the two lobes: reflection ``b``, transmission ``t``), not a
  glass BTDF; the opacity as a mix with a Transparent BSDF;
* ``material.cycles.use_bump_map_correction = False``: our model shades the normal-mapped
  microfacet frame without Cycles' grazing-light correction (left on, it darkens the cloth:
  at 20 deg elevation 6.6 % instead of 2.8 % relative L1 on the twill, 11.5 % instead of 4.3 %
  on the sheer; docs/EXPORT.md);
* ID property ``dualscale`` on the material and on the object: ``repeat_mm``, ``swatch_mm``,
  ``repeats``, ``texel_mm`` (-1 when unknown), ``tiled``, ``scale_known``, ``generator`` and
  ``provenance`` (JSON text).

The textures are float32 EXR (linear, exact; colour maps in ``Linear Rec.709``, data maps
``Non-Color``), packed into the ``.blend``, which is written to a temporary name and renamed.

Errors: :class:`~dualscale.errors.UnitsError` for a swatch or repeat size that is not finite
and positive; :class:`~dualscale.errors.ToolError` when no Python with bpy is found or Blender
fails (its last output lines in the message).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from dualscale import __version__
from dualscale.errors import ToolError, UnitsError
from dualscale.formats.atomic import atomic_path

from .exchange import Exchange
from .textures import encode_normal, write_float

BUILD_SCRIPT = Path(__file__).with_name("blend_build.py")
ENV_PYTHON = "DUALSCALE_BLENDER_PYTHON"
BPY_VERSION = "5.0.1"
TIMEOUT_S = 600


def blender_python() -> str:
    """The Python interpreter that has ``bpy`` (module docstring's order); ``ToolError`` if none."""
    env = os.environ.get(ENV_PYTHON)
    if env:
        if not os.access(env, os.X_OK):
            raise ToolError(f"{ENV_PYTHON}={env!r} is not an executable Python")
        return env
    local = Path(__file__).resolve().parents[3] / ".venv-blender" / "bin" / "python"
    if local.is_file() and os.access(local, os.X_OK):
        return str(local)
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable
    raise ToolError(f"--format blend needs Blender's Python module (PyPI bpy=={BPY_VERSION}, Python 3.11, "
                    "numpy < 2): run `make blender` in the source tree (it makes .venv-blender), or set "
                    f"{ENV_PYTHON} to a Python that imports bpy")


def diffuse_base(ex: Exchange) -> np.ndarray:
    """Principled's Base Color ``(H, W, 3)``: our ``b / (1 - E)``, clipped to [0, 1].

    Cycles' Principled BSDF layers its dielectric specular over the diffuse and attenuates the
    diffuse by ``1 - E(v)``, the specular lobe's directional albedo at the view (its maximum over
    the tinted channels; ``svm_node_principled``); our model adds the two lobes unattenuated.
    ``E`` here is our specular lobe's albedo (:func:`.shading._dir_albedo`: GGX, Smith, the
    exact Fresnel of the texel's IOR, times the tint) for the swatch's head-on view, per texel
    (through its normal): exact there, and for oblique views the attenuation Cycles applies grows
    a little (E rises towards grazing).  Measured on the twill and the sheer, 64 px: without it
    Cycles renders 4-6 % darker at every elevation (docs/EXPORT.md, "Blender")."""
    import torch

    from .exchange import standard_surface_anisotropy
    from .shading import _dir_albedo, _specular_maps

    rough, aniso, rot = standard_surface_anisotropy(ex)
    params = {"specular_roughness": rough, "specular_anisotropy": aniso, "specular_rotation": rot,
              "specular_IOR": ex.ior if ex.ior is not None else ex.ior_scalar, "normal": ex.normal}
    h, w = ex.shape
    e = _dir_albedo(_specular_maps(params, h, w), float(ex.ior_scalar),
                    torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).numpy()   # (H, W, 1)
    if ex.specular_color is not None:
        e = e * ex.specular_color
    e = np.clip(e.max(-1, keepdims=True), 0.0, 0.95)
    return np.clip(ex.base_color / (1.0 - e), 0.0, 1.0).astype(np.float32)


def _textures(ex: Exchange, folder: Path) -> dict[str, str]:
    """Float EXR textures (3 channels: Blender reads them as colour images) -> their paths."""
    def rgb(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, np.float32)
        return np.repeat(a[..., None], 3, -1) if a.ndim == 2 else a

    maps: dict[str, np.ndarray] = {"base_color": diffuse_base(ex), "roughness": rgb(ex.roughness)}
    if ex.anisotropy is not None and ex.tangent_angle is not None:
        maps["anisotropy"] = rgb(ex.anisotropy)
        two = 2.0 * ex.tangent_angle.astype(np.float64)
        maps["tangent2"] = np.stack([np.cos(two), np.sin(two), np.zeros_like(two)], -1)
    if ex.normal is not None:
        maps["normal"] = encode_normal(ex.normal)
    if ex.ior is not None:
        maps["ior"] = rgb(ex.ior)
    if ex.specular_color is not None:
        maps["specular_color"] = ex.specular_color
    if ex.transmittance is not None and float(ex.transmittance.max()) > 0:
        maps["transmittance"] = ex.transmittance
    if ex.opacity is not None and float(ex.opacity.min()) < 1.0:
        maps["opacity"] = rgb(ex.opacity)
    h, w = ex.shape
    out = {}
    for key, a in maps.items():
        if a.shape[:2] != (h, w):
            raise UnitsError(f"Blender export: map {key} is {a.shape[1]}x{a.shape[0]}, base_color {w}x{h}")
        out[key] = str(write_float(folder / f"{key}.exr", np.asarray(a, np.float32)))
    return out


def write(ex: Exchange, ctx, out: Path) -> list[Path]:
    """Write ``<name>.blend`` into ``out`` (module docstring); returns ``[path]``."""
    out = Path(out)
    sw, _ = ctx.checked_sizes("Blender export")
    python = blender_python()
    props = {"repeat_mm": list(ctx.repeat_mm) if ctx.repeat_mm else [-1.0, -1.0],
             "swatch_mm": [float(sw[0]), float(sw[1])], "repeats": [float(r) for r in ctx.repeats()],
             "texel_mm": float(ex.texel_mm) if ex.texel_mm else -1.0, "tiled": bool(ctx.tiled),
             "scale_known": ctx.repeat_mm is not None, "generator": f"dualscale {__version__}",
             "provenance": json.dumps(ctx.meta, sort_keys=True, default=str),
             "frame": "X = image right (texture u), Y = image up, Z out; metres; normals OpenGL"}
    with tempfile.TemporaryDirectory(prefix="dualscale-blend-") as tmp:
        spec = {"name": ctx.name, "swatch_m": [sw[0] * 1e-3, sw[1] * 1e-3],
                "repeats": props["repeats"], "tiled": bool(ctx.tiled),
                "textures": _textures(ex, Path(tmp)), "ior": float(ex.ior_scalar), "props": props}
        path = out / f"{ctx.name}.blend"
        with atomic_path(path) as dst:
            spec["out"] = str(dst)
            spec_path = Path(tmp) / "spec.json"
            spec_path.write_text(json.dumps(spec))
            try:
                proc = subprocess.run([python, str(BUILD_SCRIPT), str(spec_path)], capture_output=True,
                                      text=True, timeout=TIMEOUT_S)
            except (OSError, subprocess.TimeoutExpired) as e:
                raise ToolError(f"Blender export: could not run {python}: {e}") from e
            if proc.returncode != 0:
                tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-8:])
                raise ToolError(f"Blender export: bpy ({python}) failed with status {proc.returncode}:\n{tail}")
    return [path]
