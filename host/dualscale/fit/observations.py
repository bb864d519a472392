"""Photometric observations prepared for fitting: images, light directions and the per-image
polarisation weights that tell the renderer what each image contains.

Each LED image ``k`` is modelled as ``I_k = f(l_k, v; w_s[k], w_p[k], w_d[k])`` per unit LED
intensity (``dualscale.bsdf.evaluate`` weights):

* relative analyser at ``a`` deg from the LED's polariser (P0 = 0, P90 = 90): the LED light is
  S-polarised, so the specular Fresnel factor is ``R_s`` scaled by Malus' ``cos^2 a``
  (``w_s = cos^2 a``, ``w_p = 0``); diffuse light is depolarised, half passes (``w_d = 1/2``);
* no analyser: ``w_s = 1``, ``w_p = 0`` (still S-polarised light), ``w_d = 1``; with unpolarised
  lights (dome ``polarizer: "none"``, photographs imported from other rigs) ``w_s = w_p = 1/2``;
* absolute analyser angle: Malus' law between the analyser and the LED's polariser axis as seen
  by the orthographic micro camera.

The back light (a uniform panel below the sample, unit radiance per unit intensity) gives
``B = w_d (t * opacity + 1 - opacity)``.

Units: the fit reads only ``relative_radiance`` in ``linear_rec709`` (see
:mod:`dualscale.formats.dataset`); each image is divided by its ``exposure_s`` and its light's
intensity, so ``images`` are radiance per unit light intensity per second of exposure.  Raw
sensor datasets (``dn_normalized``, ``camera_raw:*``) are refused with a
:class:`~dualscale.errors.UnitsError` that says to apply a calibration first
(:func:`dualscale.calib.apply.to_radiance`, or ``dualscale digitize --calibration CAL``).

Valid samples: ``valid`` ``(N, H, W)`` (and ``back_valid`` ``(H, W)``) mark the samples the fit
may use: not clipped (no channel at or above the image's ``saturation``) and inside the
dataset's sample mask.  Every optimiser gives the others zero weight and the held-out metrics
skip them; ``None`` means every sample is valid.  A pixel with no valid sample at all (outside
the mask) is not fitted: it keeps its start values (:mod:`.init`), finite but meaningless.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dualscale.errors import InputError
from dualscale.formats.dataset import Dataset, read_dataset, resolve_root


@dataclass(frozen=True)
class WholeMap:
    """Sample counts of the whole map that a tile was cut from (:mod:`.tiled`): the Adam loss
    is a mean over the whole map, so a tile divides its sum by these counts and its pixels get
    the whole map's gradients.  ``pixels``: ``H * W``; ``counts``: ``(N,)`` float64 valid samples
    per image (``None``: every sample valid); ``back``: valid back-lit pixels (``None``: all)."""

    pixels: int
    counts: Tensor | None = None
    back: float | None = None

    @classmethod
    def of(cls, obs: "Observations") -> "WholeMap":
        h, w = obs.shape
        counts = None if obs.valid is None else obs.valid.sum(dim=(1, 2)).to(torch.float64)
        back = None if obs.back_valid is None else float(obs.back_valid.sum())
        return cls(h * w, counts, back)

    def led_samples(self, n: int) -> float:
        """Valid LED samples (pixels) over the ``n`` images of the (selected) observations."""
        return float(self.pixels * n) if self.counts is None else float(self.counts.sum())

    def back_samples(self) -> float:
        return float(self.pixels) if self.back is None else self.back


@dataclass(frozen=True)
class DatasetOrigin:
    """Where observations were read from: :func:`load_observations` of ``root`` (a resolved
    dataset folder), ``camera``, ``leds`` (sorted ids, or None: all) and ``dtype`` (torch's
    name), and ``key``, the :func:`content_key` of what it read.  A tiled fit's workers read
    their tile from there themselves (:func:`read_tile`) when the observations still have that
    key, so the driver ships coordinates, not pixels (issue 25 Sec. 2)."""

    root: str
    camera: str
    leds: tuple[int, ...] | None
    dtype: str
    key: str


def content_key(obs: "Observations") -> str:
    """A SHA-256 over what a fit reads of ``obs``: the lights (ids, directions, weights), each
    image's sum (float64), each image's valid-sample count, the back-lit image's sum and valid
    count, the size and texel size.  It tells observations changed after loading (a replaced
    mask, a subset, a crop) from the ones a :class:`DatasetOrigin` names."""
    import hashlib

    h = hashlib.sha256()
    for t in (obs.led_ids, obs.dirs, obs.w_s, obs.w_p, obs.w_d, obs.images.to(torch.float64).sum(dim=(1, 2, 3)),
              torch.zeros(0) if obs.valid is None else obs.valid.sum(dim=(1, 2)),
              torch.zeros(0) if obs.backlight is None else obs.backlight.to(torch.float64).sum().reshape(1),
              torch.zeros(0) if obs.back_valid is None else obs.back_valid.sum().reshape(1), obs.view):
        h.update(str(t.dtype).encode())
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    h.update(repr((tuple(obs.images.shape), obs.pixel_mm, obs.back_wd, obs.imported)).encode())
    return h.hexdigest()


@dataclass
class Observations:
    """LED images ``(N, H, W, 3)`` with directions ``(N, 3)`` and weights ``(N,)``, plus an
    optional back-lit image ``(H, W, 3)`` (``back_wd`` = its diffuse weight); ``valid``
    ``(N, H, W)`` bool and ``back_valid`` ``(H, W)`` bool mark the usable samples (module doc;
    ``None`` = all).  ``imported``: the images are photographs from ``dualscale import``
    (decoded and scaled by the lights there), which the fit's advice names.  ``origin``: the
    dataset they were read from (:class:`DatasetOrigin`; it names them only while
    :meth:`unchanged` holds)."""

    images: Tensor
    dirs: Tensor
    w_s: Tensor
    w_p: Tensor
    w_d: Tensor
    led_ids: Tensor
    backlight: Tensor | None = None
    back_wd: float = 0.5
    pixel_mm: float | None = 0.0018  # texel size in mm; None when unknown (photographs without a scale)
    view: Tensor | None = None
    valid: Tensor | None = None
    back_valid: Tensor | None = None
    whole: WholeMap | None = None  # set on a tile of a tiled Adam fit (WholeMap)
    imported: bool = False  # photographs from `dualscale import` (already scaled by the lights' intensities)
    origin: DatasetOrigin | None = None  # what load_observations read (valid only while content_key matches)
    #: ``(N, 3)`` float64: per image and channel, the factor from the sensor's signal to ``images``
    #: (the dataset's ``signal_scale`` over exposure and intensity); ``None``: the same for every
    #: image.  The uncertainty's noise model scales each image's read and shot noise by it.
    signal_scale: Tensor | None = None
    #: ``(3,)`` float64: the same for the back-lit image (``None`` with ``signal_scale``)
    back_signal_scale: Tensor | None = None

    def __post_init__(self) -> None:
        if self.view is None:
            self.view = torch.tensor([0.0, 0.0, 1.0], dtype=self.images.dtype)
        if self.valid is not None and tuple(self.valid.shape) != tuple(self.images.shape[:3]):
            raise ValueError(f"valid mask is {tuple(self.valid.shape)}, images are {tuple(self.images.shape[:3])}")
        if self.signal_scale is not None and tuple(self.signal_scale.shape) != (self.images.shape[0], 3):
            raise ValueError(f"signal_scale is {tuple(self.signal_scale.shape)}, needs ({self.images.shape[0]}, 3)")
        if self.back_valid is not None and (self.backlight is None
                                            or tuple(self.back_valid.shape) != tuple(self.backlight.shape[:2])):
            raise ValueError("back_valid needs a back-lit image of the same size")

    def unchanged(self) -> bool:
        """True when these are still exactly the observations their :attr:`origin` read."""
        return self.origin is not None and content_key(self) == self.origin.key

    @property
    def n(self) -> int:
        return int(self.images.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])

    @property
    def has_polarisation(self) -> bool:
        """True when some images have the specular blocked (P90) and others pass it."""
        return bool((self.w_s < 1e-6).any()) and bool((self.w_s > 1e-6).any())

    @classmethod
    def relative_p0(cls, images: Tensor, dirs: Tensor, led_ids: list[int], pixel_mm: float) -> "Observations":
        """LED images ``(N, H, W, 3)`` under the relative P0 analyser (specular passed, half the
        diffuse), directions ``(N, 3)``, ``pixel_mm`` texel size in mm."""
        n = len(led_ids)
        return cls(images, dirs, torch.ones(n), torch.zeros(n), torch.full((n,), 0.5), torch.tensor(led_ids),
                   pixel_mm=pixel_mm)

    @property
    def fitted_pixels(self) -> Tensor | None:
        """``(H, W)`` bool: pixels with at least one valid sample (``None``: all of them)."""
        if self.valid is None:
            return None
        any_led = self.valid.any(0)
        return any_led if self.back_valid is None else any_led | self.back_valid

    def select(self, index: Tensor | list[int]) -> "Observations":
        """Subset of LED images (the back-lit image is kept)."""
        idx = torch.as_tensor(index, dtype=torch.long)
        return replace(self, images=self.images[idx], dirs=self.dirs[idx], w_s=self.w_s[idx], w_p=self.w_p[idx],
                       w_d=self.w_d[idx], led_ids=self.led_ids[idx],
                       valid=None if self.valid is None else self.valid[idx],
                       signal_scale=None if self.signal_scale is None else self.signal_scale[idx],
                       whole=self.whole if self.whole is None or self.whole.counts is None
                       else replace(self.whole, counts=self.whole.counts[idx]))

    def select_leds(self, leds: set[int] | list[int], keep: bool = True) -> "Observations":
        """Images of the given LED ids (``keep=False``: all the others)."""
        s = {int(i) for i in leds}
        idx = [k for k, i in enumerate(self.led_ids.tolist()) if (i in s) == keep]
        return self.select(idx)

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "Observations":
        back = None if self.backlight is None else self.backlight[y0:y1, x0:x1]
        view = self.view[y0:y1, x0:x1] if self.view.ndim == 3 else self.view  # a per-pixel view (H, W, 3)
        return replace(self, images=self.images[:, y0:y1, x0:x1], backlight=back, view=view,
                       valid=None if self.valid is None else self.valid[:, y0:y1, x0:x1],
                       back_valid=None if self.back_valid is None else self.back_valid[y0:y1, x0:x1])

    def pixels(self, flat_index: Tensor) -> "Observations":
        """The chosen pixels (flat indices) laid out as a ``1 x M`` image (pixels are independent)."""
        n, h, w, c = self.images.shape
        imgs = self.images.reshape(n, h * w, c)[:, flat_index].unsqueeze(1)
        back = None if self.backlight is None else self.backlight.reshape(h * w, c)[flat_index].unsqueeze(0)
        valid = None if self.valid is None else self.valid.reshape(n, h * w)[:, flat_index].unsqueeze(1)
        bv = None if self.back_valid is None else self.back_valid.reshape(h * w)[flat_index].unsqueeze(0)
        view = self.view.reshape(h * w, 3)[flat_index].unsqueeze(0) if self.view.ndim == 3 else self.view
        return replace(self, images=imgs, backlight=back, valid=valid, back_valid=bv, view=view)

    def to(self, dtype: torch.dtype) -> "Observations":
        """The same observations in floating type ``dtype`` (the masks stay bool)."""
        back = None if self.backlight is None else self.backlight.to(dtype)
        return replace(self, images=self.images.to(dtype), dirs=self.dirs.to(dtype), w_s=self.w_s.to(dtype),
                       w_p=self.w_p.to(dtype), w_d=self.w_d.to(dtype), backlight=back, view=self.view.to(dtype))


#: a preset's ``led_stride`` never leaves fewer distinct LEDs than this (the draft preset's
#: stride 2 was made for the dome's 127; on 12 photographs it would fit 6, docs/PHOTOS.md)
MIN_STRIDED_LEDS = 32


def stride_leds(obs: Observations, stride: int) -> Observations:
    """Every ``stride``-th distinct LED (all its analyser images); the stride is lowered so
    that at least :data:`MIN_STRIDED_LEDS` LEDs remain (1 below twice that many)."""
    ids = sorted(set(obs.led_ids.tolist()))
    stride = min(stride, max(1, len(ids) // MIN_STRIDED_LEDS))
    if stride <= 1:
        return obs
    return obs.select_leds({i for k, i in enumerate(ids) if k % stride == 0})


def analyzer_weights(analyzer_deg: float | None, relative: bool, direction: np.ndarray,
                     polarizer: str = "s") -> tuple[float, float, float]:
    """``(w_s, w_p, w_d)`` of an LED image (see the module docstring)."""
    if analyzer_deg is None:
        return (0.5, 0.5, 1.0) if polarizer == "none" else (1.0, 0.0, 1.0)
    if relative:
        return math.cos(math.radians(analyzer_deg)) ** 2, 0.0, 0.5
    from dualscale.geometry.dome import polarizer_axis

    axis = polarizer_axis(torch.tensor(direction, dtype=torch.float64), polarizer).numpy()
    a = math.radians(analyzer_deg)
    p = np.array([axis[0], axis[1]])  # orthographic camera: the image plane is the x-y plane
    p = p / max(float(np.linalg.norm(p)), 1e-12)
    return float((p[0] * math.cos(a) + p[1] * math.sin(a)) ** 2), 0.0, 0.5


def _open(root: str | Path) -> Dataset:
    return read_dataset(resolve_root(root))


def fit_camera(ds: Dataset, camera: str | None = None) -> str:
    """The camera a fit reads: ``camera``, or ``"micro"``, or the dataset's only camera
    (``"photo"`` of an import)."""
    if camera is None:
        cams = {r.camera for r in ds.records}
        camera = cams.pop() if len(cams) == 1 and "micro" not in cams else "micro"
    return camera


def fit_layout(root: str | Path, camera: str | None = None) -> tuple[str, str, tuple[int, int], int]:
    """``(root, camera, (H, W), images)`` of what :func:`load_observations` would read, from the
    manifest alone (no pixel is read): the resolved dataset folder, the camera, the map size and
    the number of LED images; raises what :func:`load_observations` raises for the manifest,
    the units and a dataset without LED images, and :class:`~dualscale.errors.InputError` for
    images of different sizes."""
    ds = _open(root)
    camera = fit_camera(ds, camera)
    check_fit_units(ds, camera)
    recs = [r for r in ds.records if r.camera == camera and r.light_kind in ("led", "backlight")]
    leds = [r for r in recs if r.light_kind == "led"]
    if not leds:
        raise InputError(f"{ds.root}: no LED images for camera {camera!r}")
    sizes = {(r.height, r.width) for r in recs}
    if len(sizes) != 1:
        raise InputError(f"{ds.root}: the {camera} images have different sizes {sorted(sizes)}; a fit needs one")
    return str(ds.root), camera, sizes.pop(), len(leds)


def check_fit_units(ds: Dataset, camera: str | None = None) -> None:
    """Refuse a dataset whose images (of ``camera``, or all) are not ``relative_radiance`` in
    ``linear_rec709``, with a :class:`~dualscale.errors.UnitsError` naming the file, the field
    and the way out (apply a calibration): :meth:`Dataset.require_radiance`."""
    ds.require_radiance(camera, "the fit")


def load_observations(root: str | Path, camera: str | None = None, dtype: torch.dtype = torch.float32,
                      leds: set[int] | None = None, box: tuple[int, int, int, int] | None = None) -> Observations:
    """Read the ``camera`` images of a photometric dataset (``DIR`` or ``DIR/micro``) as
    radiance per unit light intensity per second of exposure, with their valid-sample masks.
    ``camera`` None: ``"micro"``, or the dataset's only camera (``"photo"`` of an import).
    ``box`` ``(y0, y1, x0, x1)``: only that region of every image (the same values as the
    whole observations' :meth:`~Observations.crop`); without it the result carries its
    :class:`DatasetOrigin`.

    Raises ``FileNotFoundError`` / ``OSError`` with the offending file named when the manifest
    or an image is missing or corrupt, :class:`~dualscale.errors.UnitsError` for units or a
    colour space the fit cannot read (module doc), and the dataset reader's
    :class:`~dualscale.errors.InputError` subclasses for bad values.
    """
    ds = _open(root)
    camera = fit_camera(ds, camera)
    check_fit_units(ds, camera)
    polar = str(ds.manifest.get("dome", {}).get("polarizer", "s"))
    imgs, dirs, ws, wp, wd, ids, valids, scales = [], [], [], [], [], [], [], []
    back, back_wd, back_valid, back_scale = None, 0.5, None, None
    for i, rec in enumerate(ds.records):
        if rec.camera != camera:
            continue
        if rec.light_kind == "led":
            if rec.direction is None or rec.light_id is None:
                raise InputError(f"dataset {ds.root}: image {rec.file}: LED image without light.id or "
                                 "light.direction")
            if leds is not None and rec.light_id not in leds:
                continue
            s, p, d = analyzer_weights(rec.analyzer_deg, rec.analyzer_relative, np.asarray(rec.direction), polar)
            img, ok = _load(ds, i, box)
            imgs.append(img)
            valids.append(ok)
            dirs.append(rec.direction)
            ws.append(s)
            wp.append(p)
            wd.append(d)
            ids.append(rec.light_id)
            scales.append(signal_scale(rec))
        elif rec.light_kind == "backlight" and back is None:
            back, back_valid = _load(ds, i, box)
            back_wd = 1.0 if rec.analyzer_deg is None else 0.5
            back_scale = signal_scale(rec)
    if not imgs:
        raise InputError(f"{ds.root}: no LED images for camera {camera!r}")
    cam = ds.manifest.get("cameras", {}).get(camera, {})
    pixel_mm: float | None = float(cam["field_mm"][0]) / float(cam["width"]) if "field_mm" in cam else 0.0018
    if not ds.texel_known:
        pixel_mm = None  # photographs imported without --texel-mm: the camera's field is nominal
    f = dict(dtype=dtype)
    valid = None
    if any(v is not None for v in valids):
        valid = torch.from_numpy(np.stack([np.ones(imgs[0].shape[:2], bool) if v is None else v for v in valids]))
    bv = None
    if back is not None and (back_valid is not None or valid is not None):
        bv = torch.from_numpy(np.ones(back.shape[:2], bool) if back_valid is None else back_valid)
    obs = Observations(images=torch.from_numpy(np.stack(imgs)).to(**f), dirs=torch.tensor(dirs, **f),
                       w_s=torch.tensor(ws, **f), w_p=torch.tensor(wp, **f), w_d=torch.tensor(wd, **f),
                       led_ids=torch.tensor(ids, dtype=torch.long),
                       backlight=None if back is None else torch.from_numpy(back).to(**f), back_wd=back_wd,
                       pixel_mm=pixel_mm, valid=valid, back_valid=bv,
                       imported="import" in (ds.manifest.get("extra") or {}))
    every = np.array(scales + ([] if back_scale is None else [back_scale]))
    if not np.all(every == every[0]):  # one scale for all: the noise model needs none
        obs = replace(obs, signal_scale=torch.from_numpy(np.array(scales)),
                      back_signal_scale=None if back_scale is None else torch.from_numpy(np.array(back_scale)))
    if box is None:
        origin = DatasetOrigin(str(ds.root), camera, None if leds is None else tuple(sorted(int(i) for i in leds)),
                               str(dtype).replace("torch.", ""), content_key(obs))
        obs = replace(obs, origin=origin)
    return obs


def signal_scale(rec) -> list[float]:
    """Per channel, the factor from an image record's sensor signal to the radiance per unit
    light intensity the fit reads (:func:`_load`): its ``signal_scale`` (``1`` when the dataset
    records none: the file's values are taken as the signal) over ``exposure_s * intensity``."""
    own = [1.0, 1.0, 1.0] if rec.signal_scale is None else rec.signal_scale
    return [float(v) / (rec.exposure_s * rec.intensity) for v in own]


def read_tile(origin: DatasetOrigin, box: tuple[int, int, int, int]) -> Observations:
    """The ``box`` ``(y0, y1, x0, x1)`` of the observations ``origin`` names, read from its
    dataset (:func:`load_observations` with ``box``): what a tiled fit's worker reads itself."""
    return load_observations(origin.root, origin.camera, getattr(torch, origin.dtype),
                             None if origin.leds is None else set(origin.leds), box=box)


def _load(ds: Dataset, index: int, box: tuple[int, int, int, int] | None = None
          ) -> tuple[np.ndarray, np.ndarray | None]:
    """Image ``index`` (its ``box``, or whole) divided by its exposure and light intensity, and
    its valid mask."""
    rec = ds.records[index]
    try:
        img = ds.load(index, box)
    except (OSError, ValueError) as e:
        raise type(e)(f"dataset {ds.root}: cannot use {rec.file}: {e}") from e
    valid = ds.valid(index, img, box)
    return img / np.float32(rec.exposure_s * rec.intensity), valid  # as Dataset.load_radiance
