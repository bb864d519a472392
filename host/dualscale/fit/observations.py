"""Photometric observations prepared for fitting: images, light directions and the per-image
polarisation weights that tell the renderer what each image contains.

Each LED image ``k`` is modelled as ``I_k = f(l_k, v; w_s[k], w_p[k], w_d[k])`` per unit LED
intensity (``dualscale.bsdf.evaluate`` weights):

* relative analyser at ``a`` deg from the LED's polariser (P0 = 0, P90 = 90): the LED light is
  S-polarised, so the specular Fresnel factor is ``R_s`` scaled by Malus' ``cos^2 a``
  (``w_s = cos^2 a``, ``w_p = 0``); diffuse light is depolarised, half passes (``w_d = 1/2``);
* no analyser: ``w_s = 1``, ``w_p = 0`` (still S-polarised light), ``w_d = 1``;
* absolute analyser angle: Malus' law between the analyser and the LED's polariser axis as seen
  by the orthographic micro camera.

The back light (a uniform panel below the sample, unit radiance per unit intensity) gives
``B = w_d (t * opacity + 1 - opacity)``.  Images are divided by their light's intensity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dualscale.dome.dataset import Dataset, read_dataset


@dataclass
class Observations:
    """LED images ``(N, H, W, 3)`` with directions ``(N, 3)`` and weights ``(N,)``, plus an
    optional back-lit image ``(H, W, 3)`` (``back_wd`` = its diffuse weight)."""

    images: Tensor
    dirs: Tensor
    w_s: Tensor
    w_p: Tensor
    w_d: Tensor
    led_ids: Tensor
    backlight: Tensor | None = None
    back_wd: float = 0.5
    pixel_mm: float = 0.0018
    view: Tensor | None = None

    def __post_init__(self) -> None:
        if self.view is None:
            self.view = torch.tensor([0.0, 0.0, 1.0], dtype=self.images.dtype)

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

    def select(self, index: Tensor | list[int]) -> "Observations":
        """Subset of LED images (the back-lit image is kept)."""
        idx = torch.as_tensor(index, dtype=torch.long)
        return replace(self, images=self.images[idx], dirs=self.dirs[idx], w_s=self.w_s[idx], w_p=self.w_p[idx],
                       w_d=self.w_d[idx], led_ids=self.led_ids[idx])

    def select_leds(self, leds: set[int] | list[int], keep: bool = True) -> "Observations":
        """Images of the given LED ids (``keep=False``: all the others)."""
        s = {int(i) for i in leds}
        idx = [k for k, i in enumerate(self.led_ids.tolist()) if (i in s) == keep]
        return self.select(idx)

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "Observations":
        back = None if self.backlight is None else self.backlight[y0:y1, x0:x1]
        return replace(self, images=self.images[:, y0:y1, x0:x1], backlight=back)

    def pixels(self, flat_index: Tensor) -> "Observations":
        """The chosen pixels (flat indices) laid out as a ``1 x M`` image (pixels are independent)."""
        n, h, w, c = self.images.shape
        imgs = self.images.reshape(n, h * w, c)[:, flat_index].unsqueeze(1)
        back = None if self.backlight is None else self.backlight.reshape(h * w, c)[flat_index].unsqueeze(0)
        return replace(self, images=imgs, backlight=back)

    def to(self, dtype: torch.dtype) -> "Observations":
        back = None if self.backlight is None else self.backlight.to(dtype)
        return replace(self, images=self.images.to(dtype), dirs=self.dirs.to(dtype), w_s=self.w_s.to(dtype),
                       w_p=self.w_p.to(dtype), w_d=self.w_d.to(dtype), backlight=back, view=self.view.to(dtype))


def analyzer_weights(analyzer_deg: float | None, relative: bool, direction: np.ndarray,
                     polarizer: str = "s") -> tuple[float, float, float]:
    """``(w_s, w_p, w_d)`` of an LED image (see the module docstring)."""
    if analyzer_deg is None:
        return 1.0, 0.0, 1.0
    if relative:
        return math.cos(math.radians(analyzer_deg)) ** 2, 0.0, 0.5
    from dualscale.dome.geometry import polarizer_axis

    axis = polarizer_axis(torch.tensor(direction, dtype=torch.float64), polarizer).numpy()
    a = math.radians(analyzer_deg)
    p = np.array([axis[0], axis[1]])  # orthographic camera: the image plane is the x-y plane
    p = p / max(float(np.linalg.norm(p)), 1e-12)
    return float((p[0] * math.cos(a) + p[1] * math.sin(a)) ** 2), 0.0, 0.5


def _open(root: str | Path) -> Dataset:
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"dataset not found: {root}")
    if root.is_dir() and not (root / "manifest.json").is_file() and (root / "micro" / "manifest.json").is_file():
        root = root / "micro"  # the directory written by `dualscale synth --dataset`
    return read_dataset(root)


def load_observations(root: str | Path, camera: str = "micro", dtype: torch.dtype = torch.float32,
                      leds: set[int] | None = None) -> Observations:
    """Read the ``camera`` images of a photometric dataset (``DIR`` or ``DIR/micro``).

    Raises ``FileNotFoundError`` / ``ValueError`` / ``OSError`` with the offending file named
    when the manifest or an image is missing or corrupt.
    """
    ds = _open(root)
    polar = str(ds.manifest.get("dome", {}).get("polarizer", "s"))
    imgs, dirs, ws, wp, wd, ids = [], [], [], [], [], []
    back, back_wd = None, 0.5
    for i, rec in enumerate(ds.records):
        if rec.camera != camera or rec.intensity <= 0:
            continue
        if rec.light_kind == "led":
            if rec.direction is None or rec.light_id is None:
                raise ValueError(f"{rec.file}: LED image without id or direction")
            if leds is not None and rec.light_id not in leds:
                continue
            s, p, d = analyzer_weights(rec.analyzer_deg, rec.analyzer_relative, np.asarray(rec.direction), polar)
            imgs.append(_load(ds, i) / rec.intensity)
            dirs.append(rec.direction)
            ws.append(s)
            wp.append(p)
            wd.append(d)
            ids.append(rec.light_id)
        elif rec.light_kind == "backlight" and back is None:
            back = _load(ds, i) / rec.intensity
            back_wd = 1.0 if rec.analyzer_deg is None else 0.5
    if not imgs:
        raise ValueError(f"{ds.root}: no LED images for camera {camera!r}")
    cam = ds.manifest.get("cameras", {}).get(camera, {})
    pixel_mm = float(cam["field_mm"][0]) / float(cam["width"]) if "field_mm" in cam else 0.0018
    f = dict(dtype=dtype)
    return Observations(images=torch.from_numpy(np.stack(imgs)).to(**f), dirs=torch.tensor(dirs, **f),
                        w_s=torch.tensor(ws, **f), w_p=torch.tensor(wp, **f), w_d=torch.tensor(wd, **f),
                        led_ids=torch.tensor(ids, dtype=torch.long),
                        backlight=None if back is None else torch.from_numpy(back).to(**f), back_wd=back_wd,
                        pixel_mm=pixel_mm)


def _load(ds: Dataset, index: int) -> np.ndarray:
    try:
        return ds.load(index)
    except (OSError, ValueError) as e:
        raise type(e)(f"dataset {ds.root}: cannot use {ds.records[index].file}: {e}") from e


def ground_truth_dir(root: str | Path) -> Path | None:
    """``maps/`` next to a synthetic dataset (``synth -o DIR --dataset`` writes DIR/maps, DIR/micro)."""
    root = Path(root)
    for cand in (root / "maps", root.parent / "maps"):
        if (cand / "material.json").is_file():
            return cand
    return None
