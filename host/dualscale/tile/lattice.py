"""Find the repeat of a periodic weave or knit: the two primitive lattice vectors of a map, from
the peaks of its normalised autocorrelation (computed by FFT), refined to sub-texel accuracy.

Issue 12 Sec. 2 ("find the repeat").  The method:

1. **Signal.**  A single-channel image ``(H, W)``: the albedo's luminance by default (Rec.709
   weights on linear RGB), or the normal's x or y, or any guidance image.  Slow shading (a
   Gaussian of sigma ``min(H, W) / 8``) is subtracted and the result is scaled to unit variance.
2. **Autocorrelation.**  ``rho(s) = sum f(x) f(x + s) / (N(s) var)`` over the ``N(s)`` texel
   pairs that overlap at shift ``s`` (zero-padded FFT, so no wrap-around), for shifts up to half
   the field on each axis: a lattice vector found there repeats at least twice in the field.
2b. **Finer grid** (issue 24 Sec. 6).  When the finest basis of a first pass (steps 3-5) is
   shorter than :data:`FINE_BELOW_PX` texels, its peaks fall between the texel samples and the
   local maxima lock onto them (a twill photo's (1.24, 2.57) came out as (1, 2)); steps 3-5 run
   again on ``rho`` evaluated exactly on a grid 2-8 times finer (:func:`autocorrelation_fine`,
   a matrix DFT of the padded spectrum) in a window of a few dozen texels, where only
   sub-lattices that fit :data:`FINE_SUBLATTICE_FIT` times in the window are considered.
3. **Peaks.**  Local maxima of ``rho`` (``skimage.feature.peak_local_max``) refined to sub-texel
   position by a least-squares quadratic fit over their 3 x 3 neighbourhood.
4. **Basis.**  The strongest peak sets the scale; peaks within ``strong`` (0.5) of its height are
   the *lattice candidates*.  The first vector is the shortest candidate, the second the shortest
   one not parallel to it (angle above 15 deg); the pair is Lagrange-Gauss reduced.  Weaker
   peaks (one yarn pitch in a twill, where half the floats match) are not lattice vectors: a
   shift by a true lattice vector maps the weave onto itself, so its peak is as high as the
   best one, up to noise.
4b. **Weave sub-lattice.**  A shift by one yarn also correlates (the yarns repeat every pitch),
   so every sub-lattice of index 2 .. ``max_index`` of the finest basis is scored: mean ``rho``
   on its points minus that on the other points, leaving out the two lattice lines through the
   origin along the finest vectors (a yarn keeps its own shade along its length, which raises
   ``rho`` along those lines for any sub-lattice containing one).  Taken when that contrast is
   at least ``min_contrast`` (0.01) and 5 standard errors (``_best_sublattice``).
5. **Least squares.**  Every lattice point ``n1 v1 + n2 v2`` inside the search window is
   re-located on ``rho`` (the local maximum within a third of the shorter vector, refined as in
   3), and the basis is the least-squares fit ``p = B n`` over those points, weighted by
   their ``rho``; then reduced again.
6. **Strength.**  ``strength`` = mean ``rho`` at the lattice points minus mean ``rho`` half way
   between them (``B (n + 1/2)``): about 1 for a clean periodic map, about 0 for a random
   texture.  Below ``min_strength`` (0.3) :class:`NoRepeatError` is raised, as it is when no
   candidate pair exists (no repeat, or fewer than two repeats in the field), and when a
   basis vector ``v`` is not a repeat of its own (``rho`` at ``v`` and ``2 v`` exceeds ``rho`` at
   ``1.5 v`` by less than ``min_step``, 0.05):
   a 1-D pattern (stripes, or twill lines whose repeat along the line is not resolved) has a
   ridge of high ``rho`` along its lines, with local maxima locked to the texel grid.

Coordinates: vectors in texels are ``(dcol, drow)`` (image axes: +col right, +row down, row 0
at the top); in mm they are ``(x, y)`` in the maps' frame (+x image right, +y image up,
:data:`dualscale.formats.maps.CONVENTIONS`), i.e. ``(dcol * t, -drow * t)``.  Each vector is
canonicalised to ``dcol > 0`` (or ``dcol == 0`` and ``drow > 0``): a lattice vector and its
negative are the same repeat.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from dualscale.bsdf import MaterialMaps
from dualscale.errors import InputError

SOURCES = ("all", "albedo", "normal_x", "normal_y")
LUMA = np.array([0.2126, 0.7152, 0.0722])
FINE_BELOW_PX = 12.0  # a finest period shorter than this is searched again on a finer grid (step 2b)
MAX_FACTOR = 8  # the finer grid's samples per texel, at most
MAX_FINE_WINDOW = 601  # samples per side of the finer autocorrelation window, at most
FINE_MIN_RADIUS_PX = 32.0  # its half-width in texels: at least this,
FINE_RADIUS_PERIODS = 8.0  # and this many of the longest first-pass vectors (within the field's half)
FINE_SUBLATTICE_FIT = 2.5  # a repeat searched there fits this many times in the half-width


class NoRepeatError(InputError):
    """The map shows no periodic repeat, or fewer than two repeats fit in its field."""


@dataclass(frozen=True)
class Lattice:
    """A periodic repeat.  ``vectors_px``: ``(2, 2)`` rows ``v1, v2`` in texels ``(dcol, drow)``,
    Lagrange-Gauss reduced (``|v1| <= |v2|``, ``|v1 . v2| <= |v1|^2 / 2``); ``texel_mm``: the
    texel size (``None`` when unknown); ``strength``: periodicity strength in [-1, 1] (see the
    module docstring); ``residual_px``: RMS distance of the re-located lattice peaks from the
    least-squares basis; ``points``: how many lattice peaks the least squares used;
    ``source``: the signal it was found on; ``shape``: the ``(H, W)`` of the field."""

    vectors_px: np.ndarray
    texel_mm: float | None
    strength: float
    residual_px: float
    points: int
    source: str
    shape: tuple[int, int]
    extra: dict = field(default_factory=dict)

    @property
    def vectors_mm(self) -> np.ndarray | None:
        """``(2, 2)`` rows in mm, ``(x, y)`` with +y up; ``None`` when the texel size is unknown."""
        if self.texel_mm is None:
            return None
        return self.vectors_px * np.array([1.0, -1.0]) * self.texel_mm

    @property
    def periods_px(self) -> np.ndarray:
        """Lengths ``|v1|, |v2|`` in texels."""
        return np.linalg.norm(self.vectors_px, axis=1)

    @property
    def line_spacing_px(self) -> float:
        """Distance in texels between the lattice's densest rows of points (the lines along
        ``v1``): ``|det B| / |v1|``; for a twill, the spacing of its diagonal lines."""
        return self.cell_area_px / float(np.linalg.norm(self.vectors_px[0]))

    @property
    def cell_area_px(self) -> float:
        """Area of one repeat in texels^2 (``|det B|``)."""
        return float(abs(np.linalg.det(self.vectors_px)))

    def meta(self) -> dict:
        """JSON-able description (texels and mm; mm entries ``None`` when the size is unknown)."""
        mm = self.vectors_mm
        return {"vectors_px": self.vectors_px.round(4).tolist(),
                "vectors_mm": None if mm is None else mm.round(6).tolist(),
                "periods_px": self.periods_px.round(4).tolist(),
                "line_spacing_px": round(self.line_spacing_px, 4), "strength": round(self.strength, 4), "residual_px": round(self.residual_px, 4),
                "points": self.points, "source": self.source, "texel_mm": self.texel_mm}


def signal_from_maps(maps: MaterialMaps, source: str = "albedo") -> np.ndarray:
    """The ``(H, W)`` float64 signal of ``maps`` to search: ``albedo`` (luminance),
    ``normal_x`` or ``normal_y``.  :class:`~dualscale.errors.InputError` if the map is absent."""
    if source == "albedo":
        return np.asarray(maps.albedo.detach().cpu().numpy(), np.float64) @ LUMA
    if source in ("normal_x", "normal_y"):
        if maps.normal is None:
            raise InputError(f"source {source}: the maps have no normal map")
        return np.asarray(maps.normal.detach().cpu().numpy()[..., 0 if source == "normal_x" else 1], np.float64)
    raise InputError(f"unknown source {source!r}; choose from {', '.join(SOURCES)} or pass an image")


def signals_from_maps(maps: MaterialMaps, source: str = "all") -> list[np.ndarray]:
    """The signals searched for ``source``: ``all`` = albedo luminance plus the normal's x and y
    when there is a normal map (a repeat of the material must repeat in every one: a rib knit's
    albedo repeats every wale, its relief every two), else the one named."""
    if source == "all":
        names = ["albedo"] + (["normal_x", "normal_y"] if maps.normal is not None else [])
        return [signal_from_maps(maps, n) for n in names]
    return [signal_from_maps(maps, source)]


def to_signal(image: np.ndarray) -> np.ndarray:
    """An ``(H, W)`` or ``(H, W, C)`` image as an ``(H, W)`` float64 signal (RGB: luminance;
    other channel counts: the channel mean)."""
    a = np.asarray(image, np.float64)
    if a.ndim == 3:
        a = a @ LUMA if a.shape[-1] == 3 else a.mean(-1)
    if a.ndim != 2:
        raise InputError(f"the repeat is searched on an (H, W) or (H, W, C) image, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError("the image for the repeat search has non-finite values")
    return a


def _padded_power(signal: np.ndarray, detrend_frac: float = 1 / 8) -> tuple[np.ndarray, float]:
    """The power spectrum (``rfft2``, zero-padded to ``(2 H, 2 W)``) of ``signal`` with slow
    shading removed and the mean subtracted, and the signal's variance."""
    h, w = signal.shape
    f = signal - ndimage.gaussian_filter(signal, detrend_frac * min(h, w), mode="reflect")
    f = f - f.mean()
    var = float((f * f).mean())
    if var <= 1e-20:
        raise NoRepeatError("the map is uniform: no repeat to find")
    F = np.fft.rfft2(f, (2 * h, 2 * w))
    return (F * np.conj(F)).real, var


def autocorrelation(signal: np.ndarray, detrend_frac: float = 1 / 8) -> np.ndarray:
    """Normalised autocorrelation of ``signal`` ``(H, W)``; returns ``(2 * (H // 2) + 1,
    2 * (W // 2) + 1)`` with shift ``(0, 0)`` at the centre (``rho = 1`` there), shifts
    ``(drow, dcol)`` up to half the field.  Zero-padded FFT, divided by the overlap count."""
    h, w = signal.shape
    P, var = _padded_power(signal, detrend_frac)
    ph, pw = 2 * h, 2 * w
    ac = np.fft.irfft2(P, (ph, pw))
    ones = np.fft.rfft2(np.ones_like(signal), (ph, pw))
    cnt = np.fft.irfft2(ones * np.conj(ones), (ph, pw))
    ac = np.fft.fftshift(ac)
    cnt = np.fft.fftshift(cnt)
    hh, hw = h // 2, w // 2
    sl = (slice(h - hh, h + hh + 1), slice(w - hw, w + hw + 1))
    return ac[sl] / (np.maximum(cnt[sl], 1.0) * var)


def autocorrelation_fine(signal: np.ndarray, radius_px: float, factor: int, detrend_frac: float = 1 / 8
                         ) -> np.ndarray:
    """The normalised autocorrelation of :func:`autocorrelation` on a grid ``factor`` times
    finer, for shifts up to ``radius_px`` on each axis: ``(2 n + 1, 2 n + 1)`` with ``n =
    round(radius_px * factor)``, shift ``(0, 0)`` at the centre, sample ``k`` at shift ``(k - n)
    / factor`` texels.

    The zero-padded autocorrelation is a finite trigonometric sum over the padded spectrum, so
    it is evaluated exactly at fractional shifts (the band-limited interpolation of its texel
    samples) by a matrix DFT restricted to the window: the upsampled DFT of Guizar-Sicairos,
    Thurman and Fienup (Opt. Lett. 33, 2008), which ``skimage.registration.
    phase_cross_correlation`` uses for its sub-pixel peak.  The overlap count ``(H - |drow|)
    (W - |dcol|)`` is exact at any shift."""
    h, w = signal.shape
    P, var = _padded_power(signal, detrend_frac)
    ph, pw = 2 * h, 2 * w
    n = int(round(radius_px * factor))
    s = np.arange(-n, n + 1) / factor
    fy, fx = np.fft.fftfreq(ph), np.fft.rfftfreq(pw)
    weight = np.full(fx.size, 2.0)  # the half spectrum stands for its conjugate half
    weight[0] = 1.0
    if pw % 2 == 0:
        weight[-1] = 1.0
    e_row = np.exp(2j * np.pi * np.outer(s, fy))
    e_col = np.exp(2j * np.pi * np.outer(fx, s))
    ac = ((e_row @ (P * weight)) @ e_col).real / (ph * pw)
    cnt = np.outer(h - np.abs(s), w - np.abs(s))
    return ac / (cnt * var)


def refine_peak(ac: np.ndarray, r: int, c: int) -> tuple[float, float, float]:
    """Sub-texel ``(row, col, value)`` of a peak at integer ``(r, c)``: least-squares quadratic
    ``a + b x + c y + d x^2 + e x y + f y^2`` over the 3 x 3 neighbourhood, its stationary point
    (clamped to +-1 texel; the integer position if the fit is not a maximum)."""
    h, w = ac.shape
    if not (1 <= r < h - 1 and 1 <= c < w - 1):
        return float(r), float(c), float(ac[r, c])
    yy, xx = np.mgrid[-1:2, -1:2]
    x, y = xx.ravel().astype(float), yy.ravel().astype(float)
    A = np.stack([np.ones(9), x, y, x * x, x * y, y * y], 1)
    coef = np.linalg.lstsq(A, ac[r - 1:r + 2, c - 1:c + 2].ravel(), rcond=None)[0]
    _, bx, by, dxx, exy, fyy = coef
    H = np.array([[2 * dxx, exy], [exy, 2 * fyy]])
    if np.linalg.det(H) <= 0 or H[0, 0] >= 0:
        return float(r), float(c), float(ac[r, c])
    dx, dy = np.clip(np.linalg.solve(H, [-bx, -by]), -1, 1)
    val = float(coef @ [1, dx, dy, dx * dx, dx * dy, dy * dy])
    return r + float(dy), c + float(dx), val


def reduce_basis(b: np.ndarray) -> np.ndarray:
    """Lagrange-Gauss reduction of a 2-D lattice basis (rows); returns ``(2, 2)`` with
    ``|v1| <= |v2|`` and ``|v1 . v2| <= |v1|^2 / 2``, each canonicalised (``dcol > 0``)."""
    u, v = np.asarray(b[0], float), np.asarray(b[1], float)
    if u @ u > v @ v:
        u, v = v, u
    for _ in range(100):
        m = round(float(u @ v) / float(u @ u))
        v = v - m * u
        if v @ v >= u @ u:
            break
        u, v = v, u
    return np.stack([_canonical(u), _canonical(v)])


def _canonical(v: np.ndarray) -> np.ndarray:
    tol = 1e-3 * float(np.hypot(*v))
    return -v if (v[0] < -tol or (abs(v[0]) <= tol and v[1] < 0)) else v


def find_lattice(image_or_maps, texel_mm: float | None = None, source: str = "all", strong: float = 0.5,
                 min_strength: float = 0.3, min_period_px: float = 2.0, max_index: int = 12,
                 min_contrast: float = 0.01, min_step: float = 0.05) -> Lattice:
    """The primitive lattice of a periodic map (see the module docstring for the method).

    ``image_or_maps``: a :class:`~dualscale.bsdf.MaterialMaps` (searched on ``source``:
    ``all`` -- the mean autocorrelation of the albedo luminance and, when present, the normal's
    x and y --, ``albedo``, ``normal_x`` or ``normal_y``) or an ``(H, W[, C])`` array (a guidance
    image or photo; RGB is reduced to luminance).  ``texel_mm``: texel size in mm, or ``None``
    (then the lattice is known in texels only).  ``strong``: fraction of the best peak's
    autocorrelation a lattice candidate must reach; ``min_strength``: refusal threshold;
    ``min_period_px``: shorter shifts are ignored (the texel-scale correlation of any image);
    ``max_index``, ``min_contrast``: the weave sub-lattices searched and the contrast one needs
    (module step 4b); ``min_step``: the 1-D test of step 6.

    Raises :class:`NoRepeatError` (an ``InputError``, exit 2) when no repeat is found or fewer
    than two repeats fit in the field, :class:`~dualscale.errors.InputError` for a bad input.
    """
    if isinstance(image_or_maps, MaterialMaps):
        sigs = signals_from_maps(image_or_maps, source)
    else:
        sigs = [to_signal(image_or_maps)]
        source = "image"
    h, w = sigs[0].shape
    if min(h, w) < 16:
        raise NoRepeatError(f"the field is {w} x {h} texels: too small to find a repeat (at least 16 x 16)")
    if texel_mm is not None and not (np.isfinite(texel_mm) and texel_mm > 0):
        raise InputError(f"texel_mm must be a positive number of mm, got {texel_mm!r}")
    acs, kept = [], []
    for sig in sigs:
        try:
            acs.append(autocorrelation(sig))
            kept.append(sig)
        except NoRepeatError:
            continue  # a uniform map (flat normals) carries no repeat: the others decide
    if not acs:
        raise NoRepeatError(f"the {w} x {h} map is uniform: no repeat to find")
    ac = np.mean(acs, axis=0)
    found = _search(ac, strong, min_period_px, max_index, min_contrast)
    if found is None:
        raise NoRepeatError(f"no repeat found in the {w} x {h} field: no two independent autocorrelation peaks "
                            "(no periodic pattern, or fewer than two repeats in the field)")
    coarse = found
    factor, radius = 1, None
    finest = float(np.linalg.norm(coarse["finest"], axis=1).min())
    if finest < FINE_BELOW_PX:
        # module step 2b: a period of a few texels is sampled too coarsely by the texel grid
        # (the peaks fall between the samples and lock onto them): search again on the
        # autocorrelation evaluated on a finer grid
        factor = int(min(MAX_FACTOR, max(2, np.ceil(FINE_BELOW_PX / finest))))
        longest = float(np.linalg.norm(coarse["B"], axis=1).max())
        radius = float(min(h // 2, w // 2, (MAX_FINE_WINDOW // 2) / factor,
                           max(FINE_MIN_RADIUS_PX, FINE_RADIUS_PERIODS * longest)))
        acf = np.mean([autocorrelation_fine(sig, radius, factor) for sig in kept], axis=0)
        fine = _search(acf, strong, min_period_px * factor, max_index, min_contrast,
                       max_len=radius * factor / FINE_SUBLATTICE_FIT)
        if fine is not None:
            found, ac = fine, acf
        else:
            factor, radius = 1, None
    B = found["B"]
    strength = _strength(ac, B)
    Bpx = B / factor
    if strength < min_strength:
        raise NoRepeatError(f"no clear repeat in the {w} x {h} field: periodicity strength {strength:.2f} < "
                            f"{min_strength} (best candidate vectors {Bpx[0].round(1).tolist()}, "
                            f"{Bpx[1].round(1).tolist()} texels)")
    for v in B:  # each vector must be a repeat, not a point on a ridge of a 1-D (stripe) pattern
        on, half = _step(ac, v)
        if on - half < min_step:
            v = v / factor
            raise NoRepeatError(f"no two-dimensional repeat in the {w} x {h} field: the pattern repeats along one "
                                f"direction only (stripes, or twill lines whose repeat along the line is not "
                                f"resolved; autocorrelation {on:.2f} at ({v[0]:.2f}, {v[1]:.2f}) texels and its "
                                f"multiples, {half:.2f} half way between)")
    if abs(Bpx[:, 0]).max() * 2 > w or abs(Bpx[:, 1]).max() * 2 > h:
        raise NoRepeatError(f"the repeat ({Bpx[0].round(1).tolist()}, {Bpx[1].round(1).tolist()} texels) fits fewer "
                            f"than twice in the {w} x {h} field")
    extra = {"finest_px": (found["finest"] / factor).round(4).tolist(), "sublattice_index": found["index"],
             "sublattice_contrast": round(found["contrast"], 4), "grid_factor": factor,
             "grid_window_px": None if radius is None else round(radius, 3)}
    if factor > 1:
        extra["texel_grid_px"] = coarse["B"].round(4).tolist()  # the first pass, on the texel grid
    return Lattice(Bpx, None if texel_mm is None else float(texel_mm), float(strength),
                   float(found["resid"]) / factor, int(found["points"]), source, (h, w), extra)


def _search(ac: np.ndarray, strong: float, min_period: float, max_index: int, min_contrast: float,
            max_len: float | None = None) -> dict | None:
    """Module steps 4-5 on an autocorrelation window ``ac`` (in its own sample units): the finest
    basis, the weave's sub-lattice (vectors up to ``max_len``), the least-squares basis; ``None``
    without two peaks."""
    B0 = _autocorrelation_basis(ac, strong, min_period)
    if B0 is None:
        return None
    B0 = reduce_basis(_refine(ac, B0)[0])
    B, index, contrast = _best_sublattice(ac, B0, max_index, min_contrast, max_len=max_len)
    B, pts, resid = _refine(ac, reduce_basis(B))
    return {"B": reduce_basis(B), "finest": B0, "index": index, "contrast": float(contrast), "points": pts,
            "resid": resid}


def spectral_peaks(sig: np.ndarray, min_period_px: float = 2.0, min_ratio: float = 8.0,
                   detrend_frac: float = 1 / 8) -> np.ndarray:
    """Significant peaks of the power spectrum of ``sig`` ``(H, W)``: rows ``(fx, fy, ratio)``
    in cycles per texel (``fx`` along columns, ``fy`` along rows), one of each ``+-`` pair,
    strongest first.  ``ratio``: the peak's power (3 x 3 mean) over the local median (15 x 15
    median filter), at least ``min_ratio``; positions refined by a parabola through the log
    power of the bins either side on each axis.  Hann window, slow shading removed."""
    from skimage.feature import peak_local_max

    h, w = sig.shape
    f = sig - ndimage.gaussian_filter(sig, detrend_frac * min(h, w), mode="reflect")
    f = (f - f.mean()) * np.outer(np.hanning(h), np.hanning(w))
    P = np.abs(np.fft.fftshift(np.fft.fft2(f))) ** 2 + 1e-30
    ratio = ndimage.uniform_filter(P, 3) / (ndimage.median_filter(P, 15) + 1e-30)
    cy, cx = h // 2, w // 2
    lp = np.log(P)
    out = []
    for r, c in peak_local_max(ratio, min_distance=2, threshold_abs=min_ratio, exclude_border=1):
        # the strongest bin of the 3 x 3 block, then a parabola per axis
        blk = P[r - 1:r + 2, c - 1:c + 2]
        dr, dc = np.unravel_index(int(np.argmax(blk)), blk.shape)
        r, c = r - 1 + dr, c - 1 + dc
        if not (1 <= r < h - 1 and 1 <= c < w - 1):
            continue
        sub = []
        for lo, mid, hi in ((lp[r, c - 1], lp[r, c], lp[r, c + 1]), (lp[r - 1, c], lp[r, c], lp[r + 1, c])):
            den = lo - 2 * mid + hi
            sub.append(float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) if den < 0 else 0.0)
        fx, fy = (c + sub[0] - cx) / w, (r + sub[1] - cy) / h
        if np.hypot(fx, fy) * min_period_px > 1 or np.hypot(fx * w, fy * h) < 1.5:
            continue
        if fy < 0 or (fy == 0 and fx < 0):
            continue
        out.append((fx, fy, float(ratio[r, c])))
    out.sort(key=lambda t: -t[2])
    return np.array(out, float).reshape(-1, 3)


def dominant_period(image: np.ndarray, min_period_px: float = 2.0) -> tuple[float, float]:
    """The strongest periodic component of an image: ``(period_px, angle_deg)`` -- the
    wavelength in texels of the highest spectral peak (:func:`spectral_peaks`) and the
    direction of its wave vector, degrees in [0, 180) CCW from +col with rows up.  For a twill, the spacing
    of its diagonal lines.  :class:`NoRepeatError` without a significant peak."""
    pk = spectral_peaks(to_signal(image), min_period_px)
    if not len(pk):
        raise NoRepeatError("no periodic component in the image's spectrum")
    fx, fy, _ = pk[0]
    return float(1 / np.hypot(fx, fy)), float(np.degrees(np.arctan2(-fy, fx)) % 180.0)


def _lattice_points(ac: np.ndarray, B: np.ndarray, offset: float = 0.0, margin: float = 2.0):
    """Integer pairs ``n`` (and positions ``B^T (n + offset)`` as ``(dcol, drow)``) inside the
    autocorrelation window, origin excluded, one of each ``+-`` pair."""
    cy, cx = np.array(ac.shape) // 2
    lim = np.array([cx - margin, cy - margin])
    inv = np.linalg.inv(B.T)
    corners = np.array([[lim[0], lim[1]], [-lim[0], lim[1]], [lim[0], -lim[1]], [-lim[0], -lim[1]]])
    nmax = np.ceil(np.abs(corners @ inv.T).max(0)).astype(int) + 1
    n1, n2 = np.meshgrid(np.arange(-nmax[0], nmax[0] + 1), np.arange(-nmax[1], nmax[1] + 1))
    n = np.stack([n1.ravel(), n2.ravel()], 1).astype(float) + offset
    p = n @ B
    keep = (np.abs(p[:, 0]) <= lim[0]) & (np.abs(p[:, 1]) <= lim[1]) & (np.hypot(*p.T) > 1e-6)
    keep &= (p[:, 0] > 1e-9) | ((np.abs(p[:, 0]) <= 1e-9) & (p[:, 1] > 0))
    return n[keep], p[keep]


def _autocorrelation_basis(ac: np.ndarray, strong: float, min_period_px: float) -> np.ndarray | None:
    """Module step 4: the reduced pair of the shortest strong autocorrelation peaks, or ``None``."""
    from skimage.feature import peak_local_max

    cy, cx = np.array(ac.shape) // 2
    peaks = []
    for r, c in peak_local_max(ac, min_distance=1, threshold_abs=0.05, exclude_border=1):
        if np.hypot(r - cy, c - cx) < min_period_px:
            continue
        rr, cc, val = refine_peak(ac, int(r), int(c))
        peaks.append((cc - cx, rr - cy, val))
    peaks = np.array(peaks, float).reshape(-1, 3)
    peaks = peaks[(peaks[:, 0] > 1e-9) | ((np.abs(peaks[:, 0]) <= 1e-9) & (peaks[:, 1] > 0))]  # one of +-v
    if len(peaks) < 2:
        return None
    cand = peaks[peaks[:, 2] >= strong * peaks[:, 2].max()]
    cand = cand[np.argsort(np.hypot(cand[:, 0], cand[:, 1]))]
    v1 = cand[0, :2]
    for p in cand[1:]:
        cross = abs(v1[0] * p[1] - v1[1] * p[0]) / (np.linalg.norm(v1) * np.linalg.norm(p[:2]))
        if cross > np.sin(np.radians(15)):
            return reduce_basis(np.stack([v1, p[:2]]))
    return None


def _relocate(ac: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every lattice point ``n`` of ``B`` in the window, re-located on ``rho``: the local maximum
    within a third of the shorter vector of ``B n``, refined (module step 3).  Returns ``(n,
    p, rho)``; a point whose maximum lies on the search window's edge (no peak there) keeps the
    predicted position and the interpolated ``rho`` and is flagged by ``rho`` only."""
    cy, cx = np.array(ac.shape) // 2
    n, p = _lattice_points(ac, B)
    reach = max(1, int(min(np.linalg.norm(B, axis=1)) / 3))
    out_p, out_v = p.copy(), np.empty(len(p))
    for k, pi in enumerate(p):
        c0, r0 = int(round(pi[0] + cx)), int(round(pi[1] + cy))
        r_lo, r_hi = max(1, r0 - reach), min(ac.shape[0] - 1, r0 + reach + 1)
        c_lo, c_hi = max(1, c0 - reach), min(ac.shape[1] - 1, c0 + reach + 1)
        out_v[k] = ndimage.map_coordinates(ac, [[pi[1] + cy], [pi[0] + cx]], order=1)[0]
        if r_lo >= r_hi or c_lo >= c_hi:
            continue
        win = ac[r_lo:r_hi, c_lo:c_hi]
        rr, cc = np.unravel_index(int(np.argmax(win)), win.shape)
        if 0 < rr < win.shape[0] - 1 and 0 < cc < win.shape[1] - 1:
            ry, rx, val = refine_peak(ac, rr + r_lo, cc + c_lo)
            out_p[k] = (rx - cx, ry - cy)
            out_v[k] = val
    return n, out_p, out_v


def sublattices(k: int) -> list[np.ndarray]:
    """Every sub-lattice of index ``k`` of the integer lattice, as ``(2, 2)`` integer bases in
    Hermite normal form (rows ``(a, b), (0, d)``, ``a d = k``, ``0 <= b < d``)."""
    out = []
    for a in range(1, k + 1):
        if k % a == 0:
            d = k // a
            out += [np.array([[a, b], [0, d]]) for b in range(d)]
    return out


def _in_sublattice(n: np.ndarray, M: np.ndarray) -> np.ndarray:
    (a, b), (_, d) = M
    x = n[:, 0] / a
    xi = np.round(x)
    y = (n[:, 1] - xi * b) / d
    return (np.abs(x - xi) < 1e-6) & (np.abs(y - np.round(y)) < 1e-6)


def _best_sublattice(ac: np.ndarray, B0: np.ndarray, max_index: int, min_contrast: float, min_t: float = 5.0,
                     max_len: float | None = None):
    """The sub-lattice of ``B0`` (index 1 .. ``max_index``) whose points stand out most: the
    largest mean ``rho`` on its points minus the mean on the other points of ``B0`` (the
    contrast), over the points of ``B0`` off the two lattice lines through the origin along its
    vectors; index 1 (``B0`` itself) unless that contrast reaches ``min_contrast`` and is
    significant, at least ``min_t`` standard errors (from the spread of ``rho`` over the
    points in and out of the sub-lattice).  ``max_len``: sub-lattices whose reduced basis has a
    longer vector are not considered (too few of their points in a small window to judge
    them)."""
    n, _, v = _relocate(ac, B0)
    # the lattice lines through the origin along v1 and v2 carry the 1-D correlation of what runs
    # along them (a yarn keeps its own shade along its length; stripes): every sub-lattice that
    # contains such a line would gain from it, weave repeat or not, so they are left out
    off_axes = (n[:, 0] != 0) & (n[:, 1] != 0)
    n, v = n[off_axes], v[off_axes]
    scored = []
    for k in range(2, max_index + 1):
        for M in sublattices(k):
            if max_len is not None and np.linalg.norm(reduce_basis(M @ B0), axis=1).max() > max_len:
                continue
            inside = _in_sublattice(n, M)
            if inside.sum() < 2 or (~inside).sum() < 2:
                continue
            c = float(v[inside].mean() - v[~inside].mean())
            se = float(np.sqrt(v[inside].var() / inside.sum() + v[~inside].var() / (~inside).sum()))
            scored.append((c, k, M, c / max(se, 1e-6)))
    if scored:
        top = max(scored, key=lambda s: s[0])
    if not scored or top[0] < min_contrast or top[3] < min_t:
        return B0, 1, (top[0] if scored else 0.0)
    # a sub-lattice of the repeat scores almost as high as the repeat itself: of the near-best
    # candidates take the coarsest-cell one's smallest super-lattice (lowest index that contains it)
    near = [s for s in scored if s[0] >= 0.85 * top[0] and top[1] % s[1] == 0
            and _contains(s[2], top[2])]
    pick = min(near, key=lambda s: (s[1], -s[0]))
    return pick[2] @ B0, pick[1], pick[0]


def _contains(M: np.ndarray, S: np.ndarray) -> bool:
    """Whether integer lattice ``S`` (rows) is a sub-lattice of integer lattice ``M``."""
    return bool(_in_sublattice(S.astype(float), M).all())


def _refine(ac: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Least-squares basis over the lattice peaks re-located near ``B n`` (module step 5)."""
    n, p, v = _relocate(ac, B)
    ok = v > 0
    if ok.sum() < 2:
        return B, int(ok.sum()), float("nan")
    N, P, W = n[ok], p[ok], np.sqrt(v[ok])[:, None]
    Bn = np.linalg.lstsq(N * W, P * W, rcond=None)[0]
    if abs(np.linalg.det(Bn)) < 0.5 * abs(np.linalg.det(B)):
        return B, int(ok.sum()), float("nan")
    resid = float(np.sqrt(((N @ Bn - P) ** 2).sum(1).mean()))
    return Bn, int(ok.sum()), resid


def _step(ac: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """``rho`` on the lattice line of ``v`` and half way between its points: ``(mean rho(v),
    rho(2v); rho(1.5 v))`` when ``2 v`` is in the window (away from the origin's own peak),
    else ``(rho(v), rho(v / 2))``."""
    cy, cx = np.array(ac.shape) // 2

    def at(p):
        return float(ndimage.map_coordinates(ac, [[p[1] + cy], [p[0] + cx]], order=1)[0])

    if abs(2 * v[0]) < cx - 1 and abs(2 * v[1]) < cy - 1:
        return 0.5 * (at(v) + at(2 * v)), at(1.5 * v)
    return at(v), at(0.5 * v)


def _strength(ac: np.ndarray, B: np.ndarray) -> float:
    """Mean ``rho`` at lattice points minus mean ``rho`` at the half-way points."""
    cy, cx = np.array(ac.shape) // 2

    radius = 4 * float(np.linalg.norm(B, axis=1).max())

    def mean_at(offsets):
        vals = []
        for off in offsets:
            _, p = _lattice_points(ac, B, margin=2.0)
            p = p[np.hypot(*p.T) <= radius]
            p = p + np.asarray(off) @ B
            ok = (np.abs(p[:, 0]) < cx - 1) & (np.abs(p[:, 1]) < cy - 1)
            vals.append(ndimage.map_coordinates(ac, [p[ok, 1] + cy, p[ok, 0] + cx], order=1))
        v = np.concatenate(vals)
        return float(v.mean()) if len(v) else 0.0

    on = mean_at([(0.0, 0.0)])
    off = mean_at([(0.5, 0.0), (0.0, 0.5), (0.5, 0.5)])
    return on - off
