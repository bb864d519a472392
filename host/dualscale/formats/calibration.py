"""The calibration file: versioned JSON with provenance, written atomically.

``{"format": "dualscale-calibration", "version": 1, "created": ISO-8601,
"rig": {"id", "layout"}, "provenance": {"captures", "manifest_sha256", "capture_dates",
"software"}, "conventions": {...}, "r_wp", "r_ws", "r_c": {camera: {light: [r, g, b]}},
"flat_field": {camera: {"coef": [[...]]}}, "dark": {camera: {"bias": [3], "rate": [3]}},
"markers": {camera: [[r0, r1, c0, c1], ...]}, "ccm": {camera: {light_kind: {...}}}}``
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dualscale.errors import CalibrationError, RigMismatchError

from .atomic import write_text
from .versioned import read_versioned_json

FORMAT = "dualscale-calibration"
VERSION = 1
CONVENTIONS = {
    "images": "linear camera raw, normalised DN per second after HDR merge and dark subtraction",
    "r_c": "mean white-sheet value per (camera, light) in those units (micro: P0 + P90)",
    "r_ws": "white-sheet reflectance, output linear RGB (Rec.709 primaries, D65)",
    "calibrated": "i_hat = i / r_c * r_ws (relative reflectance / transmittance)",
    "ccm": "3x3, output linear RGB (Rec.709, D65) = M @ white-balanced camera RGB; "
           "errors CIEDE2000 vs colour-science ColorChecker (CIELAB D50, Bradford)",
}


def write_calibration(path: str | Path, data: dict[str, Any]) -> Path:
    """Write atomically: a temporary file in the same directory, fsync, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"format": FORMAT, "version": VERSION, "conventions": CONVENTIONS, **data}, indent=1)
    write_text(path, text)
    return path


def read_calibration(path: str | Path, rig_id: str | None = None, layout: str | None = None) -> dict[str, Any]:
    """Load a calibration file; refuse another format/version, or another rig than
    ``rig_id`` (and dome ``layout``) when given."""
    path = Path(path)
    data = read_versioned_json(path, FORMAT, VERSION, CalibrationError)
    rig = data.get("rig", {})
    if rig_id is not None and rig.get("id") != rig_id:
        raise RigMismatchError(f"{path}: calibration is from rig {rig.get('id')!r}, the captures are from rig {rig_id!r}")
    if layout is not None and rig.get("layout") != layout:
        raise RigMismatchError(f"{path}: calibration is for dome layout {rig.get('layout')!r}, captures use {layout!r}")
    return data
