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
