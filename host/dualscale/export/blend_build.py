"""Build the ``.blend`` of :mod:`dualscale.export.blend` -- a script for Blender's Python
(PyPI ``bpy`` 5.0), run in a subprocess: ``python blend_build.py SPEC.json``.  It imports only
``bpy`` and the standard library (never dualscale: bpy 5.0 needs numpy < 2).

``SPEC.json`` (written by :func:`dualscale.export.blend.write`)::

    {"out": "x.blend", "name": "...", "swatch_m": [w, h], "repeats": [ru, rv], "tiled": bool,
     "textures": {"base_color": "file.exr", "roughness": ..., "anisotropy": ..., "tangent2": ...,
                  "normal": ..., "ior": ..., "specular_color": ..., "transmittance": ...,
                  "opacity": ...},    # absent keys: no such map
     "ior": eta (used without an IOR texture), "props": {...}}

The scene (frame: X = image right, Y = image up, Z = out of the sample; metres):

* the swatch: one quad of ``swatch_m`` centred on the origin, facing +Z, UV map ``UVMap`` with
  ``u`` along +X and ``v`` along +Y; image row 0 (the top) at ``v = 1`` (Blender's UV origin is
  the lower left), ``repeats`` texture repeats across it (the glTF export's UVs, mirrored in v);
* the material: a Principled BSDF (distribution ``GGX``: single scattering, like our model)
  fed by float EXR textures packed into the file; Roughness = our ``r`` and Anisotropic = our
  ``a`` (Cycles' Principled maps them as we do: ``alpha = r^2``, aspect ``sqrt(1 - 0.9 a)``,
  ``alpha_x = alpha / aspect`` along the tangent), the tangent = the UV tangent rotated by
  *Anisotropic Rotation* ``= phi / 2 pi`` (from a texture of ``(cos 2 phi, sin 2 phi)``, which
  interpolates across the axial wrap at phi = 0 = pi), Normal Map node (tangent space, OpenGL);
  the diffuse transmittance as a Translucent BSDF *added*; the opacity as a mix with a
  Transparent BSDF; ``cycles.use_bump_map_correction = False``;
* custom properties ``dualscale`` (material and object) from ``props``.
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy


def _image(nodes, links, uv, path: str, colorspace: str, extension: str, x: float, y: float):
    img = bpy.data.images.load(path)
    img.colorspace_settings.name = colorspace
    img.pack()
    n = nodes.new("ShaderNodeTexImage")
    n.image, n.interpolation, n.extension = img, "Linear", extension
    n.location = (x, y)
    links.new(uv.outputs["UV"], n.inputs["Vector"])
    return n


def _swatch(name: str, w: float, h: float, ru: float, rv: float):
    me = bpy.data.meshes.new(f"{name}_swatch")
    verts = [(-w / 2, -h / 2, 0.0), (w / 2, -h / 2, 0.0), (w / 2, h / 2, 0.0), (-w / 2, h / 2, 0.0)]
    me.from_pydata(verts, [], [(0, 1, 2, 3)])  # counter-clockwise seen from +Z
    uv = me.uv_layers.new(name="UVMap")
    for loop in me.loops:
        x, y, _ = verts[loop.vertex_index]
        uv.data[loop.index].uv = ((x / w + 0.5) * ru, 1.0 - (0.5 - y / h) * rv)
    me.update()
    return me


def _material(spec: dict):
    tex, name = spec["textures"], spec["name"]
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    ext = "REPEAT" if (spec["tiled"] or any(abs(r - 1) > 1e-9 for r in spec["repeats"])) else "EXTEND"
    uv = nodes.new("ShaderNodeUVMap")
    uv.uv_map, uv.location = "UVMap", (-1400, 0)
    p = nodes.new("ShaderNodeBsdfPrincipled")
    p.distribution, p.location = "GGX", (0, 0)
    p.inputs["Metallic"].default_value = 0.0
    p.inputs["Specular IOR Level"].default_value = 0.5  # 0.5: the IOR's own Fresnel, unscaled
    y = 600

    def image(key: str, colorspace: str = "Non-Color"):
        nonlocal y
        y -= 300
        return _image(nodes, links, uv, tex[key], colorspace, ext, -900, y)

    links.new(image("base_color", "Linear Rec.709").outputs["Color"], p.inputs["Base Color"])
    links.new(image("roughness").outputs["Color"], p.inputs["Roughness"])
    if "ior" in tex:
        links.new(image("ior").outputs["Color"], p.inputs["IOR"])
    else:
        p.inputs["IOR"].default_value = float(spec["ior"])
    if "specular_color" in tex:
        links.new(image("specular_color", "Linear Rec.709").outputs["Color"], p.inputs["Specular Tint"])
    normal = None
    if "normal" in tex:
        normal = nodes.new("ShaderNodeNormalMap")
        normal.space, normal.uv_map, normal.location = "TANGENT", "UVMap", (-400, -900)
        links.new(image("normal").outputs["Color"], normal.inputs["Color"])
        links.new(normal.outputs["Normal"], p.inputs["Normal"])
    if "anisotropy" in tex:
        links.new(image("anisotropy").outputs["Color"], p.inputs["Anisotropic"])
        sep = nodes.new("ShaderNodeSeparateXYZ")
        sep.location = (-600, -1200)
        links.new(image("tangent2").outputs["Color"], sep.inputs["Vector"])
        atan = nodes.new("ShaderNodeMath")
        atan.operation, atan.location = "ARCTAN2", (-400, -1200)   # atan2(sin 2phi, cos 2phi) = 2 phi
        links.new(sep.outputs["Y"], atan.inputs[0])
        links.new(sep.outputs["X"], atan.inputs[1])
        turn = nodes.new("ShaderNodeMath")
        turn.operation, turn.location = "DIVIDE", (-200, -1200)    # 2 phi / 4 pi = phi / 2 pi
        turn.inputs[1].default_value = 4.0 * math.pi
        links.new(atan.outputs["Value"], turn.inputs[0])
        links.new(turn.outputs["Value"], p.inputs["Anisotropic Rotation"])
        tangent = nodes.new("ShaderNodeTangent")
        tangent.direction_type, tangent.uv_map, tangent.location = "UV_MAP", "UVMap", (-200, -1500)
        links.new(tangent.outputs["Tangent"], p.inputs["Tangent"])
    shader = p.outputs["BSDF"]
    if "transmittance" in tex:
        tr = nodes.new("ShaderNodeBsdfTranslucent")
        tr.location = (0, -700)
        links.new(image("transmittance", "Linear Rec.709").outputs["Color"], tr.inputs["Color"])
        if normal is not None:
            links.new(normal.outputs["Normal"], tr.inputs["Normal"])
        add = nodes.new("ShaderNodeAddShader")
        add.location = (300, -200)
        links.new(shader, add.inputs[0])
        links.new(tr.outputs["BSDF"], add.inputs[1])
        shader = add.outputs["Shader"]
    if "opacity" in tex:
        clear = nodes.new("ShaderNodeBsdfTransparent")
        clear.location = (300, -500)
        mix = nodes.new("ShaderNodeMixShader")
        mix.location = (500, 0)
        links.new(image("opacity").outputs["Color"], mix.inputs["Fac"])
        links.new(clear.outputs["BSDF"], mix.inputs[1])
        links.new(shader, mix.inputs[2])
        shader = mix.outputs["Shader"]
    out = nodes.new("ShaderNodeOutputMaterial")
    out.location = (800, 0)
    links.new(shader, out.inputs["Surface"])
    mat.cycles.use_bump_map_correction = False
    return mat


def main(spec_path: str) -> None:
    with open(spec_path, encoding="utf-8") as f:
        spec = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.preferences.filepaths.save_version = 0  # no .blend1 backup beside the file
    name = spec["name"]
    (w, h), (ru, rv) = spec["swatch_m"], spec["repeats"]
    me = _swatch(name, w, h, ru, rv)
    mat = _material(spec)
    me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.scene.unit_settings.system = "METRIC"
    for idb in (mat, ob):
        idb["dualscale"] = spec["props"]
    out = spec["out"]
    if os.path.exists(out):
        os.remove(out)  # the caller's empty temporary file
    bpy.ops.wm.save_as_mainfile(filepath=out, compress=True)
    if not os.path.isfile(out):
        sys.exit(f"Blender did not write {out}")


if __name__ == "__main__":
    main(sys.argv[1])
