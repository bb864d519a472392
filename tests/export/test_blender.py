"""Our exports rendered by Blender's Cycles (issue 28): the GLB through Blender's own glTF importer,
and the ``.blend`` of ``--format blend``, each against our renderer (``bsdf.model.evaluate``) by
the relative L1 of :func:`dualscale.export.shading.relative_error`, per sun elevation.

Cycles runs in a subprocess (tests/export/blender_render.py) under the Python of
:func:`dualscale.export.blend.blender_python` (``make blender``'s ``.venv-blender``); without one
the tests skip and say so.  The renders are 64 x 64 px, 8 samples, of a 64 x 64 texel synthetic
twill (and sheer) at 10 um per texel: about a second per material for the four suns."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.bsdf.model import evaluate
from dualscale.errors import ToolError
from dualscale.export import ExportContext, exchange
from dualscale.export.gltf import write_glb
from dualscale.export.shading import relative_error
from dualscale.formats.exr import read_exr
from dualscale.sim.materials import generate

RENDER = Path(__file__).resolve().with_name("blender_render.py")
SIZE, TEXEL_MM, SEED = 64, 0.01, 2
ELEVATIONS = (90, 60, 35, 20)
SUNS = [(90, 0)] + [(e, 30) for e in ELEVATIONS[1:]]   # azimuth 30 deg: off the weave's axes
VIEW = np.array([0.0, 0.0, 1.0])

# The GLB as Blender 5.0's importer reads it (anisotropy misread, bump correction on).  Issue 28
# measured 4.6 / 8.4 / 10.4 / 18.0 % on a fitted twill; this synthetic twill (64 px, seed 2, 8
# samples, nearest-texel lookups) measures 10.8 / 12.5 / 11.5 / 14.8 % (3 Dec 2026): the bound is
# the larger of the two plus 1.5 points (8 vs 64 samples moves it by < 0.2 points).
GLB_BOUND = {90: 0.123, 60: 0.140, 35: 0.130, 20: 0.195}
# The .blend (--format blend): the goal of issue 28, 5 % at every elevation, opaque and sheer
# (measured 1.0 / 1.4 / 2.3 / 2.8 % twill, 2.2 / 2.9 / 3.5 / 4.3 % sheer, 3 Dec 2026).
BLEND_GOAL = 0.05


@pytest.fixture(scope="module")
def bpy_python() -> str:
    from dualscale.export.blend import blender_python

    try:
        return blender_python()
    except ToolError as e:
        pytest.skip(f"no Python with Blender's bpy (`make blender`): {e}")


def _dirs() -> np.ndarray:
    return np.array([[math.cos(math.radians(e)) * math.cos(math.radians(a)),
                      math.cos(math.radians(e)) * math.sin(math.radians(a)), math.sin(math.radians(e))]
                     for e, a in SUNS])


def cycles(python: str, src: Path, out: Path, swatch_mm: tuple[float, float], bump_correction=None) -> np.ndarray:
    """Cycles' renders of ``src`` (.glb or .blend) under :data:`SUNS`, ``(L, H, W, 3)`` [1/sr]."""
    spec = {"input": str(src), "out": str(out), "size": SIZE, "samples": 8, "sun": SUNS,
            "bump_correction": bump_correction, "interpolation": "Closest", "swatch_m": [swatch_mm[0] * 1e-3, swatch_mm[1] * 1e-3]}
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.json").write_text(json.dumps(spec))
    proc = subprocess.run([python, str(RENDER), str(out / "spec.json")], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return np.stack([read_exr(out / f"sun_{i}.exr")[..., :3] for i in range(len(SUNS))]).astype(np.float64)


@pytest.fixture(scope="module")
def materials():
    """name -> (maps, Exchange, ExportContext, our render (L, H, W, 3))."""
    import dataclasses

    out = {}
    for kind in ("twill", "sheer", "twill30"):
        maps = generate(kind.removesuffix("30"), size=SIZE, texel_mm=TEXEL_MM, seed=SEED).maps
        if kind == "twill30":  # the twill's tangents lie near 0 and 90 deg, where -phi = phi: turn them 30 deg
            maps = dataclasses.replace(maps, tangent=torch.remainder(maps.tangent + 1 / 6, 1.0))
        ex = exchange(maps, TEXEL_MM)
        ours = evaluate(maps, torch.as_tensor(_dirs(), dtype=torch.float32),
                        torch.as_tensor(VIEW, dtype=torch.float32)).double().numpy()
        out[kind] = (maps, ex, ExportContext(kind, ex.size_mm), ours)
    return out


def _glb_error(bpy_python, tmp_path, ex, ctx, ours) -> np.ndarray:
    glb = write_glb(ex, ctx, tmp_path)[0]
    return relative_error(cycles(bpy_python, glb, tmp_path / "render", ctx.swatch()), ours)


def test_glb_as_blender_imports_it(bpy_python, materials, tmp_path):
    _, ex, ctx, ours = materials["twill"]
    err = _glb_error(bpy_python, tmp_path, ex, ctx, ours)
    for e, x in zip(ELEVATIONS, err):
        assert x < GLB_BOUND[e], f"GLB in Cycles at {e} deg: {100 * x:.1f} % (bound {100 * GLB_BOUND[e]:.1f} %)"


def _damaged(ex, damage: str):
    import copy

    import colour

    ex = copy.deepcopy(ex)
    if damage == "normal_green_negated":
        ex.normal = ex.normal * np.float32([1, -1, 1])
    elif damage == "rows_flipped":
        for name in ("base_color", "roughness", "anisotropy", "tangent_angle", "normal", "ior",
                     "specular_color", "transmittance", "opacity"):
            a = getattr(ex, name)
            if a is not None:
                setattr(ex, name, np.ascontiguousarray(a[::-1]))
    elif damage == "tangent_mirrored":
        ex.tangent_angle = np.remainder(-ex.tangent_angle, np.pi).astype(np.float32)
    elif damage == "srgb_read_as_linear":
        ex.base_color = colour.models.eotf_inverse_sRGB(ex.base_color).astype(np.float32)
    else:
        raise KeyError(damage)
    return ex


@pytest.mark.parametrize("damage", ["normal_green_negated", "rows_flipped", "tangent_mirrored",
                                    "srgb_read_as_linear"])
def test_a_wrong_orientation_scores_clearly_worse(bpy_python, materials, tmp_path, damage):
    """The measurement sees each convention error a writer or reader could make: the GLB with
    the error scores worse than the right one by more than a third at some elevation, and
    is never better at any (the right GLB: test above).  On the twill with its tangents turned
    30 deg (the synthetic twill's lie near 0 and 90 deg, where a mirrored tangent is the same)."""
    _, ex, ctx, ours = materials["twill30"]
    right = _glb_error(bpy_python, tmp_path / "right", ex, ctx, ours)
    wrong = _glb_error(bpy_python, tmp_path / "wrong", _damaged(ex, damage), ctx, ours)
    assert (wrong > right).all(), f"{damage}: {np.round(100 * wrong, 1)} vs {np.round(100 * right, 1)} %"
    assert (wrong / right).max() > 1.33, f"{damage}: {np.round(100 * wrong, 1)} vs {np.round(100 * right, 1)} %"


@pytest.fixture(scope="module")
def blends(bpy_python, materials, tmp_path_factory):
    """kind -> the .blend of ``materials[kind]``, written once for the module's tests."""
    from dualscale.export.blend import write

    cache: dict[str, Path] = {}

    def get(kind: str) -> Path:
        if kind not in cache:
            _, ex, ctx, _ = materials[kind]
            cache[kind] = write(ex, ctx, tmp_path_factory.mktemp(f"blend_{kind}"))[0]
        return cache[kind]

    return get


@pytest.mark.parametrize("kind", ["twill", "sheer"])
def test_blend_renders_within_5_percent_of_ours(bpy_python, materials, blends, tmp_path, kind):
    _, ex, ctx, ours = materials[kind]
    path = blends(kind)
    err = relative_error(cycles(bpy_python, path, tmp_path / "render", ctx.swatch()), ours)
    for e, x in zip(ELEVATIONS, err):
        assert x < BLEND_GOAL, f"{kind} .blend in Cycles at {e} deg: {100 * x:.2f} % (goal 5 %)"


def test_blend_holds_the_swatch_the_material_and_the_properties(bpy_python, materials, blends, tmp_path):
    _, ex, ctx, ours = materials["sheer"]
    path = blends("sheer")
    assert sorted(p.name for p in path.parent.iterdir()) == ["sheer.blend"]   # no temp, no .blend1
    cycles(bpy_python, path, tmp_path / "render", ctx.swatch())
    scene = json.loads((tmp_path / "render" / "scene.json").read_text())
    ob = scene["objects"]["sheer"]
    assert ob["dimensions"][:2] == pytest.approx([SIZE * TEXEL_MM * 1e-3] * 2, rel=1e-6)   # metres
    mat = scene["materials"]["sheer"]
    assert mat["bump_map_correction"] is False
    types = {n["type"] for n in mat["nodes"]}
    assert {"ShaderNodeBsdfPrincipled", "ShaderNodeBsdfTranslucent", "ShaderNodeAddShader",
            "ShaderNodeBsdfTransparent", "ShaderNodeNormalMap", "ShaderNodeTangent"} <= types
    assert "ShaderNodeBsdfRefraction" not in types and "ShaderNodeBsdfGlass" not in types
    assert [n["distribution"] for n in mat["nodes"] if "distribution" in n] == ["GGX"]
    for props in (mat["props"]["dualscale"], ob["props"]["dualscale"]):
        assert props["repeat_mm"] == pytest.approx([SIZE * TEXEL_MM] * 2)
        assert props["texel_mm"] == pytest.approx(TEXEL_MM) and props["repeats"] == [1.0, 1.0]
        assert props["scale_known"] == 1 and props["tiled"] == 0


def test_blend_without_bpy_is_a_clear_error_and_writes_nothing(materials, tmp_path, monkeypatch):
    from dualscale.export import blend

    _, ex, ctx, _ = materials["twill"]
    monkeypatch.setenv(blend.ENV_PYTHON, str(tmp_path / "no-such-python"))
    with pytest.raises(ToolError, match="not an executable Python"):
        blend.write(ex, ctx, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_blender_failure_is_a_tool_error_and_leaves_no_file(tmp_path, monkeypatch):
    from dualscale.export import blend

    ex = exchange(generate("twill", size=16, texel_mm=TEXEL_MM, seed=1).maps, TEXEL_MM)
    ctx = ExportContext("small", ex.size_mm)
    monkeypatch.setenv(blend.ENV_PYTHON, "/bin/false")
    with pytest.raises(ToolError, match="failed with status 1"):
        blend.write(ex, ctx, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_cli_export_format_blend(bpy_python, tmp_path, capsys):
    """``dualscale export MAPS --format blend`` writes OUT/blend/<name>.blend; ``all`` leaves it out."""
    from dualscale.cli import main
    from dualscale.cli.export import parse_formats
    from dualscale.export.material import read_export
    from dualscale.formats.maps import save_maps

    maps = tmp_path / "maps"
    save_maps(maps, generate("twill", size=16, texel_mm=0.02, seed=1).maps, {}, texel_mm=0.02, previews=False)
    out = tmp_path / "out"
    assert main(["export", str(maps), "-o", str(out), "--name", "tw", "--format", "blend"]) == 0
    assert read_export(out)["formats"]["blend"] == ["blend/tw.blend"]
    head = (out / "blend" / "tw.blend").read_bytes()[:7]
    assert head == b"BLENDER" or head[:4] == b"\x28\xb5\x2f\xfd"   # plain, or zstd-compressed (Blender 5)
    assert str(out / "blend" / "tw.blend") in capsys.readouterr().out
    assert "blend" not in parse_formats("all") and parse_formats("glb,blend") == ["glb", "blend"]


def test_cli_without_bpy_refuses_before_writing_any_format(tmp_path, monkeypatch, capsys):
    from dualscale.cli import main
    from dualscale.export import blend
    from dualscale.formats.maps import save_maps

    maps = tmp_path / "maps"
    save_maps(maps, generate("twill", size=16, texel_mm=0.02, seed=1).maps, {}, texel_mm=0.02, previews=False)
    monkeypatch.setenv(blend.ENV_PYTHON, str(tmp_path / "no-such-python"))
    out = tmp_path / "out"
    assert main(["export", str(maps), "-o", str(out), "--format", "glb,blend"]) == 4   # ToolError
    assert not (out / "glb").exists() and not (out / "blend").exists()
    assert blend.ENV_PYTHON in capsys.readouterr().err
