"""On-disk photometric dataset format (shared by synthetic and real captures).

Layout of a dataset directory::

    manifest.json
    images/<camera>_<source><id>_<analyser>.exr     float32 EXR, channels R, G, B (layout below)
    images/<camera>_off_<analyser>_<t>us.exr         dark frames (light 'off'), exposure t in us
    mask.exr                                         optional, channel Y: 1 = sample pixel

``manifest.json`` (version 2; version 1 is read too: it has no ``saturation``, ``mask``,
``transfer`` or ``rig``)::

    {"format": "dualscale-photometric", "version": 2,
     "units": "...", "colour_space": "...",            # defaults for every image
     "cameras": {name: {kind, width, height, field_mm, position_mm, has_analyzer}},
     "dome": {"source": "regmap" | path, "polarizer": "s", "radius_mm": ...},
     "rig": {"id": str, "layout": str} | null,         # who captured it (checked against calibrations)
     "mask": "mask.exr" | null,                        # 1 = sample pixel, 0 = ignore
     "transfer": "srgb" | "linear" | "gamma:G" | null, # what the importer decoded (report only)
     "images": [{"file": "images/...exr", "camera": "micro",
                 "light": {"kind": "led"|"backlight"|"diffuse"|"off", "id": int|null,
                           "direction": [x, y, z]|null, "intensity": float},
                 "analyzer_deg": float|null, "analyzer_relative": bool,
                 "exposure_s": float, "units": "...", "colour_space": "...",
                 "saturation": float|null, "width": W, "height": H,
                 "signal_scale": [r, g, b]}, ...],         # optional (below)
     "extra": {...}}

**Units** (:data:`UNITS`; anything else is refused with :class:`~dualscale.errors.UnitsError`):

* ``relative_radiance`` -- linear radiance relative to the rig's lights: an LED at intensity 1
  gives unit irradiance on the sample plane, a back light at intensity 1 is a panel of unit
  radiance.  The renderer's output, and what a calibration produces
  (:func:`dualscale.calib.apply.to_radiance`).  An image taken with exposure ``t`` holds
  ``t`` times the radiance, so readers divide by ``exposure_s`` (the canonical dataset the fit
  reads has ``exposure_s = 1``).  The only units the fit and propagation read.
* ``dn_normalized`` -- raw sensor output in digital numbers normalised to full scale (1.0 =
  ``2^bits - 1``), dark signal included, proportional to radiance x exposure.  Must go through
  a calibration file first (dark frame, exposure, ``r_c``/``r_ws``, CCM).

**Colour spaces** (:func:`check_colour_space`):

* ``linear_rec709`` -- linear RGB on Rec.709/sRGB primaries, D65 white, no transfer curve;
* ``camera_raw:<sensitivities>`` -- the linear raw RGB of a camera whose spectral
  sensitivities are named (e.g. ``camera_raw:Nikon 5100 (NPL)``, as the calibration captures
  record them); must go through a calibration file's CCM first.

**Saturation** (per image, optional): the value, in the image's own units, at or above which a
pixel is clipped; a pixel with any channel at or above it is never fitted as valid.  An 8-bit
photo importer sets 1.0 (the top code value decodes to 1.0); the sensor model's full scale is
1.0 ``dn_normalized``.  ``null`` means no pixel is known to be clipped.

**Signal scale** (per image, optional): per channel, the factor from the sensor's signal
(dark-subtracted DN) to the file's values, as the calibration applied it
(:func:`dualscale.calib.apply.to_radiance`: ``1 / exposure``, the white balance against the
sheet, the irradiance and the CCM's row norm; the flat field, the same for every image, is left
out).  Written only where known, so other manifests are unchanged.  It is what lets the fit's
uncertainty scale each image's read and shot noise (:mod:`dualscale.fit.uncertainty`, "Noise
model"): a value ``v`` then has the variance ``a s^2 + b s v`` for a pixel's ``a`` and ``b``.
Absent, a reader takes ``1 / (exposure_s * intensity)`` relative to the file's values (the
recorded exposure and light are what made them).  Finite and > 0
(:class:`~dualscale.errors.UnitsError`).

**Mask** (dataset level, optional): a single-channel EXR the size of every camera's images;
values above 0.5 mark sample pixels, the rest is ignored by every stage.

**Transfer** (optional): the transfer function the importer decoded the photographs with
(:data:`dualscale.formats.photo.TRANSFERS`); the pixels are always linear, this is provenance
for the report.

**Image layout** (not in the manifest: every reader reads both through
:func:`~dualscale.formats.exr.read_exr`/OpenImageIO): zip-compressed float32 EXR, scanline
(the plain layout), except the images of the cameras in :data:`TILED_CAMERAS` -- the ``micro``
camera -- which :class:`DatasetWriter` writes tiled, 64 x 64 px tiles (:func:`image_tile`), so
that a fit reading its square tiles (``read_exr(box=...)``) decodes only the tiles it needs
instead of whole rows (measured in ``bench/bench_layout.py``: a 64 x 64 region of a 2048^2
image in 0.25 ms instead of 7.2 ms, the whole image in the same time; docs/APPEARANCE.md).
``DatasetWriter(tiled=False)`` writes every image plain; the mask is always plain.

Checks at read (:func:`read_dataset`; the writer refuses the same at ``add``): documented units
and colour spaces; LED directions are unit vectors strictly above the sample plane (``z > 0``,
:class:`~dualscale.errors.GeometryError`); LED, back-light and diffuse records have intensity
> 0 (:class:`~dualscale.errors.InputError`); ``exposure_s`` finite and > 0 and ``saturation``
finite and > 0 (:class:`~dualscale.errors.UnitsError`); the mask matches the image sizes;
numbers are JSON numbers (``"width": "64"`` is refused), widths and heights whole; no two
records name the same file; every image file (and the mask) is inside the dataset folder: no
``..``, no absolute path, no symbolic link that leads out of it (:class:`FormatError`).
Every error names the file and the field.  Directions are in the sample's macro frame (see
``dualscale.geometry.dome``).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from dualscale.errors import FormatError, GeometryError, InputError, UnitsError
from dualscale.geometry.cameras import Camera

from .atomic import write_json
from .exr import read_exr, write_exr
from .versioned import read_versioned_json

FORMAT = "dualscale-photometric"
VERSION = 2
READ_VERSIONS = (1, 2)
#: documented units (module doc): name -> meaning
UNITS: dict[str, str] = {
    "relative_radiance": "linear radiance; an LED at intensity 1 gives unit irradiance, divide by exposure_s",
    "dn_normalized": "raw sensor digital numbers, 1.0 = full scale, dark signal included; needs a calibration",
}
#: units the fit and propagation read directly
CANONICAL_UNITS = "relative_radiance"
CANONICAL_COLOUR_SPACE = "linear_rec709"
CAMERA_RAW = "camera_raw:"
#: documented colour spaces (module doc); ``camera_raw:<sensitivities>`` is a family
COLOUR_SPACES: dict[str, str] = {
    "linear_rec709": "linear RGB, Rec.709/sRGB primaries, D65 white, no transfer curve",
    "camera_raw:<sensitivities>": "linear raw RGB of the named camera sensitivities; needs a calibration (CCM)",
}
LIGHT_KINDS = ("led", "backlight", "diffuse", "off")
MASK_FILE = "mask.exr"
#: the cameras whose dataset images are written tiled (module doc, "Image layout"): name ->
#: tile side in px.  64 px: the fit's tile (``dualscale.fit.tiled.TILE``) and, measured, the
#: fastest square-region read with no cost to the whole read at any size (bench/bench_layout.py)
TILED_CAMERAS: dict[str, int] = {"micro": 64}


def image_tile(camera: str, tiled: bool = True) -> int | None:
    """The tile side (px) of ``camera``'s dataset images, ``None`` for the plain scanline layout
    (every camera not in :data:`TILED_CAMERAS`, or any when ``tiled`` is False)."""
    return TILED_CAMERAS.get(camera) if tiled else None
UNIT_TOLERANCE = 1e-3


def check_units(units: Any, where: str) -> str:
    """``units`` if documented, else :class:`UnitsError` naming ``where`` (file and field)."""
    if units not in UNITS:
        raise UnitsError(f"{where}: units {units!r} are not documented; dualscale reads "
                         f"{', '.join(sorted(UNITS))} (docs/APPEARANCE.md, dataset format)")
    return str(units)


def check_colour_space(space: Any, where: str) -> str:
    """``space`` if documented (``linear_rec709`` or ``camera_raw:<name>``), else
    :class:`UnitsError` naming ``where``."""
    ok = space == "linear_rec709" or (isinstance(space, str) and space.startswith(CAMERA_RAW)
                                      and space[len(CAMERA_RAW):].strip() != "")
    if not ok:
        raise UnitsError(f"{where}: colour_space {space!r} is not documented; dualscale reads "
                         f"{', '.join(COLOUR_SPACES)} (sRGB-encoded images must be linearised by "
                         "`dualscale import --transfer ...` first)")
    return str(space)


def check_transfer(transfer: Any, where: str) -> str | None:
    """``None`` or a transfer function :func:`dualscale.formats.photo.parse_transfer` knows."""
    if transfer is None:
        return None
    if str(transfer) == "curve":  # an estimated monotone curve, recorded in extra.import.radiometry
        return "curve"
    from .photo import parse_transfer

    try:
        parse_transfer(str(transfer))
    except UnitsError as e:
        raise UnitsError(f"{where}: transfer: {e}") from e
    return str(transfer)


def _is_number(value: Any) -> bool:
    """A JSON number (numpy's too), not a string that reads as one, nor a boolean."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _whole(value: Any, name: str, where: str) -> int:
    """A manifest's pixel count: a whole number (``64``, not ``"64"``), else :class:`FormatError`."""
    if not _is_number(value) or not math.isfinite(value) or value != int(value):
        raise FormatError(f"{where}: {name} must be a whole number, got {value!r}")
    return int(value)


def _check_camera_numbers(name: str, c: Any, where: str) -> None:
    """The camera record's numbers are JSON numbers (``Camera.from_json`` would read ``"64"``)."""
    if not isinstance(c, dict):
        return  # Camera.from_json refuses it, naming it
    w = f"{where}: camera {name!r}"
    for key in ("width", "height"):
        if key in c:
            _whole(c[key], key, w)
    for key in ("field_mm", "position_mm"):
        if isinstance(c.get(key), list) and not all(_is_number(v) for v in c[key]):
            raise FormatError(f"{w}: {key} must be a list of numbers in mm, got {c[key]!r}")


def _positive(value: Any, name: str, where: str, error: type[InputError]) -> float:
    try:
        v = float(value) if not isinstance(value, (str, bytes, bool)) else float("nan")
    except (TypeError, ValueError):
        v = float("nan")
    if not math.isfinite(v) or v <= 0:
        raise error(f"{where}: {name} must be a finite number > 0, got {value!r}")
    return v


def check_direction(direction: Any, where: str) -> list[float]:
    """A light direction: 3 finite numbers of unit length, strictly above the sample plane
    (``z > 0``); :class:`GeometryError` otherwise."""
    try:
        d = [float(x) for x in direction]
    except (TypeError, ValueError) as e:
        raise GeometryError(f"{where}: light.direction {direction!r} is not a list of numbers") from e
    n = math.sqrt(sum(x * x for x in d)) if len(d) == 3 else float("nan")
    if len(d) != 3 or not math.isfinite(n) or abs(n - 1) > UNIT_TOLERANCE:
        raise GeometryError(f"{where}: light.direction {direction} is not a unit vector")
    if d[2] <= 0:
        raise GeometryError(f"{where}: light.direction {direction} has z = {d[2]:g} <= 0: the light is "
                            "below or on the sample plane, where it cannot light the visible side")
    return d


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
    saturation: float | None = None
    #: per channel, the factor from the sensor's signal (dark-subtracted DN) to this file's values
    #: (module doc, "signal_scale"); ``None``: not recorded
    signal_scale: list[float] | None = None

    def to_json(self) -> dict[str, Any]:
        d = {"file": self.file, "camera": self.camera,
             "light": {"kind": self.light_kind, "id": self.light_id, "direction": self.direction,
                       "intensity": self.intensity},
             "analyzer_deg": self.analyzer_deg, "analyzer_relative": self.analyzer_relative,
             "exposure_s": self.exposure_s, "units": self.units, "colour_space": self.colour_space,
             "saturation": self.saturation, "width": self.width, "height": self.height}
        if self.signal_scale is not None:  # only when recorded: other manifests stay as they were
            d["signal_scale"] = list(self.signal_scale)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], defaults: dict[str, Any] | None = None,
                  where: str = "manifest.json") -> "ImageRecord":
        """Parse one image record (``defaults``: the manifest's ``units``/``colour_space``);
        :class:`FormatError` for a malformed record; values are checked by :meth:`validate`."""
        defaults = defaults or {}
        try:
            light = d["light"]
            sat = d.get("saturation")
            return cls(file=str(d["file"]), camera=str(d["camera"]), light_kind=str(light["kind"]),
                       light_id=None if light.get("id") is None else int(light["id"]),
                       direction=None if light.get("direction") is None else list(light["direction"]),
                       intensity=light.get("intensity", 1.0),
                       analyzer_deg=None if d.get("analyzer_deg") is None else float(d["analyzer_deg"]),
                       analyzer_relative=bool(d.get("analyzer_relative", False)), exposure_s=d["exposure_s"],
                       units=d.get("units", defaults.get("units")),
                       colour_space=d.get("colour_space", defaults.get("colour_space")),
                       width=_whole(d["width"], "width", f"{where}: image {d.get('file')!r}"),
                       height=_whole(d["height"], "height", f"{where}: image {d.get('file')!r}"), saturation=sat,
                       signal_scale=d.get("signal_scale"))
        except FormatError:
            raise
        except (KeyError, TypeError, ValueError) as e:
            raise FormatError(f"{where}: malformed image record {d!r}: {e}") from e

    def validate(self, where: str) -> "ImageRecord":
        """Check every value (module doc); normalises numbers in place and returns ``self``."""
        w = f"{where}: image {self.file}"
        if self.light_kind not in LIGHT_KINDS:
            raise FormatError(f"{w}: light.kind {self.light_kind!r} is not one of {LIGHT_KINDS}")
        self.units = check_units(self.units, w)
        self.colour_space = check_colour_space(self.colour_space, w)
        self.exposure_s = _positive(self.exposure_s, "exposure_s", w, UnitsError)
        if self.saturation is not None:
            self.saturation = _positive(self.saturation, "saturation", w, UnitsError)
        if self.light_kind == "off":
            self.intensity = float(self.intensity) if self.intensity is not None else 0.0
        else:
            self.intensity = _positive(self.intensity, "light.intensity", w, InputError)
        if self.direction is not None and self.light_kind == "led":
            self.direction = check_direction(self.direction, w)
        elif self.direction is not None:
            self.direction = [float(x) for x in self.direction]
        if self.width <= 0 or self.height <= 0:
            raise FormatError(f"{w}: width/height must be positive, got {self.width}x{self.height}")
        if self.signal_scale is not None:
            s = self.signal_scale
            if not isinstance(s, (list, tuple)) or len(s) != 3:
                raise FormatError(f"{w}: signal_scale must be a list of 3 numbers, got {s!r}")
            self.signal_scale = [_positive(v, "signal_scale", w, UnitsError) for v in s]
        return self


def _microseconds(exposure_s: Any) -> str:
    try:
        return str(int(round(float(exposure_s) * 1e6)))
    except (TypeError, ValueError, OverflowError):
        return "bad"


@dataclass
class DatasetWriter:
    """Writes images one by one (each EXR atomically), then the mask and the manifest
    (``close``, atomically).  Use as a context manager: the manifest is written only when the
    block ends without an error, so a failed run leaves no dataset a reader would accept.

    ``units`` / ``colour_space``: see the module doc; ``mask``: ``(H, W)`` array (nonzero =
    sample pixel), written as ``mask.exr``; ``transfer``: the transfer function decoded by an
    importer; ``rig``: ``{"id", "layout"}`` of the capturing rig; ``tiled``: write the images of
    the cameras in :data:`TILED_CAMERAS` (``micro``) tiled (default), or, False, every image in
    the plain scanline layout (module doc, "Image layout"; the manifest is the same).
    """

    root: Path
    units: str = "relative_radiance"
    colour_space: str = "linear_rec709"
    dome: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    records: list[ImageRecord] = field(default_factory=list)
    cameras: dict[str, dict[str, Any]] = field(default_factory=dict)
    mask: Any = None
    transfer: str | None = None
    rig: dict[str, Any] | None = None
    tiled: bool = True

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        check_units(self.units, f"dataset {self.root}")
        check_colour_space(self.colour_space, f"dataset {self.root}")
        check_transfer(self.transfer, f"dataset {self.root}")
        if self.mask is not None:
            m = np.asarray(self.mask)
            if m.ndim != 2 or not np.isfinite(m.astype(np.float64)).all():
                raise GeometryError(f"dataset {self.root}: mask must be a finite (H, W) array, got shape {m.shape}")
            self.mask = (m > 0.5) if m.dtype != bool else m
            if not self.mask.any():
                raise InputError(f"dataset {self.root}: the mask is empty (no sample pixel)")
        (self.root / "images").mkdir(parents=True, exist_ok=True)

    def add(self, image: np.ndarray, camera: Camera, light_kind: str, light_id: int | None = None,
            direction: list[float] | None = None, intensity: float = 1.0, analyzer_deg: float | None = None,
            analyzer_relative: bool = False, exposure_s: float = 1.0,
            saturation: float | None = None, signal_scale: list[float] | None = None) -> ImageRecord:
        """Write one image ``(H, W, 3)`` (the camera's size, finite) in the writer's units;
        ``saturation``: the value at/above which its pixels are clipped; ``signal_scale``: per
        channel, the factor from the sensor's signal to these values (module doc)."""
        img = np.asarray(image, dtype=np.float32)
        if img.shape != (camera.height, camera.width, 3):
            raise ValueError(f"image is {img.shape}, camera {camera.name!r} needs {(camera.height, camera.width, 3)}")
        if not np.isfinite(img).all():
            raise ValueError("image contains NaN or Inf")
        if light_kind not in LIGHT_KINDS:
            raise ValueError(f"unknown light kind {light_kind!r}")
        src = light_kind if light_id is None else f"{light_kind}{light_id:03d}"
        if analyzer_deg is None:
            pol = "nopol"
        else:
            pol = f"{'rel' if analyzer_relative else 'abs'}{int(round(analyzer_deg * 100)):05d}"
        # dark frames (light 'off') differ only by exposure: it is part of their name
        tag = f"_{_microseconds(exposure_s)}us" if light_kind == "off" else ""
        name = f"images/{camera.name}_{src}_{pol}{tag}.exr"
        if any(r.file == name for r in self.records):
            raise ValueError(f"duplicate image {name}")
        rec = ImageRecord(name, camera.name, light_kind, light_id,
                          None if direction is None else [float(x) for x in direction], intensity, analyzer_deg,
                          analyzer_relative, exposure_s, self.units, self.colour_space, camera.width,
                          camera.height, saturation, None if signal_scale is None else [float(v) for v in signal_scale])
        rec.validate(f"dataset {self.root}")
        if self.mask is not None and self.mask.shape != (camera.height, camera.width):
            raise GeometryError(f"dataset {self.root}: mask is {self.mask.shape[1]}x{self.mask.shape[0]}, camera "
                                f"{camera.name!r} images are {camera.width}x{camera.height}")
        write_exr(self.root / name, img, attributes={"dualscale:units": self.units,
                                                     "dualscale:colour_space": self.colour_space},
                  tile=image_tile(camera.name, self.tiled))
        self.records.append(rec)
        self.cameras[camera.name] = {k: v for k, v in asdict(camera).items() if k != "name"}
        return rec

    def close(self) -> Path:
        """Write the mask (if any), then the manifest; returns the manifest's path."""
        mask_name = None
        if self.mask is not None:
            mask_name = MASK_FILE
            write_exr(self.root / MASK_FILE, self.mask.astype(np.float32), ("Y",))
        manifest = {"format": FORMAT, "version": VERSION, "units": self.units, "colour_space": self.colour_space,
                    "cameras": self.cameras, "dome": self.dome, "rig": self.rig, "mask": mask_name,
                    "transfer": self.transfer, "images": [r.to_json() for r in self.records], "extra": self.extra}
        return write_json(self.root / "manifest.json", manifest)

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
    _mask: np.ndarray | None = field(default=None, repr=False)

    @property
    def version(self) -> int:
        return int(self.manifest.get("version", 1))

    @property
    def transfer(self) -> str | None:
        return self.manifest.get("transfer")

    @property
    def rig(self) -> dict[str, Any] | None:
        return self.manifest.get("rig")

    @property
    def texel_known(self) -> bool:
        """False for photographs imported without a scale (``extra.import.texel_mm_known``):
        the cameras' fields are then nominal and no stage may report a physical size."""
        return self.manifest.get("extra", {}).get("import", {}).get("texel_mm_known") is not False

    def mask(self) -> np.ndarray | None:
        """The sample mask ``(H, W)`` bool (True = sample pixel), or ``None`` without one."""
        return self._mask

    def load(self, index: int, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Image ``index`` as float32 ``(H, W, 3)``, in its record's units (not divided by the
        exposure), checked against its record; ``box`` ``(y0, y1, x0, x1)``: only that region
        (:func:`~dualscale.formats.exr.read_exr`), checked against the record's size."""
        rec = self.records[index]
        if box is not None:
            y0, y1, x0, x1 = box
            if not (0 <= y0 < y1 <= rec.height and 0 <= x0 < x1 <= rec.width):
                raise ValueError(f"{rec.file}: region rows {y0}..{y1}, columns {x0}..{x1} is outside the "
                                 f"manifest's {rec.width}x{rec.height}")
            img = read_exr(self.root / rec.file, ("R", "G", "B"), box=box, size=(rec.height, rec.width))
        else:
            img = read_exr(self.root / rec.file, ("R", "G", "B"))
        if img.shape[:2] != ((rec.height, rec.width) if box is None else (box[1] - box[0], box[3] - box[2])):
            raise ValueError(f"{rec.file}: image is {img.shape[:2]}, manifest says {(rec.height, rec.width)}")
        if not np.isfinite(img).all():
            raise ValueError(f"{rec.file}: contains NaN or Inf")
        return img

    def require_radiance(self, camera: str | None = None, stage: str = "this stage") -> None:
        """Refuse (:class:`UnitsError` naming the image and the field, and the way out) unless
        every image (of ``camera``, or all) is ``relative_radiance`` in ``linear_rec709``: the
        only data the fit and propagation read."""
        for rec in self.records:
            if camera is not None and rec.camera != camera:
                continue
            where = f"dataset {self.root}: image {rec.file}"
            how = (f"{stage} reads {CANONICAL_UNITS} in {CANONICAL_COLOUR_SPACE} only; apply a calibration first: "
                   "`dualscale digitize DATASET --calibration CAL -o RUN`, or "
                   "dualscale.calib.apply.to_radiance(DATASET, OUT, CAL), which writes the calibrated dataset")
            if rec.units != CANONICAL_UNITS:
                raise UnitsError(f"{where}: units {rec.units!r} are raw sensor values, not radiance; {how}")
            if rec.colour_space != CANONICAL_COLOUR_SPACE:
                raise UnitsError(f"{where}: colour_space {rec.colour_space!r} is a camera's raw RGB; {how}")

    def load_radiance(self, index: int) -> np.ndarray:
        """Image ``index`` as radiance per unit light intensity per second of exposure
        (``load / (exposure_s * intensity)``; dark frames: per second only), float32
        ``(H, W, 3)``; call :meth:`require_radiance` first."""
        rec = self.records[index]
        scale = rec.exposure_s * (rec.intensity if rec.light_kind != "off" else 1.0)
        return self.load(index) / np.float32(scale)

    def clipped(self, index: int, image: np.ndarray) -> np.ndarray | None:
        """``(H, W)`` bool: pixels of image ``index`` with a channel at or above its
        ``saturation``; ``None`` when the record gives none."""
        sat = self.records[index].saturation
        return None if sat is None else (np.asarray(image) >= sat).any(-1)

    def valid(self, index: int, image: np.ndarray, box: tuple[int, int, int, int] | None = None) -> np.ndarray | None:
        """``(H, W)`` bool: pixels neither clipped nor outside the mask; ``None`` when both
        are unknown (every pixel valid).  ``box``: ``image`` is that region of the image (the
        mask is cut to it)."""
        clip = self.clipped(index, image)
        m = self._mask
        if m is not None and box is not None:
            m = m[box[0]:box[1], box[2]:box[3]]
        if clip is None:
            return None if m is None else m.copy()
        return ~clip if m is None else (~clip & m)

    def select(self, **criteria: Any) -> list[int]:
        """Indices of records whose attributes equal every ``criteria`` value."""
        return [i for i, r in enumerate(self.records) if all(getattr(r, k) == v for k, v in criteria.items())]


def _read_mask(root: Path, name: Any, cameras: dict[str, Any], where: str) -> np.ndarray:
    if not isinstance(name, str) or not name or Path(name).is_absolute() or ".." in Path(name).parts:
        raise FormatError(f"{where}: mask {name!r} must be a file name inside the dataset")
    path = root / name
    if not path.is_file():
        raise FileNotFoundError(f"{path} (the manifest's mask) is missing")
    real, inside = path.resolve(), root.resolve()
    if inside not in real.parents:
        raise FormatError(f"{where}: mask {name!r} is a link to {real}, outside the dataset folder")
    m = read_exr(path)
    if not np.isfinite(m).all():
        raise ValueError(f"{path}: the mask contains NaN or Inf")
    mask = m[..., 0] > 0.5
    for cam, c in cameras.items():
        if (int(c.get("height", -1)), int(c.get("width", -1))) != mask.shape:
            raise GeometryError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, camera {cam!r} images are "
                                f"{c.get('width')}x{c.get('height')}")
    if not mask.any():
        raise InputError(f"{path}: the mask is empty (no sample pixel)")
    return mask


def resolve_root(root: str | Path) -> Path:
    """The dataset folder of ``root``: ``root`` itself, or ``root/micro`` for the folder
    ``dualscale synth --dataset`` writes; ``FileNotFoundError`` when there is none."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"dataset not found: {root}")
    if root.is_dir() and not (root / "manifest.json").is_file() and (root / "micro" / "manifest.json").is_file():
        return root / "micro"
    return root


def read_dataset(root: str | Path) -> Dataset:
    """Open a dataset directory and validate its manifest (module doc), its mask, and that
    every listed image exists (not the pixels; see ``Dataset.load``).

    Raises ``FileNotFoundError``, :class:`FormatError` (not a dataset, malformed record),
    :class:`UnitsError`, :class:`GeometryError` and :class:`InputError` naming the file and
    the field; reads versions 1 and 2."""
    root = Path(root)
    path = root / "manifest.json"
    manifest = read_versioned_json(path, FORMAT, READ_VERSIONS)
    where = str(path)
    defaults = {"units": manifest.get("units"), "colour_space": manifest.get("colour_space")}
    check_units(defaults["units"], f"{where}: dataset")
    check_colour_space(defaults["colour_space"], f"{where}: dataset")
    check_transfer(manifest.get("transfer"), where)
    images = manifest.get("images", [])
    if not isinstance(images, list):
        raise FormatError(f"{where}: images must be a list")
    records = [ImageRecord.from_json(d, defaults, where).validate(where) for d in images]
    cameras = manifest.get("cameras", {})
    if not isinstance(cameras, dict):
        raise FormatError(f"{where}: cameras must be an object of camera records")
    for name, c in cameras.items():
        _check_camera_numbers(name, c, where)
        try:
            Camera.from_json(name, c, where)
        except ValueError as e:
            raise FormatError(str(e)) from e
    inside = root.resolve()
    seen: dict[PurePosixPath, int] = {}
    for i, r in enumerate(records):
        rel = PurePosixPath(r.file.replace("\\", "/"))
        if rel.is_absolute() or ".." in rel.parts or Path(r.file).is_absolute() or str(rel)[1:3] == ":/":
            raise FormatError(f"{where}: image file {r.file!r} is not inside the dataset folder (a manifest names "
                              "its images by paths relative to it, without '..')")
        if rel in seen:
            j = seen[rel]
            raise FormatError(f"{where}: images {j} ({records[j].file}) and {i} ({r.file}) name the same file; "
                              "each image record needs its own file")
        seen[rel] = i
        real = (root / r.file).resolve()
        if real != inside and inside not in real.parents:  # a symbolic link out of the dataset: as '..'
            raise FormatError(f"{where}: image file {r.file!r} is a link to {real}, outside the dataset folder "
                              "(a manifest's images are files inside it)")
        if r.camera not in cameras:
            raise FormatError(f"{where}: image {r.file} is from camera {r.camera!r}, which the manifest's cameras "
                              f"({', '.join(sorted(cameras)) or 'none'}) do not define")
        if not (root / r.file).is_file():
            raise FileNotFoundError(f"{root / r.file} listed in the manifest is missing")
    mask = None
    if manifest.get("mask") is not None:
        mask = _read_mask(root, manifest["mask"], manifest.get("cameras", {}), where)
    return Dataset(root, manifest, records, mask)
