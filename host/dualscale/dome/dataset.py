"""On-disk photometric dataset format (shared by synthetic and real captures).

Layout of a dataset directory::

    manifest.json
    images/<camera>_<source><id>_<analyser>.exr     float32 EXR, channels R, G, B

``manifest.json``::

    {"format": "dualscale-photometric", "version": 1,
     "units": "...", "colour_space": "...",            # defaults for every image
     "cameras": {name: {kind, width, height, field_mm, position_mm, has_analyzer}},
     "dome": {"source": "regmap" | path, "polarizer": "s", "radius_mm": ...},
     "images": [{"file": "images/...exr", "camera": "micro",
                 "light": {"kind": "led"|"backlight"|"diffuse"|"off", "id": int|null,
                           "direction": [x, y, z]|null, "intensity": float},
                 "analyzer_deg": float|null, "analyzer_relative": bool,
                 "exposure_s": float, "units": "...", "colour_space": "...",
                 "width": W, "height": H}, ...],
     "extra": {...}}

Directions are unit vectors in the sample's macro frame (see ``dualscale.dome.geometry``).
``units`` is ``"relative_radiance"`` (renderer output, an LED at intensity 1 gives unit
irradiance) or ``"dn_normalized"`` (sensor output, 1.0 = full scale).  ``colour_space`` is
``"linear_rec709"`` (linear RGB, Rec.709/sRGB primaries, no transfer curve) or
``"camera_raw:<sensitivities>"``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..manifest import read_versioned_json
from .cameras import Camera
from .exr import read_exr, write_exr

FORMAT = "dualscale-photometric"
VERSION = 1
UNITS = ("relative_radiance", "dn_normalized")


@dataclass
class ImageRecord:
    file: str
    camera: str
    light_kind: str
    light_id: int | None
    direction: list[float] | None
    intensity: float
    analyzer_deg: float | None
    analyzer_relative: bool
    exposure_s: float
    units: str
    colour_space: str
    width: int
    height: int

    def to_json(self) -> dict[str, Any]:
        return {"file": self.file, "camera": self.camera,
                "light": {"kind": self.light_kind, "id": self.light_id, "direction": self.direction,
                          "intensity": self.intensity},
                "analyzer_deg": self.analyzer_deg, "analyzer_relative": self.analyzer_relative,
                "exposure_s": self.exposure_s, "units": self.units, "colour_space": self.colour_space,
                "width": self.width, "height": self.height}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ImageRecord":
        try:
            light = d["light"]
            return cls(file=str(d["file"]), camera=str(d["camera"]), light_kind=str(light["kind"]),
                       light_id=None if light.get("id") is None else int(light["id"]),
                       direction=None if light.get("direction") is None else [float(x) for x in light["direction"]],
                       intensity=float(light.get("intensity", 1.0)),
                       analyzer_deg=None if d.get("analyzer_deg") is None else float(d["analyzer_deg"]),
                       analyzer_relative=bool(d.get("analyzer_relative", False)), exposure_s=float(d["exposure_s"]),
                       units=str(d["units"]), colour_space=str(d["colour_space"]), width=int(d["width"]),
                       height=int(d["height"]))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"malformed image record {d!r}: {e}") from e


@dataclass
class DatasetWriter:
    """Writes images one by one, then the manifest (``close``).  Use as a context manager."""

    root: Path
    units: str = "relative_radiance"
    colour_space: str = "linear_rec709"
    dome: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    records: list[ImageRecord] = field(default_factory=list)
    cameras: dict[str, dict[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        if self.units not in UNITS:
            raise ValueError(f"units must be one of {UNITS}")
        (self.root / "images").mkdir(parents=True, exist_ok=True)

    def add(self, image: np.ndarray, camera: Camera, light_kind: str, light_id: int | None = None,
            direction: list[float] | None = None, intensity: float = 1.0, analyzer_deg: float | None = None,
            analyzer_relative: bool = False, exposure_s: float = 1.0) -> ImageRecord:
        img = np.asarray(image, dtype=np.float32)
        if img.shape != (camera.height, camera.width, 3):
            raise ValueError(f"image is {img.shape}, camera {camera.name!r} needs {(camera.height, camera.width, 3)}")
        if not np.isfinite(img).all():
            raise ValueError("image contains NaN or Inf")
        if light_kind not in ("led", "backlight", "diffuse", "off"):
            raise ValueError(f"unknown light kind {light_kind!r}")
        src = light_kind if light_id is None else f"{light_kind}{light_id:03d}"
        if analyzer_deg is None:
            pol = "nopol"
        else:
            pol = f"{'rel' if analyzer_relative else 'abs'}{int(round(analyzer_deg * 100)):05d}"
        name = f"images/{camera.name}_{src}_{pol}.exr"
        if any(r.file == name for r in self.records):
            raise ValueError(f"duplicate image {name}")
        write_exr(self.root / name, img, attributes={"dualscale:units": self.units,
                                                     "dualscale:colour_space": self.colour_space})
        rec = ImageRecord(name, camera.name, light_kind, light_id, direction, float(intensity), analyzer_deg,
                          analyzer_relative, float(exposure_s), self.units, self.colour_space, camera.width,
                          camera.height)
        self.records.append(rec)
        self.cameras[camera.name] = {k: v for k, v in asdict(camera).items() if k != "name"}
        return rec

    def close(self) -> Path:
        manifest = {"format": FORMAT, "version": VERSION, "units": self.units, "colour_space": self.colour_space,
                    "cameras": self.cameras, "dome": self.dome, "images": [r.to_json() for r in self.records],
                    "extra": self.extra}
        path = self.root / "manifest.json"
        path.write_text(json.dumps(manifest, indent=1))
        return path

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, *_: Any) -> None:
        if exc_type is None:
            self.close()


@dataclass
class Dataset:
    root: Path
    manifest: dict[str, Any]
    records: list[ImageRecord]

    def load(self, index: int) -> np.ndarray:
        """Image ``index`` as float32 ``(H, W, 3)``, checked against its record."""
        rec = self.records[index]
        img = read_exr(self.root / rec.file, ("R", "G", "B"))
        if img.shape[:2] != (rec.height, rec.width):
            raise ValueError(f"{rec.file}: image is {img.shape[:2]}, manifest says {(rec.height, rec.width)}")
        if not np.isfinite(img).all():
            raise ValueError(f"{rec.file}: contains NaN or Inf")
        return img

    def select(self, **criteria: Any) -> list[int]:
        """Indices of records whose attributes equal every ``criteria`` value."""
        return [i for i, r in enumerate(self.records) if all(getattr(r, k) == v for k, v in criteria.items())]


def read_dataset(root: str | Path) -> Dataset:
    """Open a dataset directory and validate its manifest (not the pixels; see ``Dataset.load``)."""
    root = Path(root)
    manifest = read_versioned_json(root / "manifest.json", FORMAT, VERSION)
    records = [ImageRecord.from_json(d) for d in manifest.get("images", [])]
    for r in records:
        if r.units not in UNITS:
            raise ValueError(f"{r.file}: unknown units {r.units!r}")
        if r.direction is not None:
            n = math.sqrt(sum(x * x for x in r.direction))
            if len(r.direction) != 3 or not math.isfinite(n) or abs(n - 1) > 1e-3:
                raise ValueError(f"{r.file}: light direction {r.direction} is not a unit vector")
        if not (root / r.file).is_file():
            raise FileNotFoundError(f"{root / r.file} listed in the manifest is missing")
    return Dataset(root, manifest, records)
