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


def _orientations(corners: np.ndarray, keep_long_side: bool = False) -> list[np.ndarray]:
    c = np.asarray(corners)
    rots = [np.roll(c, -k, axis=0) for k in ((0, 2) if keep_long_side else range(4))]
    return rots + [r[::-1] for r in rots]


def _luminance_fit(samples: np.ndarray) -> tuple[float, float]:
    """``(residual, slope)`` of the affine fit ``Y = a Y_ref + b`` of the samples' luminance to
    the reference's: the rms residual relative to the rms of the fitted signal (0 = a perfect
    match, 1 = no relation), and ``a`` (positive for a chart, negative for a negative)."""
    ref = cr.luminance(cr.reference_rgb())
    y = cr.luminance(np.asarray(samples, float)[:, :3])
    a_mat = np.stack([ref, np.ones_like(ref)], 1)
    (a, b), *_ = np.linalg.lstsq(a_mat, y, rcond=None)
    fit = a_mat @ np.array([a, b])
    signal = float(np.sqrt(np.mean((fit - fit.mean()) ** 2)))
    if signal <= 0 or not np.isfinite(signal):
        return np.inf, 0.0
    return float(np.sqrt(np.mean((y - fit) ** 2)) / signal), float(a)


def orient_corners(image: np.ndarray, corners: np.ndarray, layout: ChartLayout = ChartLayout(),
                   keep_long_side: bool = False) -> np.ndarray:
    """Reorder corners so that sampling matches the reference order: of the 8 symmetries of the
    quadrilateral (4 with ``keep_long_side``: the first side stays the first side's line), keep
    the one whose swatch luminances best match the reference, up to a gain and an offset (the
    exposure and any flare).  Raises :class:`ChartNotFoundError` if no orientation fits in the
    image."""
    return _orient(image, corners, layout, keep_long_side)[0]


def _orient(image: np.ndarray, corners: np.ndarray, layout: ChartLayout,
            keep_long_side: bool) -> tuple[np.ndarray, float, float]:
    best, best_err, runner_up = None, np.inf, np.inf
    for c in _orientations(corners, keep_long_side):
        try:
            s = sample_patches(image, c, layout)
        except ChartNotFoundError:
            continue
        err, slope = _luminance_fit(s)
        if slope <= 0:
            err = np.inf
        if err < best_err:
            best, best_err, runner_up = c, err, best_err
        elif err < runner_up:
            runner_up = err
    if best is None:
        raise ChartNotFoundError("no orientation of the chart corners fits in the image")
    return np.asarray(best), best_err, runner_up


# ---- verification ------------------------------------------------------------------------------

# Bounds of :func:`verify_chart` (docs/CALIBRATION.md, "Chart detection" gives the reasons).
ASPECT_TOLERANCE = 0.10      # |ln(measured / nominal aspect)| of the swatch area (near-frontal views)
MIN_PITCH_PX = 4.0           # swatch pitch: below it the sampled centre is < 1 px from an edge
MIN_INTERIOR_ANGLE_DEG = 45.0
MAX_ORIENTATION_RESIDUAL = 0.5    # affine luminance fit, rms residual / rms signal
MIN_ORIENTATION_MARGIN = 2.0      # runner-up residual / best residual
MAX_COLOUR_RESIDUAL = 0.25   # affine (3 x 3 + offset) fit to the reference: rms residual / rms spread
MAX_SWATCH_RESIDUAL = 0.35   # the same fit's worst swatch: |residual| / rms spread
NEUTRALS = tuple(range(18, 24))   # white 9.5 ... black 2 (decreasing reflectance)
MIN_NEUTRAL_STEP = 0.2       # each neutral step through the fit, as a fraction of the reference step


@dataclass(frozen=True)
class ChartCheck:
    """The measures a detection was verified with (all dimensionless unless stated)."""

    aspect: float              # measured width / height of the swatch area (nominal 1.5)
    pitch_px: float            # smallest swatch pitch along a side [px]
    min_angle_deg: float       # smallest interior angle of the quadrilateral
    orientation_residual: float
    orientation_margin: float
    colour_residual: float
    worst_swatch: int          # the swatch (0..23) farthest from the colour fit
    swatch_residual: float     # and its distance
    neutral_step: float        # smallest neutral step / its reference step


def _quad_geometry(c: np.ndarray, layout: ChartLayout) -> tuple[float, float, float, bool]:
    sides = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)  # top, right, bottom, left
    width, height = (sides[0] + sides[2]) / 2, (sides[1] + sides[3]) / 2
    aspect = float(width / height) if height > 0 else np.inf
    pitch = float(min(sides[0], sides[2]) / layout.cols) if layout.cols else 0.0
    pitch = min(pitch, float(min(sides[1], sides[3]) / layout.rows))
    e1 = np.roll(c, -1, axis=0) - c
    e0 = c - np.roll(c, 1, axis=0)
    cross = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]
    convex = bool(np.all(cross > 0) or np.all(cross < 0))
    cosang = np.sum(-e0 * e1, 1) / np.maximum(np.linalg.norm(e0, axis=1) * np.linalg.norm(e1, axis=1), 1e-12)
    min_angle = float(np.degrees(np.arccos(np.clip(cosang, -1, 1))).min())
    return aspect, pitch, min_angle, convex


def _colour_fit(samples: np.ndarray) -> tuple[float, int, float, float]:
    """``(residual, worst, worst_residual, neutral_step)`` of the affine colour fit (3 x 3 +
    offset) of the samples to the reference RGB: its rms residual and its worst swatch's
    residual (Euclidean), both relative to the reference's rms spread; and the smallest step
    down the neutral row of the samples mapped by that fit, relative to the reference step."""
    ref = cr.reference_rgb()
    x = np.concatenate([np.asarray(samples, float)[:, :3], np.ones((len(ref), 1))], 1)
    m, *_ = np.linalg.lstsq(x, ref, rcond=None)
    fit = x @ m
    spread = float(np.sqrt(np.mean(np.sum((ref - ref.mean(0)) ** 2, 1))))
    dist = np.linalg.norm(fit - ref, axis=1) / spread
    residual = float(np.sqrt(np.mean(dist ** 2)))
    worst = int(np.argmax(dist))
    y_fit, y_ref = cr.luminance(fit[list(NEUTRALS)]), cr.luminance(ref[list(NEUTRALS)])
    step = float(np.min(-np.diff(y_fit) / -np.diff(y_ref)))
    return residual, worst, float(dist[worst]), step


def verify_chart(image: np.ndarray, corners: np.ndarray,
                 layout: ChartLayout = ChartLayout()) -> tuple[np.ndarray, ChartCheck]:
    """Orient ``corners`` (:func:`orient_corners`, among the 4 orientations that keep the
    quadrilateral's longer sides as the chart's rows) and verify that they locate the ColorChecker:

    * geometry: a convex quadrilateral, interior angles >= ``MIN_INTERIOR_ANGLE_DEG``, aspect of
      the swatch area within ``exp(+-ASPECT_TOLERANCE)`` of ``cols / rows`` (1.5), a swatch pitch
      >= ``MIN_PITCH_PX`` and every swatch inside the image;
    * orientation: the affine fit of the swatches' luminance to the reference leaves a relative
      residual <= ``MAX_ORIENTATION_RESIDUAL``, and the next orientation is worse by a factor
      >= ``MIN_ORIENTATION_MARGIN``;
    * colour: the affine colour fit to the reference leaves a relative residual <=
      ``MAX_SWATCH_RESIDUAL`` on every swatch and <= ``MAX_COLOUR_RESIDUAL`` (rms), and the six
      neutrals, through that fit, decrease monotonically, each step >= ``MIN_NEUTRAL_STEP`` of
      the reference's.

    The swatches feed the anchor ``i_wp`` and the CCM fit (supplementary Sec. 2), so a
    misplaced quad must never reach them.  Bounds and their reasons: docs/CALIBRATION.md,
    "Chart detection".  Returns the oriented corners ``(4, 2)`` and the measures.  Raises
    :class:`ChartNotFoundError` naming the first failed check, its value and its bound (one
    line)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[-1] < 3:
        raise ValueError(f"chart image must be (H, W, 3), got {img.shape}")
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 2) or not np.isfinite(c).all():
        raise ChartNotFoundError(f"chart corners must be 4 finite (x, y) points, got shape {c.shape}")
    _, pitch, min_angle, convex = _quad_geometry(c, layout)
    if not convex:
        raise ChartNotFoundError("chart check failed: the corners do not form a convex quadrilateral")
    if min_angle < MIN_INTERIOR_ANGLE_DEG:
        raise ChartNotFoundError(f"chart check failed: interior angle {min_angle:.1f} deg < {MIN_INTERIOR_ANGLE_DEG:g} deg")
    if pitch < MIN_PITCH_PX:
        raise ChartNotFoundError(f"chart check failed: swatch pitch {pitch:.2f} px < {MIN_PITCH_PX:g} px (chart too small)")
    oriented, o_res, runner_up = _orient(img, _long_side_first(c), layout, keep_long_side=True)
    aspect = _quad_geometry(oriented, layout)[0]
    nominal = layout.cols / layout.rows
    if abs(np.log(aspect / nominal)) > ASPECT_TOLERANCE:
        raise ChartNotFoundError(f"chart check failed: aspect {aspect:.3f} outside {nominal * np.exp(-ASPECT_TOLERANCE):.3f}"
                                 f"..{nominal * np.exp(ASPECT_TOLERANCE):.3f} (nominal {nominal:g})")
    if not o_res <= MAX_ORIENTATION_RESIDUAL:
        raise ChartNotFoundError(f"chart check failed: orientation residual {o_res:.3f} > {MAX_ORIENTATION_RESIDUAL:g}")
    margin = runner_up / max(o_res, 1e-12)
    if margin < MIN_ORIENTATION_MARGIN:
        raise ChartNotFoundError(f"chart check failed: orientation ambiguous, next orientation's residual / best "
                                 f"{margin:.2f} < {MIN_ORIENTATION_MARGIN:g}")
    samples = sample_patches(img, oriented, layout)
    c_res, worst, w_res, step = _colour_fit(samples)
    if not w_res <= MAX_SWATCH_RESIDUAL:
        raise ChartNotFoundError(f"chart check failed: swatch {worst} ({cr.patch_names()[worst]}) residual "
                                 f"{w_res:.3f} > {MAX_SWATCH_RESIDUAL:g} (occluded or misplaced?)")
    if not c_res <= MAX_COLOUR_RESIDUAL:
        raise ChartNotFoundError(f"chart check failed: swatch colour residual {c_res:.3f} > {MAX_COLOUR_RESIDUAL:g} "
                                 "(affine fit to the reference)")
    if not step >= MIN_NEUTRAL_STEP:
        raise ChartNotFoundError(f"chart check failed: neutral row not decreasing, smallest step {step:.2f} of the "
                                 f"reference's < {MIN_NEUTRAL_STEP:g}")
    return oriented, ChartCheck(aspect, pitch, min_angle, o_res, margin, c_res, worst, w_res, step)


# ---- refinement ---------------------------------------------------------------------------------

def _coverage_1d(t: np.ndarray, lo: np.ndarray, hi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Fraction of a pixel of width ``w`` centred at ``t`` inside ``[lo, hi]`` (all broadcast)."""
    return np.clip((np.minimum(t + w / 2, hi) - np.maximum(t - w / 2, lo)) / w, 0.0, 1.0)


def _model_design(c: np.ndarray, xs: np.ndarray, ys: np.ndarray, layout: ChartLayout) -> np.ndarray:
    """Per-pixel coverage ``(N, 26)`` of the 24 swatches, the chart body and the outside, for
    the chart with swatch-area corners ``c`` (pixel box model along the chart's axes)."""
    unit = np.array([[0, 0], [layout.cols, 0], [layout.cols, layout.rows], [0, layout.rows]], float)
    h = homography(c, unit)  # image -> chart cells (u along columns, v along rows)
    p = np.stack([xs, ys, np.ones_like(xs)], 1) @ h.T
    u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    # one pixel's extent in cells along u and v at each point (the local Jacobian)
    jac_u = np.hypot(h[0, 0] - u * h[2, 0], h[0, 1] - u * h[2, 1]) / np.abs(p[:, 2])
    jac_v = np.hypot(h[1, 0] - v * h[2, 0], h[1, 1] - v * h[2, 1]) / np.abs(p[:, 2])
    wu, wv = np.maximum(jac_u, 1e-6), np.maximum(jac_v, 1e-6)
    half = layout.patch_mm / layout.pitch_mm / 2
    cols = np.arange(layout.cols) + 0.5
    rows = np.arange(layout.rows) + 0.5
    fu = _coverage_1d(u[:, None], cols - half, cols + half, wu[:, None])
    fv = _coverage_1d(v[:, None], rows - half, rows + half, wv[:, None])
    sw = (fv[:, :, None] * fu[:, None, :]).reshape(len(xs), -1)
    inside = _coverage_1d(u, 0.0, float(layout.cols), wu) * _coverage_1d(v, 0.0, float(layout.rows), wv)
    body = np.clip(inside - sw.sum(1), 0.0, None)
    return np.concatenate([sw, body[:, None], (1.0 - inside)[:, None]], 1)


def refine_corners(image: np.ndarray, corners: np.ndarray, layout: ChartLayout = ChartLayout(),
                   max_pixels: int = 3000) -> np.ndarray:
    """Sub-pixel swatch-area corners ``(4, 2)`` refined from a close guess (within about a
    third of a swatch pitch): a least-squares fit of the chart as 26 flat regions (24 swatches, the
    black body, the outside), each pixel covered in proportion to its area, with the regions'
    colours solved for at each step (variable projection; free colours, so exposure, white
    balance, flare and the orientation do not matter).  The fit uses the pixels within half a
    pitch of the guessed chart, decimated to at most ``max_pixels``; a robust loss lets an
    occluder or a marker lose its weight.  Corners are image ``(x, y)`` px (module doc).
    Returns the guess unchanged if the fit fails or moves a corner by more than 0.75 pitch (it
    has then left this chart); the result is only a candidate for :func:`verify_chart`."""
    from scipy.optimize import least_squares

    img = np.asarray(image, dtype=np.float64)[..., :3]
    c0 = np.asarray(corners, dtype=np.float64)
    hgt, wid = img.shape[:2]
    pitch = np.linalg.norm(c0[1] - c0[0]) / layout.cols
    lo = np.floor(c0.min(0) - 0.6 * pitch).astype(int).clip(0, [wid - 1, hgt - 1])
    hi = np.ceil(c0.max(0) + 0.6 * pitch).astype(int).clip(0, [wid - 1, hgt - 1])
    yy, xx = np.mgrid[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
    xs, ys = xx.ravel().astype(float), yy.ravel().astype(float)
    # keep the ring within half a pitch of the guessed swatch area
    unit = np.array([[0, 0], [layout.cols, 0], [layout.cols, layout.rows], [0, layout.rows]], float)
    p = np.stack([xs, ys, np.ones_like(xs)], 1) @ homography(c0, unit).T
    u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    keep = (u > -0.5) & (u < layout.cols + 0.5) & (v > -0.5) & (v < layout.rows + 0.5)
    xs, ys = xs[keep], ys[keep]
    if len(xs) > max_pixels:
        sel = np.random.default_rng(0).choice(len(xs), max_pixels, replace=False)
        xs, ys = xs[sel], ys[sel]
    vals = img[ys.astype(int), xs.astype(int)]
    scale = float(np.quantile(vals, 0.99)) or 1.0
    vals = vals / scale

    def residual(q: np.ndarray) -> np.ndarray:
        a = _model_design(q.reshape(4, 2), xs, ys, layout)
        ata = a.T @ a + 1e-9 * np.eye(a.shape[1])
        x = np.linalg.solve(ata, a.T @ vals)
        return (a @ x - vals).ravel()

    try:
        res = least_squares(residual, c0.ravel(), diff_step=1e-3, loss="soft_l1", f_scale=0.05,
                            x_scale=1.0, max_nfev=200)
    except (np.linalg.LinAlgError, ValueError):
        return c0
    c = res.x.reshape(4, 2)
    if not np.isfinite(c).all() or np.abs(c - c0).max() > 0.75 * pitch:
        return c0
    return c


def detect_chart(image: np.ndarray, layout: ChartLayout = ChartLayout()) -> np.ndarray:
    """Corners ``(4, 2)`` of the ColorChecker in a linear RGB image ``(H, W, 3)`` (any exposure).

    Candidates, in order: colour-checker-detection's segmentation detector (offline), then, if it
    finds nothing or its find fails the checks, the outline of the image's strongest block of
    edges (:func:`_moment_guesses`, for small charts the detector misses).  Each candidate is
    refined to sub-pixel precision (:func:`refine_corners`), oriented and verified
    (:func:`verify_chart`: geometry, orientation fit, agreement of the swatches with the
    reference chart); the first that passes is returned.  Raises :class:`ChartNotFoundError`
    if none passes: the message names the failed check, the measured value and its bound."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[-1] < 3 or not np.isfinite(img[..., :3]).all():
        raise ValueError("chart image must be a finite (H, W, 3) array")
    img = img[..., :3]
    errors: list[str] = []
    try:
        seg = _long_side_first(_outer_corners(_segmentation_quad(img), layout))
    except ChartNotFoundError as e:
        errors.append(str(e))
    else:
        seg_errors = []
        for cand in (refine_corners(img, seg, layout), seg):  # the refinement can only help
            try:
                return verify_chart(img, cand, layout)[0]
            except ChartNotFoundError as e:
                seg_errors.append(e)
        errors.append(f"segmentation detector's find: {seg_errors[0]}")
    fallback_errors = []
    for guess in _moment_guesses(img, layout):
        try:
            return verify_chart(img, refine_corners(img, guess, layout), layout)[0]
        except ChartNotFoundError as e:
            fallback_errors.append(e)
    if fallback_errors and not any(str(fallback_errors[0]) in e for e in errors):
        errors.append(f"edge-outline fallback: {fallback_errors[0]}")
    raise ChartNotFoundError("; ".join(errors))


def _moment_guesses(img: np.ndarray, layout: ChartLayout) -> list[np.ndarray]:
    """Chart outlines ``[(4, 2)]`` guessed from the largest connected block of strong edges
    (a chart is a grid of edges): its centroid and principal axes give the centre and the
    orientation, its second moments the size (a uniform rectangle of side L has variance
    L^2 / 12), at 3 scales; the aspect is the layout's."""
    from scipy import ndimage

    x = np.sqrt(np.clip(img / (float(np.quantile(img, 0.99)) or 1.0), 0.0, None))
    g = sum(np.hypot(ndimage.sobel(x[..., k], 0), ndimage.sobel(x[..., k], 1)) for k in range(3))
    m = ndimage.binary_closing(g > 0.25 * float(np.quantile(g, 0.98)), iterations=2)
    lab, n = ndimage.label(m)
    if n == 0:
        return []
    blob = lab == 1 + int(np.argmax(ndimage.sum(m, lab, range(1, n + 1))))
    ys, xs = np.nonzero(blob)
    if len(xs) < 16:
        return []
    c = np.array([xs.mean(), ys.mean()])
    w, v = np.linalg.eigh(np.cov(np.stack([xs - c[0], ys - c[1]])))
    major = v[:, 1] if v[0, 1] >= 0 else -v[:, 1]
    minor = np.array([-major[1], major[0]])
    aspect = layout.cols / layout.rows
    length = 0.5 * (np.sqrt(12 * w[1]) + aspect * np.sqrt(12 * max(w[0], 0.0)))
    out = []
    for scale in (1.0, 0.93, 1.07):
        hw, hh = scale * length / 2, scale * length / aspect / 2
        out.append(np.array([c - major * hw - minor * hh, c + major * hw - minor * hh,
                             c + major * hw + minor * hh, c - major * hw + minor * hh]))
    return out


def _segmentation_quad(img: np.ndarray) -> np.ndarray:
    from colour_checker_detection import detect_colour_checkers_segmentation

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
    s = w * up / _working_width()
    return (quad * s + 0.5) / up - 0.5


def _working_width() -> int:
    from colour_checker_detection import SETTINGS_SEGMENTATION_COLORCHECKER_CLASSIC

    return int(SETTINGS_SEGMENTATION_COLORCHECKER_CLASSIC["working_width"])


def _outer_corners(quad: np.ndarray, layout: ChartLayout) -> np.ndarray:
    """The detector's quadrilateral bounds the swatches; sort it clockwise from top-left and
    grow it by half the gap between swatches to the swatch area's outline (ChartLayout)."""
    c = quad.reshape(4, 2)
    centre = c.mean(0)
    ang = np.arctan2(c[:, 1] - centre[1], c[:, 0] - centre[0])
    c = c[np.argsort(ang)]
    k = int(np.argmin(c.sum(1)))
    c = np.roll(c, -k, axis=0)
    gap = (layout.pitch_mm - layout.patch_mm) / 2
    w, h = layout.size_mm
    grow = np.array([w / (w - 2 * gap), h / (h - 2 * gap)])
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    hm = homography(unit, c)
    out = np.concatenate([(unit - 0.5) * grow + 0.5, np.ones((4, 1))], 1) @ hm.T
    return out[:, :2] / out[:, 2:]


def _long_side_first(c: np.ndarray) -> np.ndarray:
    """Roll the corners so that the first side (TL -> TR) is a long side of the chart."""
    sides = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    return c if sides[0] + sides[2] >= sides[1] + sides[3] else np.roll(c, -1, axis=0)
