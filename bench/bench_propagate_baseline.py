"""Classic propagation baselines on the twill benchmark of bench/bench_propagate.py (issue 29 §3).

    PYTHONPATH=host python bench/bench_propagate_baseline.py [--work /tmp/propbench]

* ``constant``: every texel gets the micro maps' mean (normal: normalised mean; tangent: circular
  mean): the floor that any method must beat.
* ``ridge``: a per-texel ridge regression from a filter bank on the guidance to every map channel,
  fitted on the micro dataset's diffuse image and its fitted maps, applied to the guidance.
  Features, on the image divided by its mean luminance (the exposure): the linear RGB and the
  luminance at Gaussian scales 0, 1, 2, 4, 8 px, the luminance's gradient (x, y, magnitude), the
  structure-tensor terms ``gx^2 - gy^2`` and ``2 gx gy`` (orientation) and the Laplacian of
  Gaussian at 1, 2, 4 px; local contrast (luminance over its 8 px mean); a constant.
  The tangent is regressed as (cos, sin) of ``2 pi t`` and decoded axially, normals are
  normalised, [0, 1] maps clipped.  OpenCV does the filtering, numpy the least squares.
* ``gbt``: gradient-boosted trees on the same features and targets, one scikit-learn
  ``HistGradientBoostingRegressor`` per target channel (200 trees of at most 31 leaves, learning
  rate 0.1, squared error, no early stopping), fitted on every micro texel: the non-linear
  per-texel regressor.  Needs scikit-learn (``pip install -e '.[bench]'``).

Joint-bilateral or guided *upsampling* needs a low-resolution estimate of the maps over the
guidance; this benchmark's guidance (another twill patch) has none, so it is not one of the rows
(the micro field is inside the guidance only in bench_propagate's bridge test beds).

Scores: :func:`dualscale.propagate.metrics.compare`, the presets table's L1 / SSIM.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

SCALES = (0, 1, 2, 4, 8)
DERIV_SCALES = (1, 2, 4)


def features(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` linear RGB -> ``(H * W, F)`` float64 filter-bank features (see module docstring)."""
    from dualscale.propagate.guidance import LUMA

    rgb = rgb.astype(np.float32)
    rgb = rgb / max(float((rgb @ LUMA).mean()), 1e-12)
    lum = rgb @ LUMA
    feats = []
    for s in SCALES:
        b = rgb if s == 0 else cv2.GaussianBlur(rgb, (0, 0), s, borderType=cv2.BORDER_REFLECT)
        feats += [b[..., c] for c in range(3)] + [b @ LUMA]
    for s in DERIV_SCALES:
        g = cv2.GaussianBlur(lum, (0, 0), s, borderType=cv2.BORDER_REFLECT)
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, borderType=cv2.BORDER_REFLECT)
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, borderType=cv2.BORDER_REFLECT)
        feats += [gx, gy, np.hypot(gx, gy), cv2.Laplacian(g, cv2.CV_32F, borderType=cv2.BORDER_REFLECT),
                  gx * gx - gy * gy, 2 * gx * gy]  # structure-tensor terms: the local orientation
    m8 = cv2.GaussianBlur(lum, (0, 0), 8, borderType=cv2.BORDER_REFLECT)
    feats.append(lum / np.maximum(m8, 1e-6))
    f = np.stack(feats, -1).reshape(-1, len(feats)).astype(np.float64)
    return np.concatenate([f, np.ones((f.shape[0], 1))], 1)


def _targets(maps: dict[str, np.ndarray]) -> tuple[np.ndarray, list[tuple[str, slice]]]:
    cols, layout, c = [], [], 0
    for m, v in maps.items():
        v = v.reshape(-1, v.shape[-1]).astype(np.float64)
        if m == "tangent":
            a = 2 * np.pi * v[:, :1]
            v = np.concatenate([np.cos(a), np.sin(a)], 1)
        cols.append(v)
        layout.append((m, slice(c, c + v.shape[1])))
        c += v.shape[1]
    return np.concatenate(cols, 1), layout


def _decode(y: np.ndarray, layout, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    out = {}
    for m, s in layout:
        v = y[:, s]
        if m == "tangent":
            v = (np.mod(np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi) / (2 * np.pi))[:, None]
        elif m == "normal":
            v = v.copy()
            v[:, 2] = np.maximum(v[:, 2], 1e-3)
            v = v / np.linalg.norm(v, axis=1, keepdims=True)
        else:
            v = np.clip(v, 0, 1)
        out[m] = v.reshape(*shape, -1).astype(np.float32)
    return out


def ridge(train_rgb: np.ndarray, train_maps: dict[str, np.ndarray], test_rgb: np.ndarray,
          alpha: float = 1e-3) -> dict[str, np.ndarray]:
    """Fit on ``train_rgb`` ``(h, w, 3)`` -> maps ``{name: (h, w, C)}``, predict on ``test_rgb``."""
    x = features(train_rgb)
    mu, sd = x[:, :-1].mean(0), x[:, :-1].std(0) + 1e-12
    x[:, :-1] = (x[:, :-1] - mu) / sd
    y, layout = _targets(train_maps)
    a = x.T @ x + alpha * len(x) * np.diag([1.0] * (x.shape[1] - 1) + [0.0])
    w = np.linalg.solve(a, x.T @ y)
    xt = features(test_rgb)
    xt[:, :-1] = (xt[:, :-1] - mu) / sd
    return _decode(xt @ w, layout, test_rgb.shape[:2])


def gbt(train_rgb: np.ndarray, train_maps: dict[str, np.ndarray], test_rgb: np.ndarray,
        trees: int = 200, seed: int = 0) -> dict[str, np.ndarray]:
    """Like :func:`ridge`, with one gradient-boosted tree ensemble per target channel."""
    from sklearn.ensemble import HistGradientBoostingRegressor

    x = features(train_rgb)[:, :-1].astype(np.float32)
    y, layout = _targets(train_maps)
    xt = features(test_rgb)[:, :-1].astype(np.float32)
    out = np.empty((len(xt), y.shape[1]))
    for c in range(y.shape[1]):
        reg = HistGradientBoostingRegressor(max_iter=trees, early_stopping=False, random_state=seed)
        out[:, c] = reg.fit(x, y[:, c]).predict(xt)
    return _decode(out, layout, test_rgb.shape[:2])


def constant(train_maps: dict[str, np.ndarray], shape: tuple[int, int]) -> dict[str, np.ndarray]:
    from bench_propagate import constant_maps

    return constant_maps(train_maps, shape)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="/tmp/propbench")
    ap.add_argument("--alpha", type=float, default=1e-3, help="ridge penalty (per sample, on standardised features)")
    ap.add_argument("--methods", default="constant,ridge,gbt", help="comma list of constant, ridge, gbt")
    ap.add_argument("--json", help="also write the rows as JSON to this file (for bench_propagate_trade.py)")
    a = ap.parse_args()
    from bench_propagate import EVAL, load, prep, score_pairs, write_rows

    from dualscale.formats.exr import read_exr
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.data import load_source
    from dualscale.propagate.metrics import compare

    work = Path(a.work)
    if not (work / "guide" / "guidance.exr").is_file():
        prep(work)
    src = load_source(work / EVAL)
    train_rgb = src.diffuse_image().numpy().transpose(1, 2, 0)
    train_maps = {k: v.numpy().transpose(1, 2, 0) for k, v in src.maps.items()}
    guide = read_exr(work / "guide" / "guidance.exr")
    gt, _ = load_maps(work / "guide" / "gt")
    gt = {k: v.numpy() for k, v in gt.items()}
    rows = []
    for name in a.methods.split(","):
        l0 = load()
        t = time.perf_counter()
        if name == "constant":
            pred = constant(train_maps, guide.shape[:2])
        elif name == "ridge":
            pred = ridge(train_rgb, train_maps, guide, a.alpha)
        elif name == "gbt":
            pred = gbt(train_rgb, train_maps, guide)
        else:
            raise SystemExit(f"unknown method {name!r}: choose from constant, ridge, gbt")
        rows.append((name, time.perf_counter() - t, l0, compare(pred, gt)))
    maps = [m for m in train_maps if m in gt]
    print(f"\nClassic baselines on the twill benchmark (fit on the 256^2 micro diffuse image, run on the 768^2 "
          f"guidance; 1 process, load {rows[0][2]}):\n")
    print("| method | fit + run [s] (load) | " + " | ".join(f"{m} L1 / SSIM" for m in maps) + " |\n|---|---:|"
          + "---:|" * len(maps))
    for name, sec, l0, sc in rows:
        print(f"| {name} | {sec:.1f} ({l0}) | " + " | ".join(f"{sc[m]['l1']:.3f} / {sc[m]['ssim']:.2f}" for m in maps)
              + " |")
    if a.json:
        write_rows(a.json, "baselines", [{"label": name, "kind": "baseline", "method": name,
                                          "seconds": float(f"{sec:.3g}"), "load": float(l0),
                                          "maps": score_pairs({m: sc[m] for m in maps})}
                                         for name, sec, l0, sc in rows], rows[0][2])
    return 0


if __name__ == "__main__":
    sys.exit(main())
