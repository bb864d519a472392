"""Reference colour data and spectral camera responses (all through colour-science).

Spaces used here:

* **camera raw**: linear response of a named camera (``colour.MSDS_CAMERA_SENSITIVITIES``),
  normalised so that a perfect white reflector under the light gives raw green = 1;
* **output RGB**: linear Rec.709/sRGB primaries, D65 white, no transfer curve -- what a CCM
  produces;
* **CIELAB D50**: the ColorChecker reference (colour-science ships xyY under D50).  Output RGB
  is taken to XYZ (D65) and adapted to D50 with Bradford before Lab and CIEDE2000.
"""

from __future__ import annotations

import functools

import numpy as np

CHECKER = "ColorChecker24 - After November 2014"
CHECKER_SPECTRA = "BabelColor Average"
N_PATCHES = 24
WHITE_PATCH = 18  # "white 9.5 (.05 D)"


@functools.lru_cache(maxsize=1)
def _checker():
    import colour

    ccs = colour.CCS_COLOURCHECKERS[CHECKER]
    xyy = np.array(list(ccs.data.values()), dtype=np.float64)
    return list(ccs.data.keys()), colour.xyY_to_XYZ(xyy), np.asarray(ccs.illuminant, dtype=np.float64)


def patch_names() -> list[str]:
    """The 24 patch names in ColorChecker order (row by row from dark skin)."""
    return list(_checker()[0])


def reference_lab_d50() -> np.ndarray:
    """CIELAB (D50) of the 24 patches ``(24, 3)``."""
    import colour

    _, xyz, wp = _checker()
    return colour.XYZ_to_Lab(xyz, wp)


@functools.lru_cache(maxsize=1)
def _rgb_to_xyz_d50() -> np.ndarray:
    import colour

    cs = colour.RGB_COLOURSPACES["sRGB"]
    wp_d50 = _checker()[2]
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        colour.xy_to_XYZ(cs.whitepoint), colour.xy_to_XYZ(wp_d50), "Bradford")
    return cat @ cs.matrix_RGB_to_XYZ


def reference_rgb() -> np.ndarray:
    """Output linear RGB (Rec.709, D65) of the 24 patches ``(24, 3)``, Bradford from D50."""
    return xyz_d50_to_rgb(_checker()[1])


def xyz_d50_to_rgb(xyz: np.ndarray) -> np.ndarray:
    return np.asarray(xyz) @ np.linalg.inv(_rgb_to_xyz_d50()).T


def rgb_to_lab_d50(rgb: np.ndarray) -> np.ndarray:
    """Output linear RGB (Rec.709, D65) -> CIELAB relative to D50 (Bradford)."""
    import colour

    return colour.XYZ_to_Lab(np.asarray(rgb, dtype=np.float64) @ _rgb_to_xyz_d50().T, _checker()[2])


def delta_e2000(lab_a: np.ndarray, lab_b: np.ndarray) -> np.ndarray:
    """CIEDE2000 between two CIELAB arrays (colour-science)."""
    import colour

    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 2000"))


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Relative luminance of linear Rec.709 RGB ``(..., 3) -> (...)``."""
    return np.asarray(rgb) @ np.array([0.2126, 0.7152, 0.0722])


@functools.lru_cache(maxsize=64)
def _sensitivities(camera: str):
    import colour

    if camera not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise ValueError(f"unknown camera sensitivities {camera!r}; known: {sorted(colour.MSDS_CAMERA_SENSITIVITIES)}")
    return colour.MSDS_CAMERA_SENSITIVITIES[camera]


def camera_raw(reflectances: list, camera: str, illuminant: str) -> np.ndarray:
    """Camera raw RGB ``(N, 3)`` of spectral reflectances (``colour.SpectralDistribution``)
    under a named illuminant (``colour.SDS_ILLUMINANTS``): ``sum R E S_c / sum E S_g``."""
    import colour

    sens = _sensitivities(camera)
    shape = sens.shape
    if illuminant not in colour.SDS_ILLUMINANTS:
        raise ValueError(f"unknown illuminant {illuminant!r}")
    e = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape).values
    s = sens.values
    r = np.stack([sd.copy().align(shape).values for sd in reflectances])
    return (r * e) @ s / float(e @ s[:, 1])


def flat_spectrum(v400: float, v700: float):
    """A smooth reflectance/transmittance spectrum, linear from ``v400`` at 400 nm to ``v700``."""
    import colour

    wl = np.arange(360.0, 831.0, 5.0)
    vals = np.clip(v400 + (v700 - v400) * (wl - 400.0) / 300.0, 0.0, 1.0)
    return colour.SpectralDistribution(dict(zip(wl, vals)))
