"""The guidance image: the mid-range picture of the whole sample that propagation runs over
(seed Section 7.2: diffuse light, mid-range camera, 4072 x 4072 px over 10 x 10 cm).

:func:`read_guidance` accepts

* a photometric dataset folder (what ``dualscale synth --mid`` writes): its ``diffuse`` capture,
  else its only image; the texel size comes from the manifest's camera (``field_mm / width``, the
  pixel pitch on the sample plane at the optical axis);
* an EXR file: linear already (a stated transfer other than ``linear`` is refused);
* a PNG, JPEG or TIFF file: display-encoded, linearised by the *stated* transfer (``srgb``,
  ``linear`` or ``gamma:G``, :func:`dualscale.formats.photo.read_photo`); refused when none is
  stated, since guessing it would bias every propagated map.

Non-finite pixels are **refused** (:class:`~dualscale.errors.InputError` naming the file, the
count and the first position): a single NaN pixel poisons every tile that sees it and, through
the exposure gain, every map.  Masking them would invent maps where the camera saw nothing;
repairing the image is the user's call (e.g. ``oiiotool IMG --fixnan box3 -o FIXED.exr``).
Clipped pixels of integer images are counted and reported as a warning (maps there are less
reliable); a dataset whose ``colour_space`` is a camera's raw space is refused (calibrate it
first: the network was trained on linear Rec.709 radiance).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualscale.errors import FormatError, InputError, UnitsError
from dualscale.geometry.cameras import Camera

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)  # Rec.709 luminance weights
CLIPPED_WARNING = 0.01  # warn when more than this fraction of the pixels is clipped


@dataclass
class Guidance:
    """A linear guidance image.

    ``rgb``: float32 ``(H, W, 3)`` linear Rec.709 radiance (arbitrary scale); ``file``: the image
    file read; ``texel_mm``: its pixel pitch on the sample in mm (``None`` when unknown) and
    ``texel_source`` (``"given"``, ``"dataset camera"`` or ``None``); ``camera``: the camera of
    the dataset it came from (``None`` for a plain image file); ``transfer``: how it was
    linearised; ``clipped``: the fraction of clipped pixels; ``warnings``: for the user.
    """

    rgb: np.ndarray
    file: Path
    texel_mm: float | None
    texel_source: str | None
    camera: Camera | None = None
    transfer: str = "linear"
    clipped: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.rgb.shape[0]), int(self.rgb.shape[1])

    def luminance(self) -> np.ndarray:
        """``(H, W)`` float32 Rec.709 luminance."""
        return self.rgb @ LUMA


def _dataset_image(folder: Path) -> tuple[Path, Camera | None, str]:
    """``(image file, its camera, its colour space)`` of a guidance dataset folder."""
    from dualscale.formats.dataset import read_dataset

    ds = read_dataset(folder)
    pick = ds.select(light_kind="diffuse") or (list(range(len(ds.records))) if len(ds.records) == 1 else [])
    if not pick:
        raise InputError(f"{folder}: no diffuse image to use as guidance (the dataset has {len(ds.records)} "
                         "images and none under the diffuse light)")
    rec = ds.records[pick[0]]
    cam = None
    doc = (ds.manifest.get("cameras") or {}).get(rec.camera)
    if doc:
        try:
            cam = Camera.from_json(rec.camera, doc, "guidance dataset")
        except (KeyError, TypeError, ValueError) as e:
            raise FormatError(f"{folder / 'manifest.json'}: camera {rec.camera!r} is malformed ({e})") from e
    return folder / rec.file, cam, rec.colour_space


def _check_finite(path: Path, rgb: np.ndarray) -> None:
    bad = ~np.isfinite(rgb).all(-1)
    if bad.any():
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise InputError(f"guidance {path}: {int(bad.sum())} pixel(s) are NaN or Inf (first at row {r}, col {c}); "
                         "every propagated map would be NaN. Repair the image (e.g. `oiiotool "
                         f"{path.name} --fixnan box3 -o fixed.exr`) and run again")


def _read_exr_rgb(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    from dualscale.formats.exr import read_exr

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    names = list(inp.spec().channelnames)
    inp.close()
    if not {"R", "G", "B"} <= set(names):
        raise FormatError(f"guidance must be an RGB image (channels R, G, B[, A]); {path} has {len(names)} "
                          f"channel(s) {names}")
    return read_exr(path, ("R", "G", "B"))


def read_guidance(path: str | Path, transfer: str | None = None, texel_mm: float | None = None) -> Guidance:
    """Read and linearise a guidance image (see the module docstring).

    ``transfer``: required for PNG/JPEG/TIFF (``srgb``, ``linear``, ``gamma:G``); for EXR and
    dataset folders only ``None`` or ``linear``.  ``texel_mm``: the guidance's pixel pitch in mm,
    overriding the dataset camera's.  Raises ``FileNotFoundError``,
    :class:`~dualscale.errors.UnitsError` (transfer missing or not applicable, raw colour space),
    :class:`~dualscale.errors.FormatError` (not RGB), :class:`~dualscale.errors.InputError`
    (non-finite pixels, a bad ``texel_mm``); nothing is written.
    """
    from dualscale.formats.photo import parse_transfer, read_photo

    path = Path(path)
    if texel_mm is not None and not (np.isfinite(texel_mm) and texel_mm > 0):
        raise InputError(f"the guidance texel size must be a positive number of mm, got {texel_mm!r}")
    cam, source = None, None
    if path.is_dir():
        file, cam, space = _dataset_image(path)
        if space != "linear_rec709":
            raise UnitsError(f"{path / 'manifest.json'}: colour_space {space!r} of the guidance is not linear "
                             "Rec.709; calibrate the dataset first (dualscale calibrate / digitize --calibration)")
        if transfer is not None and parse_transfer(transfer)[0] != "linear":
            raise UnitsError(f"{path}: a dataset holds linear images; --transfer {transfer} does not apply")
        if cam is not None:
            source = "dataset camera"
    else:
        file = path
    if not file.is_file():
        raise FileNotFoundError(f"guidance image not found: {file}")
    warnings: list[str] = []
    clipped = 0.0
    if file.suffix.lower() == ".exr":
        if transfer is not None and parse_transfer(transfer)[0] != "linear":
            raise UnitsError(f"{file}: an EXR image is linear already; drop --transfer or use --transfer linear")
        rgb = _read_exr_rgb(file)
        _check_finite(file, rgb)
        used = "linear"
    else:
        photo = read_photo(file, transfer)
        rgb, used = photo.rgb, photo.transfer
        _check_finite(file, rgb)
        clipped = float(photo.clipped.mean())
        if clipped > CLIPPED_WARNING:
            warnings.append(f"{file.name}: {100 * clipped:.1f} % of the guidance pixels are clipped (at the top "
                            "code value); the maps there are less reliable")
    if texel_mm is not None:
        tex, source = float(texel_mm), "given"
    elif cam is not None:
        tex = cam.pixel_mm[0]
    else:
        tex = None
    return Guidance(np.ascontiguousarray(rgb, np.float32), file, tex, source, cam, used, clipped, warnings)
