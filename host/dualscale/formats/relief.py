"""The relief of a sample (``geometry.exr`` beside its maps): base height field and fly-out
fibre layer on the map grid.  One reader (:func:`load_geometry`) and one writer
(:func:`save_geometry`); :class:`SurfaceGeometry` is the in-memory form.

Units: mm; ``+z`` up from the sample plane; row 0 of every array is the top of the image (+y),
as for the maps (:mod:`dualscale.formats.maps`).  The renderer's use of it (cast shadows) is in
:mod:`dualscale.sim.shadow`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualscale.errors import FormatError

from .exr import read_exr, read_exr_attributes, write_exr


@dataclass(frozen=True)
class SurfaceGeometry:
    """Relief of a sample on its map grid.

    ``height_mm`` (H, W): base surface height; ``texel_mm``: map pitch; ``fibre_mask`` (H, W)
    bool: texels covered by fly-out fibres; ``fibre_axis_mm`` (H, W): height of the fibre axis
    there; ``fibre_top_mm`` (H, W): height of the fibre's visible surface there.
    """

    height_mm: np.ndarray
    texel_mm: float
    fibre_mask: np.ndarray | None = None
    fibre_axis_mm: np.ndarray | None = None
    fibre_top_mm: np.ndarray | None = None
    fibre_radius_mm: float = 0.0

    def __post_init__(self) -> None:
        h = np.asarray(self.height_mm)
        if h.ndim != 2 or not np.isfinite(h).all():
            raise ValueError("height_mm must be a finite (H, W) array")
        if not self.texel_mm > 0:
            raise ValueError("texel_mm must be positive")
        for name in ("fibre_mask", "fibre_axis_mm", "fibre_top_mm"):
            a = getattr(self, name)
            if a is not None and np.shape(a) != h.shape:
                raise ValueError(f"{name} is {np.shape(a)}, height_mm is {h.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(np.shape(self.height_mm))  # type: ignore[return-value]

    def surface_mm(self) -> np.ndarray:
        """Height of what the camera sees at each texel (fibre surface over fibre texels)."""
        if self.fibre_mask is None or self.fibre_top_mm is None:
            return np.asarray(self.height_mm, np.float64)
        return np.where(self.fibre_mask, self.fibre_top_mm, self.height_mm).astype(np.float64)


GEOMETRY_CHANNELS = ("height", "fibre_mask", "fibre_axis", "fibre_top")


def save_geometry(path, geom: SurfaceGeometry) -> None:
    """Write ``geom`` as one float32 EXR: channels :data:`GEOMETRY_CHANNELS` (mm; mask 0/1,
    fibre channels 0 where there is no fibre) and the attributes ``dualscale:texel_mm`` and
    ``dualscale:fibre_radius_mm``."""
    h = np.asarray(geom.height_mm, np.float64)
    zero = np.zeros_like(h)
    mask = zero if geom.fibre_mask is None else np.asarray(geom.fibre_mask, np.float64)
    axis = zero if geom.fibre_axis_mm is None else np.asarray(geom.fibre_axis_mm, np.float64)
    top = zero if geom.fibre_top_mm is None else np.asarray(geom.fibre_top_mm, np.float64)
    write_exr(path, np.stack([h, mask, axis, top], -1), GEOMETRY_CHANNELS,
              {"dualscale:texel_mm": repr(float(geom.texel_mm)),
               "dualscale:fibre_radius_mm": repr(float(geom.fibre_radius_mm))})


def load_geometry(path) -> SurfaceGeometry:
    """Read a file written by :func:`save_geometry`; a missing attribute or channel, or
    non-finite data, is a :class:`~dualscale.errors.FormatError`."""
    data = read_exr(path, GEOMETRY_CHANNELS).astype(np.float64)
    attrs = read_exr_attributes(path)
    missing = [k for k in ("texel_mm", "fibre_radius_mm") if k not in attrs]
    if missing:
        raise FormatError(f"{path}: not a dualscale geometry file (missing {missing})")
    if not np.isfinite(data).all():
        raise FormatError(f"{path}: non-finite heights")
    mask = data[..., 1] > 0.5
    return SurfaceGeometry(data[..., 0], float(attrs["texel_mm"]), mask if mask.any() else None,
                           data[..., 2] if mask.any() else None, data[..., 3] if mask.any() else None,
                           float(attrs["fibre_radius_mm"]))
