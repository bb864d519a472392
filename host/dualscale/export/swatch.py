"""A flat swatch mesh at real-world size for the glTF export (issue 12), with a tangent frame
that makes the texture's tangent space our image tangent space.

Geometry (glTF 2.0 spec Sec. 3.4 "Coordinate system and units": +Y up, metres, right-handed):
the swatch lies in the XZ plane, centred on the origin, facing +Y (front faces wind
counter-clockwise seen from +Y).

Tangent frame (glTF 2.0 spec Sec. 3.7.2.1, ``TANGENT``: ``bitangent = cross(normal,
tangent.xyz) * tangent.w``) and texture coordinates (spec Sec. 3.8.1: the UV origin is the
*top-left* of the image, ``u`` to the right, ``v`` down):

* ``NORMAL = +Y``, ``TANGENT = (+X, w = +1)``, so ``bitangent = cross(+Y, +X) = -Z``;
* ``u`` increases along +X (the tangent: image right, our +x);
* ``v`` increases along +Z, so image row 0 (the top, ``v = 0``) lies at ``z = -height/2``
  and image *up* (decreasing ``v``) is -Z, the bitangent.

Hence our tangent space (+x image right, +y image up, +z out, :mod:`.exchange`) *is* glTF's
(tangent, bitangent, normal): an OpenGL (+Y up) normal map and the anisotropy direction
(``KHR_materials_anisotropy``, tangent/bitangent space) are read with our conventions, with no
flip.  Seen from above (+Y) with -Z at the top, the image appears unmirrored and upright.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dualscale.errors import UnitsError


@dataclass
class SwatchMesh:
    """Vertex arrays of the swatch (``N`` vertices, ``M`` triangles), float32 unless noted.

    ``positions`` (N, 3) metres; ``normals`` (N, 3) unit; ``tangents`` (N, 4) unit xyz with
    ``w = +1``; ``texcoords`` (N, 2) glTF UV in [0, 1] (origin top-left, v down);
    ``indices`` (3 M,) uint16, counter-clockwise seen from +Y."""

    positions: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    texcoords: np.ndarray
    indices: np.ndarray

    @property
    def size_m(self) -> tuple[float, float]:
        """(width along X, height along Z) in metres."""
        lo, hi = self.positions.min(0), self.positions.max(0)
        return float(hi[0] - lo[0]), float(hi[2] - lo[2])


def swatch_mesh(width_mm: float, height_mm: float, segments: tuple[int, int] = (4, 4)) -> SwatchMesh:
    """A ``width_mm`` x ``height_mm`` swatch (converted to metres, glTF's unit) of
    ``segments = (nx, ny)`` quads, in the frame described in the module docstring.

    Raises :class:`~dualscale.errors.UnitsError` for a size that is not finite and positive.
    """
    for field, v in (("width_mm", width_mm), ("height_mm", height_mm)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise UnitsError(f"swatch: {field} must be a finite size > 0 mm, got {v!r}")
    nx, ny = int(segments[0]), int(segments[1])
    if nx < 1 or ny < 1 or (nx + 1) * (ny + 1) > 65535:
        raise ValueError(f"swatch: segments must be >= 1 and fit uint16 indices, got {segments}")
    w, h = width_mm * 1e-3, height_mm * 1e-3
    u = np.linspace(0.0, 1.0, nx + 1)
    v = np.linspace(0.0, 1.0, ny + 1)
    uu, vv = np.meshgrid(u, v)  # (ny+1, nx+1): row j = image row band from the top
    n = uu.size
    pos = np.stack([(uu - 0.5) * w, np.zeros_like(uu), (vv - 0.5) * h], -1).reshape(n, 3)
    normals = np.tile([0.0, 1.0, 0.0], (n, 1))
    tangents = np.tile([1.0, 0.0, 0.0, 1.0], (n, 1))
    tex = np.stack([uu, vv], -1).reshape(n, 2)
    idx = []
    for j in range(ny):
        for i in range(nx):
            a = j * (nx + 1) + i          # top-left (smaller z)
            b, c, d = a + 1, a + nx + 1, a + nx + 2  # top-right, bottom-left, bottom-right
            idx += [a, c, b, b, c, d]     # counter-clockwise seen from +Y
    return SwatchMesh(pos.astype(np.float32), normals.astype(np.float32),
                      tangents.astype(np.float32), tex.astype(np.float32),
                      np.asarray(idx, np.uint16))
