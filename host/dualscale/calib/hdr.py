"""High dynamic range: Debevec-Malik response recovery and merge, bracket planning.

Conventions.  Linear sensor data are normalised DN (1.0 = full scale) with exposure times in
seconds; a merged image is in DN/s ("relative radiance", linear camera RGB).  Integer codes
(e.g. 8-bit JPEG-like brackets of a non-linear camera) go through a response curve ``g`` with
``g[z] = ln(E t)`` (Debevec & Malik 1997, Eq. 2), one curve per channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dualscale.errors import ImageSizeError, MissingBracketsError, SaturatedError


def hat_weight(z: np.ndarray, z_min: float, z_max: float) -> np.ndarray:
    """Debevec-Malik hat ``w(z) = z - z_min`` below the midpoint, ``z_max - z`` above, 0 outside."""
    mid = 0.5 * (z_min + z_max)
    w = np.where(z <= mid, z - z_min, z_max - z)
    return np.clip(w, 0.0, None)


def _check_stack(images: list[np.ndarray] | np.ndarray, exposures_s: list[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(images) == 0:
        raise MissingBracketsError("no exposure brackets given")
    if len(images) != len(exposures_s):
        raise MissingBracketsError(f"{len(images)} images but {len(exposures_s)} exposure times")
    shapes = {np.shape(i) for i in images}
    if len(shapes) != 1:
        raise ImageSizeError(f"brackets have different sizes: {sorted(shapes)}")
    t = np.asarray(exposures_s, dtype=np.float64)
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError(f"exposure times must be positive, got {t.tolist()}")
    return np.stack([np.asarray(i) for i in images]), t


def recover_response(images: list[np.ndarray], exposures_s: list[float], smoothness: float = 50.0,
                     n_samples: int = 200, levels: int = 256, seed: int = 0) -> np.ndarray:
    """Response curves ``g`` ``(levels, C)`` with ``g[z] = ln(E t)`` from integer-coded brackets.

    Solves Debevec & Malik's least-squares system per channel on ``n_samples`` pixels (chosen
    at random but spread over the brightness range) with hat weights, second-difference
    smoothness ``smoothness`` and ``g[levels // 2] = 0``.
    """
    z, t = _check_stack(images, exposures_s)
    z = z.astype(np.int64)
    if z.ndim == 3:
        z = z[..., None]
    if z.min() < 0 or z.max() >= levels:
        raise ValueError(f"codes must be integers in [0, {levels - 1}]")
    n, h, w, c = z.shape
    rng = np.random.default_rng(seed)
    flat = z.reshape(n, h * w, c)
    weight = hat_weight(np.arange(levels, dtype=np.float64), 0, levels - 1) + 1.0
    log_t = np.log(t)
    out = np.empty((levels, c))
    for ch in range(c):
        # stratify by the middle exposure's code so that the whole range is sampled
        ref = flat[n // 2, :, ch]
        order = np.argsort(ref, kind="stable")
        picks = order[np.linspace(0, len(order) - 1, n_samples).astype(int)]
        picks = np.unique(np.concatenate([picks, rng.choice(h * w, size=min(n_samples // 4, h * w), replace=False)]))
        p = len(picks)
        rows = n * p + 1 + (levels - 2)
        a = np.zeros((rows, levels + p))
        b = np.zeros(rows)
        k = 0
        for j in range(n):
            zz = flat[j, picks, ch]
            wij = weight[zz]
            a[k + np.arange(p), zz] = wij
            a[k + np.arange(p), levels + np.arange(p)] = -wij
            b[k:k + p] = wij * log_t[j]
            k += p
        a[k, levels // 2] = 1.0
        k += 1
        for zi in range(1, levels - 1):
            lw = smoothness * weight[zi]
            a[k, zi - 1:zi + 2] = (lw, -2 * lw, lw)
            k += 1
        sol = np.linalg.lstsq(a, b, rcond=None)[0]
        out[:, ch] = sol[:levels]
    return out


@dataclass(frozen=True)
class HDRResult:
    """Merged linear image ``radiance`` ``(H, W, C)`` [DN/s or relative], with ``valid``
    ``(H, W, C)`` (some sample was neither saturated nor lost in noise), ``saturated`` (every
    sample saturated) and ``underexposed`` (every sample lost in noise)."""

    radiance: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    underexposed: np.ndarray


def merge_debevec(images: list[np.ndarray], exposures_s: list[float], response: np.ndarray | None = None,
                  dark: list[np.ndarray] | np.ndarray | None = None, saturation: float = 0.98,
                  noise_floor: float = 0.002, domain: str = "log", max_saturated_fraction: float = 0.0,
                  name: str = "") -> HDRResult:
    """Merge brackets into one linear image (Debevec & Malik 1997, Eq. 6).

    ``response=None``: images are linear normalised DN; a sample counts if ``noise_floor <
    z - dark`` and ``z < saturation``; hat weights on ``[0, saturation]``.  With a response
    ``g`` (``(levels, C)``, from :func:`recover_response`) images are integer codes and the
    weights are the hat on the code range.  ``domain='log'`` averages ``ln E`` as in the paper,
    ``'linear'`` averages ``E``.  Pixels that are saturated in every bracket raise
    :class:`MissingBracketsError` above ``max_saturated_fraction`` (a shorter exposure is
    missing), and :class:`SaturatedError` when no pixel is usable at all.  Pixels lost in
    noise in every bracket fall back to the longest exposure and are flagged.
    """
    z, t = _check_stack(images, exposures_s)
    if z.ndim == 3:
        z = z[..., None]
    tag = f" ({name})" if name else ""
    if response is None:
        zf = z.astype(np.float64)
        if dark is not None:
            d = np.asarray(dark, dtype=np.float64)
            d = d.reshape(z.shape) if d.shape == z.shape else np.broadcast_to(d, z.shape)
            sig = zf - d
        else:
            sig = zf
        sat = zf >= saturation
        low = sig <= noise_floor
        w = hat_weight(zf, 0.0, saturation) * ~sat * ~low
        lin = np.clip(sig, 1e-12, None) / t[:, None, None, None]
    else:
        g = np.asarray(response, dtype=np.float64)
        levels = g.shape[0]
        zi = z.astype(np.int64)
        if zi.min() < 0 or zi.max() >= levels:
            raise ValueError(f"codes must be in [0, {levels - 1}] for this response")
        c = zi.shape[-1]
        lg = np.stack([g[zi[..., k], k if g.shape[1] > 1 else 0] for k in range(c)], -1)
        sat = zi >= levels - 1
        low = zi <= 0
        w = hat_weight(zi.astype(np.float64), 0, levels - 1)
        lin = np.exp(lg) / t[:, None, None, None]
    wsum = w.sum(0)
    valid = wsum > 0
    sat_all = sat.all(0)
    low_all = low.all(0) | (~valid & ~sat_all)
    if sat_all.all():
        raise SaturatedError(f"every capture is saturated{tag}: expose shorter")
    frac = float(sat_all.any(-1).mean())
    if frac > max_saturated_fraction:
        raise MissingBracketsError(f"{frac:.1%} of pixels are saturated in every bracket{tag}: "
                                   f"a shorter exposure is missing (shortest {t.min():g} s)")
    safe = np.where(valid, wsum, 1.0)
    if domain == "log":
        merged = np.exp((w * np.log(lin)).sum(0) / safe)
    elif domain == "linear":
        merged = (w * lin).sum(0) / safe
    else:
        raise ValueError(f"domain must be 'log' or 'linear', got {domain!r}")
    longest = int(np.argmax(t))
    fallback = lin[longest] if response is not None else sig[longest] / t[longest]
    merged = np.where(valid, merged, np.where(sat_all, lin[int(np.argmin(t))], fallback))
    return HDRResult(merged, valid, sat_all, low_all)


def plan_brackets(metering: np.ndarray, exposure_s: float, low: float = 0.05, high: float = 0.8,
                  step: float = 4.0, saturation: float = 0.98, max_brackets: int = 8,
                  ignore_fraction: float = 0.0, dark: tuple[float, float] = (0.0, 0.0)) -> list[float]:
    """Exposure times [s] so that every pixel gets one sample in ``[low, high]`` DN.

    From a linear metering shot (normalised DN) at ``exposure_s``: the brightest pixel sets
    the shortest exposure (it lands at ``high``), the darkest (its brightest channel) sets the
    longest (it lands at ``high`` too), and consecutive exposures differ by ``step <=
    high/low`` so the usable ranges overlap.  A metering shot with saturated pixels is refused
    (meter again shorter); pixels lost in noise are taken at ``low`` (a lower bound of their
    signal, so the plan reaches far enough).  ``ignore_fraction`` drops that fraction of the
    darkest pixels (e.g. holes).  ``metering`` must be dark-subtracted; ``dark = (bias [DN],
    rate [DN/s])`` keeps signal plus dark signal at or below ``high``.
    """
    if not 1.0 < step <= high / low:
        raise ValueError(f"step must be in (1, high/low = {high / low:g}]")
    m = np.asarray(metering, dtype=np.float64)
    m = m.max(-1) if m.ndim == 3 else m
    if (m >= saturation).any():
        raise SaturatedError(f"metering shot at {exposure_s:g} s has saturated pixels: meter shorter")
    bright = max(float(m.max()), low) / exposure_s
    dark_val = float(np.quantile(m, ignore_fraction)) if ignore_fraction > 0 else float(m.min())
    dark_rate = max(dark_val, low * 0.5) / exposure_s
    bias, rate = dark
    if bias >= high:
        raise ValueError(f"dark bias {bias:g} DN leaves no range below {high:g}")
    t_short = (high - bias) / (bright + rate)
    t_long = (high - bias) / (dark_rate + rate)
    n = 1 if t_long <= t_short * 1.0001 else int(math.ceil(math.log(t_long / t_short) / math.log(step))) + 1
    if n > max_brackets:
        raise ValueError(f"the scene needs {n} brackets (> {max_brackets}); raise max_brackets or step")
    return [t_short * step ** k for k in range(n)]


def meter(capture, exposure_s: float = 1e-2, saturation: float = 0.98, tries: int = 12) -> tuple[np.ndarray, float]:
    """Metering shot: call ``capture(t)`` (normalised DN) and shorten/lengthen by 8x until no
    pixel is saturated and the brightest is above 5 % of full scale."""
    t = exposure_s
    for _ in range(tries):
        img = np.asarray(capture(t))
        peak = float(img.max())
        if peak >= saturation:
            t /= 8.0
        elif peak < 0.05:
            t *= 8.0
        else:
            return img, t
    raise SaturatedError(f"could not meter within {tries} tries (last exposure {t:g} s, peak {peak:.3f})")
