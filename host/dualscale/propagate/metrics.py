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
