"""Figures for the reports (matplotlib, Agg): every axis labelled with its unit, constrained
layout, colour scales that never saturate silently.

Colour-scale rule: a scalar image is drawn between robust limits (by default the 0.5th and
99.5th percentiles), or over its fixed physical range where one exists: tangent 0–180°, and the
unitless maps bounded to [0, 1] by the map conventions (:data:`UNIT_RANGE_MAPS`: roughness,
anisotropy, specular tint, opacity), which therefore never saturate and share one scale between
the fitted and the propagated maps. When
values fall outside, the colorbar gets end arrows and the returned caption says how many and
where; nothing is clipped without saying so. Scatter plots of a few values (the hemisphere)
use the data's own maximum, so no point is capped; a range over two decades switches to a
labelled log scale.

Every function returns ``(figure, caption)``; the caller saves the figure (``html.Assets``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from . import format as fmt

ROBUST_PCT = 99.5
DISPLAY_MAX_PX = 1024
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec.709 luminance weights (linear RGB)


def _plt():
    import matplotlib

    if matplotlib.get_backend().lower() != "agg":
        matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 8.5, "axes.titlesize": 9.5, "axes.labelsize": 8.5,
                         "figure.dpi": 110, "savefig.dpi": 110, "image.interpolation": "nearest"})
    return plt


def figure(w: float, h: float, **kw):
    """A figure with constrained layout (the only layout engine the reports use)."""
    return _plt().figure(figsize=(w, h), layout="constrained", **kw)


# ---------------------------------------------------------------------------------------------
# ranges, encodings, display copies

@dataclass(frozen=True)
class Range:
    vmin: float
    vmax: float
    below: float  # share of finite values < vmin
    above: float  # share of finite values > vmax
    finite: float  # share of finite values

    @property
    def clipped(self) -> float:
        return self.below + self.above

    @property
    def extend(self) -> str:
        lo, hi = self.below > 0, self.above > 0
        return "both" if lo and hi else "min" if lo else "max" if hi else "neither"


def robust_range(data, lo_pct: float | None = 100 - ROBUST_PCT, hi_pct: float = ROBUST_PCT,
                 vmin: float | None = None, vmax: float | None = None) -> Range:
    """Colour limits from percentiles of the finite values (fixed ``vmin``/``vmax`` win), with
    the share of values that fall outside. A constant image gets a small symmetric range."""
    a = np.asarray(data, dtype=np.float64).ravel()
    fin = a[np.isfinite(a)]
    if fin.size == 0:
        return Range(0.0, 1.0, 0.0, 0.0, 0.0)
    lo = vmin if vmin is not None else (float(np.percentile(fin, lo_pct)) if lo_pct is not None else float(fin.min()))
    hi = vmax if vmax is not None else float(np.percentile(fin, hi_pct))
    if not hi > lo:
        pad = max(abs(hi) * 0.05, 1e-6)
        lo, hi = lo - pad, hi + pad
    return Range(lo, hi, float((fin < lo).mean()), float((fin > hi).mean()), fin.size / a.size)


def clip_note(r: Range, unit: str = "", what: str = "texels") -> str:
    """One sentence on the colour scale and what falls outside it ('' when nothing does)."""
    parts = []
    if r.below > 0:
        parts.append(f"{fmt.percent(r.below, 2)} of {what} are below {fmt.quantity(r.vmin, unit)}")
    if r.above > 0:
        parts.append(f"{fmt.percent(r.above, 2)}{'' if parts else ' of ' + what} are above {fmt.quantity(r.vmax, unit)}")
    if not parts:
        return ""
    return "Clipped: " + " and ".join(parts) + " (drawn in the end colours, arrows on the colorbar)."


def srgb_encode(linear) -> np.ndarray:
    """IEC 61966-2-1 on [0, 1]-clipped linear values (display only)."""
    x = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float64)), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def luminance(rgb) -> np.ndarray:
    a = np.asarray(rgb, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] >= 3:
        return a[..., :3] @ LUMA
    return a[..., 0] if a.ndim == 3 else a


def display_copy(arr, max_px: int = DISPLAY_MAX_PX) -> np.ndarray:
    """Block-mean downsample so the longer side is at most ``max_px`` (large guidance images)."""
    a = np.asarray(arr, dtype=np.float64)
    s = int(math.ceil(max(a.shape[:2]) / max_px))
    if s <= 1:
        return a
    h, w = (a.shape[0] // s) * s, (a.shape[1] // s) * s
    a = a[:h, :w]
    return a.reshape(h // s, s, w // s, s, *a.shape[2:]).mean(axis=(1, 3))


def _frame(ax, h: int, w: int, texel_mm: float | None):
    """Extent and axis labels: millimetres (x right, y up) when the texel size is known."""
    if texel_mm:
        ext = (0.0, w * texel_mm, 0.0, h * texel_mm)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
    else:
        ext = (-0.5, w - 0.5, h - 0.5, -0.5)
        ax.set_xlabel("column [px]")
        ax.set_ylabel("row [px]")
    return ext


def _to_plot(col, row, h: int, texel_mm: float | None):
    """Pixel coordinates (col, row; row 0 at top) to the plotted frame of :func:`_frame`."""
    col, row = np.asarray(col, float), np.asarray(row, float)
    if texel_mm:
        return (col + 0.5) * texel_mm, (h - row - 0.5) * texel_mm
    return col, row


def _colorbar(fig, mappable, ax, label: str, extend: str = "neither"):
    """A colorbar with its label; small or large values get a ×10ⁿ factor instead of long ticks."""
    from matplotlib.ticker import ScalarFormatter

    cb = fig.colorbar(mappable, ax=ax, extend=extend, shrink=0.9, pad=0.02)
    cb.set_label(label)
    vmax = max(abs(float(mappable.norm.vmin)), abs(float(mappable.norm.vmax)))
    if 0 < vmax < 0.01 or vmax >= 1e4:
        f = ScalarFormatter(useMathText=True)
        f.set_powerlimits((-2, 4))
        cb.ax.yaxis.set_major_formatter(f)
    return cb


# ---------------------------------------------------------------------------------------------
# maps

def scalar_image(img, *, title: str, label: str, unit: str = "", cmap: str = "viridis",
                 texel_mm: float | None = None, vmin: float | None = None, vmax: float | None = None,
                 robust: bool = True, size=(4.3, 3.5), ticks: Sequence[float] | None = None):
    """One scalar image with a labelled colorbar; returns ``(fig, caption)``."""
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., 0]
    r = robust_range(a, vmin=vmin, vmax=vmax) if robust else robust_range(a, None, 100.0, vmin, vmax)
    fig = figure(*size)
    ax = fig.add_subplot()
    ext = _frame(ax, a.shape[0], a.shape[1], texel_mm)
    im = ax.imshow(display_copy(a), cmap=cmap, vmin=r.vmin, vmax=r.vmax, extent=ext)
    ax.set_title(title)
    cb = _colorbar(fig, im, ax, label, r.extend)
    fin = a[np.isfinite(a)]
    if fin.size and fin.min() == fin.max():
        cb.set_ticks([float(fin[0])], labels=[fmt.number(fin[0])])
    elif ticks is not None:
        cb.set_ticks(list(ticks), labels=[fmt.quantity(t, unit) for t in ticks])
    cap = ""
    if fin.size and fin.min() == fin.max():
        cap = f"Constant {fmt.quantity(fin.min(), unit)}."
    elif fin.size:
        cap = (f"Values {fmt.quantity(fin.min(), unit)} to {fmt.quantity(fin.max(), unit)}, "
               f"mean {fmt.quantity(fin.mean(), unit)}; colour scale {fmt.quantity(r.vmin, unit)} to "
               f"{fmt.quantity(r.vmax, unit)}.")
        note = clip_note(r, unit)
        cap = f"{cap} {note}".strip()
    if r.finite < 1:
        cap += f" {fmt.percent(1 - r.finite, 2)} of texels are not finite (blank)."
    return fig, cap


def rgb_image(img, *, title: str, texel_mm: float | None = None, encode: str = "srgb",
              exposure: float = 1.0, size=(4.0, 3.5)):
    """An RGB image: ``encode='srgb'`` for linear colour, ``'linear'`` for values already in
    display range (e.g. 0.5 n + 0.5). Returns ``(fig, caption)``; the caption gives the clipped share."""
    a = np.asarray(img, dtype=np.float64)[..., :3] * exposure
    over = float((a > 1.0).any(-1).mean())
    under = float((a < 0.0).any(-1).mean())
    shown = srgb_encode(a) if encode == "srgb" else np.clip(a, 0, 1)
    fig = figure(*size)
    ax = fig.add_subplot()
    ext = _frame(ax, a.shape[0], a.shape[1], texel_mm)
    ax.imshow(display_copy(shown), extent=ext)
    ax.set_title(title)
    cap = "Linear RGB shown through the sRGB transfer curve." if encode == "srgb" else ""
    if exposure != 1.0:
        cap += f" Display exposure ×{fmt.number(exposure)}."
    if over > 0:
        cap += f" {fmt.percent(over, 2)} of texels exceed 1 in some channel and are drawn at 1."
    if under > 0:
        cap += f" {fmt.percent(under, 2)} are below 0 and drawn at 0."
    return fig, cap.strip()


def normal_image(n, *, title: str = "normal", texel_mm: float | None = None):
    """Normal map as RGB = 0.5 n + 0.5, with a key disc showing the colour of each direction."""
    a = np.asarray(n, dtype=np.float64)[..., :3]
    fig = figure(5.0, 3.5)
    gs = fig.add_gridspec(1, 2, width_ratios=[4, 1.35])
    ax = fig.add_subplot(gs[0])
    ext = _frame(ax, a.shape[0], a.shape[1], texel_mm)
    ax.imshow(display_copy(np.clip(0.5 * a + 0.5, 0, 1)), extent=ext)
    ax.set_title(title)
    key = fig.add_subplot(gs[1])
    g = np.linspace(-1, 1, 101)
    x, y = np.meshgrid(g, -g)
    r2 = x * x + y * y
    z = np.sqrt(np.clip(1 - r2, 0, 1))
    disc = np.dstack([0.5 * x + 0.5, 0.5 * y + 0.5, 0.5 * z + 0.5])
    disc = np.concatenate([disc, (r2 <= 1)[..., None].astype(float)], -1)
    key.imshow(disc, extent=(-1, 1, -1, 1))
    key.set_title("key", fontsize=8.5)
    key.set_xticks([-1, 0, 1])
    key.set_yticks([-1, 0, 1])
    key.set_xlabel("n_x (right)")
    key.set_ylabel("n_y (up)")
    key.set_aspect("equal")
    nz = a[..., 2]
    tilt = np.degrees(np.arccos(np.clip(nz, -1, 1)))
    fin = tilt[np.isfinite(tilt)]
    cap = ("Colour = 0.5·n + 0.5 (R = x right, G = y up, B = z out of the surface); a flat texel "
           "(0, 0, 1) is lavender. The key shows the colour of every unit normal seen from above.")
    if fin.size:
        cap += (f" Tilt from +z: mean {fmt.quantity(fin.mean(), '°')}, 99.5th percentile "
                f"{fmt.quantity(np.percentile(fin, ROBUST_PCT), '°')}.")
    return fig, cap


MAP_TITLES = {
    "albedo": "albedo", "normal": "normal", "roughness": "roughness", "anisotropy": "anisotropy",
    "tangent": "tangent azimuth", "ior": "index of refraction η", "specular_tint": "specular tint",
    "transmittance": "transmittance", "opacity": "opacity",
}


#: scalar maps whose values are in [0, 1] by convention (``dualscale.bsdf.maps``): drawn 0 to 1
UNIT_RANGE_MAPS = ("roughness", "anisotropy", "specular_tint", "opacity")


def map_figure(name: str, arr, texel_mm: float | None = None, prefix: str = ""):
    """The figure of one SVBSDF map by the map conventions; returns ``(fig, caption)``."""
    a = np.asarray(arr, dtype=np.float64)
    title = prefix + MAP_TITLES.get(name, name)
    if name in ("albedo", "transmittance"):
        return rgb_image(a, title=title, texel_mm=texel_mm)
    if name == "normal":
        return normal_image(a, title=title, texel_mm=texel_mm)
    if a.ndim == 3:
        a = a[..., 0]
    if name == "ior":
        fig, cap = scalar_image(1.0 + 2.0 * a, title=title, label="η (unitless)", texel_mm=texel_mm, cmap="cividis")
        return fig, "η = 1 + 2·(stored value). " + cap
    if name == "tangent":
        deg = np.mod(180.0 * a, 180.0)
        fig, cap = scalar_image(deg, title=title, label="azimuth [°], counter-clockwise from +x", unit="°",
                                cmap="twilight", texel_mm=texel_mm, vmin=0.0, vmax=180.0,
                                ticks=(0, 45, 90, 135, 180))
        return fig, ("Azimuth = 180°·(stored value), axial, so 0° and 180° are the same direction "
                     "(cyclic colour map). " + cap)
    if name in UNIT_RANGE_MAPS:
        return scalar_image(a, title=title, label=f"{MAP_TITLES.get(name, name)} (unitless)", texel_mm=texel_mm,
                            vmin=0.0, vmax=1.0, ticks=(0, 0.25, 0.5, 0.75, 1))
    return scalar_image(a, title=title, label=f"{MAP_TITLES.get(name, name)} (unitless)", texel_mm=texel_mm)


def residual_figure(res, texel_mm: float | None = None):
    """Fit residual (relative L1 per texel, shown in %), robust max, clipped share in the caption."""
    a = 100.0 * np.asarray(res, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., 0]
    r = robust_range(a, None, ROBUST_PCT, vmin=0.0)
    fig = figure(4.3, 3.5)
    ax = fig.add_subplot()
    ext = _frame(ax, a.shape[0], a.shape[1], texel_mm)
    im = ax.imshow(display_copy(a), cmap="magma", vmin=r.vmin, vmax=r.vmax, extent=ext)
    ax.set_title("fit residual (training lights)")
    _colorbar(fig, im, ax, "mean |render − capture| / mean capture [%]", r.extend)
    fin = a[np.isfinite(a)]
    cap = (f"Per texel: mean over the training lights of |render − capture|, divided by the mean capture. "
           f"Median {fmt.quantity(np.median(fin), '%')}, 99.5th percentile "
           f"{fmt.quantity(np.percentile(fin, ROBUST_PCT), '%')}, max {fmt.quantity(fin.max(), '%')}. "
           if fin.size else "")
    return fig, (cap + clip_note(r, "%")).strip()


def heldout_figure(capture, render, *, title: str = "", texel_mm: float | None = None,
                   capture_title: str = "held-out capture", render_title: str = "render of the fit"):
    """Capture | render under the same display exposure | luminance of |render − capture|
    (``capture``, ``render``: ``(H, W, 3)`` linear radiance).  ``capture_title`` and
    ``render_title`` label the first two panels: say whether the light was held out of the fit
    that rendered it."""
    cap_a = np.asarray(capture, dtype=np.float64)[..., :3]
    ren_a = np.asarray(render, dtype=np.float64)[..., :3]
    ref = np.percentile(cap_a.max(-1), ROBUST_PCT) if cap_a.size else 1.0
    expo = 1.0 / ref if ref > 0 else 1.0
    fig = figure(10.0, 3.3)
    axes = fig.subplots(1, 3)
    h, w = cap_a.shape[:2]
    for ax, img, t in ((axes[0], cap_a, capture_title), (axes[1], ren_a, render_title)):
        ext = _frame(ax, h, w, texel_mm)
        ax.imshow(display_copy(srgb_encode(img * expo)), extent=ext)
        ax.set_title(t)
    diff = luminance(np.abs(ren_a - cap_a))
    r = robust_range(diff, None, ROBUST_PCT, vmin=0.0)
    ext = _frame(axes[2], h, w, texel_mm)
    im = axes[2].imshow(display_copy(diff), cmap="magma", vmin=r.vmin, vmax=r.vmax, extent=ext)
    axes[2].set_title("|render − capture|")
    _colorbar(fig, im, axes[2], "luminance [relative radiance]", r.extend)
    for ax in axes[1:]:
        ax.set_ylabel("")
    if title:
        fig.suptitle(title, fontsize=9.5)
    clip_c = float(((cap_a * expo) > 1).any(-1).mean())
    clip_r = float(((ren_a * expo) > 1).any(-1).mean())
    cap = (f"Capture and render share one display exposure (×{fmt.number(expo)}: the capture's "
           f"{fmt.number(ROBUST_PCT)}th percentile maps to white, sRGB curve); {fmt.percent(clip_c, 2)} of capture "
           f"and {fmt.percent(clip_r, 2)} of render pixels are brighter and drawn white. ")
    return fig, (cap + clip_note(r, "", "pixels")).strip()


# ---------------------------------------------------------------------------------------------
# hemisphere

def hemisphere(ax, theta_deg: Sequence[float], phi_deg: Sequence[float], values: Sequence[float], *,
               norm=None, cmap: str = "viridis", size: float = 46.0, centre: float | None = None,
               r_max: float = 90.0):
    """Polar scatter on ``ax`` (a polar axes): radius = angle from the zenith [°], angle =
    azimuth (counter-clockwise from +x). ``centre`` (e.g. the diffuse group) is drawn as a large
    disc at the pole. The colour range comes from ``norm`` (see :func:`hemisphere_norm`)."""
    th = np.asarray(theta_deg, float)
    ph = np.radians(np.asarray(phi_deg, float))
    sc = ax.scatter(ph, th, c=np.asarray(values, float), cmap=cmap, norm=norm, s=size,
                    edgecolors="0.25", linewidths=0.4, zorder=3)
    if centre is not None:
        ax.scatter([0.0], [0.0], c=[centre], cmap=cmap, norm=norm, s=size * 5, marker="o",
                   edgecolors="0.25", linewidths=0.6, zorder=4)
    ax.set_ylim(0, r_max)
    ticks = [t for t in (30, 60) if t < r_max]  # the rim needs no label: it sits by the azimuth labels
    ax.set_yticks(ticks, [f"{t}°" for t in ticks], fontsize=7, color="0.35")
    ax.set_rlabel_position(112.5)
    ax.set_xticks(np.radians(np.arange(0, 360, 45)), [f"{d}°" for d in range(0, 360, 45)], fontsize=7)
    ax.tick_params(axis="x", pad=0)
    ax.grid(True, lw=0.4, alpha=0.6)
    return sc


def hemisphere_norm(values, vmin: float = 0.0, log_decades: float = 2.0):
    """A colour normalisation that covers every value: linear ``vmin``..max, or log when the
    positive values span more than ``log_decades`` decades. Never caps the data."""
    import matplotlib.colors as mcolors

    v = np.asarray([x for x in np.ravel(values) if x is not None and np.isfinite(x)], float)
    if v.size == 0:
        return mcolors.Normalize(0, 1), False
    hi = float(v.max())
    pos = v[v > 0]
    if pos.size and pos.min() > 0 and hi / pos.min() > 10 ** log_decades and (v > 0).all():
        return mcolors.LogNorm(float(pos.min()), hi), True
    lo = min(vmin, float(v.min()))
    if hi <= lo:
        hi = lo + (abs(lo) * 0.1 or 1.0)
    return mcolors.Normalize(lo, hi), False


def hemisphere_figure(panels, *, label: str, goal: float | None = None, goal_text: str = "",
                      cmap: str = "viridis", size=None, r_max: float = 90.0, ncols: int | None = None):
    """Hemisphere panels sharing one colour scale whose maximum is the data maximum over all
    panels (nothing is capped), on a grid of ``ncols`` columns.

    ``panels``: list of ``(title, theta_deg, phi_deg, values, centre_value_or_None)``. ``goal``
    draws a red line on the colorbar and counts the points above it. Returns
    ``(fig, caption, norm)``."""
    allv = [x for p in panels for x in list(p[3]) + ([p[4]] if p[4] is not None else [])]
    norm, is_log = hemisphere_norm(allv)
    n = len(panels)
    ncols = ncols or n
    nrows = int(math.ceil(n / ncols))
    fig = figure(*(size or (3.0 * ncols + 1.1, 3.2 * nrows + 0.2)))
    axes = [fig.add_subplot(nrows, ncols, i + 1, projection="polar") for i in range(n)]
    sc = None
    for ax, (title, th, ph, vals, centre) in zip(axes, panels):
        sc = hemisphere(ax, th, ph, vals, norm=norm, cmap=cmap, centre=centre, r_max=r_max)
        ax.set_title(title, pad=12)
    cb = fig.colorbar(sc, ax=axes, shrink=0.85 if nrows == 1 else 0.6, pad=0.04)
    cb.set_label(label + (" (log scale)" if is_log else ""))
    if goal is not None and norm.vmin <= goal <= norm.vmax:
        cb.ax.axhline(goal, color="w", lw=2.2)
        cb.ax.axhline(goal, color="crimson", lw=1.2)
    vals = np.asarray([x for x in allv if x is not None and np.isfinite(x)], float)
    cap = ("Radius: angle from the zenith [°]; angle: azimuth, counter-clockwise from +x. "
           f"One colour scale for all panels, {fmt.number(norm.vmin)} to {fmt.number(norm.vmax)} = the data's full "
           f"range ({'log' if is_log else 'linear'}), so no point is capped.")
    if any(p[4] is not None for p in panels):
        cap += " The large disc at the centre is the diffuse group."
    if goal is not None:
        above = int((vals > goal).sum()) if vals.size else 0
        cap += (f" Red line on the colorbar: {goal_text or 'goal'} {fmt.number(goal)}"
                f"{'' if norm.vmin <= goal <= norm.vmax else ' (outside the range shown)'}; "
                f"{above} of {vals.size} values exceed it.")
    return fig, cap, norm


# ---------------------------------------------------------------------------------------------
# other panels

def time_bars(stages: Sequence[str], seconds: Sequence[float | None]):
    """Horizontal bars of seconds per stage, each annotated with its human duration."""
    secs = [float(s) if s is not None else 0.0 for s in seconds]
    fig = figure(6.4, 0.5 + 0.34 * max(len(stages), 1) + 0.6)
    ax = fig.add_subplot()
    y = np.arange(len(stages))
    ax.barh(y, secs, color="#4c78a8", height=0.6)
    ax.set_yticks(y, list(stages))
    ax.invert_yaxis()
    ax.set_xlabel("time [s]")
    top = max(secs) if secs and max(secs) > 0 else 1.0
    ax.set_xlim(0, top * 1.3)
    for yi, s, raw in zip(y, secs, seconds):
        ax.text(s + top * 0.01, yi, fmt.duration(raw) if raw is not None else "not recorded",
                va="center", ha="left", fontsize=7.5)
    ax.spines[["top", "right"]].set_visible(False)
    total = sum(secs)
    return fig, f"Wall time per stage, total {fmt.duration(total)}."


def max_pool(mask, max_px: int) -> np.ndarray:
    """A boolean mask reduced by block maximum so the longer side is at most ``max_px``: a
    1-texel line stays visible at any display size (a block mean or nearest sampling loses it).
    The blocks are those of :func:`block_mean` with the same ``max_px``."""
    m = np.asarray(mask, bool)
    s = _block_side(m.shape, max_px)
    return m if s <= 1 else _blocks(m, s).any(axis=(1, 3))


def block_mean(arr, max_px: int) -> np.ndarray:
    """Block mean so the longer side is at most ``max_px``; edge blocks are padded by
    repeating the last row and column, so the shape matches :func:`max_pool`'s."""
    a = np.asarray(arr, dtype=np.float64)
    s = _block_side(a.shape, max_px)
    return a if s <= 1 else _blocks(a, s).mean(axis=(1, 3))


def _block_side(shape, max_px: int) -> int:
    return int(math.ceil(max(shape[:2]) / max(1, max_px)))


def _blocks(a: np.ndarray, s: int) -> np.ndarray:
    pad = [(0, -a.shape[0] % s), (0, -a.shape[1] % s)] + [(0, 0)] * (a.ndim - 2)
    a = np.pad(a, pad, mode="edge")
    return a.reshape(a.shape[0] // s, s, a.shape[1] // s, s, *a.shape[2:])


FLYOUT_RED = (0.86, 0.0, 0.0)  # the mask overlay's colour (opaque over the dimmed albedo)
FLYOUT_YELLOW = "#ffd400"


def flyout_figure(background, polylines_px, *, mask=None, texel_mm: float | None = None):
    """Fly-outs over the dimmed (sRGB) ``background`` ``(H, W[, 3])``: the mask ``(H, W)``
    (1 on fibre texels) as a red overlay in the left panel, the polylines (pixel ``[col, row]``,
    row 0 at the top) in yellow in the right one.  They are drawn apart because the detector's
    mask is its polylines rasterised: a line drawn over the mask would hide it.  The mask is
    block-max reduced to the panel's pixel size so that 1-texel fibres stay visible."""
    bg = np.asarray(background, dtype=np.float64)
    if bg.ndim == 2:
        bg = np.repeat(bg[..., None], 3, -1)
    h, w = bg.shape[:2]
    dim_full = 0.35 + 0.65 * srgb_encode(bg[..., :3]) * 0.8
    dim = display_copy(dim_full)
    panels = 2 if mask is not None else 1
    fig = figure(4.3 * panels + 0.3, 3.8)
    axes = list(np.atleast_1d(fig.subplots(1, panels)))
    ax_lines = axes[-1]
    n_mask = 0
    if mask is not None:
        ax = axes[0]
        ext = _frame(ax, h, w, texel_mm)
        m = np.asarray(mask, dtype=np.float64)
        m = (m[..., 0] if m.ndim == 3 else m) > 0.5
        n_mask = int(m.sum())
        # about the panel's width in pixels (4 inches at the save dpi): one display pixel per block
        px = max(64, int(3.2 * _plt().rcParams["savefig.dpi"]))
        shown = max_pool(m, px)
        over = np.where(shown[..., None], np.asarray(FLYOUT_RED), block_mean(dim_full, px))
        ax.imshow(over, extent=ext, interpolation="nearest")
        ax.set_title("fly-out mask (red)")
    ext = _frame(ax_lines, h, w, texel_mm)
    ax_lines.imshow(dim, extent=ext)
    for i, line in enumerate(polylines_px):
        p = np.asarray(line, float).reshape(-1, 2)
        x, y = _to_plot(p[:, 0], p[:, 1], h, texel_mm)
        ax_lines.plot(x, y, "-", color=FLYOUT_YELLOW, lw=1.6, label="fly-out" if i == 0 else None)
        ax_lines.plot(x, y, "-", color="k", lw=0.5)
    ax_lines.set_title("fly-out fibres (polylines)")
    if panels == 2:
        ax_lines.set_ylabel("")
    if len(polylines_px):
        ax_lines.legend(loc="upper right", fontsize=7, framealpha=0.8)
        cap = f"{len(polylines_px)} detected fly-out fibres over the albedo"
        cap += (f": left, the fly-out mask in red ({n_mask} texels); right, the fibres as yellow polylines."
                if mask is not None else " (yellow polylines).")
    else:
        cap = "No fly-out fibre was detected; the albedo is shown for reference."
    return fig, cap


def guidance_figure(guidance, box=None, *, texel_mm: float | None = None):
    """Guidance image (linear RGB, robust exposure, sRGB) with the micro field's box."""
    import matplotlib.patches as mpatches

    g = np.asarray(guidance, dtype=np.float64)[..., :3]
    ref = np.percentile(g.max(-1), ROBUST_PCT) if g.size else 1.0
    expo = 1.0 / ref if ref > 0 else 1.0
    fig, cap = rgb_image(g, title="guidance image", texel_mm=texel_mm, exposure=expo, size=(4.6, 3.8))
    ax = fig.axes[0]
    h = g.shape[0]
    if box is not None and len(box) == 4:
        x, y, bw, bh = (float(v) for v in box)
        t = texel_mm or 1.0
        if texel_mm:
            xy = (x * t, (h - y - bh) * t)
        else:
            xy = (x - 0.5, y - 0.5)
        ax.add_patch(mpatches.Rectangle(xy, bw * t, bh * t, fill=False, ec="#ff2d55", lw=1.5,
                                        label="micro field"))
        ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
        cap += " Red box: where the micro capture lies."
    return fig, cap



# ---------------------------------------------------------------------------------------------
# per-pixel uncertainty (issue 26): sigma maps, shared with the viewer (dualscale.view)

#: the colour map of a sigma image (perceptual, 0 = dark) and the flat colour of undetermined texels
SIGMA_CMAP = "viridis"
UNDETERMINED_RGB = (1.0, 0.0, 1.0)
UNDETERMINED_NAME = "magenta"
UNDETERMINED_HEX = "#ff00ff"
#: the short unit of each map's sigma on axes (the full one is ``SIGMA_UNITS`` of dualscale.formats.maps)
SIGMA_SHORT_UNITS = {"normal": "°", "tangent": "°", "ior": "η"}


def sigma_unit(name: str) -> str:
    """The axis unit of a map's sigma: degrees, eta, or the map's own (unitless) value."""
    return SIGMA_SHORT_UNITS.get(name, "map value")


def sigma_display(sigma, undetermined) -> tuple[np.ndarray, np.ndarray]:
    """One value per texel of a sigma ``(H, W, C)``: the largest of its channels, and the texels
    where any channel is undetermined (``(H, W)`` float, bool)."""
    s = np.asarray(sigma, dtype=np.float64)
    u = np.asarray(undetermined, bool)
    s = s[..., None] if s.ndim == 2 else s
    u = u[..., None] if u.ndim == 2 else u
    und = u.any(-1) | ~np.isfinite(s).all(-1)
    with np.errstate(invalid="ignore"):
        top = np.where(und, np.nan, np.nanmax(np.where(np.isfinite(s), s, -np.inf), axis=-1))
    return top, und


def sigma_range(values) -> Range:
    """The colour scale of a sigma image: 0 to the 99.5th percentile of the determined values."""
    return robust_range(values, None, ROBUST_PCT, vmin=0.0)


def sigma_colours(values, undetermined, vmax: float) -> np.ndarray:
    """``(H, W, 3)`` display RGB in [0, 1] (already display-encoded: no transfer curve) of a
    sigma image on 0..``vmax`` in :data:`SIGMA_CMAP`, undetermined texels in
    :data:`UNDETERMINED_RGB`.  The report's figures and the viewer's PNG use this one mapping."""
    import matplotlib

    cmap = matplotlib.colormaps[SIGMA_CMAP]
    a = np.asarray(values, dtype=np.float64)
    t = np.clip(np.nan_to_num(a / vmax if vmax > 0 else a * 0.0), 0.0, 1.0)
    rgb = cmap(t)[..., :3]
    rgb[np.asarray(undetermined, bool)] = UNDETERMINED_RGB
    return rgb


#: the sigma histogram turns to a log axis when the 1st percentile of sigma is below the colour
#: scale's top over this (a noise-free fit's sigma, or a fly-out fibre's, spans decades)
LOG_SPAN = 100.0


def sigma_figure(name: str, sigma, undetermined, *, units: str = "", error=None, texel_mm: float | None = None):
    """The sigma of one map: its image (largest channel per texel, :data:`SIGMA_CMAP` from 0,
    undetermined texels in :data:`UNDETERMINED_NAME`, colour bar in the map's sigma unit), the
    absolute error against ground truth on the same scale when ``error`` ``(H, W, C)`` is given,
    and a histogram of sigma over the determined texels per channel with the medians marked.
    Returns ``(fig, caption)``."""
    from matplotlib.patches import Patch

    s = np.asarray(sigma, dtype=np.float64)
    s = s[..., None] if s.ndim == 2 else s
    u = np.asarray(undetermined, bool)
    u = u[..., None] if u.ndim == 2 else u
    top, und = sigma_display(s, u)
    r = sigma_range(top)
    unit = sigma_unit(name)
    label = f"1σ [{unit}]"
    panels = 3 if error is not None else 2
    fig = figure(3.9 * panels + 0.4, 3.4)
    axes = list(fig.subplots(1, panels, width_ratios=[1.15] * (panels - 1) + [1.0]))
    h, w = top.shape
    title = MAP_TITLES.get(name, name)
    ax = axes[0]
    ext = _frame(ax, h, w, texel_mm)
    ax.imshow(display_copy(sigma_colours(top, und, r.vmax)), extent=ext)
    sm = _plt().cm.ScalarMappable(cmap=SIGMA_CMAP, norm=_plt().Normalize(r.vmin, r.vmax))
    _colorbar(fig, sm, ax, label, r.extend)
    ax.set_title(f"σ of {title}")
    if und.any():
        ax.legend(handles=[Patch(facecolor=UNDETERMINED_RGB, edgecolor="0.3", label="undetermined")],
                  loc="upper right", fontsize=7, framealpha=0.85)
    cap = (f"1σ of the {title} in {units or unit}"
           + (" (the largest of its channels per texel)" if s.shape[2] > 1 else "")
           + f"; colour scale 0 to {fmt.quantity(r.vmax, '' if unit == 'map value' else unit)}, "
           f"undetermined texels in {UNDETERMINED_NAME} ({fmt.percent(float(und.mean()), 2)} of texels).")
    note = clip_note(r, "" if unit == "map value" else unit)
    if note:
        cap += " " + note
    if error is not None:
        e = np.asarray(error, dtype=np.float64)
        e = e[..., None] if e.ndim == 2 else e
        etop = np.nanmax(np.where(np.isfinite(e), e, -np.inf), axis=-1)
        etop = np.where(np.isfinite(etop), etop, np.nan)
        ax = axes[1]
        ext = _frame(ax, h, w, texel_mm)
        ax.imshow(display_copy(sigma_colours(etop, ~np.isfinite(etop), r.vmax)), extent=ext)
        er = robust_range(etop, None, 100.0, vmin=r.vmin, vmax=r.vmax)
        _colorbar(fig, sm, ax, f"|error| [{unit}]", er.extend)
        ax.set_title(f"|fit − truth|, {title}")
        ax.set_ylabel("")
        cap += (" Middle: |fitted − ground truth| on the same colour scale"
                + (", the largest channel" if e.shape[2] > 1 else "") + ".")
    ax = axes[-1]
    colours = ("#d62728", "#2ca02c", "#1f77b4") if s.shape[2] == 3 else ("#4c78a8",)
    names = ("R", "G", "B") if s.shape[2] == 3 else ("",)
    medians = []
    hi = r.vmax if r.vmax > 0 else 1.0
    det = s[~u & np.isfinite(s) & (s > 0)]
    lo = float(np.percentile(det, 1)) if det.size else 0.0
    log = det.size > 0 and 0 < lo < hi / LOG_SPAN  # a heavy tail: most texels would share the first bin
    bins = np.geomspace(lo, hi, 41) if log else np.linspace(0.0, hi, 41)
    for c in range(s.shape[2]):
        v = s[..., c][~u[..., c] & np.isfinite(s[..., c])]
        if not v.size:
            medians.append(None)
            continue
        med = float(np.median(v))
        medians.append(med)
        ax.hist(np.clip(v, bins[0], hi), bins=bins, histtype="step", color=colours[c], lw=1.2,
                label=f"{names[c]} median {fmt.number(med)}".strip())
        ax.axvline(med, color=colours[c], ls="--", lw=1.0)
    if log:
        ax.set_xscale("log")
    ax.set_xlabel(label)
    ax.set_ylabel("texels")
    ax.set_title("σ over the determined texels")
    ax.spines[["top", "right"]].set_visible(False)
    if any(m is not None for m in medians):
        ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
        cap += (" Right: histogram of σ over the determined texels"
                + (" per channel" if s.shape[2] > 1 else "") + ", dashed lines at the median"
                + (f", on a log axis (σ spans {np.log10(hi / lo):.0f} decades; values below "
                   f"{fmt.number(lo)} counted in the first bin)" if log else "")
                + (f" (values above {fmt.number(hi)} counted in the last bin)" if r.above > 0 else "") + ".")
    else:
        ax.text(0.5, 0.5, "every texel undetermined", ha="center", va="center", transform=ax.transAxes)
    return fig, cap


def sigma_colorbar(width: int = 256, height: int = 12) -> np.ndarray:
    """The colour bar of :data:`SIGMA_CMAP`, 0 on the left, ``(height, width, 3)`` in [0, 1]."""
    row = sigma_colours(np.linspace(0.0, 1.0, width)[None, :], np.zeros((1, width), bool), 1.0)
    return np.repeat(row, height, 0)


def settle(fig) -> None:
    """Draw twice: constrained layout moves labels once more after the ticks (and a ×10ⁿ
    offset) are known, and the saved image must be the settled one."""
    fig.canvas.draw()
    fig.canvas.draw()


def _drawn_texts(fig):
    """The texts a reader sees: titles, axis labels, tick labels inside the view, annotations,
    legend entries and figure texts (each once)."""
    seen, out = set(), []

    def add(t):
        if id(t) in seen or not t.get_visible() or not t.get_text().strip():
            return
        seen.add(id(t))
        out.append(t)

    for t in fig.texts:
        add(t)
    if getattr(fig, "_suptitle", None) is not None:
        add(fig._suptitle)
    for ax in fig.axes:
        if not ax.get_visible():
            continue
        for t in (ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label,
                  ax.xaxis.offsetText, ax.yaxis.offsetText, *ax.texts):
            add(t)
        for axis, lim in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
            lo, hi = min(lim), max(lim)
            span = hi - lo
            for tick in axis.get_major_ticks():
                loc = tick.get_loc()
                if ax.name == "polar" and axis is ax.xaxis or lo - 1e-9 * span <= loc <= hi + 1e-9 * span:
                    for lab in (tick.label1, tick.label2):
                        if lab.get_visible():
                            add(lab)
        leg = ax.get_legend()
        if leg is not None:
            for t in leg.get_texts():
                add(t)
    return out


def overlapping_texts(fig, tol_px: float = 1.0) -> list[tuple[str, str]]:
    """Pairs of drawn texts of ``fig`` whose boxes overlap by more than ``tol_px`` pixels each
    way, plus texts that stick out of the figure. Used by the tests to keep labels apart."""
    settle(fig)
    rnd = fig.canvas.get_renderer()
    W, H = fig.canvas.get_width_height()
    boxes = [(t.get_text(), t.get_window_extent(rnd)) for t in _drawn_texts(fig)]
    out = []
    for text, bb in boxes:
        if bb.x0 < -tol_px or bb.y0 < -tol_px or bb.x1 > W + tol_px or bb.y1 > H + tol_px:
            out.append((text, "<figure edge>"))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            a, b = boxes[i][1], boxes[j][1]
            if min(a.x1, b.x1) - max(a.x0, b.x0) > tol_px and min(a.y1, b.y1) - max(a.y0, b.y0) > tol_px:
                out.append((boxes[i][0], boxes[j][0]))
    return out


__all__ = ["Range", "robust_range", "clip_note", "srgb_encode", "luminance", "display_copy", "figure",
           "scalar_image", "rgb_image", "normal_image", "map_figure", "residual_figure", "heldout_figure",
           "hemisphere", "hemisphere_norm", "hemisphere_figure", "time_bars", "flyout_figure", "max_pool", "block_mean",
           "guidance_figure", "overlapping_texts", "MAP_TITLES", "UNIT_RANGE_MAPS", "SIGMA_CMAP", "UNDETERMINED_RGB",
           "UNDETERMINED_NAME", "UNDETERMINED_HEX", "sigma_unit", "sigma_display", "sigma_range", "sigma_colours",
           "sigma_figure", "sigma_colorbar"]
