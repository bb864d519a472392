"""Device evaluation (supplementary Sec. 3): colour accuracy, sharpness, polarisation and
collimation.  Inputs are a capture set and a calibration (see :mod:`.pipeline`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from . import colourref as cr
from .ccm import apply_ccm, delta_e_patches
from .chart import ChartLayout
from .pipeline import Session, calibrated, light_kind, measure_patches


def merges_needed(cs, camera: str = "micro") -> int:
    """How many HDR merges a full device evaluation makes (the unit of its progress): the chart
    and patch captures (colour), the first dot grid (sharpness), the polarisation sweep and the
    white sheet under each LED (collimation) of ``camera``."""
    n = sum(g.target in ("patch", "chart") for g in cs.groups)
    n += min(1, len(cs.select(target="dot_grid")))
    n += sum(g.target == "polarization" and g.camera == camera for g in cs.groups)
    n += sum(g.target == "white_sheet" and g.camera == camera and g.light.startswith("led") for g in cs.groups)
    return n


# ---- colour ---------------------------------------------------------------------------------

def colour_accuracy(s: Session) -> dict[str, dict[str, dict[str, list[float]]]]:
    """CIEDE2000 per patch ``{camera: {light: {"before": [24], "after": [24]}}}``: before = white
    balance only, after = the camera's CCM for that light kind."""
    out: dict = {}
    for cam, per_light in measure_patches(s).items():
        for light, d in per_light.items():
            ccm = s.calib.get("ccm", {}).get(cam, {}).get(light_kind(light))
            m = np.eye(3) if ccm is None else np.asarray(ccm["matrix"])
            out.setdefault(cam, {})[light] = {"before": delta_e_patches(np.eye(3), d["rgb"]).tolist(),
                                              "after": delta_e_patches(m, d["rgb"]).tolist()}
    return out


# ---- sharpness -------------------------------------------------------------------------------

def detect_dots(image: np.ndarray, crop: int = 64) -> np.ndarray:
    """Centres ``(N, 2)`` image ``(x, y)`` of dark dots whose ``crop`` x ``crop`` window fits."""
    y = np.asarray(image, np.float64)
    y = y.mean(-1) if y.ndim == 3 else y
    thr = 0.5 * (np.quantile(y, 0.02) + np.quantile(y, 0.98))
    lab, n = ndimage.label(y < thr)
    if n == 0:
        return np.zeros((0, 2))
    weight = np.clip(thr - y, 0, None)
    cy_cx = np.asarray(ndimage.center_of_mass(weight, lab, range(1, n + 1)))
    xy = cy_cx[:, ::-1]
    h, w = y.shape
    half = crop // 2
    keep = (xy[:, 0] >= half) & (xy[:, 0] < w - half) & (xy[:, 1] >= half) & (xy[:, 1] < h - half)
    return xy[keep]


def dot_sharpness(crop: np.ndarray) -> float:
    """Sharpness of one dot crop: max |gradient| (second-order central differences) of the row
    and column mean projections, over that of the ideal binary dot with the crop's min/max."""
    c = np.asarray(crop, np.float64)
    lo, hi = float(c.min()), float(c.max())
    if hi - lo <= 0:
        return float("nan")
    ideal = np.where(c < 0.5 * (lo + hi), lo, hi)
    num = max(np.abs(np.gradient(c.mean(0))).max(), np.abs(np.gradient(c.mean(1))).max())
    den = max(np.abs(np.gradient(ideal.mean(0))).max(), np.abs(np.gradient(ideal.mean(1))).max())
    return float(num / den)


def sharpness_map(image: np.ndarray, crop: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (N, 2), sharpness (N,))`` for a dot-grid capture (luminance)."""
    y = np.asarray(image, np.float64)
    y = cr.luminance(y) if y.ndim == 3 else y
    xy = detect_dots(y, crop)
    half = crop // 2
    vals = [dot_sharpness(y[int(round(cy)) - half:int(round(cy)) + half, int(round(cx)) - half:int(round(cx)) + half])
            for cx, cy in xy]
    return xy, np.asarray(vals)


def ideal_dot_crop(sigma_px: float, phase: tuple[float, float] = (0.0, 0.0), pixel_um: float = 1.8,
                   crop: int = 64, supersample: int = 8) -> np.ndarray:
    """A dark dot of the 125 um grid (62.5 um diameter) at ``phase`` px from the crop centre,
    blurred by a Gaussian ``sigma_px`` and integrated over pixels: the model of a capture."""
    from .chart import DOT_DIAMETER_UM

    n = crop * supersample
    coords = (np.arange(n) + 0.5) / supersample - 0.5 - (crop - 1) / 2
    x, y = np.meshgrid(coords - phase[0], coords - phase[1])
    r = DOT_DIAMETER_UM / pixel_um / 2
    img = 1.0 - (x * x + y * y <= r * r)
    img = ndimage.gaussian_filter(img, sigma_px * supersample, mode="nearest") if sigma_px > 0 else img
    return img.reshape(crop, supersample, crop, supersample).mean((1, 3))


def blur_from_sharpness(value: float, phase: tuple[float, float] = (0.0, 0.0), pixel_um: float = 1.8,
                        crop: int = 64) -> float:
    """Invert the metric for one dot: the Gaussian blur sigma [px] whose ideal capture at the
    same sub-pixel phase has the measured sharpness (bisection; the metric falls with blur)."""
    lo, hi = 0.05, 12.0
    f = lambda sg: dot_sharpness(ideal_dot_crop(sg, phase, pixel_um, crop))  # noqa: E731
    if value >= f(lo):
        return lo
    if value <= f(hi):
        return hi
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) > value else (lo, mid)
    return 0.5 * (lo + hi)


def dot_phases(centres: np.ndarray, crop: int = 64) -> np.ndarray:
    """Sub-pixel offset of each dot centre from its crop's centre (the crops of
    :func:`sharpness_map` start at ``round(c) - crop/2``)."""
    c = np.asarray(centres, np.float64)
    return c - (np.round(c) - 0.5)


# ---- polarisation ----------------------------------------------------------------------------

@dataclass
class PolarizationResult:
    led: int
    angles_deg: np.ndarray
    intensity: np.ndarray
    max_deg: float
    min_deg: float
    theory_max_deg: float
    contrast: float

    @property
    def error_deg(self) -> float:
        """Signed max-angle error, wrapped to (-90, 90]."""
        return float((self.max_deg - self.theory_max_deg + 90.0) % 180.0 - 90.0)


def fit_malus(angles_deg: np.ndarray, intensity: np.ndarray) -> tuple[float, float, float]:
    """Least squares ``I = a + b cos 2x + c sin 2x`` -> ``(max angle [deg], mean, amplitude)``."""
    a = np.radians(np.asarray(angles_deg, np.float64))
    m = np.stack([np.ones_like(a), np.cos(2 * a), np.sin(2 * a)], -1)
    c0, c1, c2 = np.linalg.lstsq(m, np.asarray(intensity, np.float64), rcond=None)[0]
    return float(np.degrees(0.5 * math.atan2(c2, c1)) % 180.0), float(c0), float(math.hypot(c1, c2))


def polarization(s: Session, camera: str = "micro") -> list[PolarizationResult]:
    """Per LED: mean luminance against absolute analyser angle, fitted max/min angles and the
    theoretical max (the LED polariser axis projected on the image plane)."""
    from dualscale.geometry.dome import DomeGeometry

    dome = DomeGeometry.from_regmap()
    cam = s.cs.camera(camera)
    right, up, _ = (v.numpy() for v in cam.basis())
    out = []
    per_led: dict[int, list] = {}
    for g in s.cs.select(target="polarization", camera=camera):
        per_led.setdefault(int(g.light_id), []).append(g)
    for led, gs in sorted(per_led.items()):
        ang = np.array([g.analyzer_deg for g in gs])
        inten = np.array([float(cr.luminance(s.merged(g).radiance).mean()) for g in gs])
        mx, mean, amp = fit_malus(ang, inten)
        axis = dome.polarizer_axes[led].numpy()
        theory = math.degrees(math.atan2(axis @ up, axis @ right)) % 180.0
        order = np.argsort(ang)
        out.append(PolarizationResult(led, ang[order], inten[order], mx, (mx + 90.0) % 180.0, theory, amp / mean))
    return out


# ---- collimation -----------------------------------------------------------------------------

def collimation(s: Session, camera: str = "micro") -> dict[str, float]:
    """Std of the white sheet's normalised luminance (flat-fielded, P0 + P90) per LED."""
    out = {}
    for light, gs in s.by_light("white_sheet", camera).items():
        if not light.startswith("led"):
            continue
        y = cr.luminance(calibrated(s, camera, light, s.summed(gs)))
        out[light] = float(y.std() / y.mean())
    return out


def hemisphere_coords(lights: list[str]) -> dict[str, tuple[float, float]]:
    """``(theta_deg, phi_deg)`` of each LED key; the diffuse group sits at the centre."""
    from dualscale.geometry.dome import DomeGeometry

    tp = DomeGeometry.from_regmap().led_theta_phi_deg().numpy()
    out = {}
    for k in lights:
        if k.startswith("led"):
            out[k] = (float(tp[int(k[3:]), 0]), float(tp[int(k[3:]), 1]))
        elif k == "diffuse":
            out[k] = (0.0, 0.0)
    return out


__all__ = ["apply_ccm", "ChartLayout", "colour_accuracy", "sharpness_map", "polarization", "collimation"]
