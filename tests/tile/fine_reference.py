"""An independent reference for a lattice of a few texels' period (issue 24 Sec. 6): a fine-grid
search of the periodic correlation of the image, for the tests and the benchmark.

Not the method of :mod:`dualscale.tile.lattice` (the zero-padded, overlap-normalised
autocorrelation on a finer grid, its peaks fitted by least squares over the lattice): here the
signal is windowed (Hann), its circular autocorrelation is the trigonometric sum over its
periodogram, evaluated exactly at any shift, and each basis vector ``v`` is the maximum of
``rho(v) + rho(2 v) + rho(3 v)`` on a grid of 0.02 texel over +-0.4 texel around a rough
starting vector (read off the spectrum by hand), then of 0.001 texel around the best point."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def periodic_correlation(sig: np.ndarray):
    """``grid(cols, rows) -> rho`` ``(len(rows), len(cols))``: the windowed signal's circular
    autocorrelation (``rho(0) = 1``) at the shifts ``(dcol, drow)`` of a separable grid."""
    h, w = sig.shape
    f = sig - ndimage.gaussian_filter(sig, min(h, w) / 8, mode="reflect")
    f = (f - f.mean()) * np.outer(np.hanning(h), np.hanning(w))
    P = np.abs(np.fft.fft2(f)) ** 2
    P /= P.sum()
    fy, fx = np.fft.fftfreq(h), np.fft.fftfreq(w)

    def grid(cols, rows):
        e_row = np.exp(2j * np.pi * np.outer(rows, fy))
        e_col = np.exp(2j * np.pi * np.outer(fx, cols))
        return ((e_row @ P) @ e_col).real

    return grid


def reference_vector(grid, v, multiples=(1, 2, 3), half: float = 0.4, steps=(0.02, 0.001)) -> np.ndarray:
    """The vector near ``v`` (texels, ``(dcol, drow)``) maximising the periodic correlation at its
    ``multiples``, by two nested grid searches; the maximum must lie inside each grid."""
    v = np.asarray(v, float)
    for st in steps:
        d = np.arange(-half, half + st / 2, st)
        score = sum(grid(m * (v[0] + d), m * (v[1] + d)) for m in multiples)
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        assert 0 < r < len(d) - 1 and 0 < c < len(d) - 1, "the correlation maximum is outside the search grid"
        v = v + [d[c], d[r]]
        half = 2 * st
    return v


def reference_lattice(sig: np.ndarray, rough) -> np.ndarray:
    """``(2, 2)`` rows: each rough vector refined by :func:`reference_vector`."""
    grid = periodic_correlation(sig)
    return np.array([reference_vector(grid, v) for v in rough])


def relative_error(found: np.ndarray, ref: np.ndarray) -> float:
    """Largest ``|v_ref - v| / |v_ref|`` over the reference vectors, each matched to the nearest
    of the found basis' ``+-v1, +-v2, +-(v1 + v2), +-(v1 - v2)`` (a reduced basis is unique
    only up to these)."""
    cands = [s * v for v in (found[0], found[1], found[0] + found[1], found[0] - found[1]) for s in (1, -1)]
    return float(max(min(np.linalg.norm(k - c) for c in cands) / np.linalg.norm(k) for k in ref))
