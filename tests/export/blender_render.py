"""Render a swatch with Blender's Cycles, as a measurement: run by the Blender tests
(tests/export/test_blender.py) in a subprocess, under a Python that has PyPI ``bpy`` (the
``.venv-blender`` of ``make blender``; bpy 5.0.1 needs numpy < 2, the project's venv has numpy 2).
It imports nothing of dualscale.

    python blender_render.py SPEC.json

``SPEC.json``::

    {"input": "x.glb" | "x.blend", "out": "folder", "size": 64, "samples": 8,
     "sun": [[elevation_deg, azimuth_deg], ...], "bump_correction": null | true | false,
     "swatch_m": [w, h], "interpolation": null | "Closest" | "Linear"}

Writes ``out/sun_<i>.exr`` (RGB float32, linear, rows top to bottom) per sun, and
``out/scene.json`` (what the scene held: materials, their nodes, custom properties).

The setup (docs/EXPORT.md, "Blender"): Cycles on the CPU, ``Standard`` view transform, a BOX
pixel filter of one pixel, a black world, ``max_bounces = 0`` (a flat sheet sees nothing but the
sun), one SUN of strength 1 W/m^2 and angle 0 (so a pixel is ``f cos(theta_l)`` in 1/sr, our
renderer's unit), an orthographic camera straight above the swatch whose frame is the swatch
(image up = +Y, the glTF importer's and our .blend's bitangent), OPEN_EXR at 32 bits.  ``interpolation`` (``"Closest"`` in the tests) sets every image
texture's lookup: with one pixel per texel, a pixel then shades its texel's parameters alone, as
our renderer does; with ``Linear`` (what a user renders) the box filter also averages the
bilinear blend of neighbouring texels, which the comparison would count as error.

A glTF import puts the swatch in Blender's Z-up frame: glTF +X -> +X, glTF -Z (image up) -> +Y,
glTF +Y (the normal) -> +Z, so Blender's world (X, Y, Z) is our tangent frame (right, up, out).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import bpy  # first: it puts Blender's own modules (addon_utils, mathutils) on the path
import addon_utils  # noqa: E402
from mathutils import Vector  # noqa: E402


def _load(spec: dict) -> None:
    src = spec["input"]
    if src.endswith(".blend"):
        bpy.ops.wm.open_mainfile(filepath=src)
        return
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon_utils.enable("io_scene_gltf2")
    bpy.ops.import_scene.gltf(filepath=src)


def _scene(spec: dict):
    scene = bpy.context.scene
    for ob in [o for o in scene.objects if o.type in ("LIGHT", "CAMERA")]:
        bpy.data.objects.remove(ob)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(spec.get("samples", 8))
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = float(spec.get("filter_width", 1.0))
    scene.cycles.seed = 1
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.resolution_x = scene.render.resolution_y = int(spec["size"])
    scene.render.resolution_percentage = 100
    s = scene.render.image_settings
    s.file_format = "OPEN_EXR"
    s.color_depth = "32"
    s.color_mode = "RGB"
    s.exr_codec = "ZIP"

    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    if world.node_tree is None:  # Blender < 5: a world without nodes until asked
        world.use_nodes = True
    for node in world.node_tree.nodes:
        if node.type == "BACKGROUND":
            node.inputs["Strength"].default_value = 0.0
            node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    scene.world = world

    cam_data = bpy.data.cameras.new("ortho")
    cam_data.type = "ORTHO"
    w, h = spec["swatch_m"]
    cam_data.ortho_scale = max(w, h)
    cam_data.clip_start, cam_data.clip_end = 1e-3, 10.0
    cam = bpy.data.objects.new("camera", cam_data)
    cam.location = (0.0, 0.0, 1.0)
    cam.rotation_euler = (0.0, 0.0, 0.0)   # looks down -Z, image up = +Y
    scene.collection.objects.link(cam)
    scene.camera = cam

    sun_data = bpy.data.lights.new("sun", "SUN")
    sun_data.energy = 1.0                  # W/m^2: the irradiance normal to the sun
    sun_data.angle = 0.0
    sun = bpy.data.objects.new("sun", sun_data)
    scene.collection.objects.link(sun)
    bc, interp = spec.get("bump_correction"), spec.get("interpolation")
    for mat in bpy.data.materials:
        if bc is not None:
            mat.cycles.use_bump_map_correction = bool(bc)
        if interp is not None and mat.node_tree is not None:
            for node in mat.node_tree.nodes:
                if node.type == "TEX_IMAGE":
                    node.interpolation = interp
    return scene, sun


def _describe() -> dict:
    mats = {}
    for mat in bpy.data.materials:
        nodes = []
        if mat.node_tree is not None:
            for n in mat.node_tree.nodes:
                d = {"name": n.name, "type": n.bl_idname}
                if n.type == "BSDF_PRINCIPLED":
                    d["distribution"] = n.distribution
                nodes.append(d)
        mats[mat.name] = {"nodes": nodes, "bump_map_correction": mat.cycles.use_bump_map_correction,
                          "props": {k: _plain(mat[k]) for k in mat.keys()}}
    obs = {o.name: {"type": o.type, "dimensions": list(o.dimensions),
                    "props": {k: _plain(o[k]) for k in o.keys()}} for o in bpy.data.objects}
    return {"materials": mats, "objects": obs, "version": bpy.app.version_string}


def _plain(v):
    try:
        json.dumps(v)
        return v
    except TypeError:
        return v.to_dict() if hasattr(v, "to_dict") else list(v)


def main(spec_path: str) -> None:
    spec = json.loads(Path(spec_path).read_text())
    out = Path(spec["out"])
    out.mkdir(parents=True, exist_ok=True)
    _load(spec)
    scene, sun = _scene(spec)
    (out / "scene.json").write_text(json.dumps(_describe(), indent=1))
    for i, (el, az) in enumerate(spec["sun"]):
        e, a = math.radians(el), math.radians(az)
        to_sun = Vector((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))
        sun.rotation_euler = to_sun.to_track_quat("Z", "Y").to_euler()  # the light travels along -Z
        scene.render.filepath = str(out / f"sun_{i}.exr")
        bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main(sys.argv[1])
