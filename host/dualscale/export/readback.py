"""What a user's tool reads back from each export: the format's parameters, decoded from the
written files only (no access to our maps), for the format's shading model in :mod:`.shading`.

This is how docs/EXPORT.md prices each format: render the read-back parameters with the
format's model and compare with our model's render of the source maps.  Each reader returns the
``params`` dict of :func:`.shading.gltf_bsdf` (glTF, GLB, U3M) or
:func:`.shading.standard_surface_bsdf` (exchange EXR, MaterialX).

Errors: ``FormatError`` naming the file for anything missing or not understood.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import FormatError
from dualscale.formats.exr import read_exr


def read_exchange_exr(folder: str | Path) -> dict[str, Any]:
    """Standard Surface parameters of an exchange EXR set (:mod:`.exr`)."""
    folder = Path(folder)
    doc_path = folder / "exchange.json"
    if not doc_path.is_file():
        raise FormatError(f"{folder}: no exchange.json (not an exchange EXR set)")
    doc = json.loads(doc_path.read_text())
    chans = {"base_color": ("R", "G", "B"), "specular_color": ("R", "G", "B"), "subsurface_color": ("R", "G", "B"),
             "normal": ("X", "Y", "Z")}
    p: dict[str, Any] = {}
    for name in doc["maps"]:
        arr = read_exr(folder / f"{name}.exr", chans.get(name, ("Y",)))
        p[name] = arr if name in chans else arr[..., 0]
    if "specular_IOR" not in p:
        p["specular_IOR"] = float(doc["specular_IOR"])
    for key in ("base_color", "specular_roughness"):
        if key not in p:
            raise FormatError(f"{doc_path}: no {key}")
    return p


def _read_texture(path: Path, srgb: bool) -> np.ndarray:
    from .textures import read_png

    if path.suffix.lower() == ".exr":
        from dualscale.formats.exr import open_image

        inp = open_image(path)
        try:
            arr = np.asarray(inp.read_image("float"), np.float64)
        finally:
            inp.close()
    else:
        arr = read_png(path, srgb=srgb)
    return arr[..., 0] if arr.shape[-1] == 1 else arr


def _mtlx_source(inp, where: str) -> tuple[str, list[str], Any]:
    """Follow a shader input through the node graph: (file, categories passed, image node)."""
    out = inp.getConnectedOutput()
    if out is None:
        raise FormatError(f"{where}: input {inp.getName()} is not connected")
    node = out.getConnectedNode()
    chain = []
    while node is not None and node.getCategory() not in ("image", "tiledimage"):
        chain.append(node.getCategory())
        up = node.getInput("in")
        node = None if up is None else up.getConnectedNode()
    if node is None:
        raise FormatError(f"{where}: input {inp.getName()} reaches no image node")
    return node.getInputValue("file"), chain, node


def read_mtlx(path: str | Path, shader: str = "standard_surface") -> dict[str, Any]:
    """Standard Surface parameters of a MaterialX export's ``standard_surface`` (``shader``), the
    textures decoded as MaterialX would: ``srgb_texture`` images through the sRGB curve,
    ``normalmap`` inputs as ``2 x - 1`` normalised in the (T, B, N) = (+u, +v up, out) frame."""
    import MaterialX as mx

    path = Path(path)
    doc = mx.createDocument()
    try:
        mx.readFromXmlFile(doc, str(path))
    except Exception as e:  # MaterialX raises its own exception types
        raise FormatError(f"{path}: not a MaterialX document ({e})") from e
    nodes = [n for n in doc.getNodes() if n.getCategory() == shader]
    if not nodes:
        raise FormatError(f"{path}: no {shader} node")
    sh = nodes[0]
    p: dict[str, Any] = {}
    for inp in sh.getInputs():
        name = inp.getName()
        if inp.getConnectedOutput() is None:
            val = inp.getValue()
            p[name] = float(val) if isinstance(val, (int, float)) and not isinstance(val, bool) else val
            continue
        fname, chain, img = _mtlx_source(inp, str(path))
        space = img.getInput("file").getColorSpace() or img.getColorSpace()
        arr = _read_texture(path.parent / fname, srgb=space == "srgb_texture")
        if "normalmap" in chain:
            v = 2.0 * arr - 1.0
            arr = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
        if name in ("opacity",) and arr.ndim == 3:
            arr = arr[..., 0]
        p[name] = arr
    out: dict[str, Any] = {"base_color": p["base_color"], "specular_roughness": p["specular_roughness"],
                           "specular_IOR": p.get("specular_IOR", 1.5), "specular_color": p.get("specular_color"),
                           "normal": p.get("normal"), "opacity": p.get("opacity")}
    if isinstance(out["specular_color"], np.ndarray) is False:
        out["specular_color"] = None
    if isinstance(p.get("specular_anisotropy"), np.ndarray):
        t = p.get("tangent")
        if not isinstance(t, np.ndarray):
            raise FormatError(f"{path}: anisotropic standard_surface without a tangent texture")
        out["specular_anisotropy"] = p["specular_anisotropy"]
        out["specular_rotation"] = np.remainder(np.arctan2(t[..., 1], t[..., 0]), np.pi) / np.pi
    if bool(p.get("thin_walled")) and isinstance(p.get("subsurface"), np.ndarray):
        out["subsurface"] = p["subsurface"]
    return out


def read_u3ma(path: str | Path) -> dict[str, Any]:
    """Principled parameters of the front side of a ``.u3ma`` (:func:`.shading.principled_bsdf`):
    every ``texture_and_*`` field as its texture (``offset + factor * mean(rgb)``) or constant."""
    import zipfile

    import colour

    path = Path(path)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise FormatError(f"{path}: not a zip archive ({e})") from e
    with zf:
        names = zf.namelist()
        u3m = [n for n in names if n.endswith(".u3m")]
        if len(u3m) != 1:
            raise FormatError(f"{path}: expected one .u3m entry, found {u3m}")
        doc = json.loads(zf.read(u3m[0]))
        front = doc["material"]["front"]

        def image(entry: str, srgb: bool) -> np.ndarray:
            import tempfile

            with tempfile.TemporaryDirectory() as tmp:
                p = Path(tmp) / Path(entry).name
                p.write_bytes(zf.read(entry))
                return _read_texture(p, srgb)

        def scalar(key: str) -> np.ndarray | float:
            f = front[key]
            tex = f.get("texture")
            if not tex:
                return float(f["constant"])
            img = image(tex["image"]["path"], srgb=False)
            img = img.mean(-1) if img.ndim == 3 else img
            return tex.get("offset", 0.0) + tex.get("factor", 1.0) * img

        bc = front["basecolor"]
        if bc.get("texture"):
            base = image(bc["texture"]["image"]["path"], srgb=True)[..., :3]
        else:
            c = bc["constant"]
            base = colour.models.eotf_sRGB(np.array([c["r"], c["g"], c["b"]], np.float64))
        normal = None
        if front["normal"].get("texture"):
            v = 2.0 * image(front["normal"]["texture"]["image"]["path"], srgb=False)[..., :3] - 1.0
            normal = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
        return {"base_color": base, "roughness": scalar("roughness"), "anisotropy": scalar("anisotropy_value"),
                "rotation": scalar("anisotropy_rotation"), "normal": normal, "specular": scalar("specular_value"),
                "specular_tint": scalar("specular_tint"), "transmission": scalar("transmission"),
                "alpha": scalar("alpha")}


def read_gltf(path: str | Path) -> dict[str, Any]:
    """glTF parameters (:func:`.shading.gltf_bsdf`) of the first material of a ``.gltf`` (with
    its ``.bin`` and PNG files) or a ``.glb`` (images in buffer views), decoded as the glTF spec
    says: base colour sRGB (alpha linear), metallic-roughness G = roughness, normal ``2 x - 1``,
    anisotropy RG = direction ``2 x - 1`` and B = strength (times ``anisotropyStrength``),
    specular colour sRGB times ``specularColorFactor``, transmission R times its factor."""
    import tempfile

    import pygltflib

    path = Path(path)
    try:
        doc = pygltflib.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises bare exceptions for malformed files
        raise FormatError(f"{path}: not a glTF file ({e})") from e
    if doc is None or not doc.materials:
        raise FormatError(f"{path}: no material")
    mat = doc.materials[0]
    blob = doc.binary_blob() if path.suffix.lower() == ".glb" else None

    def image(info: Any, srgb: bool) -> np.ndarray:
        index = info["index"] if isinstance(info, dict) else info.index
        img = doc.images[doc.textures[index].source]
        if img.uri:
            return _read_texture(path.parent / img.uri, srgb)
        view = doc.bufferViews[img.bufferView]
        data = (blob or b"")[view.byteOffset or 0:(view.byteOffset or 0) + view.byteLength]
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "texture.png"
            p.write_bytes(data)
            return _read_texture(p, srgb)

    pbr = mat.pbrMetallicRoughness
    base = image(pbr.baseColorTexture, srgb=True)
    base = base * np.asarray(pbr.baseColorFactor, np.float64)[: base.shape[-1]]
    mr = image(pbr.metallicRoughnessTexture, srgb=False)
    p: dict[str, Any] = {"base_color": base[..., :3], "roughness": mr[..., 1] * pbr.roughnessFactor,
                         "alpha": base[..., 3] if mat.alphaMode == "BLEND" and base.shape[-1] == 4 else None}
    if mat.normalTexture is not None:
        v = 2.0 * image(mat.normalTexture, srgb=False)[..., :3] - 1.0
        v[..., :2] *= mat.normalTexture.scale
        p["normal"] = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    ext = mat.extensions or {}
    p["ior"] = float(ext.get("KHR_materials_ior", {}).get("ior", 1.5))
    spec = ext.get("KHR_materials_specular")
    if spec is not None:
        col = np.asarray(spec.get("specularColorFactor", [1.0, 1.0, 1.0]), np.float64)
        p["specular_color"] = image(spec["specularColorTexture"], srgb=True)[..., :3] * col
    an = ext.get("KHR_materials_anisotropy")
    if an is not None:
        a = image(an["anisotropyTexture"], srgb=False)
        d = 2.0 * a[..., :2] - 1.0
        p["anisotropy_direction"] = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        p["anisotropy_strength"] = a[..., 2] * float(an.get("anisotropyStrength", 1.0))
    tr = ext.get("KHR_materials_transmission")
    if tr is not None:
        t = image(tr["transmissionTexture"], srgb=False)
        p["transmission"] = (t[..., 0] if t.ndim == 3 else t) * float(tr.get("transmissionFactor", 0.0))
    return p
