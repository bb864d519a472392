"""Seam score of a tile: how visible its wrap-around border is when the tile repeats.

``score = E_border / E_inside`` where ``E_border`` is the mean squared difference between the
last and the first column and between the last and the first row (the neighbours that meet
when the tile repeats), and ``E_inside`` the mean squared difference of horizontal and
vertical neighbours inside the tile.  About 1 for a seamless tile (the border is as smooth as
any other line of the tile), above 1 for a visible seam.  The goal of issue 12 Sec. 2 is
``<= 1.1``.
"""

from __future__ import annotations

import numpy as np

from dualscale.bsdf import MaterialMaps

GOAL = 1.1
LUMA = np.array([0.2126, 0.7152, 0.0722])


def seam_score(image: np.ndarray) -> float:
    """Seam score of an ``(H, W)`` or ``(H, W, C)`` tile (channels summed); ``nan`` for a tile
    smaller than 2 x 2 or a constant one."""
    a = np.asarray(image, np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[0] < 2 or a.shape[1] < 2:
        return float("nan")
    inside = np.concatenate([(np.diff(a, axis=1) ** 2).sum(-1).ravel(), (np.diff(a, axis=0) ** 2).sum(-1).ravel()])
    border = np.concatenate([((a[:, -1] - a[:, 0]) ** 2).sum(-1).ravel(), ((a[-1] - a[0]) ** 2).sum(-1).ravel()])
    e_in = float(inside.mean())
    return float(border.mean() / e_in) if e_in > 0 else float("nan")


def maps_seam_scores(maps: MaterialMaps) -> dict[str, float]:
    """Seam score of every map of ``maps`` (the albedo as luminance; the tangent, an axial angle
    ``pi v``, as ``(cos 2 pi v, sin 2 pi v)``, so 0.02 and 0.98 are neighbours), by name."""
    out = {}
    for name, t in maps.items():
        a = t.detach().cpu().numpy().astype(np.float64)
        if name == "albedo":
            a = a @ LUMA
        elif name == "tangent":
            a = np.concatenate([np.cos(2 * np.pi * a), np.sin(2 * np.pi * a)], -1)
        out[name] = round(seam_score(a), 4)
    return out
