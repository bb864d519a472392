"""The viewer's localhost HTTP server (stdlib ``http.server``), bound to 127.0.0.1 only.

Routes (all ``GET``; docs/VIEWER.md):

* ``/`` and the static page: ``index.html``, ``viewer.js``, ``viewer.css``, ``vendor/...``
  (three.js, copied from npm by ``make node``; nothing is fetched from the network);
* ``/scene.json``: :meth:`dualscale.view.scene.Scene.to_json`;
* ``/files/<key>/<path>``: the files of export folder ``key`` (the glTF and its textures);
* ``/api/led/<id>.json``: one LED of a run: direction, analyser weights, the relative error of
  our render against the capture, the display exposure and the two image URLs;
* ``/api/led/<id>/captured.png`` and ``/api/led/<id>/rendered.png``: the captured image and our
  renderer's image of the fitted maps under that LED (:class:`dualscale.view.scene.LedImages`),
  both at one exposure, sRGB-encoded 8-bit PNG, computed on first request and cached in a
  temporary folder removed by :meth:`ViewerServer.close`;
* ``/api/sigma/<key>.json``: the per-pixel uncertainty (issue 26) of export ``key``'s maps
  (:meth:`ViewerServer.sigma_info`; 404 when it has none), and ``/api/sigma/<key>/<map>.png``:
  that map's 1-sigma as a false-colour PNG (largest channel per texel, 0 to the 99.5th
  percentile in the report's colour map, undetermined texels in its flat colour:
  :func:`dualscale.report.plots.sigma_colours`), cached like the LED images.

Unknown paths answer 404, a bad LED id 400 (JSON ``{"error": ...}``), anything that escapes a
served folder 404; an uncertainty whose files are damaged 500 (the rest of the page still works;
the viewer's terminal gets one warning).
"""

from __future__ import annotations

import http.server
import json
import math
import re
import shutil
import sys
import tempfile
import threading
import urllib.parse
from pathlib import Path

from dualscale.errors import InputError

from .scene import LedImages, Scene, display_scale

STATIC = Path(__file__).resolve().parent / "static"
VENDOR_HINT = "run `make node` (copies three.js from npm into host/dualscale/view/static/vendor)"
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css",
         ".json": "application/json", ".glb": "model/gltf-binary", ".gltf": "model/gltf+json",
         ".bin": "application/octet-stream", ".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg",
         ".ktx2": "image/ktx2", ".webp": "image/webp", ".exr": "image/x-exr"}
_LED = re.compile(r"^/api/led/(\d+)(\.json|/captured\.png|/rendered\.png)$")
_SIGMA = re.compile(r"^/api/sigma/([^/]+?)(\.json|/([a-z_]+)\.png)$")


def vendor_missing() -> list[str]:
    """The three.js files the page imports that are absent from ``static/vendor``."""
    need = ["three.module.js", "three.core.js", "addons/loaders/GLTFLoader.js", "addons/controls/OrbitControls.js",
            "addons/utils/BufferGeometryUtils.js"]
    return [n for n in need if not (STATIC / "vendor" / n).is_file()]


def _inside(base: Path, rel: str) -> Path | None:
    """``base / rel`` when it is a file inside ``base`` (no ``..`` escape), else ``None``."""
    try:
        p = (base / rel).resolve()
        p.relative_to(base.resolve())
    except (ValueError, OSError):
        return None
    return p if p.is_file() else None


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_Http"

    def log_message(self, *args):  # the command prints the URL; per-request lines are noise
        pass

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, doc) -> None:
        self._send(status, json.dumps(doc).encode(), TYPES[".json"])

    def _file(self, path: Path | None) -> None:
        if path is None:
            self._json(404, {"error": f"not found: {self.path}"})
            return
        self._send(200, path.read_bytes(), TYPES.get(path.suffix.lower(), "application/octet-stream"))

    def do_HEAD(self):  # noqa: N802 - http.server's hook
        self.do_GET()

    def do_GET(self):  # noqa: N802 - http.server's hook
        path = urllib.parse.urlsplit(self.path).path
        view: ViewerServer = self.server.view
        try:
            if path in ("/", "/index.html"):
                return self._file(_inside(STATIC, "index.html"))
            if path == "/scene.json":
                return self._json(200, view.scene.to_json())
            if path.startswith("/files/"):
                key, _, rel = path[len("/files/"):].partition("/")
                try:
                    root = view.scene.export(urllib.parse.unquote(key)).root
                except KeyError:
                    return self._file(None)
                return self._file(_inside(root, urllib.parse.unquote(rel)))
            m = _LED.match(path)
            if m:
                return self._led(int(m.group(1)), m.group(2))
            m = _SIGMA.match(path)
            if m:
                key = urllib.parse.unquote(m.group(1))
                try:
                    if m.group(2) == ".json":
                        return self._json(200, view.sigma_info(key))
                    return self._file(view.sigma_png(key, m.group(3)))
                except (InputError, OSError) as e:  # a damaged file on our side, not a bad request
                    view.warn_once(f"the uncertainty of {key!r} is not readable: {e}")
                    return self._json(500, {"error": f"the uncertainty of {key!r} is not readable: {e}"})
            return self._file(_inside(STATIC, urllib.parse.unquote(path.lstrip("/"))))
        except InputError as e:
            return self._json(400, {"error": str(e)})
        except KeyError as e:
            return self._json(404, {"error": f"not found: {self.path} ({e.args[0] if e.args else e})"})
        except (BrokenPipeError, ConnectionResetError):
            return None

    def _led(self, led: int, what: str) -> None:
        view: ViewerServer = self.server.view
        if view.leds is None:
            return self._json(404, {"error": view.scene.no_capture})
        if what == ".json":
            return self._json(200, view.led_info(led))
        return self._file(view.led_png(led, what.split("/")[1].split(".")[0]))


class _Http(http.server.ThreadingHTTPServer):
    daemon_threads = True
    view: "ViewerServer"


class ViewerServer:
    """Serve the page of ``scene`` on ``http://127.0.0.1:PORT/`` (``port=0``: any free port).

    ``start()`` runs the server in a daemon thread and returns the URL; ``close()`` stops it
    and removes the PNG cache.  Also a context manager.  ``OSError`` when the port is taken."""

    def __init__(self, scene: Scene, port: int = 0):
        self.scene = scene
        self.leds = LedImages(scene) if scene.no_capture is None else None
        self._http = _Http(("127.0.0.1", int(port)), _Handler)
        self._http.view = self
        self._cache = Path(tempfile.mkdtemp(prefix="dualscale-view-"))
        self._png_lock = threading.Lock()
        self._sigma_cache: dict[str, tuple] = {}
        self._warned: set[str] = set()
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self._http.server_address[1]}/"

    def start(self) -> str:
        self._thread = threading.Thread(target=self._http.serve_forever, name="dualscale-view", daemon=True)
        self._thread.start()
        return self.url

    def serve_forever(self) -> None:
        """Serve in the calling thread until :meth:`close` (or Ctrl-C)."""
        self._http.serve_forever()

    def close(self) -> None:
        if self._thread is not None:
            self._http.shutdown()
            self._thread.join(5)
        self._http.server_close()
        shutil.rmtree(self._cache, ignore_errors=True)

    def __enter__(self) -> "ViewerServer":
        self.start()
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def led_info(self, led: int) -> dict:
        """The JSON of ``/api/led/<id>.json`` (module doc)."""
        p = self.leds.pair(led)
        x, y, z = p.dir
        return {"led": p.led, "dir": p.dir, "theta_deg": math.degrees(math.acos(max(-1.0, min(1.0, z)))),
                "phi_deg": math.degrees(math.atan2(y, x)) % 360.0, "w_s": p.w_s, "w_d": p.w_d,
                "rel_error": p.rel_error, "display_scale": display_scale(p),
                "size": [int(p.captured.shape[1]), int(p.captured.shape[0])],
                "captured": f"api/led/{led}/captured.png", "rendered": f"api/led/{led}/rendered.png"}

    def warn_once(self, text: str) -> None:
        """Print ``text`` on stderr the first time it is seen (the terminal the viewer runs in)."""
        if text not in self._warned:
            self._warned.add(text)
            print(f"dualscale view: warning: {text}", file=sys.stderr, flush=True)

    def _sigma(self, key: str):
        """``(sigma, undetermined, doc)`` of export ``key``'s maps (read once); ``KeyError``
        when the export is unknown or has no uncertainty."""
        from dualscale.formats.maps import load_uncertainty

        ex = self.scene.export(key)
        if ex.sigma is None:
            raise KeyError(f"the export {key!r} has no uncertainty folder beside its maps")
        with self._png_lock:
            cached = self._sigma_cache.get(key)
            if cached is None:
                cached = self._sigma_cache[key] = load_uncertainty(ex.sigma)
        return cached

    def sigma_info(self, key: str) -> dict:
        """The JSON of ``/api/sigma/<key>.json``: per map its label, unit (full and short), the
        colour scale's top, the median sigma per channel, the share undetermined and the PNG's
        URL; the colour bar (its colours left to right) and the undetermined texels' colour."""
        import numpy as np

        from dualscale.formats.maps import SIGMA_UNITS
        from dualscale.report import plots

        sigma, und, doc = self._sigma(key)
        order = [n for n in plots.MAP_TITLES if n in sigma] + [n for n in sigma if n not in plots.MAP_TITLES]
        maps = []
        for n in order:
            s, u = sigma[n], und[n]
            top, any_und = plots.sigma_display(s, u)
            r = plots.sigma_range(top)
            med = [float(np.median(s[..., c][~u[..., c]])) if (~u[..., c]).any() else None for c in range(s.shape[2])]
            maps.append({"name": n, "label": f"σ {plots.MAP_TITLES.get(n, n)}", "units": (doc.get("units") or {}).get(
                n, SIGMA_UNITS.get(n, "")), "unit": plots.sigma_unit(n), "vmax": r.vmax, "clipped": r.above,
                "median": med, "undetermined_fraction": float(any_und.mean()), "channels": int(s.shape[2]),
                "url": f"api/sigma/{urllib.parse.quote(key)}/{n}.png"})
        bar = (plots.sigma_colorbar(64, 1)[0] * 255).round().astype(int).tolist()
        return {"export": key, "maps": maps, "colormap": plots.SIGMA_CMAP, "colorbar": bar,
                "undetermined": {"colour": plots.UNDETERMINED_HEX, "name": plots.UNDETERMINED_NAME}}

    def sigma_png(self, key: str, name: str) -> Path:
        """The cached false-colour PNG of map ``name``'s sigma (module doc)."""
        from dualscale.export.textures import write_png
        from dualscale.report import plots

        sigma, und, _ = self._sigma(key)
        if name not in sigma:
            raise KeyError(f"no uncertainty of the map {name!r} (it has {', '.join(sigma)})")
        safe = "".join(c if c.isalnum() else "_" for c in key)
        out = self._cache / f"sigma_{safe}_{name}.png"
        with self._png_lock:
            if not out.is_file():
                top, any_und = plots.sigma_display(sigma[name], und[name])
                write_png(out, plots.sigma_colours(top, any_und, plots.sigma_range(top).vmax), srgb=False)
        return out

    def led_png(self, led: int, which: str) -> Path:
        """The cached PNG (``which`` = ``captured`` or ``rendered``) of LED ``led``."""
        import numpy as np

        from dualscale.export.textures import write_png

        out = self._cache / f"led{led}_{which}.png"
        with self._png_lock:
            if not out.is_file():
                p = self.leds.pair(led)
                s = display_scale(p)
                for name, img in (("captured", p.captured), ("rendered", p.rendered)):
                    write_png(self._cache / f"led{led}_{name}.png", np.clip(img * s, 0.0, 1.0), srgb=True)
        return out
