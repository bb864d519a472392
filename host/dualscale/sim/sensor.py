"""Camera sensor realism, each effect switchable: spectral response, vignetting, shot and read
noise, saturation and quantisation.

Spectral response (through colour-science): a linear-RGB channel value ``c_k`` is read as the
weight of a basis reflectance spectrum ``S_k`` (Smits 1999 spectra of the RGB primaries), lit
by an illuminant ``E``.  The camera's raw response is then ``raw = M rgb`` with
``M[c, k] = sum_lambda S_k E R_c``; because everything the renderer outputs is linear in the
channel values this is exact under that spectral interpretation.  ``M`` is scaled so that a
white reflector gives raw green = 1.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dualscale.geometry.cameras import Camera


@functools.lru_cache(maxsize=8)
def spectral_matrix(camera: str = "Nikon 5100 (NPL)", illuminant: str = "D65") -> np.ndarray:
    """3x3 matrix from linear RGB (Rec.709 primaries) to the named camera's raw RGB."""
    import colour

    if camera not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise ValueError(f"unknown camera sensitivities {camera!r}; known: {sorted(colour.MSDS_CAMERA_SENSITIVITIES)}")
    sens = colour.MSDS_CAMERA_SENSITIVITIES[camera]
    shape = sens.shape
    ill = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
    basis = []
    for rgb in np.eye(3):
        sd = colour.recovery.RGB_to_sd_Smits1999(colour.XYZ_to_RGB(
            colour.sRGB_to_XYZ(rgb, apply_cctf_decoding=False), "sRGB", apply_cctf_encoding=False))
        with warnings.catch_warnings():
            # Smits' basis is tabulated on non-uniform wavelengths; aligning it to the camera's
            # grid interpolates, which is what is wanted (colour warns "not uniform" each time)
            warnings.filterwarnings("ignore", ".*spectral distribution is not uniform.*",
                                    colour.utilities.ColourRuntimeWarning)
            basis.append(sd.copy().align(shape).values)
    s = np.stack(basis, 0)  # (3 basis, n_lambda)
    r = sens.values.T  # (3 channels, n_lambda)
    m = r @ (s * ill.values[None]).T  # (channel, basis)
    return m / m[1].sum()


@dataclass(frozen=True)
class SensorModel:
    """Sensor parameters.  Radiance ``x`` (relative units) becomes ``x * exposure_s * gain_e``
    photo-electrons; the output is in DN normalised to full scale (1.0 = 2^bits - 1).

    ``white_level`` (normalised DN, one value or one per raw channel R, G, B): with
    ``saturate``, a sensor whose pixels clip below nominal full scale (their well, or the
    converter, tops out there).  The clip is applied to the photo-electrons before read noise,
    so the plateau carries read noise and quantisation as a real one does;
    ``white_level_spread`` adds a fixed per-pixel relative spread (sigma) of that level (the
    wells' non-uniformity).  With the defaults (1.0, 0.0) the sensor clips at full scale after
    read noise, as it always did."""

    exposure_s: float = 0.01
    gain_e: float = 2.0e5
    full_well_e: float = 20000.0
    read_noise_e: float = 5.0
    bits: int = 12
    shot_noise: bool = False
    read_noise: bool = False
    saturate: bool = False
    quantize: bool = False
    vignetting: float = 0.0
    spectral_camera: str | None = None
    illuminant: str = "D65"
    white_level: float | tuple[float, float, float] = 1.0
    white_level_spread: float = 0.0

    def __post_init__(self) -> None:
        wl = np.broadcast_to(np.asarray(self.white_level, dtype=np.float64), (3,))
        if not np.all((wl > 0) & (wl <= 1.0)):
            raise ValueError(f"white_level must be in (0, 1] normalised DN, got {self.white_level}")
        if not 0.0 <= self.white_level_spread < 0.2:
            raise ValueError(f"white_level_spread must be in [0, 0.2), got {self.white_level_spread}")

    @classmethod
    def realistic(cls, **kw) -> "SensorModel":
        """Every effect on, with the given overrides."""
        base = dict(shot_noise=True, read_noise=True, saturate=True, quantize=True, vignetting=0.3,
                    spectral_camera="Nikon 5100 (NPL)")
        base.update(kw)
        return cls(**base)


def vignetting_map(camera: Camera, strength: float, dtype=torch.float64) -> Tensor:
    """Radial falloff ``1 - strength r^2`` (``r`` = 1 at the image corner), ``(H, W, 1)``."""
    ys = torch.linspace(-1, 1, camera.height, dtype=dtype)
    xs = torch.linspace(-1, 1, camera.width, dtype=dtype)
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    return (1.0 - strength * (x * x + y * y) / 2.0).clamp(min=0.0)[..., None]


def capture(radiance: Tensor, camera: Camera, sensor: SensorModel, seed: int | None = 0) -> Tensor:
    """Sensor image ``(H, W, 3)`` in normalised DN from linear radiance ``(H, W, 3)``."""
    if radiance.ndim != 3 or radiance.shape[-1] != 3 or tuple(radiance.shape[:2]) != (camera.height, camera.width):
        raise ValueError(f"radiance must be ({camera.height}, {camera.width}, 3), got {tuple(radiance.shape)}")
    if not bool(torch.isfinite(radiance).all()):
        raise ValueError("radiance contains NaN or Inf")
    x = radiance.to(torch.float64)
    if sensor.spectral_camera is not None:
        m = torch.from_numpy(spectral_matrix(sensor.spectral_camera, sensor.illuminant))
        x = x @ m.T
    if sensor.vignetting > 0:
        x = x * vignetting_map(camera, sensor.vignetting)
    e = x.clamp(min=0.0) * (sensor.exposure_s * sensor.gain_e)
    g = torch.Generator().manual_seed(seed) if seed is not None else None
    if sensor.shot_noise:
        e = torch.poisson(e, generator=g)
    wl = torch.as_tensor(np.broadcast_to(np.asarray(sensor.white_level, np.float64), (3,)).copy())
    if sensor.saturate and (bool((wl < 1.0).any()) or sensor.white_level_spread > 0):
        well = wl * sensor.full_well_e
        if sensor.white_level_spread > 0:  # fixed pattern: the same for every shot of this size
            fp = torch.Generator().manual_seed(7919 + camera.height * 65537 + camera.width)
            well = well * (1.0 + sensor.white_level_spread * torch.randn((camera.height, camera.width, 1),
                                                                         generator=fp, dtype=e.dtype))
        e = torch.minimum(e, well.to(e.dtype))
    if sensor.read_noise:
        e = e + sensor.read_noise_e * torch.randn(e.shape, generator=g, dtype=e.dtype)
    if sensor.saturate:
        e = e.clamp(0.0, sensor.full_well_e)
    dn = e / sensor.full_well_e
    if sensor.quantize:
        levels = 2 ** sensor.bits - 1
        dn = torch.round(dn.clamp(0.0, 1.0) * levels) / levels
    return dn.to(radiance.dtype)


def radiance_per_dn(sensor: SensorModel) -> float:
    """Radiance that yields 1.0 normalised DN (ignoring vignetting/spectral): for inverting."""
    return sensor.full_well_e / (sensor.exposure_s * sensor.gain_e)
