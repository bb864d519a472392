"""What ``dualscale view`` shows: the glTF exports of a RUN or OUT folder and, for a run, the
captured LED images next to our renderer's images of the fitted maps (issue 12 Sec. 3).

Folders (docs/VIEWER.md):

* an **export folder** ``OUT`` (``dualscale export``): ``OUT/export.json`` =
  ``{"format": "dualscale-export", "version": 1, "name", "formats": {"glb": [paths], "gltf":
  [...], ...}, "repeat_mm": [w, h] | null, "tiled": bool, "source": maps dir}``;
* a **digitize run** ``RUN`` (``run.json``, :mod:`dualscale.formats.run`): its export folders
  ``RUN/export/micro`` and ``RUN/export/mesoscale``, its fitted maps ``RUN/fit/maps`` and its
  calibrated dataset ``RUN/calibrate/dataset`` (else ``run.json``'s ``input``).

:func:`locate` finds them; :class:`LedImages` renders one LED's captured and modelled images:
the dataset's image (radiance per unit LED intensity, :mod:`dualscale.fit.observations`) and
``dualscale.fit.render.render_leds`` of the fitted maps under the same LED direction, analyser
weights and view (seed Sec. 5, supplementary Sec. 4), both clamped at the fit's limit of 2.

Errors: :class:`~dualscale.errors.InputError` when the path holds no glTF/GLB export (the message
says which command writes one), :class:`~dualscale.errors.FormatError` for a malformed
``export.json``.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import FormatError, InputError
RUN_EXPORTS = ("micro", "mesoscale")  # RUN/export/<name>/, in the order the page lists them


@dataclass
class ExportView:
    """One export folder as the page loads it: ``gltf`` is the ``.glb`` (preferred) or ``.gltf``
    file, relative to ``root``; ``repeat_mm`` ``(w, h)`` of one texture repeat (``None``:
    unknown scale)."""

    key: str
    root: Path
    name: str
    gltf: str
    repeat_mm: tuple[float, float] | None
    tiled: bool
    #: the maps folder whose ``uncertainty/`` (issue 26) belongs to this export's maps, or ``None``
    sigma: Path | None = None

    def to_json(self) -> dict[str, Any]:
        return {"key": self.key, "name": self.name, "url": f"files/{self.key}/{self.gltf}",
                "repeat_mm": None if self.repeat_mm is None else list(self.repeat_mm), "tiled": self.tiled,
                "sigma": f"api/sigma/{self.key}.json" if self.sigma is not None else None}


def _has_uncertainty(maps: Path) -> bool:
    from dualscale.formats.maps import UNCERTAINTY_DIR

    return (maps / UNCERTAINTY_DIR / "uncertainty.json").is_file()


def _sigma_source(root: Path, source: Any) -> Path | None:
    """The maps folder holding an untiled export's uncertainty (a tiled one's texels are not
    the maps'): its own ``maps/`` copy (written with it since issue 26's exports), else the maps
    folder it was written from (``export.json``'s ``source``, absolute or relative to it)."""
    candidates = [root / "maps"] + ([Path(str(source)), root / str(source)] if source else [])
    for p in candidates:
        try:
            if p.is_dir() and _has_uncertainty(p):
                return p
        except OSError:
            continue
    return None


@dataclass
class Scene:
    """What to show: ``exports`` (at least one), and for a run its ``maps`` folder (the fit) and
    ``dataset`` folder; ``no_capture`` says why the side-by-side is absent (``None``: present)."""

    root: Path
    kind: str                         # "run" or "export"
    exports: list[ExportView]
    maps: Path | None = None
    dataset: Path | None = None
    no_capture: str | None = None
    leds: list[dict[str, Any]] = field(default_factory=list)

    def export(self, key: str) -> ExportView:
        for e in self.exports:
            if e.key == key:
                return e
        raise KeyError(key)

    def to_json(self) -> dict[str, Any]:
        """The page's ``scene.json``."""
        return {"title": self.root.resolve().name, "kind": self.kind,
                "exports": [e.to_json() for e in self.exports], "leds": self.leds,
                "side_by_side": self.no_capture is None, "no_capture": self.no_capture}


def read_export(root: Path, key: str) -> ExportView | None:
    """The glTF of export folder ``root`` (``None`` when ``export.json`` lists no glb/gltf).
    Raises :class:`FormatError` for a malformed ``export.json`` or a listed file that is
    missing."""
    from dualscale.export.material import read_export as read_export_json

    path = root / "export.json"
    doc = read_export_json(root)
    formats = doc.get("formats", {})
    if not isinstance(formats, dict):
        raise FormatError(f"{path}: formats must be an object")
    for fmt, suffix in (("glb", ".glb"), ("gltf", ".gltf")):
        files = formats.get(fmt) or []
        if not isinstance(files, list):
            raise FormatError(f"{path}: formats.{fmt} must be a list of paths")
        for rel in files:
            p = Path(str(rel))
            if p.suffix.lower() != suffix:
                continue
            if p.is_absolute() or ".." in p.parts:
                raise FormatError(f"{path}: formats.{fmt}: {rel!r} must be a path inside the folder")
            if not (root / p).is_file():
                raise FormatError(f"{path}: formats.{fmt} lists {rel}, which is missing")
            rep = doc.get("repeat_mm")
            if rep is not None:
                if not (isinstance(rep, list) and len(rep) == 2 and all(isinstance(v, (int, float)) and v > 0
                                                                       for v in rep)):
                    raise FormatError(f"{path}: repeat_mm must be [width, height] in mm (> 0) or null, got {rep!r}")
                rep = (float(rep[0]), float(rep[1]))
            tiled = bool(doc.get("tiled"))
            return ExportView(key, root, str(doc.get("name") or p.stem), p.as_posix(), rep, tiled,
                              None if tiled else _sigma_source(root, doc.get("source")))
    return None


def _run_dataset(run: Path) -> Path | None:
    """The run's calibrated dataset, else its input as recorded (relative to the working
    folder of the run, or to the run's parent)."""
    cal = run / "calibrate" / "dataset"
    if (cal / "manifest.json").is_file():
        return cal
    from dualscale.formats.run import read_run

    src = read_run(run).get("input")
    if not src:
        return None
    for base in (Path.cwd(), run.parent):
        p = Path(src) if Path(src).is_absolute() else base / src
        for cand in (p, p / "micro"):
            if (cand / "manifest.json").is_file():
                return cand
    return None


def led_list(dataset: Path) -> list[dict[str, Any]]:
    """The dataset's LEDs ``[{"id", "theta_deg", "phi_deg", "dir"}]`` (first record of each id;
    ``theta`` from the sample normal, ``phi`` CCW from image +x), sorted by id."""
    from dualscale.formats.dataset import read_dataset

    ds = read_dataset(dataset)
    seen: dict[int, dict[str, Any]] = {}
    for r in ds.records:
        if r.light_kind != "led" or r.light_id is None or r.direction is None or r.light_id in seen:
            continue
        x, y, z = (float(v) for v in r.direction)
        seen[r.light_id] = {"id": int(r.light_id), "dir": [x, y, z],
                            "theta_deg": round(math.degrees(math.acos(max(-1.0, min(1.0, z)))), 2),
                            "phi_deg": round(math.degrees(math.atan2(y, x)) % 360.0, 2)}
    return [seen[k] for k in sorted(seen)]


def locate(path: str | Path) -> Scene:
    """The :class:`Scene` of a RUN or OUT folder (module doc).  Raises :class:`InputError` when
    it holds no glTF/GLB export, naming the command that writes one."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder (give a digitize RUN folder or an export folder)")
    if (root / "export.json").is_file():
        ex = read_export(root, "export")
        if ex is None:
            raise InputError(f"{root}/export.json lists no glTF or GLB file; run "
                             f"`dualscale export MAPS -o {root} --format glb`")
        return Scene(root, "export", [ex], no_capture="this is an export folder, not a digitize run: there are "
                     "no captured images to compare with (open the RUN folder for the side-by-side)")
    if not (root / "run.json").is_file():
        raise InputError(f"{root}: neither an export folder (export.json) nor a digitize run (run.json); run "
                         f"`dualscale export MAPS -o OUT --format glb` and view OUT")
    exports = []
    for key in RUN_EXPORTS:
        d = root / "export" / key
        if (d / "export.json").is_file():
            ex = read_export(d, key)
            if ex is not None:
                exports.append(ex)
    if not exports:
        raise InputError(f"{root}: the run has no glTF or GLB export (RUN/export/micro/export.json); run "
                         f"`dualscale export {root}/fit/maps -o {root}/export/micro --format glb`, "
                         "or digitize with the glb export")
    scene = Scene(root, "run", exports)
    maps = root / "fit" / "maps"
    for ex in exports:  # the micro export is of the fitted maps: their uncertainty is its
        if ex.key == "micro" and ex.sigma is None and not ex.tiled and _has_uncertainty(maps):
            ex.sigma = maps
    dataset = _run_dataset(root)
    if not (maps / "material.json").is_file():
        scene.no_capture = f"the run has no fitted maps ({maps}/material.json)"
    elif dataset is None:
        scene.no_capture = "the run's dataset was not found (RUN/calibrate/dataset, or run.json's input)"
    else:
        scene.maps, scene.dataset = maps, dataset
        scene.leds = led_list(dataset)
        if not scene.leds:
            scene.no_capture = f"the dataset {dataset} has no LED images"
    return scene


# -- captured vs. rendered ------------------------------------------------------------------------

@dataclass
class LedPair:
    """One LED's captured and rendered images, linear ``(H, W, 3)`` float32 (radiance per unit
    LED intensity per second), with the LED ``id``, ``dir`` (unit, sample frame), the analyser
    weights used and the relative error ``sum|r - c| / sum c`` over valid pixels."""

    led: int
    dir: list[float]
    captured: np.ndarray
    rendered: np.ndarray
    w_s: float
    w_d: float
    rel_error: float


class LedImages:
    """Captured and rendered images per LED of a run :class:`Scene`, computed on demand and
    cached (thread-safe).  Of several images of one LED (P0/P90 analysers) the one passing the
    most specular light is shown (largest ``w_s``)."""

    def __init__(self, scene: Scene):
        if scene.maps is None or scene.dataset is None:
            raise InputError(f"{scene.root}: no captured images to compare with ({scene.no_capture})")
        self.scene = scene
        self._lock = threading.Lock()
        self._maps = None
        self._cache: dict[int, LedPair] = {}

    def ids(self) -> list[int]:
        return [d["id"] for d in self.scene.leds]

    def pair(self, led: int) -> LedPair:
        """The :class:`LedPair` of LED ``led``; :class:`InputError` for an id the dataset lacks."""
        if led not in self.ids():
            raise InputError(f"LED {led} is not in the dataset {self.scene.dataset} "
                             f"(LEDs {self.ids()[0]}..{self.ids()[-1]})")
        with self._lock:
            if led not in self._cache:
                self._cache[led] = self._compute(led)
            return self._cache[led]

    def _compute(self, led: int) -> LedPair:
        import torch

        from dualscale.fit.observations import load_observations
        from dualscale.fit.render import clamp_images, render_leds
        from dualscale.formats.maps import load_maps

        if self._maps is None:
            self._maps = load_maps(self.scene.maps)[0]
        maps = self._maps
        obs = load_observations(self.scene.dataset, leds={led})
        k = int(torch.argmax(obs.w_s))
        obs = obs.select([k])
        if obs.shape != maps.shape:
            raise InputError(f"{self.scene.dataset}: LED images are {obs.shape}, the fitted maps "
                             f"{self.scene.maps} are {maps.shape}")
        with torch.no_grad():
            rendered = render_leds(maps, maps.components(), obs)[0].numpy()
        captured = clamp_images(obs.images)[0].numpy()
        valid = np.ones(captured.shape[:2], bool) if obs.valid is None else obs.valid[0].numpy()
        den = float(captured[valid].sum())
        err = float(np.abs(rendered - captured)[valid].sum() / den) if den > 0 else float("nan")
        return LedPair(led, [float(v) for v in obs.dirs[0]], captured.astype(np.float32),
                       rendered.astype(np.float32), float(obs.w_s[0]), float(obs.w_d[0]), err)


def display_scale(pair: LedPair) -> float:
    """One exposure for both images of a pair: the 99.5th percentile of the captured image maps
    to 1 (a black capture falls back to the render)."""
    for img in (pair.captured, pair.rendered):
        p = float(np.percentile(img, 99.5))
        if p > 0:
            return 1.0 / p
    return 1.0
