"""Score fitted maps against ground-truth maps by rows (``dualscale fit --gt`` out of core,
issue 25): neither map is held whole.

:func:`.metrics.map_errors` reduces per-texel terms (:func:`.metrics.error_values`: squared and
absolute differences, normal angles) to means, root means and the normal angle's 95th
percentile.  Here both maps folders are read a band of rows at a time
(:func:`~dualscale.formats.maps.load_maps` with a ``box``), each band's terms are appended in
order to one raw float64 file per term in a temporary folder beside the fit, and the files,
memory-mapped, are reduced by the same :func:`.metrics.reduce_errors`: the very tensors the
in-memory scoring reduces, so the very numbers (``tests/fit/test_stream.py``).  Memory: a band
of both maps (:data:`BAND_PIXELS` texels) and the pages of the terms' files the reduction
touches (8 bytes per scored texel and term; the percentile sorts a copy of the angles, 8 more).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch

from .metrics import error_values, reduce_errors

#: texels of each band read from the two maps folders (about 0.5 KiB each with the float64 copies)
BAND_PIXELS = 1 << 20


def score_by_rows(fit_dir: str | Path, gt_dir: str | Path, fit_ior: float, spill: str | Path) -> dict[str, float]:
    """:func:`.metrics.map_errors` of the maps folder ``fit_dir`` against ``gt_dir`` (the same
    ``(H, W)``, else ``ValueError``), read by bands of rows; ``fit_ior``: the fit's fixed IOR
    (``Components.ior``); ``spill``: an existing folder for the temporary term files (removed
    after).  Raises what :func:`~dualscale.formats.maps.load_maps` raises for a bad folder."""
    from dualscale.formats.maps import read_material_json
    from dualscale.formats.maps import load_maps

    a, b = read_material_json(fit_dir), read_material_json(gt_dir)
    h, w = a["height"], a["width"]
    if (b["height"], b["width"]) != (h, w):
        raise ValueError(f"--gt {gt_dir}: maps are {b['height']} x {b['width']}, the fit is {h} x {w}")
    rows = max(1, BAND_PIXELS // max(1, w))
    with tempfile.TemporaryDirectory(prefix="score-", dir=spill) as tmp:
        files: dict[str, Path] = {}
        for y0 in range(0, h, rows):
            box = (y0, min(y0 + rows, h), 0, w)
            terms = error_values(load_maps(fit_dir, box=box)[0], load_maps(gt_dir, box=box)[0], fit_ior)
            for name, t in terms.items():
                files.setdefault(name, Path(tmp) / f"{name}.f64")
                with open(files[name], "ab") as fh:
                    t.numpy().astype(np.float64, copy=False).tofile(fh)
        values = {n: _mapped(p) for n, p in files.items()}
        out = reduce_errors(values)
        del values
    return out


def _mapped(path: Path) -> torch.Tensor:
    """The float64 terms of ``path`` as a tensor on a copy-on-write memory map (empty: a new
    empty tensor: ``np.memmap`` refuses an empty file)."""
    if path.stat().st_size == 0:
        return torch.zeros(0, dtype=torch.float64)
    return torch.from_numpy(np.memmap(path, dtype=np.float64, mode="c"))


__all__ = ["score_by_rows", "BAND_PIXELS"]
