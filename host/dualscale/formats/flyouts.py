"""Fly-out fibres on disk (ground truth written by ``synth``, detections by ``flyouts`` and
``digitize``): ``flyouts.json``, ``flyout_mask.exr`` (+ ``.png`` preview) and ``flyouts.svg``.

``flyouts.json``: ``{"count": N, "coordinates": ..., "texel_mm": t, "polylines_px": [[[col,
row], ...], ...], "polylines_mm": [[[x, y], ...], ...], ...extra}``.  Pixel coordinates have
row 0 at the top of the image; mm coordinates are in the macro frame (``+x`` right, ``+y`` up,
origin at the image centre).  The mask is 1 on fibre pixels (channel ``Y``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from dualscale.errors import FormatError

from .atomic import write_json, write_text
from .exr import read_exr, write_exr, write_png_preview
from .versioned import read_json

COORDINATES = "pixel [col, row] (row 0 at top); mm [x, y] macro frame, origin at the image centre"


def _svg(polylines_px: Sequence[Sequence[Sequence[float]]], h: int, w: int) -> str:
    body = "\n".join('<polyline fill="none" stroke="red" stroke-width="1" points="'
                     + " ".join(f"{c + 0.5:.1f},{r + 0.5:.1f}" for c, r in p) + '"/>' for p in polylines_px)
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}">\n'
            f'<rect width="{w}" height="{h}" fill="black"/>\n{body}\n</svg>\n')


def write_flyouts(root: str | Path, polylines_px: Sequence[Sequence[Sequence[float]]], mask: np.ndarray,
                  texel_mm: float, extra: dict[str, Any] | None = None, previews: bool = True) -> Path:
    """Write the fibres (polylines ``[[col, row], ...]`` in pixels) and the ``(H, W)`` bool mask
    under ``root``; returns the path of ``flyouts.json``."""
    root = Path(root)
    m = np.asarray(mask, bool)
    h, w = m.shape

    def mm(c: float, r: float) -> list[float]:
        return [(c + 0.5 - w / 2) * texel_mm, (h / 2 - r - 0.5) * texel_mm]

    pls = [[[float(c), float(r)] for c, r in pl] for pl in polylines_px]
    write_exr(root / "flyout_mask.exr", m.astype(np.float32), ("Y",))
    if previews:
        write_png_preview(root / "flyout_mask.png", m.astype(np.float32), srgb=False)
        write_text(root / "flyouts.svg", _svg(pls, h, w))
    doc = {"count": len(pls), "coordinates": COORDINATES, "texel_mm": float(texel_mm), **(extra or {}),
           "polylines_px": pls, "polylines_mm": [[mm(c, r) for c, r in pl] for pl in pls]}
    return write_json(root / "flyouts.json", doc)


def read_flyouts(root: str | Path) -> tuple[dict[str, Any], np.ndarray]:
    """``(flyouts.json as a dict, (H, W) bool mask)`` of a folder written by :func:`write_flyouts`."""
    root = Path(root)
    doc = read_json(root / "flyouts.json")
    if "polylines_px" not in doc:
        raise FormatError(f"{root / 'flyouts.json'}: no polylines_px")
    mask = read_exr(root / "flyout_mask.exr", ("Y",))[..., 0] > 0.5
    return doc, mask
