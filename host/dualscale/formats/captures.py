"""Calibration capture sets on disk: a JSON manifest and one float32 EXR per bracket.

``captures.json``::

    {"format": "dualscale-calib-captures", "version": 2, "date": ISO-8601,
     "rig": {"id": str, "layout": str},          # who took them (checked against calib files)
     "units": "dn_normalized",                    # 1.0 = full scale, linear
     "cameras": {name: {kind, width, height, field_mm, position_mm, has_analyzer,
                        "sensitivities": str,     # colour space: camera_raw:<sensitivities>
                        "white_level": [r, g, b]}},   # optional, version 2: see below
     "markers": {camera: [[row0, row1, col0, col1], ...]},   # white markers on the holder
     "chart": {"layout": {rows, cols, pitch_mm, patch_mm}, "corners": {camera: [[x, y] x 4]}},
     "groups": [{"id", "target", "patch", "camera", "light": {"kind", "id"},
                 "analyzer_deg", "analyzer_relative", "exposures_s": [...], "files": [...],
                 "date"}],
     "extra": {...}}

``target`` is one of ``dark``, ``white_sheet``, ``chart``, ``patch`` (one ColorChecker patch
filling the micro field, index in ``patch``), ``dot_grid`` or ``polarization``.  A group is
one scene under one light and analyser setting; its files are the exposure brackets.

``white_level`` (version 2, optional): the raw level per channel, in normalised DN before dark
subtraction, at which the camera clips (a sensor may top out below nominal full scale 1.0).  It
must be in ``(0, 1]``.  When a camera record has none (every version 1 file), the calibration
measures it from the brackets (:func:`dualscale.calib.hdr.measure_white_level`).  Version 1
files still read; the writer writes version 2.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.geometry.cameras import Camera
from dualscale.formats.atomic import write_json
from dualscale.formats.exr import read_exr, write_exr
from dualscale.formats.versioned import read_versioned_json

from dualscale.errors import CalibrationError, ImageSizeError, MissingBracketsError

FORMAT = "dualscale-calib-captures"
VERSION = 2
READ_VERSIONS = (1, 2)
"""Versions :func:`read_captures` accepts: 1 (no white level) and 2 (optional ``white_level``)."""
TARGETS = ("dark", "white_sheet", "chart", "patch", "dot_grid", "polarization")


def light_key(kind: str, light_id: int | None) -> str:
    """``led012``, ``backlight0``, ``diffuse``, ``off``."""
    if kind == "led":
        return f"led{int(light_id):03d}"
    if kind == "backlight":
        return f"backlight{int(light_id or 0)}"
    if kind in ("diffuse", "off"):
        return kind
    raise ValueError(f"unknown light kind {kind!r}")


@dataclass
class Group:
    id: str
    target: str
    camera: str
    light_kind: str
    light_id: int | None
    exposures_s: list[float]
    files: list[str]
    patch: int | None = None
    analyzer_deg: float | None = None
    analyzer_relative: bool = False
    date: str = ""

    @property
    def light(self) -> str:
        return light_key(self.light_kind, self.light_id)

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "target": self.target, "patch": self.patch, "camera": self.camera,
                "light": {"kind": self.light_kind, "id": self.light_id}, "analyzer_deg": self.analyzer_deg,
                "analyzer_relative": self.analyzer_relative, "exposures_s": self.exposures_s,
                "files": self.files, "date": self.date}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Group":
        try:
            g = cls(id=str(d["id"]), target=str(d["target"]), camera=str(d["camera"]),
                    light_kind=str(d["light"]["kind"]),
                    light_id=None if d["light"].get("id") is None else int(d["light"]["id"]),
                    exposures_s=[float(t) for t in d["exposures_s"]], files=[str(f) for f in d["files"]],
                    patch=None if d.get("patch") is None else int(d["patch"]),
                    analyzer_deg=None if d.get("analyzer_deg") is None else float(d["analyzer_deg"]),
                    analyzer_relative=bool(d.get("analyzer_relative", False)), date=str(d.get("date", "")))
        except (KeyError, TypeError, ValueError) as e:
            raise CalibrationError(f"malformed capture group {d!r}: {e}") from e
        if g.target not in TARGETS:
            raise CalibrationError(f"group {g.id}: unknown target {g.target!r}")
        if not g.files or len(g.files) != len(g.exposures_s):
            raise MissingBracketsError(f"group {g.id}: {len(g.files)} files for {len(g.exposures_s)} exposures")
        return g


def white_level_record(value: Any, where: str) -> list[float] | None:
    """A camera record's ``white_level`` as ``[r, g, b]`` normalised DN, or ``None`` when absent;
    one number stands for all three channels.  :class:`CalibrationError` naming ``where`` when
    it is not 1 or 3 finite numbers in ``(0, 1]``."""
    if value is None:
        return None
    try:
        v = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"{where}: white_level must be 1 or 3 numbers in (0, 1] normalised DN, "
                               f"got {value!r}") from e
    if v.size == 1:
        v = np.repeat(v, 3)
    if v.size != 3 or not np.all(np.isfinite(v)) or np.any(v <= 0) or np.any(v > 1.0):
        raise CalibrationError(f"{where}: white_level must be 1 or 3 numbers in (0, 1] normalised DN, got {value!r}")
    return [float(x) for x in v]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@dataclass
class CaptureWriter:
    """Writes groups of brackets, then the manifest (``close``, atomic)."""

    root: Path
    rig: dict[str, str]
    cameras: dict[str, dict[str, Any]] = field(default_factory=dict)
    markers: dict[str, list[list[int]]] = field(default_factory=dict)
    chart: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    groups: list[Group] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        (self.root / "images").mkdir(parents=True, exist_ok=True)

    def add_camera(self, camera: Camera, sensitivities: str, white_level: float | list[float] | None = None) -> None:
        """Describe a camera; ``white_level`` (one value or ``[r, g, b]``, normalised raw DN in
        ``(0, 1]``) declares where it clips; ``None`` leaves it to be measured."""
        rec = {**{k: v for k, v in asdict(camera).items() if k != "name"}, "sensitivities": sensitivities}
        wl = white_level_record(white_level, f"camera {camera.name!r}")
        if wl is not None:
            rec["white_level"] = wl
        self.cameras[camera.name] = rec

    def add(self, target: str, camera: Camera, light_kind: str, light_id: int | None, exposures_s: list[float],
            images: list[np.ndarray], patch: int | None = None, analyzer_deg: float | None = None,
            analyzer_relative: bool = False) -> Group:
        if target not in TARGETS:
            raise ValueError(f"unknown target {target!r}")
        if camera.name not in self.cameras:
            raise ValueError(f"add_camera({camera.name!r}) first")
        pol = "nopol" if analyzer_deg is None else f"{'rel' if analyzer_relative else 'abs'}{int(round(analyzer_deg * 100)):05d}"
        gid = f"{camera.name}_{target}{'' if patch is None else f'{patch:02d}'}_{light_key(light_kind, light_id)}_{pol}"
        if any(g.id == gid for g in self.groups):
            raise ValueError(f"duplicate group {gid}")
        files = []
        for k, (t, img) in enumerate(zip(exposures_s, images)):
            name = f"images/{gid}_b{k}.exr"
            write_exr(self.root / name, np.asarray(img, np.float32), attributes={"dualscale:exposure_s": f"{t:.9g}"})
            files.append(name)
        g = Group(gid, target, camera.name, light_kind, light_id, [float(t) for t in exposures_s], files, patch,
                  analyzer_deg, analyzer_relative, _now())
        self.groups.append(g)
        return g

    def close(self) -> Path:
        manifest = {"format": FORMAT, "version": VERSION, "date": _now(), "rig": self.rig, "units": "dn_normalized",
                    "cameras": self.cameras, "markers": self.markers, "chart": self.chart,
                    "groups": [g.to_json() for g in self.groups], "extra": self.extra}
        return write_json(self.root / "captures.json", manifest)


@dataclass
class CaptureSet:
    root: Path
    manifest: dict[str, Any]
    groups: list[Group]

    @property
    def rig(self) -> dict[str, str]:
        return dict(self.manifest.get("rig", {}))

    def camera(self, name: str) -> Camera:
        try:
            c = dict(self.manifest["cameras"][name])
        except KeyError as e:
            raise CalibrationError(f"camera {name!r} is not described in the capture manifest") from e
        c.pop("sensitivities", None)
        c.pop("white_level", None)
        return Camera.from_json(name, c, f"{self.root / 'captures.json'}")

    def white_level(self, name: str) -> list[float] | None:
        """The declared white level ``[r, g, b]`` (normalised raw DN) of camera ``name``, or
        ``None`` when the manifest declares none (version 1, or left to be measured)."""
        try:
            rec = self.manifest["cameras"][name]
        except KeyError as e:
            raise CalibrationError(f"camera {name!r} is not described in the capture manifest") from e
        return white_level_record(rec.get("white_level"),
                                  f"{self.root / 'captures.json'}: cameras.{name}.white_level")

    def select(self, **criteria: Any) -> list[Group]:
        return [g for g in self.groups if all(getattr(g, k) == v for k, v in criteria.items())]

    def load(self, group: Group) -> list[np.ndarray]:
        """The group's brackets as float64 ``(H, W, 3)``, checked against its camera's size."""
        cam = self.camera(group.camera)
        out = []
        for f in group.files:
            p = self.root / f
            if not p.is_file():
                raise MissingBracketsError(f"group {group.id}: bracket {f} is missing")
            img = read_exr(p, ("R", "G", "B")).astype(np.float64)
            if img.shape[:2] != (cam.height, cam.width):
                raise ImageSizeError(f"{f}: image is {img.shape[1]}x{img.shape[0]}, camera {cam.name!r} "
                                     f"is {cam.width}x{cam.height}")
            out.append(img)
        return out


def read_captures(root: str | Path) -> CaptureSet:
    """Open and validate a capture set (version 1 or 2; every listed bracket must exist, every
    declared white level must be valid)."""
    root = Path(root)
    path = root / "captures.json"
    m = read_versioned_json(path, FORMAT, READ_VERSIONS, CalibrationError)
    if not m.get("rig", {}).get("id"):
        raise CalibrationError(f"{path}: no rig identity")
    for name, rec in (m.get("cameras") or {}).items():
        if isinstance(rec, dict):
            white_level_record(rec.get("white_level"), f"{path}: cameras.{name}.white_level")
    groups = [Group.from_json(d) for d in m.get("groups", [])]
    for g in groups:
        if g.camera not in m.get("cameras", {}):
            raise CalibrationError(f"group {g.id}: camera {g.camera!r} not described")
        for f in g.files:
            if not (root / f).is_file():
                raise MissingBracketsError(f"group {g.id}: bracket {f} listed in the manifest is missing")
    return CaptureSet(root, m, groups)
