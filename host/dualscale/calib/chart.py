"""Finding a ColorChecker Classic in an image and sampling its 24 patches.

Corners are image ``(x, y)`` pixel coordinates (x = column, y = row, pixel centres at
integers) of the chart's outer swatch area, in the order top-left, top-right, bottom-right,
bottom-left as seen with dark skin at the top left.  They come from colour-checker-detection's
segmentation detector (:func:`detect_chart`) or from the user (:func:`sample_patches`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import colourref as cr
from dualscale.errors import ChartNotFoundError


# The micro camera's sharpness target: a grid of opaque dots (supplementary Sec. 3).
DOT_PITCH_UM, DOT_DIAMETER_UM = 125.0, 62.5


@dataclass(frozen=True)
class ChartLayout:
    """4 x 6 swatches; ``pitch_mm`` centre to centre, ``patch_mm`` swatch width (the rest is the
    black chart body).  The default is a ColorChecker Classic Mini-sized chart that fits the
    10 cm mid-range field."""

    rows: int = 4
    cols: int = 6
    pitch_mm: float = 14.0
    patch_mm: float = 11.0

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.cols * self.pitch_mm, self.rows * self.pitch_mm

    def patch_of(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Patch index at chart-plane points (origin at the chart centre, +y up), -1 for the
        chart body and -2 outside the chart."""
        w, h = self.size_mm
        u = x_mm + w / 2
        v = h / 2 - y_mm
        col = np.floor(u / self.pitch_mm).astype(int)
        row = np.floor(v / self.pitch_mm).astype(int)
        du = u - (col + 0.5) * self.pitch_mm
        dv = v - (row + 0.5) * self.pitch_mm
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        on = inside & (np.abs(du) < self.patch_mm / 2) & (np.abs(dv) < self.patch_mm / 2)
        return np.where(on, row * self.cols + col, np.where(inside, -1, -2))


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3 x 3 projective map taking 4 ``src`` points to 4 ``dst`` points (DLT)."""
    a = []
    for (x, y), (u, v) in zip(np.asarray(src, float), np.asarray(dst, float)):
        a.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        a.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, vt = np.linalg.svd(np.asarray(a))
    h = vt[-1].reshape(3, 3)
    return h / h[2, 2]


def patch_centres(corners: np.ndarray, layout: ChartLayout = ChartLayout()) -> tuple[np.ndarray, float]:
    """Image ``(x, y)`` of the 24 swatch centres ``(24, 2)`` and a safe sampling half-size [px]."""
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 2) or not np.isfinite(c).all():
        raise ValueError(f"chart corners must be 4 (x, y) points, got {c.shape}")
    unit = np.array([[0, 0], [layout.cols, 0], [layout.cols, layout.rows], [0, layout.rows]], float)
    h = homography(unit, c)
    g = np.array([[(k % layout.cols) + 0.5, (k // layout.cols) + 0.5, 1.0] for k in range(layout.rows * layout.cols)])
    p = g @ h.T
    xy = p[:, :2] / p[:, 2:]
    side = min(np.linalg.norm(c[1] - c[0]) / layout.cols, np.linalg.norm(c[3] - c[0]) / layout.rows)
    half = 0.3 * side * layout.patch_mm / layout.pitch_mm
    return xy, half


def sample_patches(image: np.ndarray, corners: np.ndarray, layout: ChartLayout = ChartLayout()) -> np.ndarray:
    """Mean colour of the central part of each swatch ``(24, C)`` given chart corners."""
    img = np.asarray(image, dtype=np.float64)
    xy, half = patch_centres(corners, layout)
    h, w = img.shape[:2]
    r = max(int(np.floor(half)), 0)
    out = []
    for x, y in xy:
        cx, cy = int(round(x)), int(round(y))
        if not (0 <= cx - r and cx + r < w and 0 <= cy - r and cy + r < h):
            raise ChartNotFoundError(f"swatch centre ({x:.1f}, {y:.1f}) is outside the {w}x{h} image")
        out.append(img[cy - r:cy + r + 1, cx - r:cx + r + 1].reshape(-1, img.shape[-1]).mean(0))
    return np.asarray(out)


def _orientations(corners: np.ndarray) -> list[np.ndarray]:
    c = np.asarray(corners)
    rots = [np.roll(c, -k, axis=0) for k in range(4)]
    return rots + [r[::-1] for r in rots]


def orient_corners(image: np.ndarray, corners: np.ndarray, layout: ChartLayout = ChartLayout()) -> np.ndarray:
    """Reorder corners so that sampling matches the reference order: of the 8 symmetries of
    the quadrilateral, keep the one whose swatch luminances best match the reference (log)."""
    ref = np.log(np.clip(cr.luminance(cr.reference_rgb()), 1e-4, None))
    best, best_err = None, np.inf
    for c in _orientations(corners):
        try:
            s = sample_patches(image, c, layout)
        except ChartNotFoundError:
            continue
        y = np.log(np.clip(cr.luminance(s[:, :3]), 1e-6, None))
        err = float(np.var(y - ref))  # a free scale: exposure and white balance
        if err < best_err:
            best, best_err = c, err
    if best is None:
        raise ChartNotFoundError("no orientation of the chart corners fits in the image")
    return np.asarray(best)


def detect_chart(image: np.ndarray, layout: ChartLayout = ChartLayout()) -> np.ndarray:
    """Corners ``(4, 2)`` of the ColorChecker in a linear RGB image (any exposure), found by
    colour-checker-detection's segmentation detector (offline).  Raises
    :class:`ChartNotFoundError` if there is none."""
    from colour_checker_detection import detect_colour_checkers_segmentation

    img = np.asarray(image, dtype=np.float64)[..., :3]
    if img.ndim != 3 or not np.isfinite(img).all():
        raise ValueError("chart image must be a finite (H, W, 3) array")
    h, w = img.shape[:2]
    up = max(1, int(np.ceil(720 / w)))  # small images: upsample so swatches span enough pixels
    if up > 1:
        import cv2

        img_d = cv2.resize(img.astype(np.float32), (w * up, h * up), interpolation=cv2.INTER_LINEAR)
    else:
        img_d = img
    scale = float(np.quantile(img_d, 0.99)) or 1.0
    disp = np.clip(img_d / scale, 0.0, 1.0)
    disp = np.where(disp <= 0.0031308, 12.92 * disp, 1.055 * disp ** (1 / 2.4) - 0.055).astype(np.float32)
    found = detect_colour_checkers_segmentation(disp, additional_data=True)
    if not found:
        raise ChartNotFoundError("no ColorChecker found in the image (segmentation detector)")
    quad = np.asarray(found[0].quadrilateral, dtype=np.float64)
    # the detector works on a resized copy (its working width); map back to image pixels
    work_w = _working_width()
    s = w * up / work_w
    quad = (quad * s + 0.5) / up - 0.5
    return orient_corners(img, _outer_corners(quad, layout), layout)


def _working_width() -> int:
    from colour_checker_detection import SETTINGS_SEGMENTATION_COLORCHECKER_CLASSIC

    return int(SETTINGS_SEGMENTATION_COLORCHECKER_CLASSIC["working_width"])


def _outer_corners(quad: np.ndarray, layout: ChartLayout) -> np.ndarray:
    """The detector's quadrilateral bounds the swatches; sort it clockwise from top-left."""
    c = quad.reshape(4, 2)
    centre = c.mean(0)
    ang = np.arctan2(c[:, 1] - centre[1], c[:, 0] - centre[0])
    c = c[np.argsort(ang)]
    k = int(np.argmin(c.sum(1)))
    return np.roll(c, -k, axis=0)
