"""Writing a synthetic material's ground truth: maps, fly-out fibres and relief, each through
its one writer in :mod:`dualscale.formats`."""

from __future__ import annotations

from pathlib import Path

from dualscale.formats.atomic import remove_file
from dualscale.formats.flyouts import write_flyouts
from dualscale.formats.maps import save_maps
from dualscale.formats.relief import save_geometry

from .common import SyntheticMaterial

FLYOUT_FILES = ("flyouts.json", "flyout_mask.exr", "flyout_mask.png", "flyouts.svg")


def save_material(root: str | Path, mat: SyntheticMaterial, previews: bool = True) -> None:
    """Maps (with their texel size), plus fly-out ground truth and the relief (``geometry.exr``)
    when present."""
    root = Path(root)
    texel = float(mat.meta.get("texel_mm", 0.0)) or None
    # what this material lacks must not survive from an earlier one in the same folder: a stale
    # relief would cast another material's shadows (render --shadows), stale fibres score a fit
    if mat.geometry is not None:
        save_geometry(root / "geometry.exr", mat.geometry)
    else:
        remove_file(root / "geometry.exr")
    if mat.flyout_mask is not None:
        write_flyouts(root, mat.flyouts, mat.flyout_mask, texel or 0.0, previews=previews)
    else:
        for name in FLYOUT_FILES:
            remove_file(root / name)
    save_maps(root, mat.maps, mat.meta, previews, texel_mm=texel)
