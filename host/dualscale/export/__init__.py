"""Exports: our SVBSDF maps as materials that users' tools open (issue 12).

:func:`export_material` writes one maps folder (``material.json`` + EXR, see
:mod:`dualscale.formats.maps`) in each requested format of :data:`EXPORT_FORMATS`, a
colour-science-style ``method=`` registry::

    exr   full-precision EXR maps in the exchange conventions (:mod:`.exr`)
    mtlx  MaterialX document with standard_surface and open_pbr_surface (:mod:`.mtlx`)
    gltf  glTF 2.0 swatch (.gltf + .bin + textures) at real-world size (:mod:`.gltf`)
    glb   the same as one binary .glb
    u3m   U3M 1.1 material, zipped as .u3ma (:mod:`.u3m`)
    blend Blender .blend, a Cycles material (:mod:`.blend`; needs bpy: ``make blender``;
          not part of ``all``)

Every writer has the signature ``write(ex: Exchange, ctx: ExportContext, out: Path) ->
list[Path]``: ``out`` is the format's own folder (created by :func:`export_material`, written
in a temporary folder that is renamed when complete), the result lists the files written.  The
conversion from our parameters happens once, in :mod:`.exchange`; docs/EXPORT.md tabulates it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .exchange import Exchange, exchange

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")  # a material's name: the files' stem
DEFAULT_SWATCH_MM = 100.0  # the side of the glTF swatch when the texel size is unknown


@dataclass
class ExportContext:
    """What every format writer needs besides the maps.

    ``name``: the material's name (file stem, safe characters only).
    ``repeat_mm``: physical ``(width, height)`` in mm of one texture repeat (the whole map, or
    the seamless tile), ``None`` when the texel size is unknown.
    ``tiled``: the maps are a seamless tile (:mod:`dualscale.tile`); formats then repeat them.
    ``swatch_mm``: ``(width, height)`` in mm of the swatch geometry (glTF); by default the
    repeat itself, or a 2 x 2 repeat of a tile.
    ``meta``: provenance written into the formats' free-form fields (generator, version, source).
    ``uncertainty``: the maps' 1-sigma uncertainty, ``(sigma, undetermined, doc)`` of
    :func:`dualscale.formats.maps.load_uncertainty` (issue 26), or ``None``; only the exchange
    EXR set carries it (:mod:`.exr`; docs/EXPORT.md "Uncertainty").  ``uncertainty_note``: why
    an uncertainty beside the maps is not carried (e.g. a tiled export), recorded in
    ``exchange.json``; ``None`` otherwise.
    """

    name: str
    repeat_mm: tuple[float, float] | None
    tiled: bool = False
    swatch_mm: tuple[float, float] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    uncertainty: tuple[dict, dict, dict] | None = None
    uncertainty_note: str | None = None

    def swatch(self) -> tuple[float, float]:
        """The swatch size in mm (see the class docstring)."""
        if self.swatch_mm is not None:
            return self.swatch_mm
        if self.repeat_mm is None:
            return DEFAULT_SWATCH_MM, DEFAULT_SWATCH_MM
        k = 2.0 if self.tiled else 1.0
        return k * self.repeat_mm[0], k * self.repeat_mm[1]

    def checked_sizes(self, what: str) -> tuple[tuple[float, float], tuple[float, float] | None]:
        """``(swatch_mm, repeat_mm)``, refused with :class:`~dualscale.errors.UnitsError` naming
        ``what`` (e.g. ``"glTF export"``) unless each is two finite sizes > 0 mm (the repeat may
        be ``None``): a format that places the material at real size checks before any file."""
        from dualscale.errors import UnitsError

        def ok(v) -> bool:
            return (v is not None and len(v) == 2
                    and all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in v))

        if self.repeat_mm is not None and not ok(self.repeat_mm):
            raise UnitsError(f"{what} {self.name!r}: repeat_mm must be two finite sizes > 0 mm, got {self.repeat_mm!r}")
        sw = self.swatch()
        if not ok(sw):
            raise UnitsError(f"{what} {self.name!r}: swatch_mm must be two finite sizes > 0 mm, got {sw!r}")
        return (float(sw[0]), float(sw[1])), self.repeat_mm

    def repeats(self) -> tuple[float, float]:
        """How many texture repeats cover the swatch along (u, v)."""
        if self.repeat_mm is None:
            return 1.0, 1.0
        sw = self.swatch()
        return sw[0] / self.repeat_mm[0], sw[1] / self.repeat_mm[1]


Writer = Callable[[Exchange, ExportContext, Path], list[Path]]


def _registry() -> dict[str, Writer]:
    """The writers by format name (imported on first use: pygltflib and MaterialX load only when
    an export runs)."""
    from . import blend as _blend
    from . import exr as _exr
    from . import gltf as _gltf
    from . import mtlx as _mtlx
    from . import u3m as _u3m

    return {"exr": _exr.write, "mtlx": _mtlx.write, "gltf": _gltf.write_gltf, "glb": _gltf.write_glb,
            "u3m": _u3m.write, "blend": _blend.write}


__all__ = ["Exchange", "ExportContext", "exchange"]
