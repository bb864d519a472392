"""Bridging the two scales: where the micro camera's field of view lies in the guidance image.

The micro capture is a few um per pixel (e.g. 512 px of 1.8 um = 0.92 mm); the guidance (the
mid-range camera, seed Section 7.2) is ~25 um per pixel over the whole sample.  Propagation is
trained at one scale and run at the other, so the stage needs to know both texel sizes and, to
match exposures and check itself, where the micro field sits in the guidance.

1. **Prior from the rig geometry** (:func:`prior_box`): the micro field (``field_mm`` of the
   micro camera, centred on the sample origin unless a calibration gives ``centre_mm``) is
   projected into the guidance camera (:mod:`dualscale.geometry.cameras`; the mid camera looks
   straight down at the origin, so the plane maps linearly to its pixels).  A guidance without a
   camera is taken as an orthographic view centred on the origin at its texel size.
2. **Refinement by registration** (:func:`register_micro`, OpenCV): the micro image's luminance
   is area-averaged to the guidance texel (``cv2.resize``, ``INTER_AREA``) and matched by
   normalised cross-correlation (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``) inside a search
   window of ``search_mm`` around the prior; then ``cv2.findTransformECC`` (translation) refines
   the peak to sub-pixel.  Periodic textures (a weave repeat shorter than the search window)
   give several near-equal peaks: every local maximum within ``AMBIGUITY`` of the best is a
   candidate and the one nearest the prior wins (``ambiguous`` is reported).
3. **Failure** is explicit: a template under :data:`MIN_TEMPLATE_PX` pixels, a flat image, or a
   peak below ``min_score`` falls back to the prior with a warning (``method = "prior"``), or
   raises :class:`~dualscale.errors.GeometryError` with ``strict=True``.

Boxes are ``(x, y, w, h)`` in guidance pixels: ``x`` from the left image edge, ``y`` from the
top edge (pixel ``(row r, col c)`` covers ``[c, c + 1) x [r, r + 1)``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from dualscale.errors import GeometryError
from dualscale.geometry.cameras import Camera

MIN_TEMPLATE_PX = 8  # below this the micro field is a handful of guidance pixels: no registration
MIN_SCORE = 0.5  # NCC below this is no match
AMBIGUITY = 0.03  # peaks within this NCC of the best are equally good candidates
SEARCH_MM = 1.5  # default search radius around the prior


@dataclass
class Registration:
    """Where the micro field is in the guidance (see the module docstring).

    ``box_px`` and ``prior_px``: ``(x, y, w, h)`` guidance pixels; ``score``: NCC at the chosen
    peak; ``second``: the best NCC of another peak at least ``exclusion_px`` away (how distinct the
    match is); ``ecc``: the ECC correlation after sub-pixel refinement; ``method``: ``"ncc+ecc"``,
    ``"ncc"`` or ``"prior"``; ``shift_px``: box minus prior (x, y); ``ambiguous``: several peaks
    within :data:`AMBIGUITY`; ``scale``: micro texel / guidance texel.
    """

    box_px: tuple[float, float, float, float]
    prior_px: tuple[float, float, float, float]
    method: str
    scale: float
    score: float | None = None
    second: float | None = None
    ecc: float | None = None
    ambiguous: bool = False
    candidates: int = 0
    search_px: float = 0.0
    exclusion_px: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def shift_px(self) -> tuple[float, float]:
        return self.box_px[0] - self.prior_px[0], self.box_px[1] - self.prior_px[1]

    def to_json(self) -> dict:
        d = asdict(self)
        d["box_px"], d["prior_px"] = list(self.box_px), list(self.prior_px)
        d["shift_px"] = list(self.shift_px)
        return d


def project(camera: Camera, points_mm: np.ndarray) -> np.ndarray:
    """Sample-plane points ``(N, 2)`` mm -> image coordinates ``(N, 2)`` ``(x, y)`` in pixels from
    the top-left image corner (the inverse of :meth:`Camera.pixel_geometry`)."""
    p = np.asarray(points_mm, np.float64).reshape(-1, 2)
    fx, fy = camera.field_mm
    if camera.kind == "orthographic":
        nx, ny = p[:, 0] / fx, p[:, 1] / fy
    else:
        right, up, fwd = (v.numpy() for v in camera.basis())
        c = np.asarray(camera.position_mm, np.float64)
        d = np.concatenate([p, np.zeros((len(p), 1))], 1) - c
        s = (d @ fwd) / np.linalg.norm(c)
        if (s <= 0).any():
            raise GeometryError(f"camera {camera.name!r}: some points are behind the camera")
        nx, ny = (d @ right) / (s * fx), (d @ up) / (s * fy)
    return np.stack([(nx + 0.5) * camera.width, (0.5 - ny) * camera.height], -1)


def prior_box(guidance_shape: tuple[int, int], texel_mm: float, micro_field_mm: tuple[float, float],
              camera: Camera | None = None, centre_mm: tuple[float, float] = (0.0, 0.0)) -> tuple[float, ...]:
    """The micro field ``micro_field_mm`` (w, h), centred at ``centre_mm`` on the sample plane, as
    an ``(x, y, w, h)`` box in the guidance: through ``camera`` when given (its size must match
    the image), else an orthographic view centred on the origin at ``texel_mm`` per pixel."""
    h, w = guidance_shape
    if camera is None:
        camera = Camera("guidance", "orthographic", w, h, (w * texel_mm, h * texel_mm))
    elif (camera.height, camera.width) != (h, w):
        raise GeometryError(f"guidance camera {camera.name!r} is {camera.width}x{camera.height}, the image is "
                            f"{w}x{h}")
    cx, cy = centre_mm
    hw, hh = micro_field_mm[0] / 2, micro_field_mm[1] / 2
    corners = project(camera, np.array([[cx - hw, cy + hh], [cx + hw, cy + hh], [cx + hw, cy - hh],
                                        [cx - hw, cy - hh]]))
    x0, y0 = corners.min(0)
    x1, y1 = corners.max(0)
    return float(x0), float(y0), float(x1 - x0), float(y1 - y0)


def downsample_to(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` (H, W[, C]) resized by ``scale`` (new size rounded, at least 1 px): area average
    when shrinking (``cv2.INTER_AREA``), bilinear when enlarging."""
    import cv2

    h, w = image.shape[:2]
    size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(image, np.float32), size, interpolation=interp)


def _local_maxima(res: np.ndarray, floor: float) -> np.ndarray:
    """``(N, 2)`` (x, y) of the 3x3 local maxima of ``res`` at or above ``floor``."""
    import cv2

    peak = (res >= cv2.dilate(res, np.ones((3, 3), np.uint8))) & (res >= floor)
    ys, xs = np.nonzero(peak)
    return np.stack([xs, ys], -1)


def register_micro(guidance_lum: np.ndarray, micro_lum: np.ndarray, scale: float,
                   prior: tuple[float, float, float, float], texel_mm: float, search_mm: float = SEARCH_MM,
                   min_score: float = MIN_SCORE, ecc: bool = True, strict: bool = False) -> Registration:
    """Locate the micro image in the guidance (see the module docstring).

    ``guidance_lum`` ``(H, W)`` and ``micro_lum`` ``(h, w)``: linear luminance (any gain: NCC is
    gain- and offset-invariant); ``scale``: micro texel / guidance texel; ``prior``: the box from
    :func:`prior_box`; ``texel_mm``: the guidance texel (for ``search_mm``).  Returns a
    :class:`Registration`; raises :class:`~dualscale.errors.GeometryError` only with ``strict``.
    """
    import cv2

    h_m, w_m = micro_lum.shape
    box_w, box_h = w_m * scale, h_m * scale
    # the prior's centre, with the size of the micro image at the guidance scale
    cx, cy = prior[0] + prior[2] / 2, prior[1] + prior[3] / 2
    prior = (cx - box_w / 2, cy - box_h / 2, box_w, box_h)
    search = search_mm / texel_mm
    reg = Registration(tuple(float(v) for v in prior), tuple(float(v) for v in prior), "prior", float(scale),
                       search_px=float(search))

    def fail(why: str) -> Registration:
        if strict:
            raise GeometryError(f"cannot locate the micro field in the guidance: {why}")
        reg.warnings.append(f"micro field not registered in the guidance ({why}); using the rig geometry's "
                            f"prior box {[round(v, 1) for v in reg.prior_px]}")
        return reg

    tpl = downsample_to(micro_lum, scale)
    th, tw = tpl.shape
    if min(th, tw) < MIN_TEMPLATE_PX:
        return fail(f"the micro field is only {tw}x{th} guidance pixels, fewer than {MIN_TEMPLATE_PX}")
    if float(tpl.std()) <= 1e-6 * max(float(np.abs(tpl).mean()), 1e-12):
        return fail("the micro image is flat at the guidance scale")
    H, W = guidance_lum.shape
    x0 = int(np.clip(np.floor(prior[0] - search), 0, W))
    y0 = int(np.clip(np.floor(prior[1] - search), 0, H))
    x1 = int(np.clip(np.ceil(prior[0] + box_w + search), 0, W))
    y1 = int(np.clip(np.ceil(prior[1] + box_h + search), 0, H))
    win = np.ascontiguousarray(guidance_lum[y0:y1, x0:x1], np.float32)
    if win.shape[0] < th or win.shape[1] < tw:
        return fail(f"the search window {win.shape[1]}x{win.shape[0]} px around the prior is smaller than the "
                    f"micro field ({tw}x{th} px): the prior is off the image")
    res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
    res = np.where(np.isfinite(res), res, -1.0).astype(np.float32)
    best = float(res.max())
    excl = max(2.0, min(th, tw) / 4)
    reg.exclusion_px = float(excl)
    peaks = _local_maxima(res, best - AMBIGUITY)
    # the prior's offset inside the result map (top-left corner of the template)
    px, py = prior[0] - x0, prior[1] - y0
    d = np.hypot(peaks[:, 0] - px, peaks[:, 1] - py)
    bx, by = (int(v) for v in peaks[int(np.argmin(d))])
    yy, xx = np.mgrid[0:res.shape[0], 0:res.shape[1]]
    far = np.hypot(xx - bx, yy - by) > excl
    reg.score = float(res[by, bx])
    reg.second = float(res[far].max()) if far.any() else None
    far_peaks = peaks[np.hypot(peaks[:, 0] - bx, peaks[:, 1] - by) > excl]
    reg.candidates = int(len(far_peaks) + 1)
    reg.ambiguous = bool(len(far_peaks))
    if reg.score < min_score:
        return fail(f"normalised cross-correlation {reg.score:.2f} < {min_score}")
    sx, sy, method = float(bx), float(by), "ncc"
    if ecc and min(th, tw) >= MIN_TEMPLATE_PX:
        warp = np.array([[1, 0, bx], [0, 1, by]], np.float32)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
        try:
            reg.ecc, warp = cv2.findTransformECC(tpl, win, warp, cv2.MOTION_TRANSLATION, crit, None, 1)
            ex, ey = float(warp[0, 2]), float(warp[1, 2])
            if np.hypot(ex - bx, ey - by) <= 1.5:
                sx, sy, method = ex, ey, "ncc+ecc"
            else:
                reg.warnings.append(f"sub-pixel refinement (ECC) moved {np.hypot(ex - bx, ey - by):.1f} px from "
                                    "the correlation peak; kept the whole-pixel peak")
        except cv2.error as e:  # ECC did not converge
            reg.warnings.append(f"sub-pixel refinement (ECC) failed ({str(e).strip().splitlines()[-1]}); kept the "
                                "whole-pixel peak")
    # the template spans round(w * scale) px; centre the exact-size box on it
    reg.box_px = (x0 + sx + (tw - box_w) / 2, y0 + sy + (th - box_h) / 2, box_w, box_h)
    reg.method = method
    if reg.ambiguous:
        reg.warnings.append(f"the match is ambiguous: {reg.candidates} peaks within {AMBIGUITY} of the best NCC "
                            "(a periodic texture); took the one nearest the rig geometry's prior")
    return reg
