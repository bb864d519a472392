"""The known repeat of the synthetic fabrics (dualscale.sim.materials.fabrics), derived from
the weave predicate and the pitch, for the tests and the benchmark."""

from __future__ import annotations

import numpy as np

from dualscale.tile.lattice import reduce_basis


def weave_lattice(kind: str) -> np.ndarray:
    """``(2, 2)`` reduced basis, in yarn units ``(a, b)`` (warp index i along x, weft index j
    along y), of the shifts that map ``WEAVES[kind]`` onto itself."""
    from dualscale.sim.materials.fabrics import WEAVES

    pred = WEAVES[kind]
    i, j = np.meshgrid(np.arange(12), np.arange(12))
    ref = pred(i, j)
    shifts = [(a, b) for a in range(-6, 7) for b in range(-6, 7) if (a, b) != (0, 0)
              and np.array_equal(pred(i + a, j + b), ref)]
    shifts.sort(key=lambda s: np.hypot(*s))
    v1 = np.array(shifts[0], float)
    v2 = next(np.array(s, float) for s in shifts if abs(v1[0] * s[1] - v1[1] * s[0]) > 1e-9)
    # v1, v2 are the two shortest independent shifts: a basis of the 2-D lattice
    return reduce_basis(np.stack([v1, v2]))


def known_lattice_px(name: str, texel_mm: float, **params) -> np.ndarray:
    """The known lattice of synthetic material ``name`` in texels ``(dcol, drow)`` (row down)."""
    if name in ("plain", "twill", "satin", "denim", "sheer"):
        kind = "plain" if name == "sheer" else name
        pitch = params.get("pitch_mm", 0.3)
        yarn = weave_lattice(kind)
        mm = yarn * pitch  # (x, y) mm with y up
    elif name == "rib_knit":
        # 1x1 rib: knit and purl wales alternate, so the repeat is two wales by one course
        mm = np.array([[2 * params.get("wale_mm", 0.6), 0.0], [0.0, params.get("course_mm", 0.4)]])
    else:
        raise KeyError(name)
    return reduce_basis(mm / texel_mm * np.array([1.0, -1.0]))


def lattice_error_px(found: np.ndarray, known: np.ndarray) -> float:
    """Largest distance (texels) between the found and the known basis, after matching each
    known vector to a found lattice vector (any sign, the sum or difference: a reduced basis is
    unique only up to these)."""
    cands = [s * v for v in (found[0], found[1], found[0] + found[1], found[0] - found[1]) for s in (1, -1)]
    return max(min(np.linalg.norm(k - c) for c in cands) for k in known)
