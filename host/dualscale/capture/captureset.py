"""The calibration targets' capture set: the holder record, the finished parts under
``CAL/parts/<plan>/`` and the capture set ``CAL/captures.json`` written from them (module doc of
:mod:`dualscale.capture.session`, "Calibration targets"; docs/CAPTURE.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import FormatError, InputError
from dualscale.formats.exr import read_exr
from dualscale.geometry.cameras import Camera as GeometryCamera

from .plan import TARGET_PLANS

FORMAT = "dualscale-capture"        # capture.json's format
PARTS = "parts"                    # a capture set's folder of calibration-target parts
RGB = ("R", "G", "B")


def _holder_record(holder: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``{"markers": {camera: [[row0, row1, col0, col1], ...]}, "chart_corners": {camera: [[x, y] x 4]}}``
    checked (``InputError`` naming the entry)."""
    unknown = sorted(set(holder) - {"markers", "chart_corners"})
    if unknown:
        raise InputError(f"holder: unknown key(s) {unknown}: markers, chart_corners")
    out: dict[str, dict[str, Any]] = {"markers": {}, "chart_corners": {}}
    for cam, boxes in (holder.get("markers") or {}).items():
        try:
            b = [[int(x) for x in box] for box in boxes]
        except (TypeError, ValueError):
            b = []
        if not b or any(len(x) != 4 or x[0] >= x[1] or x[2] >= x[3] or min(x) < 0 for x in b):
            raise InputError(f"holder: markers.{cam} must be boxes [row0, row1, col0, col1] (row0 < row1, col0 < col1)")
        out["markers"][str(cam)] = b
    for cam, pts in (holder.get("chart_corners") or {}).items():
        try:
            c = np.asarray(pts, dtype=np.float64)
        except (TypeError, ValueError):
            c = np.zeros(0)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            raise InputError(f"holder: chart_corners.{cam} must be 4 [x, y] pixel corners (TL, TR, BR, BL)")
        out["chart_corners"][str(cam)] = c.tolist()
    return out


def read_parts(root: str | Path) -> list[dict[str, Any]]:
    """The finished calibration-target parts of the capture set at ``root``, in
    :data:`~dualscale.capture.plan.TARGET_PLANS` order: each ``{"plan", "date", **captureset}``
    from ``root/parts/<plan>/capture.json`` (a part is finished when its record holds a
    ``captureset``; an interrupted one is left out until ``--resume`` finishes it)."""
    root = Path(root)
    out = []
    for name in TARGET_PLANS:
        path = root / PARTS / name / "capture.json"
        if not path.is_file():
            continue
        rec = read_capture_record(path.parent)
        part = rec.get("captureset")
        if isinstance(part, dict):
            out.append({"plan": name, "date": rec.get("date"), **part})
    return out


def _check_parts(parts: list[dict[str, Any]], root: Path) -> None:
    """``InputError`` unless the parts come from one rig and agree on every camera they share."""
    seen_rig: tuple[str, dict] | None = None
    cams: dict[str, tuple[str, dict]] = {}
    for p in parts:
        if seen_rig is not None and p["rig"] != seen_rig[1]:
            raise InputError(f"{root}: the {p['plan']} part is from rig {p['rig']}, the {seen_rig[0]} part from "
                             f"{seen_rig[1]}: one capture set holds one rig's targets (--rig-id, or another folder)")
        seen_rig = seen_rig or (p["plan"], p["rig"])
        for name, rec in p["cameras"].items():
            want = {k: rec[k] for k in ("geometry", "sensitivities", "white_level")}
            if name in cams and cams[name][1] != want:
                raise InputError(f"{root}: camera {name!r} of the {p['plan']} part differs from the one of the "
                                 f"{cams[name][0]} part ({want} vs {cams[name][1]}): capture the targets of one "
                                 "capture set with the same cameras, or use another folder")
            cams.setdefault(name, (p["plan"], want))


def write_capture_set(root: str | Path) -> Path:
    """Write ``root/captures.json`` and ``root/images/`` (:class:`dualscale.formats.captures.CaptureWriter`,
    their only writer) from every finished part under ``root/parts/`` (:func:`read_parts`): each
    part's groups with their brackets, one dark group per camera with the dark frames of every
    part, the markers and the chart record; images no group lists any more are removed.  Returns
    the manifest's path; ``InputError`` when the parts disagree (:func:`_check_parts`)."""
    from dualscale.formats.captures import CaptureWriter

    root = Path(root)
    parts = read_parts(root)
    if not parts:
        raise InputError(f"{root}: no finished calibration-target capture under {PARTS}/")
    _check_parts(parts, root)
    w = CaptureWriter(root, rig=dict(parts[0]["rig"]))
    cams: dict[str, GeometryCamera] = {}
    for p in parts:
        for name, rec in p["cameras"].items():
            if name not in cams:
                cams[name] = GeometryCamera.from_json(name, rec["geometry"], f"{root / PARTS / p['plan']}")
                w.add_camera(cams[name], rec["sensitivities"], white_level=rec["white_level"])
    darks: dict[str, list[tuple[float, str]]] = {}
    for p in parts:
        for name, pairs in p["darks"].items():
            darks.setdefault(name, []).extend((float(t), str(f)) for t, f in pairs)
    for name in cams:
        pairs = sorted(darks.get(name, []))
        if pairs:
            w.add("dark", cams[name], "off", None, [t for t, _ in pairs], [read_exr(root / f, RGB) for _, f in pairs])
    for p in parts:
        w.markers.update(p.get("markers", {}))
        if "chart" in p:
            w.chart["layout"] = p["chart"]["layout"]
            w.chart.setdefault("corners", {}).update(p["chart"]["corners"])
        for g in p["groups"]:
            w.add(g["target"], cams[g["camera"]], g["light_kind"], g["light_id"], g["exposures_s"],
                  [read_exr(root / f, RGB) for f in g["files"]], patch=g["patch"], analyzer_deg=g["analyzer_deg"],
                  analyzer_relative=g["analyzer_relative"])
    w.extra["capture"] = {"parts": {p["plan"]: {"record": f"{PARTS}/{p['plan']}/capture.json", "date": p["date"]}
                                    for p in parts}}
    path = w.close()
    keep = {f for g in w.groups for f in g.files}
    for f in (root / "images").glob("*.exr"):
        if f"images/{f.name}" not in keep:
            f.unlink()
    return path


def read_capture_record(root: str | Path) -> dict[str, Any]:
    """``DATASET/capture.json`` (module doc); ``FormatError`` if missing or not a capture record."""
    path = Path(root) / "capture.json"
    try:
        rec = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise FormatError(f"{path}: not a capture record ({e})") from e
    if rec.get("format") != FORMAT:
        raise FormatError(f"{path}: format is {rec.get('format')!r}, not {FORMAT!r}")
    return rec
