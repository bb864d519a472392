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
    e_in = inside_energy(a)
    return border_energy(a[:, [0, -1]], a[[0, -1]]) / e_in if e_in > 0 else float("nan")


def inside_energy(a: np.ndarray) -> float:
    """``E_inside`` of an ``(H, W, C)`` tile: the mean squared difference (channels summed) of its
    horizontal and vertical neighbours."""
    return float(np.concatenate([(np.diff(a, axis=1) ** 2).sum(-1).ravel(),
                                 (np.diff(a, axis=0) ** 2).sum(-1).ravel()]).mean())


def border_energy(cols: np.ndarray, rows: np.ndarray):
    """``E_border`` of a tile from its first and last columns ``cols`` ``(..., H, 2, C)`` and its
    first and last rows ``rows`` ``(..., 2, W, C)``: the mean squared difference (channels
    summed) of the texels that meet when the tile repeats; a float, or an array over the
    leading axes (a batch of tiles)."""
    e = np.concatenate([((cols[..., 1, :] - cols[..., 0, :]) ** 2).sum(-1),
                        ((rows[..., 1, :, :] - rows[..., 0, :, :]) ** 2).sum(-1)], -1).mean(-1)
    return float(e) if np.ndim(e) == 0 else e


def scored_channels(name: str, a: np.ndarray) -> np.ndarray:
    """Map ``name``'s values ``(..., C)`` as the seam score sees them, ``(..., C')``: the
    albedo as its luminance (Rec.709, ``C' = 1``); the tangent, an axial angle ``pi v``, as
    ``(cos 2 pi v, sin 2 pi v)`` (so 0.02 and 0.98 are neighbours); any other map as it is."""
    a = np.asarray(a, np.float64)
    if name == "albedo":
        return (a @ LUMA)[..., None]
    if name == "tangent":
        return np.concatenate([np.cos(2 * np.pi * a), np.sin(2 * np.pi * a)], -1)
    return a


def maps_seam_scores(maps: MaterialMaps) -> dict[str, float]:
    """Seam score of every map of ``maps`` (as :func:`scored_channels` gives it), by name,
    rounded to 4 decimals; ``nan`` for a constant map."""
    return {name: round(seam_score(scored_channels(name, t.detach().cpu().numpy())), 4) for name, t in maps.items()}


def worst_seam(scores: dict[str, float]) -> tuple[str | None, float]:
    """The map with the highest finite seam score of ``scores`` (as :func:`maps_seam_scores`
    gives them) and that score; ``(None, nan)`` when every map is constant.  A user's tile
    wraps every map, so this is the tile's seam."""
    finite = {k: v for k, v in scores.items() if np.isfinite(v)}
    if not finite:
        return None, float("nan")
    name = max(finite, key=finite.get)
    return name, float(finite[name])
