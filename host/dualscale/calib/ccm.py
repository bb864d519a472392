"""Colour correction matrices: least squares baseline and Nelder-Mead on mean CIEDE2000.

Input colours are white-balanced linear camera RGB (after :mod:`.radiometric`); a CCM ``M``
maps them to output linear RGB (Rec.709, D65) as ``out = M @ rgb``.  Errors are CIEDE2000
against the colour-science ColorChecker reference (CIELAB D50, see :mod:`.colourref`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from . import colourref as cr

HELD_OUT = (1, 5, 9, 13, 17, 21)  # fixed validation patches, spread over hues and greys


def patch_mask(rgb: np.ndarray, saturated: np.ndarray | None = None, white: float | None = None,
               min_relative: float = 0.02) -> np.ndarray:
    """Patches usable for fitting ``(24,)``: not clipped and not very dark (luminance below
    ``min_relative`` of the white patch, or of ``white``)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    y = cr.luminance(rgb)
    ref = float(y[cr.WHITE_PATCH]) if white is None else white
    ok = np.isfinite(rgb).all(-1) & (y > min_relative * ref)
    if saturated is not None:
        ok &= ~np.asarray(saturated, dtype=bool)
    return ok


def apply_ccm(m: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` linear camera RGB -> output linear RGB with CCM ``m`` ``(3, 3)``."""
    return np.asarray(rgb) @ np.asarray(m).T


def delta_e_patches(m: np.ndarray, rgb: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """CIEDE2000 of each patch after CCM ``m`` (``idx`` selects patches)."""
    idx = np.arange(len(rgb)) if idx is None else np.asarray(idx)
    lab = cr.rgb_to_lab_d50(apply_ccm(m, rgb[idx]))
    return cr.delta_e2000(lab, cr.reference_lab_d50()[idx])


def fit_ccm_ls(rgb: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Least-squares CCM in linear RGB on patches ``idx``."""
    sol = np.linalg.lstsq(np.asarray(rgb)[idx], cr.reference_rgb()[idx], rcond=None)[0]
    return sol.T


def fit_ccm_de2000(rgb: np.ndarray, idx: np.ndarray, start: np.ndarray | None = None, restarts: int = 3,
                   max_evals: int = 4000) -> np.ndarray:
    """CCM minimising mean CIEDE2000 on patches ``idx`` with Nelder-Mead (scipy), started from
    the least-squares CCM and restarted ``restarts`` times from the last optimum."""
    x = (fit_ccm_ls(rgb, idx) if start is None else np.asarray(start)).ravel()
    ref = cr.reference_lab_d50()[idx]
    sel = np.asarray(rgb, dtype=np.float64)[idx]

    def loss(v: np.ndarray) -> float:
        return float(cr.delta_e2000(cr.rgb_to_lab_d50(sel @ v.reshape(3, 3).T), ref).mean())

    best = loss(x)
    for _ in range(restarts):
        r = minimize(loss, x, method="Nelder-Mead",
                     options=dict(maxfev=max_evals, xatol=1e-7, fatol=1e-7, adaptive=True))
        if r.fun >= best - 1e-6:
            if r.fun < best:
                x, best = r.x, float(r.fun)
            break
        x, best = r.x, float(r.fun)
    return x.reshape(3, 3)


@dataclass
class CCMFit:
    """A fitted CCM with its errors (mean CIEDE2000) on the fit and held-out patches."""

    matrix: np.ndarray
    fit_patches: list[int]
    held_out: list[int]
    de: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"matrix": np.asarray(self.matrix).tolist(), "fit_patches": self.fit_patches,
                "held_out": self.held_out, "mean_delta_e2000": self.de}


def fit_and_validate(rgb: np.ndarray, mask: np.ndarray | None = None, held_out: tuple[int, ...] = HELD_OUT) -> CCMFit:
    """Fit the CIEDE2000 CCM on the masked patches not held out, and report mean CIEDE2000
    before (identity), with the least-squares baseline and with Nelder-Mead, on both sets."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape != (cr.N_PATCHES, 3):
        raise ValueError(f"need (24, 3) patch colours, got {rgb.shape}")
    mask = patch_mask(rgb) if mask is None else np.asarray(mask, dtype=bool)
    fit = np.array([i for i in range(cr.N_PATCHES) if mask[i] and i not in held_out])
    ho = np.array([i for i in held_out if mask[i]])
    if len(fit) < 6:
        raise ValueError(f"only {len(fit)} usable patches to fit a CCM (need 6)")
    m_ls = fit_ccm_ls(rgb, fit)
    m_de = fit_ccm_de2000(rgb, fit, start=m_ls)
    de = {}
    for name, m in (("before", np.eye(3)), ("least_squares", m_ls), ("ciede2000", m_de)):
        de[name] = {"fit": float(delta_e_patches(m, rgb, fit).mean()),
                    "held_out": float(delta_e_patches(m, rgb, ho).mean()) if len(ho) else float("nan")}
    return CCMFit(m_de, fit.tolist(), ho.tolist(), de)
