"""High dynamic range: Debevec-Malik response recovery and merge, bracket planning.

Conventions.  Linear sensor data are normalised DN (1.0 = full scale) with exposure times in
seconds; a merged image is in DN/s ("relative radiance", linear camera RGB).  Integer codes
(e.g. 8-bit JPEG-like brackets of a non-linear camera) go through a response curve ``g`` with
``g[z] = ln(E t)`` (Debevec & Malik 1997, Eq. 2), one curve per channel.

White level.  A linear sensor may clip below nominal full scale (its wells or converter top out
at, say, 0.95 DN).  Such clipped samples look valid to a fixed 0.98 DN threshold, and merging
them pulls highlights down and tints them (the channel that clips first is the one pulled
down).  :class:`WhiteLevel` is the per-channel level at which a camera clips: declared in the
capture set, or measured from the brackets by :func:`measure_white_level`; the merge excludes,
per channel, every sample at or above its :attr:`WhiteLevel.threshold`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dualscale.errors import ImageSizeError, MissingBracketsError, SaturatedError


def hat_weight(z: np.ndarray, z_min: float, z_max: float | np.ndarray) -> np.ndarray:
    """Debevec-Malik hat ``w(z) = z - z_min`` below the midpoint, ``z_max - z`` above, 0 outside;
    ``z_max`` may be one value per channel ``(C,)`` (broadcast over ``z``'s last axis)."""
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


WHITE_MARGIN = 0.02
"""Relative margin below the white level at and above which the merge drops a sample
(docs/CALIBRATION.md, "White level"): it covers the sensor's knee below the hard clip and the
plateau's noise, and costs nothing because the brackets put every pixel at or below 0.8 of the
white level in some exposure (hat weights above 0.98 of it are at most 2 % of the peak).  For a
sensor clipping at full scale it is the former fixed 0.98 DN threshold."""

NOMINAL_WHITE = 1.0
"""Nominal full scale of normalised DN: the white level assumed when none is declared or seen."""


@dataclass(frozen=True)
class WhiteLevel:
    """Per-channel level ``level`` ``(C,)`` [normalised raw DN, before dark subtraction] at which
    a camera clips, and where it comes from: ``source`` is ``declared`` (capture set),
    ``measured`` (:func:`measure_white_level`) or ``nominal`` (nothing declared and no clipped
    sample seen: :data:`NOMINAL_WHITE`).  A measurement also gives the plateau's robust spread
    ``spread`` ``(C,)`` (1.4826 MAD) and the number of clipped samples ``n_clipped`` it used per
    channel (0 for a channel filled from the others)."""

    level: tuple[float, ...]
    source: str = "declared"
    spread: tuple[float, ...] = ()
    n_clipped: tuple[int, ...] = ()
    margin: float = WHITE_MARGIN

    def __post_init__(self) -> None:
        lv = np.asarray(self.level, dtype=np.float64)
        if lv.ndim != 1 or lv.size == 0 or not np.all(np.isfinite(lv)) or np.any(lv <= 0) or np.any(lv > NOMINAL_WHITE):
            raise ValueError(f"white level must be one value per channel in (0, {NOMINAL_WHITE:g}] normalised DN, "
                             f"got {list(self.level)}")
        if not 0.0 <= self.margin < 0.5:
            raise ValueError(f"white-level margin must be in [0, 0.5), got {self.margin}")

    @classmethod
    def uniform(cls, level: float, channels: int = 3, source: str = "declared") -> "WhiteLevel":
        return cls(tuple([float(level)] * channels), source)

    @classmethod
    def from_record(cls, rec: dict) -> "WhiteLevel":
        """From a validated calibration record (:func:`dualscale.formats.calibration.white_level`)."""
        return cls(tuple(rec["level"]), rec["source"], tuple(rec.get("spread") or ()), tuple(rec.get("n_clipped") or ()),
                   float(rec.get("margin", WHITE_MARGIN)))

    @property
    def clip(self) -> np.ndarray:
        """``(C,)``: a single exposure's sample at or above this is clipped: ``level - 4 spread``
        (the plateau's noise; a declared level is taken as where clipping starts)."""
        lv = np.asarray(self.level, dtype=np.float64)
        sp = np.asarray(self.spread, dtype=np.float64) if self.spread else np.zeros_like(lv)
        return lv - 4.0 * sp

    @property
    def threshold(self) -> np.ndarray:
        """``(C,)``: the HDR merge excludes samples at or above this:
        ``level - max(margin level, 4 spread)`` (never above :attr:`clip`)."""
        lv = np.asarray(self.level, dtype=np.float64)
        return np.minimum(self.clip, lv * (1.0 - self.margin))

    def to_json(self) -> dict:
        """``{"level": [C], "clip": [C], "threshold": [C], "margin", "source", "spread": [C] | null,
        "n_clipped": [C] | null}`` (the calibration file's ``white_level[camera]``)."""
        return {"level": [float(v) for v in self.level], "clip": [float(v) for v in self.clip],
                "threshold": [float(v) for v in self.threshold],
                "margin": float(self.margin), "source": self.source,
                "spread": [float(v) for v in self.spread] if self.spread else None,
                "n_clipped": [int(v) for v in self.n_clipped] if self.n_clipped else None}


def measure_white_level(stacks, tolerance: float = 0.1, min_signal: float = 0.02, min_samples: int = 50,
                        bin_width: float = 0.002, enough: int | None = None) -> WhiteLevel:
    """Measure a linear camera's per-channel white level from its exposure brackets.

    ``stacks``: iterable of ``(images, exposures_s, dark)``, one per bracket group of the same
    camera: ``images`` normalised raw DN ``(H, W, C)`` (not dark-subtracted), ``dark`` the dark
    level per image (``(H, W, C)`` or broadcastable) or ``None``.

    Method: within each group, for each pair of consecutive exposures ``t_a < t_b`` (ratio
    ``r = t_b / t_a >= 1 + 2 tolerance``), the shorter sample predicts the longer one,
    ``d_b + (z_a - d_a) r``.  A longer sample that lies more than ``tolerance`` below its
    prediction, where the shorter one has at least ``min_signal`` DN of signal, has stopped
    rising with exposure: it is clipped.  Clipped samples of one channel sit on a plateau,
    noise aside; samples flagged by noise alone are scattered.  The plateau is the mode of
    their histogram (``bin_width`` DN bins, smoothed over 5 bins); the level is the median of
    the samples within ``max(4 sigma, 0.005)`` of it, ``sigma`` being their robust spread
    (1.4826 MAD).  A channel with fewer than ``min_samples`` clipped samples takes the median
    of the other channels' levels (a raw sensor clips all channels at one level); when no
    channel has enough, the result is :data:`NOMINAL_WHITE` with ``source = "nominal"``.
    ``enough``: stop reading ``stacks`` once every channel has that many clipped samples.

    Accuracy (docs/CALIBRATION.md, "White level"; ``tests/calib/test_white_level.py``): within
    0.002 DN of the simulated sensor's level at 0.80, 0.90, 0.95 and 1.0, with shot and read
    noise, 12-bit quantisation and a 0.5 % fixed-pattern spread of the wells.
    """
    samples: list[list[np.ndarray]] | None = None
    for images, exposures_s, dark in stacks:
        z, t = _check_stack(images, exposures_s)
        z = z.astype(np.float64)
        if z.ndim == 3:
            z = z[..., None]
        d = np.zeros_like(z) if dark is None else np.broadcast_to(
            np.stack([np.broadcast_to(np.asarray(x, np.float64), z.shape[1:]) for x in dark]), z.shape)
        if samples is None:
            samples = [[] for _ in range(z.shape[-1])]
        if len(samples) != z.shape[-1]:
            raise ImageSizeError(f"brackets have {z.shape[-1]} channels, earlier ones {len(samples)}")
        order = np.argsort(t, kind="stable")
        for a, b in zip(order[:-1], order[1:]):
            r = t[b] / t[a]
            if r < 1.0 + 2.0 * tolerance:
                continue
            sa = z[a] - d[a]
            pred = d[b] + sa * r
            clipped = (sa >= min_signal) & (pred > z[b] * (1.0 + tolerance))
            for c in range(z.shape[-1]):
                samples[c].append(z[b][..., c][clipped[..., c]])
        if enough is not None and all(sum(x.size for x in per) >= enough for per in samples):
            break
    if samples is None:
        raise MissingBracketsError("no bracket groups to measure the white level from")
    levels, spreads, counts = [], [], []
    edges = np.arange(0.0, NOMINAL_WHITE + 2 * bin_width, bin_width)
    for per in samples:
        v = np.concatenate(per) if per else np.zeros(0)
        if v.size < min_samples:
            levels.append(np.nan)
            spreads.append(np.nan)
            counts.append(0)
            continue
        hist = np.convolve(np.histogram(v, edges)[0], np.ones(5), mode="same")
        mode = 0.5 * (edges[int(np.argmax(hist))] + edges[int(np.argmax(hist)) + 1])
        near = v[np.abs(v - mode) <= 0.05]
        level = float(np.median(near))
        sigma = 1.4826 * float(np.median(np.abs(near - level)))
        for _ in range(3):
            near = v[np.abs(v - level) <= max(4.0 * sigma, 0.005)]
            level = float(np.median(near))
            sigma = 1.4826 * float(np.median(np.abs(near - level)))
        ok = near.size >= min_samples
        levels.append(min(level, NOMINAL_WHITE) if ok else np.nan)
        spreads.append(sigma if ok else np.nan)
        counts.append(int(near.size) if ok else 0)
    lv = np.asarray(levels)
    if np.all(np.isnan(lv)):
        return WhiteLevel(tuple([NOMINAL_WHITE] * len(lv)), "nominal", n_clipped=tuple([0] * len(lv)))
    sp = np.asarray(spreads)
    lv = np.where(np.isnan(lv), np.nanmedian(lv), lv)
    sp = np.where(np.isnan(sp), np.nanmedian(sp), sp)
    return WhiteLevel(tuple(float(x) for x in lv), "measured", tuple(float(x) for x in sp), tuple(counts))


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
                  dark: list[np.ndarray] | np.ndarray | None = None, saturation: float | np.ndarray = 0.98,
                  noise_floor: float = 0.002, domain: str = "log", max_saturated_fraction: float = 0.0,
                  name: str = "", white_level: WhiteLevel | None = None) -> HDRResult:
    """Merge brackets into one linear image (Debevec & Malik 1997, Eq. 6).

    ``response=None``: images are linear normalised DN; a sample counts, per channel, if
    ``noise_floor < z - dark`` and ``z < saturation`` (raw ``z``, before dark subtraction);
    hat weights on ``[0, saturation]``.  ``saturation`` is one value or one per channel
    ``(C,)``; a ``white_level`` (:class:`WhiteLevel`) replaces it with its per-channel
    ``threshold``, so that a sensor clipping below full scale has its clipped samples
    excluded channel by channel (it does not apply to integer codes, whose top code is the
    clip).  With a response
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
        thr = white_level.threshold if white_level is not None else np.asarray(saturation, dtype=np.float64)
        try:
            thr = np.broadcast_to(thr, (zf.shape[-1],))
        except ValueError as e:
            raise ImageSizeError(f"{np.size(thr)} saturation levels for {zf.shape[-1]} channels{tag}") from e
        sat = zf >= thr
        low = sig <= noise_floor
        w = hat_weight(zf, 0.0, thr) * ~sat * ~low
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
