"""Light directions from photos of a mirror (chrome) sphere, one light per photo.

The classic reflective-sphere light calibration (as used for RTI domes, light stages and
photometric stereo): the highlight of a distant light on a mirror sphere sits where the sphere's
normal ``n`` bisects the view ``v`` and the light ``L``, so ``L = 2 (n . v) n - v``.  Other domes
than ours calibrate this way; our own dome's nominal layout is Garces et al. 2023, Sec. 2.

Conventions.
  * Pixel coordinates ``(x, y)``: ``x`` = column, ``y`` = row (rows go *down*), pixel centres at
    integers (the centre of the top-left pixel is ``(0, 0)``).
  * Camera frame of the result: ``+x`` image right, ``+y`` image up, ``+z`` towards the camera;
    directions are unit vectors from the sphere towards the light (the ``.lp`` convention, see
    :mod:`dualscale.formats.lightfile`).
  * Orthographic camera, ``v = (0, 0, 1)``.  The normal at pixel ``(x, y)`` of a sphere of
    centre ``(cx, cy)`` and radius ``r`` [px] is ``((x - cx) / r, (cy - y) / r, sqrt(1 - ...))``.
    A perspective camera biases directions by about the sphere's angular size; keep the sphere
    small in the frame and near the optical axis.
  * Images: 8-/16-bit files are decoded from sRGB to linear (unless OpenImageIO tags them
    linear), float files (EXR) are taken as linear; colour is averaged to one channel.

Errors: :class:`LightSphereError` (a ``ValueError``) naming the image, when no highlight stands
out of the sphere, when the only highlight lies outside the sphere, or when the sphere cannot be
found (then pass a mask).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import ndimage, optimize
from skimage import measure

from dualscale.formats.lightfile import LightRecord

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")


class LightSphereError(ValueError):
    """The sphere or a highlight could not be found; the message names the image."""


@dataclass(frozen=True)
class Sphere:
    """The sphere's image disc: centre ``(cx, cy)`` and radius ``r`` in pixels (conventions in
    the module docstring), the RMS distance [px] of the edge points to the fitted circle, and
    where it came from (``"mask"``, ``"mask:<file>"`` or ``"auto"``)."""

    cx: float
    cy: float
    r: float
    fit_rms_px: float
    source: str


@dataclass
class SphereLights:
    """Recovered lights, ``N`` of them, in input order.

    ``directions`` ``(N, 3)`` unit, camera frame; ``highlights_px`` ``(N, 2)`` ``(x, y)`` sub-pixel
    highlight centroids; ``residual_deg`` ``(N,)`` the angle between the directions given by the
    intensity-weighted and the unweighted (area) centroid of the highlight, an asymmetry measure
    (flare, clipping, a second reflection merged in); ``deg_per_px`` ``(N,)`` how far the light
    moves per pixel of highlight error there; ``confidence`` ``(N,)`` in ``[0, 1]``, the share of
    the above-threshold energy on the sphere that the chosen highlight holds (1 = one clean
    highlight); ``spread_px`` ``(N,)`` RMS radius of the highlight; ``n_blobs`` ``(N,)`` bright
    blobs on the sphere holding >= 5 % of the chosen one's energy; ``saturated_px`` ``(N,)``
    clipped pixels in the highlight (integer images only)."""

    files: list[str]
    directions: np.ndarray
    highlights_px: np.ndarray
    sphere: Sphere
    residual_deg: np.ndarray
    deg_per_px: np.ndarray
    confidence: np.ndarray
    spread_px: np.ndarray
    n_blobs: np.ndarray
    saturated_px: np.ndarray
    notes: list[str] = field(default_factory=list)

    @property
    def elevation_deg(self) -> np.ndarray:
        """Elevation above the image plane, ``asin(z)`` in degrees, ``(N,)``."""
        return np.degrees(np.arcsin(np.clip(self.directions[:, 2], -1, 1)))

    def to_records(self) -> list[LightRecord]:
        """One :class:`LightRecord` per image (intensity unknown: ``None``), for the writers."""
        return [LightRecord(f, tuple(float(c) for c in d), None) for f, d in zip(self.files, self.directions)]

    def source(self) -> dict[str, Any]:
        """The ``source`` block of the JSON light file: method, sphere and per-light diagnostics."""
        s = self.sphere
        return {"method": "mirror-sphere", "camera": "orthographic",
                "sphere": {"centre_px": [s.cx, s.cy], "radius_px": s.r, "fit_rms_px": s.fit_rms_px, "from": s.source},
                "pixel_convention": "x = column, y = row (down), pixel centres at integers",
                "per_light": [{"file": f, "highlight_px": [float(h[0]), float(h[1])], "residual_deg": float(e),
                               "deg_per_px": float(g), "confidence": float(c), "n_blobs": int(b)}
                              for f, h, e, g, c, b in zip(self.files, self.highlights_px, self.residual_deg,
                                                          self.deg_per_px, self.confidence, self.n_blobs)],
                "notes": list(self.notes)}


# ------------------------------------------------------------------------------------- images
def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def read_gray(path: str | Path, decode: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an image with OpenImageIO: ``(linear gray (H, W) float64, clipped (H, W) bool or None)``.
    Integer files are sRGB-decoded unless tagged linear or ``decode`` is False (masks: their
    anti-aliased edge is coverage, stored as is); ``clipped`` marks code values at full scale in
    any channel (None for float files)."""
    import OpenImageIO as oiio

    path = Path(path)
    buf = oiio.ImageBuf(str(path))
    # read the pixels now: ImageBuf reads lazily, and a truncated file fails only then (and
    # get_pixels would hand back whatever buffer was there -- another image's pixels)
    if buf.has_error or not buf.read(0, 0, True) or buf.has_error:
        raise LightSphereError(f"{path}: cannot read image ({buf.geterror() or 'truncated or corrupt'})")
    spec = buf.spec()
    px = buf.get_pixels(oiio.FLOAT)
    if px is None or buf.has_error:
        raise LightSphereError(f"{path}: cannot read its pixels ({buf.geterror() or 'truncated or corrupt'})")
    px = np.asarray(px, dtype=np.float64)
    if px.ndim == 2:
        px = px[..., None]
    px = px[..., : 3 if spec.nchannels >= 3 else 1]
    is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    clipped = None
    if not is_float:
        clipped = (px >= 1.0 - 0.5 / 255).any(-1)
        cs = spec.get_string_attribute("oiio:ColorSpace").lower()
        if decode and not ("lin" in cs or cs == "raw"):
            px = _srgb_to_linear(px)
    return px.mean(-1), clipped


def _as_gray(img: "str | Path | np.ndarray") -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(img, (str, Path)):
        return read_gray(img)
    a = np.asarray(img)
    clipped = None
    if a.dtype.kind in "ui":
        full = float(np.iinfo(a.dtype).max)
        clipped = (a >= full).any(-1) if a.ndim == 3 else a >= full
        a = _srgb_to_linear(a.astype(np.float64) / full)
    a = a.astype(np.float64)
    if a.ndim == 3:
        a = a[..., :3].mean(-1)
    if a.ndim != 2:
        raise LightSphereError(f"image of shape {np.shape(img)}: expected (H, W) or (H, W, C)")
    return a, clipped


def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


# ------------------------------------------------------------------------------------- sphere
def _fit_circle(pts: np.ndarray) -> tuple[float, float, float, float]:
    """Geometric least-squares circle through ``(x, y)`` points (Kasa start): cx, cy, r, rms."""
    x, y = pts[:, 0], pts[:, 1]
    A = np.c_[2 * x, 2 * y, np.ones_like(x)]
    c, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    r0 = math.sqrt(max(c[2] + c[0] ** 2 + c[1] ** 2, 1e-12))
    res = optimize.least_squares(lambda p: np.hypot(x - p[0], y - p[1]) - p[2], [c[0], c[1], r0], loss="soft_l1", f_scale=0.5)
    cx, cy, r = res.x
    rms = float(np.sqrt(np.mean((np.hypot(x - cx, y - cy) - r) ** 2)))
    return float(cx), float(cy), float(abs(r)), rms


def _largest_component(binary: np.ndarray) -> np.ndarray:
    lab, n = ndimage.label(binary)
    if n == 0:
        return np.zeros_like(binary, bool)
    sizes = ndimage.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
    return ndimage.binary_fill_holes(lab == 1 + int(np.argmax(sizes)))


def _circle_from_level(img: np.ndarray, level: float, keep: np.ndarray, what: str) -> tuple[float, float, float, float]:
    """Fit a circle to the sub-pixel ``level`` contours of ``img`` around region ``keep``,
    leaving out points on the image border (a sphere cut by the frame)."""
    h, w = img.shape
    cs = [c for c in measure.find_contours(np.where(ndimage.binary_dilation(keep, iterations=3), img, img.min()), level)
          if len(c) >= 8]
    if not cs:
        raise LightSphereError(f"{what}: no sphere outline found")
    pts = np.concatenate(cs)[:, ::-1]  # (row, col) -> (x, y)
    inner = (pts[:, 0] > 0.5) & (pts[:, 0] < w - 1.5) & (pts[:, 1] > 0.5) & (pts[:, 1] < h - 1.5)
    if inner.sum() < 16:
        raise LightSphereError(f"{what}: sphere outline has only {int(inner.sum())} points inside the frame")
    return _fit_circle(pts[inner])


def sphere_from_mask(mask: np.ndarray, source: str = "mask", max_rms_px: float = 1.5) -> Sphere:
    """The sphere's disc from a mask ``(H, W)`` (binary or anti-aliased; any scale, ``> half`` of
    its maximum is inside): largest component, holes filled, sub-pixel 0.5 outline, circle fit.
    Raises :class:`LightSphereError` when the outline is not a circle (RMS > ``max_rms_px``)."""
    m = np.asarray(mask, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    top = float(m.max()) if m.size else 0.0
    if top <= 0:
        raise LightSphereError(f"{source}: empty mask")
    m = m / top
    keep = _largest_component(m > 0.5)
    m = np.where(keep, np.maximum(m, 0.5 + 1e-6), np.where(ndimage.binary_dilation(keep, iterations=2), m, 0.0))
    cx, cy, r, rms = _circle_from_level(m, 0.5, keep, source)
    if rms > max_rms_px:
        raise LightSphereError(f"{source}: the mask is not a disc (circle fit RMS {rms:.2f} px > {max_rms_px} px)")
    return Sphere(cx, cy, r, rms, source)


def _radial_edges(img: np.ndarray, cx: float, cy: float, r: float, n_rays: int = 720, reach: float = 4.0) -> np.ndarray:
    """Sub-pixel outline points ``(M, 2)``: along ``n_rays`` rays through ``(cx, cy)``, where the
    image falls fastest within ``r +- reach`` (a step's steepest point is its 50 % point whatever
    its height, so a rim that is brighter on one side does not pull the outline); rays with a
    weak or inward edge (a highlight or a stand at the limb) are left out."""
    a = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    step = 0.05
    t = np.arange(-reach, reach + step / 2, step)
    rr = r + t
    X, Y = cx + np.cos(a)[:, None] * rr, cy + np.sin(a)[:, None] * rr
    g = np.gradient(ndimage.map_coordinates(img, [Y, X], order=3, mode="nearest"), step, axis=1)
    k = np.clip(np.argmin(g, axis=1), 1, len(t) - 2)
    ar = np.arange(n_rays)
    g0, g1, g2 = g[ar, k - 1], g[ar, k], g[ar, k + 1]
    den = g0 - 2 * g1 + g2
    off = np.where(np.abs(den) > 1e-15, 0.5 * (g0 - g2) / np.where(den == 0, 1, den), 0.0)
    rad = r + t[k] + np.clip(off, -1, 1) * step
    ok = (g1 < 0) & (-g1 >= 0.25 * np.median(-g1)) & (k > 1) & (k < len(t) - 2)
    h, w = img.shape
    pts = np.c_[cx + np.cos(a) * rad, cy + np.sin(a) * rad][ok]
    inside = (pts[:, 0] > 1) & (pts[:, 0] < w - 2) & (pts[:, 1] > 1) & (pts[:, 1] < h - 2)
    return pts[inside]


def sphere_auto(stack: np.ndarray, max_rms_px: float = 1.0, what: str = "images") -> Sphere:
    """Find the sphere without a mask, from ``stack`` ``(N, H, W)`` linear images: the per-pixel
    median (the highlights drop out; what is left is the sphere's reflection of the room),
    Otsu threshold, largest component and a first circle; then the outline's steepest point
    along 720 rays (:func:`_radial_edges`) and a robust circle fit.  Needs the sphere to stand
    out of the background all round; raises :class:`LightSphereError` (pass a mask) otherwise."""
    med = np.median(stack, axis=0)
    sm = ndimage.gaussian_filter(med, 1.0)
    lo, hi = np.percentile(sm, [1, 99.5])
    if not hi > lo:
        raise LightSphereError(f"{what}: the sphere does not stand out of the background; pass a mask")
    from skimage.filters import threshold_otsu

    keep = _largest_component(sm > threshold_otsu(np.clip(sm, lo, hi)))
    if keep.sum() < 50:
        raise LightSphereError(f"{what}: no sphere found automatically; pass a mask")
    cx, cy, r, _ = _circle_from_level(keep.astype(np.float64), 0.5, keep, what)
    pts = _radial_edges(ndimage.gaussian_filter(med, 0.7), cx, cy, r)
    if len(pts) < 90:
        raise LightSphereError(f"{what}: the sphere's outline is visible on only {len(pts)} of 720 rays; pass a mask")
    cx, cy, r, rms = _fit_circle(pts)
    if rms > max_rms_px or abs(keep.sum() / (math.pi * r * r) - 1) > 0.1:
        raise LightSphereError(f"{what}: automatic sphere outline is not a disc (fit RMS {rms:.2f} px, "
                               f"{keep.sum() / (math.pi * r * r):.2f} of the disc's area); pass a mask")
    return Sphere(cx, cy, r, rms, "auto")


# ----------------------------------------------------------------------------------- highlight
def pixel_to_light(x: np.ndarray | float, y: np.ndarray | float, sphere: Sphere) -> np.ndarray:
    """Light direction(s) ``(..., 3)`` for highlight position(s) ``(x, y)`` [px] on ``sphere``
    (orthographic, ``v = +z``): ``L = 2 (n . v) n - v``.  Positions are clamped to the disc."""
    nx = (np.asarray(x, np.float64) - sphere.cx) / sphere.r
    ny = (sphere.cy - np.asarray(y, np.float64)) / sphere.r
    rho = np.hypot(nx, ny)
    s = np.where(rho > 1 - 1e-9, (1 - 1e-9) / np.maximum(rho, 1e-12), 1.0)
    nx, ny = nx * s, ny * s
    nz = np.sqrt(np.clip(1 - nx * nx - ny * ny, 0, 1))
    return np.stack([2 * nz * nx, 2 * nz * ny, 2 * nz * nz - 1], -1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b))))


def _highlight(img: np.ndarray, clipped: np.ndarray | None, sphere: Sphere, name: str, rel_threshold: float):
    h, w = img.shape
    yy, xx = np.mgrid[:h, :w]
    rr = np.hypot(xx - sphere.cx, yy - sphere.cy)
    on = rr <= sphere.r
    vals = img[on]
    bg = float(np.median(vals))
    noise = 1.4826 * float(np.median(np.abs(vals - bg))) + 1e-12
    near = rr <= sphere.r + 2
    wgt = np.clip(img - bg, 0, None)

    def blobs(peak: float):
        lab, n = ndimage.label(img > bg + rel_threshold * (peak - bg), structure=np.ones((3, 3)))
        idx = np.arange(1, n + 1)
        energy = ndimage.sum_labels(wgt, lab, idx)
        e = np.maximum(energy, 1e-300)
        return lab, idx, energy, ndimage.sum_labels(wgt * xx, lab, idx) / e, ndimage.sum_labels(wgt * yy, lab, idx) / e

    def outside(peak: float) -> LightSphereError:
        _, _, energy, bx, by = blobs(peak)
        k = int(np.argmax(energy))
        return LightSphereError(f"{name}: the highlight at ({bx[k]:.1f}, {by[k]:.1f}) px is outside the sphere "
                                f"(centre ({sphere.cx:.1f}, {sphere.cy:.1f}), r {sphere.r:.1f} px)")

    significant = max(8 * noise, 1e-6)
    peak = float(img[near].max())
    if not peak - bg > significant:
        top = float(img.max())
        if top - bg > significant:
            raise outside(top)
        raise LightSphereError(f"{name}: no highlight on the sphere (brightest {peak:.4g} vs median {bg:.4g}, "
                               f"noise {noise:.3g})")
    lab, idx, energy, cx_, cy_ = blobs(peak)
    inside = np.hypot(cx_ - sphere.cx, cy_ - sphere.cy) <= sphere.r + 1.0
    if not inside.any():
        raise outside(peak)
    k = int(idx[inside][np.argmax(energy[inside])]) - 1
    blob = lab == k + 1
    region = ndimage.binary_dilation(blob, iterations=2) & near
    ww = wgt * region
    e = ww.sum()
    x, y = float((ww * xx).sum() / e), float((ww * yy).sum() / e)
    spread = float(np.sqrt((ww * ((xx - x) ** 2 + (yy - y) ** 2)).sum() / e))
    xa, ya = float(xx[blob].mean()), float(yy[blob].mean())
    on_energy = energy[inside]
    conf = float(energy[k] / on_energy.sum())
    n_blobs = int((on_energy >= 0.05 * energy[k]).sum())
    sat = int((clipped & blob).sum()) if clipped is not None else 0
    return x, y, (xa, ya), spread, conf, n_blobs, sat


def recover_lights(images: Sequence["str | Path | np.ndarray"], mask: "str | Path | np.ndarray | None" = None,
                   names: Sequence[str] | None = None, rel_threshold: float = 0.5) -> SphereLights:
    """Light directions from ``N`` photos of a mirror sphere, one light each.

    ``images``: file paths (read with OpenImageIO) or arrays ``(H, W)`` / ``(H, W, C)`` (integer
    arrays are taken as sRGB, float as linear), all the same size.  ``mask``: the sphere's mask
    (path or array, binary or anti-aliased), or ``None`` to find the sphere automatically (see
    :func:`sphere_auto`).  ``names``: names for the records and messages (default: file names,
    or ``image <i>``).  ``rel_threshold``: a highlight is the pixels above
    ``median + rel_threshold * (peak - median)`` on the sphere; its centroid is weighted by
    ``I - median`` over that blob grown by 2 px.

    Returns :class:`SphereLights`; raises :class:`LightSphereError` naming the image."""
    if len(images) == 0:
        raise LightSphereError("no images given")
    if names is None:
        names = [Path(i).name if isinstance(i, (str, Path)) else f"image {k}" for k, i in enumerate(images)]
    if len(names) != len(images):
        raise LightSphereError(f"{len(images)} images but {len(names)} names")
    grays = [_as_gray(i) for i in images]
    shapes = {g.shape for g, _ in grays}
    if len(shapes) != 1:
        raise LightSphereError(f"images have different sizes: {sorted(shapes)}")
    if mask is None:
        sphere = sphere_auto(np.stack([g for g, _ in grays]), what=f"{names[0]}..{names[-1]}")
    else:
        src = f"mask:{Path(mask).name}" if isinstance(mask, (str, Path)) else "mask"
        m = read_gray(mask, decode=False)[0] if isinstance(mask, (str, Path)) else np.asarray(mask)
        if m.shape[:2] != next(iter(shapes)):
            raise LightSphereError(f"{src}: mask is {m.shape[:2]}, images are {next(iter(shapes))}")
        sphere = sphere_from_mask(m, src)
    out = [_highlight(g, c, sphere, nm, rel_threshold) for (g, c), nm in zip(grays, names)]
    hl = np.array([[o[0], o[1]] for o in out])
    dirs = pixel_to_light(hl[:, 0], hl[:, 1], sphere)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    resid = np.array([_angle_deg(d, pixel_to_light(*o[2], sphere)) for d, o in zip(dirs, out)])
    dpp = np.array([max(_angle_deg(d, pixel_to_light(x + 1, y, sphere)), _angle_deg(d, pixel_to_light(x, y + 1, sphere)))
                    for d, (x, y) in zip(dirs, hl)])
    notes = []
    if (dirs[:, 2] <= 0).any():
        notes.append("some lights are at or below the horizon (z <= 0): light files refuse them")
    return SphereLights(list(names), dirs, hl, sphere, resid, dpp, np.array([o[4] for o in out]),
                        np.array([o[3] for o in out]), np.array([o[5] for o in out], int),
                        np.array([o[6] for o in out], int), notes)


def find_images(folder: str | Path, pattern: str | None = None) -> tuple[list[Path], list[Path]]:
    """``(images, masks)`` in ``folder``: files matching ``pattern`` (a glob; default: every
    PNG/JPEG/TIFF/EXR), those with 'mask' in their name apart, each list sorted naturally
    (``x.10`` after ``x.9``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"not a folder: {folder}")
    files = [p for p in folder.glob(pattern or "*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    imgs = sorted((p for p in files if "mask" not in p.name.lower()), key=_natural_key)
    masks = sorted((p for p in files if "mask" in p.name.lower()), key=_natural_key)
    return imgs, masks


def recover_from_folder(folder: str | Path, mask: "str | Path | np.ndarray | None" = None,
                        pattern: str | None = None) -> SphereLights:
    """:func:`recover_lights` over the images of ``folder`` (see :func:`find_images`).
    ``mask``: a path or array; ``None`` uses the folder's one image with 'mask' in its name
    (looked for among all image files, whatever ``pattern``) and otherwise finds the sphere
    automatically; ``"auto"`` always finds it automatically."""
    imgs, _ = find_images(folder, pattern)
    if not imgs:
        raise LightSphereError(f"{folder}: no images (PNG/JPEG/TIFF/EXR{', matching ' + pattern if pattern else ''})")
    if isinstance(mask, str) and mask == "auto":
        mask = None
    elif mask is None:
        masks = find_images(folder)[1]
        if len(masks) > 1:
            raise LightSphereError(f"{folder}: several mask images {[m.name for m in masks]}; pass one")
        mask = masks[0] if masks else None
    return recover_lights(imgs, mask)
