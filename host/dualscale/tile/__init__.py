"""Seamless tiles at real-world scale (issue 12 Sec. 2): find the weave or knit repeat
(:mod:`.lattice`), cut a tile of whole repeats sheared to the axes where needed and feathered
so it wraps without a seam (:mod:`.cut`), score the seam (:mod:`.seam`), and write it as a maps
folder whose ``material.json`` carries the tile's physical size (:func:`save_tile`).

Public API (used by ``dualscale tile`` and the exports)::

    find_lattice(image_or_maps, texel_mm=None, source="all") -> Lattice
    make_tile(maps, texel_mm, lattice=None, repeats=None, blend_px=None) -> Tile
    save_tile(tile, out_dir, meta=None) -> Path            # material.json
"""

from __future__ import annotations

from pathlib import Path

from dualscale.formats.maps import save_maps

from .cut import Tile, choose_cell, make_tile
from .lattice import Lattice, NoRepeatError, find_lattice
from .seam import GOAL, maps_seam_scores, seam_score, worst_seam


def save_tile(tile: Tile, out_dir: str | Path, meta: dict | None = None, previews: bool = True) -> Path:
    """Write ``tile.maps`` as a maps folder (:func:`dualscale.formats.maps.save_maps`, atomic)
    with ``texel_mm`` = the tile's texel and ``meta["tile"]`` = :meth:`Tile.meta` (its size in
    mm, lattice, repeats, seam scores); ``meta``: further entries (e.g. the source folder).
    Returns the path of ``material.json``."""
    return save_maps(out_dir, tile.maps, meta={**(meta or {}), "tile": tile.meta()}, previews=previews,
                     texel_mm=tile.texel_mm)


__all__ = ["GOAL", "Lattice", "NoRepeatError", "Tile", "choose_cell", "find_lattice", "make_tile",
           "maps_seam_scores", "save_tile", "seam_score", "worst_seam"]
