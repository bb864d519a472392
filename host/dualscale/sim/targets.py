"""Synthetic calibration captures on the virtual dome, with known truth and injected defects.

Every capture is physically composed: per-pixel geometry factors come from the dome renderer
(:func:`dualscale.sim.render.render`, a grey surface with albedo 1 and 0, so the diffuse part
``G_d`` and the white specular part ``G_s`` are separated), and colour comes from spectral
reflectances x the light's spectrum x the camera's spectral sensitivities (colour-science), never
from RGB: ``raw(x) = sum_k [label(x) = k] raw_k G_d(x) + raw_white G_s(x)``.  This is exact
because the renderer is linear in albedo and the specular is white.  The calibration targets
(white sheet, markers, ColorChecker) are matte Lambertian, ``G_d = l_z / pi`` and ``G_s = 0``,
as the calibration assumes (:attr:`SynthConfig.target_brdf`; ``"burley"`` for the earlier
Burley + specular targets).

Defects (all with known truth): per-LED irradiance gains, a per-LED linear irradiance ramp over
the micro field (collimation), analyser misalignment, spatially varying Gaussian blur of the
micro optics, vignetting, dark signal (bias + dark current), shot/read noise, 12-bit
quantisation and saturation, and exposure jitter of the mid-range (DSLR) diffuse captures.

A sensor that clips below nominal full scale is ``SynthConfig(white_level=0.95)`` (every camera;
one value or ``(r, g, b)``); ``declare_white_level`` says whether the capture set declares it
(else the calibration has to measure it).  The virtual rig's capture tool meters and plans its
brackets against the sensor's white level, as a real one does against the declared one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from dualscale.bsdf import MaterialMaps
from dualscale.geometry.cameras import Camera, micro_camera, mid_camera, polar_camera
from dualscale.geometry.dome import DomeGeometry
from dualscale.sim.render import Analyzer, LightState, render
from dualscale.sim.sensor import SensorModel, capture, vignetting_map

from dualscale.calib import colourref as cr
from dualscale.formats.captures import CaptureWriter, light_key
from dualscale.calib.chart import DOT_DIAMETER_UM, DOT_PITCH_UM, ChartLayout
from dualscale.calib.hdr import WHITE_MARGIN, meter, plan_brackets
from dualscale.calib.radiometric import micro_footprint_mask
from dualscale.errors import InputError
from dualscale.progress import Progress, Tracker, tracker

MICRO_FIELD_MM = 0.9216  # 512 px x 1.8 um
SHEET_R = (0.55, 0.60)  # white diffuser reflectance at 400 / 700 nm
SHEET_T = (0.37, 0.43)  # and transmittance (the spec's 38/40/42 % in R, G, B)
HOLDER_R = 0.05
CHART_BODY_R = 0.03
DOT_R, DOT_BG_R = 0.04, 0.85


@dataclass(frozen=True)
class Defects:
    """Injected defects (see module doc); ``blur_sigma_um`` is (centre, corner) PSF sigma."""

    led_gain_sigma: float = 0.05
    collimation_max: float = 0.08
    analyzer_offset_deg: float = 0.0
    blur_sigma_um: tuple[float, float] = (2.0, 8.0)
    vignetting: float = 0.25
    diffuse_jitter: float = 0.05
    seed: int = 0


TARGET_BRDFS = ("lambert", "burley")
"""How the calibration targets reflect (:attr:`SynthConfig.target_brdf`)."""


@dataclass(frozen=True)
class SynthConfig:
    """Sizes and the rig's optics; the micro camera keeps the 0.92 mm footprint, binned.

    ``target_brdf``: the reflection of the calibration targets (white sheet, holder markers,
    ColorChecker): ``"lambert"`` (default) is a matte Lambertian reflector, ``rho l_z / pi``
    per unit LED irradiance, with no specular -- the sheet the calibration assumes
    (:mod:`dualscale.calib.apply`, step ``irradiance``; docs/CALIBRATION.md); ``"burley"`` is
    Burley's diffuse of roughness ``roughness`` with a white specular lobe (what the virtual rig
    had before: its sheet is 1.107 x Lambert at l_z 0.31 and its specular adds 3-6 % to ``r_c``,
    so a calibrated capture comes out 0.85 x the truth on the lowest ring), to study what a
    non-Lambertian sheet costs.  The dot grid and the polarisation target keep their own models."""

    micro_px: int = 16
    other_px: int = 48
    led_step: int = 8
    dot_px: int = 384
    pol_step_deg: float = 10.0
    roughness: float = 0.9
    pol_roughness: float = 0.5
    sensitivities: tuple[tuple[str, str], ...] = (("micro", "Nikon 5100 (NPL)"), ("mid", "Sigma SDMerill (NPL)"),
                                                  ("polar0", "Nikon 5100 (NPL)"), ("polar1", "Nikon 5100 (NPL)"))
    illuminants: tuple[tuple[str, str], ...] = (("led", "LED-B3"), ("diffuse", "LED-B4"), ("backlight", "LED-B3"))
    dark_bias: float = 0.004
    dark_rate: float = 0.01
    rig_id: str = "virtual-dome-0"
    cameras: tuple[str, ...] = ("micro", "mid", "polar0", "polar1")
    white_level: float | tuple[float, float, float] = 1.0
    white_level_spread: float = 0.0
    declare_white_level: bool = True
    target_brdf: str = "lambert"

    def __post_init__(self) -> None:
        if self.target_brdf not in TARGET_BRDFS:
            raise InputError(f"unknown target_brdf {self.target_brdf!r}; choose from {list(TARGET_BRDFS)}")

    def sensor(self) -> SensorModel:
        """The cameras' sensor model (:data:`SENSOR` with this white level)."""
        return replace(SENSOR, white_level=self.white_level, white_level_spread=self.white_level_spread)

    def saturation(self) -> float:
        """The raw level the capture tool meters and plans against: the lowest channel's white
        level less the merge's margin (:data:`dualscale.calib.hdr.WHITE_MARGIN`)."""
        return float(np.min(self.white_level)) * (1.0 - WHITE_MARGIN)

    def sens(self, cam: str) -> str:
        return dict(self.sensitivities)[cam]

    def illum(self, kind: str) -> str:
        return dict(self.illuminants)[kind]


SENSOR = SensorModel(shot_noise=True, read_noise=True, saturate=True, quantize=True)


def rig_cameras(cfg: SynthConfig) -> dict[str, Camera]:
    micro = micro_camera(cfg.micro_px, pixel_um=MICRO_FIELD_MM * 1000 / cfg.micro_px)
    cams = {"micro": micro, "mid": mid_camera(cfg.other_px), "polar0": polar_camera(0, cfg.other_px),
            "polar1": polar_camera(1, cfg.other_px)}
    return {k: cams[k] for k in cfg.cameras}


def lights(cfg: SynthConfig, dome: DomeGeometry) -> list[tuple[str, int | None]]:
    """The LEDs used (every ``led_step``-th), the diffuse group and back light 0."""
    return [("led", i) for i in range(0, dome.n_leds, cfg.led_step)] + [("diffuse", None), ("backlight", 0)]


def _grey_maps(albedo: float, roughness: float) -> MaterialMaps:
    one = torch.ones(1, 1, 1, dtype=torch.float64)
    return MaterialMaps(albedo=one.expand(1, 1, 3).clone() * albedo, roughness=one * roughness)


def geometry_factors(camera: Camera, kind: str, light_id: int | None, analyzer: Analyzer | None,
                     roughness: float, dome: DomeGeometry, diffuse: str = "burley") -> tuple[np.ndarray, np.ndarray]:
    """``(G_d, G_s)`` ``(H, W)``: radiance of a grey surface per unit diffuse albedo, and of its
    white specular lobe, under one LED (unit irradiance) or the diffuse group (unit radiance).
    ``diffuse``: the diffuse lobe (:data:`dualscale.bsdf.maps.DIFFUSE_MODELS`); ``"lambert"``
    gives ``G_d = l_z / pi`` (LED) and ``sum_k w_k l_kz / pi`` (diffuse group) exactly."""
    if kind == "backlight":
        raise ValueError("back lights have no reflection factors")
    light = LightState.led(light_id) if kind == "led" else LightState.diffuse_group()
    cam = camera
    if camera.kind == "orthographic":  # every pixel sees the same: render one
        cam = replace(camera, width=1, height=1, field_mm=(camera.field_mm[0] / camera.width,
                                                            camera.field_mm[1] / camera.height))
    comps = replace(_grey_maps(1.0, roughness).components(), diffuse=diffuse)
    kw = dict(dome=dome, analyzer=analyzer, texel_mm=1.0, light_chunk=None, comps=comps)
    r1 = render(_grey_maps(1.0, roughness), cam, light, **kw)[..., 0].numpy()
    r0 = render(_grey_maps(0.0, roughness), cam, light, **kw)[..., 0].numpy()
    shape = (camera.height, camera.width)
    return np.broadcast_to(r1 - r0, shape).copy(), np.broadcast_to(r0, shape).copy()


@dataclass
class Scene:
    """Labels ``(H, W)`` into ``reflect`` (raw colours are computed per camera/illuminant)."""

    labels: np.ndarray
    reflect: list[Any]
    transmit: list[Any]


def _points(camera: Camera) -> np.ndarray:
    return camera.pixel_geometry()[0].numpy()


def scene_for(target: str, camera: Camera, layout: ChartLayout, patch: int | None = None) -> Scene:
    import colour

    sheet_r, sheet_t = cr.flat_spectrum(*SHEET_R), cr.flat_spectrum(*SHEET_T)
    zero = cr.flat_spectrum(0.0, 0.0)
    if target == "white_sheet":
        return Scene(np.zeros((camera.height, camera.width), int), [sheet_r], [sheet_t])
    if target == "patch":
        sd = list(colour.SDS_COLOURCHECKERS[cr.CHECKER_SPECTRA].values())[int(patch)]
        return Scene(np.zeros((camera.height, camera.width), int), [sd], [zero])
    if target == "chart":
        p = _points(camera)
        lab = layout.patch_of(p[..., 0], p[..., 1])
        labels = np.where(lab >= 0, lab, np.where(lab == -1, 24, 25))
        marker = np.zeros(labels.shape, bool)
        for cx, cy in marker_centres_mm():
            marker |= (np.abs(p[..., 0] - cx) < 3.5) & (np.abs(p[..., 1] - cy) < 3.5)
        labels = np.where(marker, 26, labels)
        sds = list(colour.SDS_COLOURCHECKERS[cr.CHECKER_SPECTRA].values())
        return Scene(labels, sds + [cr.flat_spectrum(CHART_BODY_R, CHART_BODY_R), cr.flat_spectrum(HOLDER_R, HOLDER_R),
                                    sheet_r], [zero] * 26 + [sheet_t])
    raise ValueError(f"no scene for target {target!r}")


def marker_centres_mm() -> list[tuple[float, float]]:
    """The two white markers on the holder frame (mm in the sample plane)."""
    return [(-42.0, 42.0), (42.0, -42.0)]


def marker_boxes(camera: Camera) -> list[list[int]]:
    """Pixel boxes ``[row0, row1, col0, col1]`` inside each marker, as seen by ``camera``."""
    p = _points(camera)
    out = []
    for cx, cy in marker_centres_mm():
        m = (np.abs(p[..., 0] - cx) < 2.5) & (np.abs(p[..., 1] - cy) < 2.5)
        rows, cols = np.nonzero(m)
        if len(rows) == 0:
            raise ValueError(f"marker at {(cx, cy)} mm is not visible to {camera.name}")
        out.append([int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1])
    return out


def collimation_ramp(camera: Camera, led_id: int, defects: Defects) -> np.ndarray:
    """Per-pixel irradiance multiplier of LED ``led_id`` (1 +- its ramp over the micro field)."""
    if defects.collimation_max <= 0:
        return np.ones((camera.height, camera.width))
    rng = np.random.default_rng([defects.seed, 7, led_id])
    amp = defects.collimation_max * rng.uniform(0.1, 1.0)
    ang = rng.uniform(0, 2 * math.pi)
    p = _points(camera)
    u = (p[..., 0] * math.cos(ang) + p[..., 1] * math.sin(ang)) / (MICRO_FIELD_MM / 2)
    return 1.0 + amp * np.clip(u, -1.0, 1.0)


def led_gains(n: int, defects: Defects) -> np.ndarray:
    if defects.led_gain_sigma <= 0:
        return np.ones(n)
    rng = np.random.default_rng([defects.seed, 3])
    return np.clip(1.0 + defects.led_gain_sigma * rng.standard_normal(n), 0.5, 1.5)


def true_radiance(target: str, camera: Camera, kind: str, light_id: int | None, cfg: SynthConfig, defects: Defects,
                  dome: DomeGeometry, layout: ChartLayout, patch: int | None = None, analyzer: Analyzer | None = None,
                  roughness: float | None = None) -> np.ndarray:
    """Noise-free camera-raw radiance ``(H, W, 3)`` with the light-side defects (gain, ramp)."""
    scene = scene_for(target, camera, layout, patch)
    sens, ill = cfg.sens(camera.name), cfg.illum(kind)
    if kind == "backlight":
        w_d = 0.5 if analyzer is not None else 1.0
        cols = cr.camera_raw(scene.transmit, sens, ill) * w_d
        return cols[scene.labels]
    cols = cr.camera_raw(scene.reflect, sens, ill)
    rough = cfg.roughness if roughness is None else roughness
    if cfg.target_brdf == "lambert":  # matte Lambertian targets: the calibration's convention
        g_d, _ = geometry_factors(camera, kind, light_id, analyzer, rough, dome, diffuse="lambert")
        rad = cols[scene.labels] * g_d[..., None]
    else:
        white = cr.camera_raw([cr.flat_spectrum(1.0, 1.0)], sens, ill)[0]
        g_d, g_s = geometry_factors(camera, kind, light_id, analyzer, rough, dome)
        rad = cols[scene.labels] * g_d[..., None] + white * g_s[..., None]
    if kind == "led":
        rad = rad * led_gains(dome.n_leds, defects)[light_id] * collimation_ramp(camera, light_id, defects)[..., None]
    return rad


class Exposer:
    """The sensor side: vignetting, dark signal (fixed-pattern bias + dark current), noise,
    saturation, quantisation.  ``__call__(radiance, t)`` returns normalised DN.  ``noise=False``
    leaves out shot and read noise (everything else, the dark fixed pattern included, is the
    same), for checks that must be exact."""

    def __init__(self, camera: Camera, cfg: SynthConfig, defects: Defects, seed: int, noise: bool = True) -> None:
        self.camera, self.cfg, self.defects, self.seed, self.noise = camera, cfg, defects, seed, noise
        self.vig = vignetting_map(camera, defects.vignetting).numpy() if defects.vignetting > 0 else 1.0
        rng = np.random.default_rng([defects.seed, 11, seed])
        self.bias = cfg.dark_bias * (1.0 + 0.1 * rng.standard_normal((camera.height, camera.width, 1)))
        self.count = 0

    def __call__(self, radiance: np.ndarray, exposure_s: float, shot: object = None) -> np.ndarray:
        """``shot``: the shot's identity (any value with a stable ``repr``, e.g. the scene, the
        lights, the analyser and the exposure): its noise is drawn from a seed made of it, so
        the same shot taken again -- a capture resumed after a kill -- has the same noise.
        ``None``: the seed counts this exposer's calls (a fresh draw per call)."""
        s = self.cfg.sensor()
        if not self.noise:  # the deterministic sensor: dark signal, saturation and 12 bits only
            s = replace(s, shot_noise=False, read_noise=False)
        dark_dn = self.bias + self.cfg.dark_rate * exposure_s
        x = radiance * self.vig + dark_dn * s.full_well_e / (exposure_s * s.gain_e)
        self.count += 1
        if shot is None:
            seed = self.seed * 100003 + self.count
        else:
            import hashlib

            key = repr((self.defects.seed, self.seed, self.camera.name, shot)).encode()
            seed = int.from_bytes(hashlib.blake2b(key, digest_size=7).digest(), "little")
        out = capture(torch.from_numpy(np.ascontiguousarray(x)), self.camera, replace(s, exposure_s=exposure_s),
                      seed=seed)
        return out.numpy()


def rig_exposer(camera: Camera, cfg: SynthConfig = SynthConfig(), defects: Defects = Defects(),
                noise: bool = True) -> Exposer:
    """The sensor side of the virtual rig's camera ``camera.name``: one per camera, as in
    :func:`write_session` (same seed, hence the same dark fixed pattern at the same size)."""
    return Exposer(camera, cfg, defects, cfg.cameras.index(camera.name) + 1, noise=noise)


def raw_signal(radiance: np.ndarray, camera: Camera, kind: str, light_id: int | None,
               cfg: SynthConfig = SynthConfig(), defects: Defects = Defects()) -> np.ndarray:
    """The raw camera signal ``(H, W, 3)`` float64 of ``camera`` (the input of an :class:`Exposer`)
    for one light's rendered radiance: what reaches the sensor before vignetting and the dark signal.

    ``radiance``: linear Rec.709 relative radiance ``(H, W, 3)`` from :func:`dualscale.sim.render.render`
    for one light (``kind`` ``led`` with ``light_id``, ``diffuse`` or ``backlight``).  Its colour is
    read as Smits (1999) spectra under the rig's illuminant for that light (``cfg.illum(kind)``) and
    integrated against the camera's sensitivities (:func:`dualscale.sim.sensor.spectral_matrix`,
    white -> raw green 1, like :func:`dualscale.calib.colourref.camera_raw`); an LED adds its
    irradiance gain (:func:`led_gains`) and collimation ramp (:func:`collimation_ramp`).  Linear in
    ``radiance``, so the signals of several lights add.  Used by :func:`capture_material`
    (``synth --realistic``) and the simulated camera (:mod:`dualscale.sim.camera`)."""
    from dualscale.sim.sensor import spectral_matrix

    m = spectral_matrix(cfg.sens(camera.name), cfg.illum(kind))
    raw = np.asarray(radiance, np.float64) @ m.T
    if kind == "led":
        n = DomeGeometry.from_regmap().n_leds
        raw = raw * led_gains(n, defects)[light_id] * collimation_ramp(camera, light_id, defects)[..., None]
    return raw


def capture_material(radiance: np.ndarray, exposer: Exposer, kind: str, light_id: int | None,
                     target: float = 0.8) -> tuple[np.ndarray, float]:
    """The virtual rig capturing a rendered sample the way it captures its calibration targets,
    so that a calibration from :func:`write_session` applies to it: ``(normalised DN (H, W, 3),
    exposure [s])``.

    ``radiance``: linear Rec.709 relative radiance ``(H, W, 3)`` from :func:`dualscale.sim.render.render`
    for one light (``kind`` ``led`` with ``light_id``, ``diffuse`` or ``backlight``), made the raw
    camera signal by :func:`raw_signal` (spectra, LED gain and collimation ramp); then ``exposer``
    (:func:`rig_exposer`: vignetting, dark signal, noise, 12 bits) takes one exposure, metered so
    that the 99.9th percentile of the signal lands at ``target`` of the sensor's white level (full
    scale unless ``SynthConfig.white_level`` is lower) (the rig's auto-exposure; a black image,
    e.g. an opaque sample's back light, meters to the longest exposure, 1 s).
    """
    cfg = exposer.cfg
    raw = raw_signal(radiance, exposer.camera, kind, light_id, cfg, exposer.defects)
    if float(raw.max()) <= 0:
        return exposer(raw, 1.0), 1.0
    shot, t = meter(lambda t: exposer(raw, t), saturation=cfg.saturation())
    dark = float(exposer.bias.mean()) + cfg.dark_rate * t
    peak = max(float(np.percentile(shot - dark, 99.9)), 1e-6)
    t = float(f"{t * target * float(np.min(cfg.white_level)) / peak:.3g}")
    return exposer(raw, t), t


def rig_record(cfg: SynthConfig = SynthConfig()) -> dict[str, str]:
    """The ``rig`` record of datasets captured by the virtual rig (checked against calibrations)."""
    return {"id": cfg.rig_id, "layout": DomeGeometry.from_regmap().signature()}


def bracket(exposer: Exposer, radiance: np.ndarray, dark_pixels_ignore: float = 0.0) -> tuple[list[float], list[np.ndarray]]:
    """Meter, plan brackets from the metering shot and capture them."""
    cfg = exposer.cfg
    mshot, t0 = meter(lambda t: exposer(radiance, t), saturation=cfg.saturation())
    dark = exposer.bias.mean() + cfg.dark_rate * t0
    times = plan_brackets(np.clip(mshot - dark, 0, None), t0, ignore_fraction=dark_pixels_ignore,
                          dark=(float(exposer.bias.max()), cfg.dark_rate), saturation=cfg.saturation(),
                          high=0.8 * float(np.min(cfg.white_level)))
    return times, [exposer(radiance, t) for t in times]


# ---- dot grid -------------------------------------------------------------------------------

def dot_grid_truth(size: int, pixel_um: float, defects: Defects) -> tuple[np.ndarray, Any]:
    """Dot centres ``(N, 2)`` as image ``(x, y)`` px, and ``sigma_px(x, y)`` of the injected blur."""
    pitch = DOT_PITCH_UM / pixel_um
    c = (size - 1) / 2
    k = np.arange(-int(c // pitch) - 1, int(c // pitch) + 2)
    gx, gy = np.meshgrid(c + k * pitch, c + k * pitch)
    pts = np.stack([gx.ravel(), gy.ravel()], -1)
    pts = pts[(pts >= 0).all(1) & (pts <= size - 1).all(1)]
    s0, s1 = (s / pixel_um for s in defects.blur_sigma_um)
    def sigma_px(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return s0 + (s1 - s0) * np.clip(((x - c) ** 2 + (y - c) ** 2) / (c * c), 0.0, 1.0)

    return pts, sigma_px


def dot_albedo(size: int, pixel_um: float, sigma_px: Any = None, supersample: int = 4) -> np.ndarray:
    """Reflectance weight of the dots ``(H, W)`` in [0, 1] (1 = dot), box-integrated over each
    pixel and blurred by a spatially varying Gaussian ``sigma_px(x, y)`` [px]."""
    n = size * supersample
    c = (size - 1) / 2
    coords = (np.arange(n) + 0.5) / supersample - 0.5
    x, y = np.meshgrid(coords, coords)
    pitch = DOT_PITCH_UM / pixel_um
    r = DOT_DIAMETER_UM / pixel_um / 2
    dx = (x - c) - pitch * np.round((x - c) / pitch)
    dy = (y - c) - pitch * np.round((y - c) / pitch)
    dots = (dx * dx + dy * dy <= r * r).astype(np.float64)
    if sigma_px is None:
        return dots.reshape(size, supersample, size, supersample).mean((1, 3))
    sig = sigma_px(x, y) * supersample
    levels = np.linspace(sig.min(), sig.max(), 9)
    stack = np.stack([gaussian_filter(dots, s, mode="nearest") for s in levels])
    pos = np.interp(sig, levels, np.arange(len(levels)))
    lo = np.floor(pos).astype(int).clip(0, len(levels) - 2)
    f = pos - lo
    img = np.take_along_axis(stack, lo[None], 0)[0] * (1 - f) + np.take_along_axis(stack, lo[None] + 1, 0)[0] * f
    return img.reshape(size, supersample, size, supersample).mean((1, 3))


# ---- the whole synthetic session ---------------------------------------------------------------

@dataclass
class Truth:
    """What the synthetic session injected (for tests and the report)."""

    led_gains: dict[int, float] = field(default_factory=dict)
    white_sheet: dict[tuple[str, str], list[float]] = field(default_factory=dict)
    collimation_std: dict[int, float] = field(default_factory=dict)
    analyzer_offset_deg: float = 0.0
    dot_centres: list[list[float]] = field(default_factory=list)
    dot_sigma_px: list[float] = field(default_factory=list)
    dot_pixel_um: float = 1.8

    def to_json(self) -> dict[str, Any]:
        return {"led_gains": {str(k): v for k, v in self.led_gains.items()},
                "white_sheet": {f"{c}/{l}": v for (c, l), v in self.white_sheet.items()},
                "collimation_std": {str(k): v for k, v in self.collimation_std.items()},
                "analyzer_offset_deg": self.analyzer_offset_deg, "dot_centres": self.dot_centres,
                "dot_sigma_px": self.dot_sigma_px, "dot_pixel_um": self.dot_pixel_um}


PARTS = ("white_sheet", "chart", "dot_grid", "polarization")
"""The parts of a calibration session :func:`write_session` can write."""


def write_session(root: str | Path, cfg: SynthConfig = SynthConfig(), defects: Defects = Defects(),
                  parts: tuple[str, ...] = PARTS, progress: Progress = None) -> Truth:
    """Write a complete synthetic calibration session (``captures.json`` + EXRs) and return the
    truth.  Parts: white sheet (all cameras, lights; micro P0 and P90), ColorChecker (micro:
    one capture per patch, P0 + P90; others: the whole chart), dot grid, polarisation sweep.
    ``progress`` (:mod:`dualscale.progress`): one unit per camera and light, the dot grid, and
    each LED of the polarisation sweep."""
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise InputError(f"unknown session parts {unknown}; choose from {list(PARTS)}")
    if cfg.led_step < 1:
        raise InputError(f"led_step must be at least 1, got {cfg.led_step}")
    dome = DomeGeometry.from_regmap()
    layout = ChartLayout()
    cams = rig_cameras(cfg)
    n_leds = sum(k == "led" for k, _ in lights(cfg, dome))
    total = len(cams) * len(lights(cfg, dome)) + ("dot_grid" in parts) \
        + (n_leds if "polarization" in parts and "micro" in cams else 0)
    with tracker(progress, total, "synth-targets", "step") as bar:
        return _write_session(Path(root), cfg, defects, parts, dome, layout, cams, bar)


def _write_session(root: Path, cfg: SynthConfig, defects: Defects, parts: tuple[str, ...], dome: DomeGeometry,
                   layout: ChartLayout, cams: dict[str, Camera], bar: Tracker) -> Truth:
    w = CaptureWriter(root, rig={"id": cfg.rig_id, "layout": dome.signature()})
    truth = Truth(analyzer_offset_deg=defects.analyzer_offset_deg)
    gains = led_gains(dome.n_leds, defects)
    seed = 0
    for name, cam in cams.items():
        w.add_camera(cam, cfg.sens(name), white_level=cfg.white_level if cfg.declare_white_level else None)
        if name == "mid":
            w.markers[name] = marker_boxes(cam)
        seed += 1
        ex = Exposer(cam, cfg, defects, seed)
        ts = [1e-3, 1e-1, 1.0]
        w.add("dark", cam, "off", None, ts, [ex(np.zeros((cam.height, cam.width, 3)), t) for t in ts])
        for kind, lid in lights(cfg, dome):
            if kind == "led":
                truth.led_gains[lid] = float(gains[lid])
            pols: list[float | None] = [0.0, 90.0] if name == "micro" else [None]
            jitter = 1.0
            if name == "mid" and kind == "diffuse":
                jitter = 1.0 + defects.diffuse_jitter * np.random.default_rng([defects.seed, 13]).standard_normal()
            if "white_sheet" in parts:
                tot = 0.0
                for a in pols:
                    an = None if a is None else Analyzer(a, relative=True)
                    rad = true_radiance("white_sheet", cam, kind, lid, cfg, defects, dome, layout, analyzer=an)
                    tot = tot + rad
                    t, imgs = bracket(ex, rad * jitter)
                    w.add("white_sheet", cam, kind, lid, t, imgs, analyzer_deg=a, analyzer_relative=a is not None)
                region = None if name == "micro" else micro_footprint_mask(cam, cams.get("micro", rig_cameras(SynthConfig())["micro"]))
                truth.white_sheet[(name, light_key(kind, lid))] = (tot.reshape(-1, 3).mean(0) if region is None
                                                                   else tot[region].mean(0)).tolist()
                if name == "micro" and kind == "led":
                    ramp = collimation_ramp(cam, lid, defects)
                    truth.collimation_std[lid] = float(ramp.std() / ramp.mean())
            if "chart" in parts and kind != "backlight":
                if name == "micro":
                    for k in range(cr.N_PATCHES):
                        for a in pols:
                            an = Analyzer(a, relative=True)
                            rad = true_radiance("patch", cam, kind, lid, cfg, defects, dome, layout, patch=k, analyzer=an)
                            t, imgs = bracket(ex, rad)
                            w.add("patch", cam, kind, lid, t, imgs, patch=k, analyzer_deg=a, analyzer_relative=True)
                else:
                    rad = true_radiance("chart", cam, kind, lid, cfg, defects, dome, layout)
                    t, imgs = bracket(ex, rad * jitter, dark_pixels_ignore=0.0)
                    w.add("chart", cam, kind, lid, t, imgs)
            bar.update(what=f"{name} {light_key(kind, lid)}")
        if name != "mid":
            w.chart.setdefault("corners", {})[name] = chart_corners(cam, layout).tolist()
    w.chart["layout"] = {"rows": layout.rows, "cols": layout.cols, "pitch_mm": layout.pitch_mm,
                         "patch_mm": layout.patch_mm}
    if "dot_grid" in parts:
        _dot_grid(w, cfg, defects, dome, truth)
        bar.update(what="dot grid")
    if "polarization" in parts and "micro" in cams:
        _polarization(w, cams["micro"], cfg, defects, dome, bar)
    w.extra["truth"] = truth.to_json()
    w.extra["synthetic"] = {"config": repr(cfg), "defects": repr(defects)}
    w.close()
    return truth


def chart_corners(camera: Camera, layout: ChartLayout) -> np.ndarray:
    """Image ``(x, y)`` of the chart's swatch-area corners (TL, TR, BR, BL) through the camera
    model: the 'corners given by hand' of a known holder position."""
    w, h = layout.size_mm
    pts = np.array([[-w / 2, h / 2, 0], [w / 2, h / 2, 0], [w / 2, -h / 2, 0], [-w / 2, -h / 2, 0]])
    right, up, fwd = (v.numpy() for v in camera.basis())
    c = np.asarray(camera.position_mm)
    d = pts - c
    depth = d @ fwd
    dist = np.linalg.norm(c)
    u = (d @ right) / depth * dist / camera.field_mm[0]
    v = (d @ up) / depth * dist / camera.field_mm[1]
    return np.stack([(u + 0.5) * camera.width - 0.5, (0.5 - v) * camera.height - 0.5], -1)


def _dot_grid(w: CaptureWriter, cfg: SynthConfig, defects: Defects, dome: DomeGeometry, truth: Truth) -> None:
    cam = micro_camera(cfg.dot_px, 1.8)
    cam = replace(cam, name="micro_dots")
    w.add_camera(cam, cfg.sens("micro"))
    pts, sig = dot_grid_truth(cfg.dot_px, 1.8, defects)
    weight = dot_albedo(cfg.dot_px, 1.8, sig)
    sens, ill = cfg.sens("micro"), cfg.illum("diffuse")
    cols = cr.camera_raw([cr.flat_spectrum(DOT_BG_R, DOT_BG_R), cr.flat_spectrum(DOT_R, DOT_R)], sens, ill)
    white = cr.camera_raw([cr.flat_spectrum(1.0, 1.0)], sens, ill)[0]
    g_d, g_s = geometry_factors(cam, "diffuse", None, None, cfg.roughness, dome)
    refl = cols[0] * (1 - weight[..., None]) + cols[1] * weight[..., None]
    rad = refl * g_d[..., None] + white * g_s[..., None]
    ex = Exposer(cam, cfg, replace(defects, vignetting=0.0), 99)
    t, imgs = bracket(ex, rad)
    w.add("dot_grid", cam, "diffuse", None, t, imgs)
    ts = [1e-3, 1e-1, 1.0]
    w.add("dark", cam, "off", None, ts, [ex(np.zeros((cam.height, cam.width, 3)), t) for t in ts])
    truth.dot_centres = pts.tolist()
    truth.dot_sigma_px = sig(pts[:, 0], pts[:, 1]).tolist()


def _polarization(w: CaptureWriter, cam: Camera, cfg: SynthConfig, defects: Defects, dome: DomeGeometry,
                  bar: Tracker) -> None:
    """Absolute analyser sweep per LED on a glossy dark target; the analyser's physical axis is
    off by ``defects.analyzer_offset_deg`` from the recorded angle."""
    ex = Exposer(cam, cfg, defects, 77)
    angles = np.arange(0.0, 180.0, cfg.pol_step_deg)
    sens, ill = cfg.sens("micro"), cfg.illum("led")
    col = cr.camera_raw([cr.flat_spectrum(0.05, 0.05)], sens, ill)[0]
    white = cr.camera_raw([cr.flat_spectrum(1.0, 1.0)], sens, ill)[0]
    for kind, lid in lights(cfg, dome):
        if kind != "led":
            continue
        rads = []
        for a in angles:
            g_d, g_s = geometry_factors(cam, "led", lid, Analyzer(float(a) + defects.analyzer_offset_deg), cfg.pol_roughness, dome)
            rads.append(col * g_d[..., None] + white * g_s[..., None])
        # one metered exposure for the whole sweep, so intensities compare across angles
        brightest = max(rads, key=lambda r: float(r.max()))
        mshot, t0 = meter(lambda t: ex(brightest, t), saturation=cfg.saturation())
        t = 0.8 * float(np.min(cfg.white_level)) * t0 / max(float(mshot.max()), 1e-6)
        for a, rad in zip(angles, rads):
            w.add("polarization", cam, "led", lid, [t], [ex(rad, t)], analyzer_deg=float(a), analyzer_relative=False)
        bar.update(what=f"polarisation led{lid}")
