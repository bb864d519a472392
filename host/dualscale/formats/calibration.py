"""The calibration file: versioned JSON with provenance, written atomically.

``{"format": "dualscale-calibration", "version": 1, "created": ISO-8601,
"rig": {"id", "layout"}, "provenance": {"captures", "manifest_sha256", "capture_dates",
"software"}, "conventions": {...}, "r_wp", "r_ws", "r_c": {camera: {light: [r, g, b]}},
"flat_field": {camera: {"coef": [[...]]}}, "dark": {camera: {"bias": [3], "rate": [3]}},
"markers": {camera: [[r0, r1, c0, c1], ...]}, "ccm": {camera: {light_kind: {...}}},
"white_level": {camera: {"level": [3], "clip": [3], "threshold": [3], "margin", "source", "spread",
"n_clipped"}}}``

``white_level`` (optional: files written before it have none, and applying them keeps nominal
full scale): per camera, the raw level (normalised DN, before dark subtraction) at which it
clips, per channel; ``clip`` is the level at and above which a single raw sample counts as
clipped (``level`` less four times the plateau's spread; a dataset's clipping mask), and
``threshold`` the lower level at and above which the HDR merge drops a bracket's sample
(``level`` less the margin); ``source`` is ``declared`` (captures), ``measured`` (from the
brackets) or ``nominal``.
"""

from __future__ import annotations

import json
import math
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
    "white_level": "per camera and raw channel, normalised DN before dark subtraction: level = where the sensor "
                   "clips; a sample at or above clip marks a dataset pixel clipped; HDR merges drop samples at or "
                   "above threshold",
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


WHITE_SOURCES = ("declared", "measured", "nominal")


def white_level(data: dict[str, Any], camera: str, path: str | Path = "calibration") -> dict[str, Any] | None:
    """The validated ``white_level[camera]`` record of a calibration (``None`` when the file has
    none for that camera): ``{"level": [3], "clip": [3], "threshold": [3], "margin": float,
    "source": str, "spread": [3] | None, "n_clipped": [3] | None}``, levels in ``(0, 1]``
    normalised DN and ``0 < threshold <= clip <= level`` (``clip`` defaults to ``level``).  :class:`CalibrationError` naming the file and field otherwise."""
    rec = (data.get("white_level") or {}).get(camera)
    if rec is None:
        return None
    where = f"{path}: white_level.{camera}"
    try:
        level = [float(v) for v in rec["level"]]
        thr = [float(v) for v in rec["threshold"]]
        clip = [float(v) for v in rec.get("clip", level)]
        margin = float(rec.get("margin", 0.0))
        source = str(rec.get("source", "declared"))
        spread = None if rec.get("spread") is None else [float(v) for v in rec["spread"]]
        n_clipped = None if rec.get("n_clipped") is None else [int(v) for v in rec["n_clipped"]]
    except (KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"{where} is malformed ({e!r}); it needs level [r, g, b] and threshold [r, g, b]") from e
    ok = (len(level) == 3 and len(thr) == 3 and all(math.isfinite(v) and 0 < v <= 1.0 for v in level)
          and len(clip) == 3 and all(math.isfinite(c) and 0 < c <= v for c, v in zip(clip, level))
          and all(math.isfinite(t) and 0 < t <= c for t, c in zip(thr, clip)) and 0 <= margin < 0.5
          and source in WHITE_SOURCES and (spread is None or len(spread) == 3)
          and (n_clipped is None or len(n_clipped) == 3))
    if not ok:
        raise CalibrationError(f"{where}: needs 3 levels in (0, 1] normalised DN, 3 clip levels in (0, level], "
                               f"3 thresholds in (0, clip], "
                               f"a margin in [0, 0.5) and a source in {WHITE_SOURCES}; got {rec!r}")
    return {"level": level, "clip": clip, "threshold": thr, "margin": margin, "source": source, "spread": spread,
            "n_clipped": n_clipped}
