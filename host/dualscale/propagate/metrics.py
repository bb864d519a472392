"""Quality of propagated maps against ground truth: L1 and SSIM per map.

Maps are ``(H, W, C)`` arrays in the conventions of :mod:`dualscale.bsdf.maps`.  SSIM uses
scikit-image with ``data_range`` 1 (2 for normals, whose components lie in [-1, 1]).  The
tangent L1 is axial (``min(|d|, 1 - |d|)``); its SSIM is on the raw values.
"""

from __future__ import annotations

import numpy as np


def map_scores(name: str, pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    from skimage.metrics import structural_similarity

    if pred.shape != gt.shape:
        raise ValueError(f"{name}: prediction {pred.shape} vs ground truth {gt.shape}")
    d = np.abs(pred.astype(np.float64) - gt)
    if name == "tangent":
        d = np.minimum(d, 1 - d)
    rng = 2.0 if name == "normal" else 1.0
    ssim = structural_similarity(gt.astype(np.float64), pred.astype(np.float64), data_range=rng, channel_axis=-1)
    return {"l1": float(d.mean()), "ssim": float(ssim)}


def compare(pred: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Scores for every map present in both."""
    return {m: map_scores(m, pred[m], gt[m]) for m in pred if m in gt}


def seam_score(a: np.ndarray, tile: int, overlap: int) -> float:
    """Tile seams of a tiled inference ``(N, N, C)``: the largest mean row/column step within a
    tile's overlap band, over the median step (1 = no seam; a hard seam is several times it)."""
    from .infer import tile_positions

    a = a.mean(-1)
    n = a.shape[0]
    gx, gy = np.abs(np.diff(a, axis=1)).mean(0), np.abs(np.diff(a, axis=0)).mean(1)
    band = sorted({c for p in tile_positions(n, tile, tile - overlap)[1:]
                   for c in range(p - 1, min(p + max(overlap, 1), n - 1))})
    return max(gx[band].max() / np.median(gx), gy[band].max() / np.median(gy))
