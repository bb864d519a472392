"""``dualscale view RUN|OUT``: a localhost web viewer of an exported material (issue 12 Sec. 3).

The page (``static/``, three.js from npm copied by ``make node``; nothing is fetched at run
time) shows the exported glTF on its swatch and on a draped cloth or a sphere at the physical
repeat size, with an orbiting camera, a movable light, false-colour map inspection and, for a
digitize run, the captured image of an LED beside our renderer's image of the fitted maps.

* :mod:`.scene` -- what to show: :func:`locate` a RUN or OUT folder, :class:`LedImages`;
* :mod:`.server` -- :class:`ViewerServer`, the HTTP server on 127.0.0.1 (docs/VIEWER.md).
"""

from .scene import LedImages, Scene, locate
from .server import ViewerServer, vendor_missing

__all__ = ["LedImages", "Scene", "ViewerServer", "locate", "vendor_missing"]
