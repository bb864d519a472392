"""``sim``: a simulated camera on the simulated rig's trigger lines (issue 14 §2).

The POSIX firmware simulator (``firmware/targets/posix``; ``dualscale sim --hw-socket PATH``,
:class:`dualscale.rig.launcher.SimulatedRig`) publishes its "hardware" on a Unix socket as
newline-delimited JSON (``hello``, ``light`` {kind, index, intensity}, ``polarizer`` {cdeg},
``triggers`` {mask}, ``event`` {kind, arg, step, seq}, ``preload``, ``latch``; each with ``t_us``,
the device clock in µs) and takes camera-master edges ``{"ev":"edge","camera":C}``.  This camera
is a client of that socket, driven by it exactly as a real camera is driven by the rig's trigger
lines (the paper's Sec. 3 rig: micro camera with the servo-turned analyser, mid-range camera,
oblique polar cameras; PROTOCOL.md §3.1 device-master and §3.2 camera-master timing):

* a reader thread consumes the side channel without ever blocking it (the simulator drops a
  client that stalls 2 s) and keeps the live state: lights and their intensities, the analyser
  angle, the trigger mask, the last device time;
* ``edge`` mode: each rising edge of its trigger bit (``rm.TRIGGER_NAMES.index(camera)``) starts
  one exposure of the prepared ``exposure_s``; ``gate`` mode: the exposure lasts from the rising
  to the falling edge (device time).  The light state is the one live at the rising edge (the
  firmware latches a step's light before its trigger rises, §3.1).  An edge while the camera is
  still exposing or reading out (``readout_ms`` after each exposure) is missed, as on a real
  camera (``busy_triggers``); edges beyond the armed count are ignored (``ignored_triggers``);
* ``internal`` mode: :meth:`SimCamera.trigger` exposes the state now (an idle rig gives a dark
  frame).  With ``master=1`` (camera-master, §3.2) it first sends its exposure-active edge to
  the simulator and exposes the state after the firmware handled it (the latched step's light);
  the firmware's ``CAMERA_EDGE`` event is in the frame's metadata (``master_edge``);
* a render worker turns each exposure into a frame: the radiance of every light that is on
  (:func:`dualscale.sim.render.render`, intensity = register value / ``INTENSITY_MAX``, the
  analyser at ``polarizer_cdeg / 100`` degrees relative to each LED's polariser for the cameras
  with an analyser) made camera raw signal by :func:`dualscale.sim.targets.raw_signal` (the
  rig's LED spectra, camera sensitivities, LED gain and collimation ramp), summed over the lights
  (the renderer is linear in the light), then the camera's sensor
  (:func:`dualscale.sim.targets.rig_exposer`: vignetting, dark signal, shot/read noise, 12 bits)
  at this frame's exposure: exactly the sensor path of ``dualscale synth --realistic``.  The raw
  signal is cached per (lights, analyser) state, so the brackets of one step render once.  A
  frame comes as soon as it is rendered, which for a long internal-trigger exposure is before
  the exposure has ended on the device clock; so :meth:`SimCamera.arm` for the rig's edges
  (``edge``/``gate``) first waits until the sensor is free, as a real camera is free only once
  it delivered that frame: a 4 s dark followed at once by a sequence waits 4 s / speed of wall
  time (the adaptive capture's darks at a round's end, then its metering, docs/CAPTURE.md).

Spec: ``sim:CAMERA?hw=SOCKET&OPTION=VALUE&...`` with CAMERA one of ``rm.CAMERA_NAMES`` (``micro``,
``mid``, ``polar0``, ``polar1``).  Options (:data:`OPTIONS`):

* ``hw`` (required): the simulator's side-channel socket;
* the sample: ``material=NAME`` (a :data:`dualscale.sim.materials.MATERIALS` name, default
  ``twill``, generated at ``size`` texels of ``texel_um`` with ``seed``, as ``dualscale synth``)
  or ``maps=PATH`` (any maps folder, :func:`dualscale.formats.maps.load_maps`);
* or a calibration target: ``target=white_sheet|chart|dot_grid|polarization`` (:class:`TargetScene`:
  ``dualscale synth-targets``' radiance, :mod:`dualscale.sim.targets`, with ``seed`` as the
  defects' seed), ``patch=K`` (``target=chart``, micro camera: ColorChecker patch K, 0..23, fills
  the field; without it the chart is centred), ``analyzer_offset=DEG`` (the analyser's
  misalignment, seen on the polarisation target); the micro camera's default ``texel_um`` is then
  ``921.6 / size`` (the rig's 0.92 mm micro field at any binning).  :meth:`SimCamera.place` (the
  virtual operator of ``dualscale capture``'s target plans) changes the target while the camera
  is open;
* ``size`` [px]: the image (micro: the map grid, one pixel per texel, as ``synth --dataset``;
  default 512, or the maps' width; mid/polar: the image size, default 256, as ``synth --mid``);
* ``texel_um`` [µm]: the texel (= micro pixel) size (micro default 1.8; mid/polar default
  ``field_mm / size``, which generates the material as ``synth --mid`` does; with ``maps`` the
  folder's own texel when it records one);
* ``field_mm`` [mm]: the field of the mid/polar cameras (default 100, the rig's);
* ``seed`` (default 0), ``shadows=0|1`` (cast shadows of the relief; micro only),
  ``noise=1|0`` (0: no shot/read noise, for exact checks), ``white_level`` (normalised DN where
  the sensor clips, default 1.0), ``readout_ms`` (dead time after each exposure, default 5);
* ``master=0|1``: camera-master (``internal`` triggers send edges to the simulator);
* fault injection: ``drop=P`` (probability that an exposed frame never arrives; its index is
  used up, so the delivered indices show the gap) with ``fault_seed=N``.

The serial is stable for a sample: ``SIM-<camera>-<8 hex digits of the sample, size and seed>``.

Timestamps (``Frame.timestamp_s``) are device time [s]: exact (the side-channel line's ``t_us``)
for edge, gate and camera-master frames; for a plain internal trigger the camera's estimate of
the device clock (last side-channel time + real time since x the simulator's speed;
``metadata["device_t_exact"]`` is False).

This module registers the ``sim`` scheme of :func:`dualscale.capture.camera.open_camera` when
imported; no production module imports it (the CLI does, to offer ``sim:`` cameras).
"""

from __future__ import annotations

import hashlib
import json
import math
import queue
import socket
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.capture.camera import (Deadline, Frame, SensorInfo, TriggerInfo, TriggerMode, collect_deadline,
                                      frame_metadata, register_backend, split_options)
from dualscale.errors import CameraDisconnected, CameraError, CameraTimeout, InputError
from dualscale.protocol import regmap as rm

OPTIONS = ("hw", "material", "maps", "target", "patch", "analyzer_offset", "size", "texel_um", "field_mm", "seed",
           "shadows", "noise", "white_level", "readout_ms", "master", "drop", "fault_seed")
"""The spec options this backend knows (module docstring); any other is an ``InputError``."""

DEFAULT_MATERIAL = "twill"
DEFAULT_READOUT_MS = 5.0
EXPOSURE_RANGE_S = (1e-6, 60.0)
"""The exposures a frame may have [s]: the firmware's bracket range (PROTOCOL.md §5: 1 µs .. 60 s)."""
HELLO_S = 5.0
"""Longest wait for the simulator's ``hello`` after connecting [s]."""
SYNC_S = 2.0
"""Longest wait for the side channel's answer to a synchronising line [s] (the simulator itself
drops a client that stalls this long)."""
SOURCE_KIND = {int(rm.Source.LED): "led", int(rm.Source.BACKLIGHT): "backlight", int(rm.Source.DIFFUSE): "diffuse"}
"""Side-channel light ``kind`` (``rm.Source``) -> the light kind of :mod:`dualscale.sim.targets`."""
TARGETS = ("white_sheet", "chart", "dot_grid", "polarization")
"""The calibration targets a simulated camera can look at (``target=``; :mod:`dualscale.sim.targets`)."""
RADIANCE_CACHE = 16
"""How many (lights, analyser) states keep their raw signal (a step's brackets reuse it)."""

Lights = tuple[tuple[int, int, int], ...]  # ((kind, index, intensity register value), ...), sorted


# ---- the spec ------------------------------------------------------------------------------------

def _opt_int(opts: dict[str, str], key: str, spec: str, default: int, low: int = 0) -> int:
    if key not in opts:
        return default
    try:
        v = int(opts[key])
    except ValueError:
        v = low - 1
    if v < low:
        raise InputError(f"camera {spec!r}: option {key}={opts[key]!r} must be an integer >= {low}")
    return v


def _opt_num(opts: dict[str, str], key: str, spec: str, default: float | None, low: float = 0.0,
             high: float = math.inf, low_open: bool = True) -> float | None:
    if key not in opts:
        return default
    try:
        v = float(opts[key])
    except ValueError:
        v = math.nan
    ok = math.isfinite(v) and (v > low if low_open else v >= low) and v <= high
    if not ok:
        rng = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise InputError(f"camera {spec!r}: option {key}={opts[key]!r} must be a number in {rng}")
    return v


def _opt_bool(opts: dict[str, str], key: str, spec: str, default: bool) -> bool:
    if key not in opts:
        return default
    if opts[key] not in ("0", "1"):
        raise InputError(f"camera {spec!r}: option {key}={opts[key]!r} must be 0 or 1")
    return opts[key] == "1"


@dataclass(frozen=True)
class SimOptions:
    """A parsed ``sim:`` spec (module docstring; lengths in the units their names say)."""

    camera: str
    hw: str
    material: str | None = DEFAULT_MATERIAL
    maps: str | None = None
    target: str | None = None
    patch: int | None = None
    analyzer_offset: float = 0.0
    size: int | None = None
    texel_um: float | None = None
    field_mm: float = 100.0
    seed: int = 0
    shadows: bool = False
    noise: bool = True
    white_level: float = 1.0
    readout_ms: float = DEFAULT_READOUT_MS
    master: bool = False
    drop: float = 0.0
    fault_seed: int = 0

    @classmethod
    def parse(cls, rest: str) -> SimOptions:
        """``"micro?hw=/tmp/hw.sock&material=twill&size=32"`` -> options; ``InputError`` naming the
        spec and the option for anything it cannot use."""
        spec = f"sim:{rest}"
        name, opts = split_options(rest)
        if name not in rm.CAMERA_NAMES:
            raise InputError(f"camera {spec!r}: give sim:CAMERA?hw=SOCKET with CAMERA one of "
                             f"{', '.join(rm.CAMERA_NAMES)}")
        unknown = sorted(set(opts) - set(OPTIONS))
        if unknown:
            raise InputError(f"camera {spec!r}: unknown option(s) {', '.join(unknown)}; known: {', '.join(OPTIONS)}")
        if not opts.get("hw"):
            raise InputError(f"camera {spec!r}: option hw=SOCKET (the simulator's --hw-socket) is required")
        if "material" in opts and "maps" in opts:
            raise InputError(f"camera {spec!r}: give material=NAME or maps=PATH, not both")
        target = opts.get("target")
        if target is not None and ("material" in opts or "maps" in opts):
            raise InputError(f"camera {spec!r}: give a sample (material=NAME or maps=PATH) or a calibration "
                             f"target (target=...), not both")
        if "patch" in opts and target is None:
            raise InputError(f"camera {spec!r}: patch= places a ColorChecker patch: it needs target=chart")
        patch = _opt_int(opts, "patch", spec, -1) if "patch" in opts else None
        check_target(name, target, patch, spec)
        shadows = _opt_bool(opts, "shadows", spec, False)
        if shadows and name != "micro":
            raise InputError(f"camera {spec!r}: shadows=1 works on the map grid only (the micro camera)")
        if shadows and target is not None:
            raise InputError(f"camera {spec!r}: shadows=1 needs a sample with relief, not target={target}")
        return cls(camera=name, hw=opts["hw"],
                   material=None if ("maps" in opts or target) else opts.get("material", DEFAULT_MATERIAL),
                   maps=opts.get("maps"), target=target, patch=patch,
                   analyzer_offset=_opt_num(opts, "analyzer_offset", spec, 0.0, low=-90.0, high=90.0, low_open=False),
                   size=_opt_int(opts, "size", spec, 0, low=8) or None,
                   texel_um=_opt_num(opts, "texel_um", spec, None), field_mm=_opt_num(opts, "field_mm", spec, 100.0),
                   seed=_opt_int(opts, "seed", spec, 0), shadows=shadows, noise=_opt_bool(opts, "noise", spec, True),
                   white_level=_opt_num(opts, "white_level", spec, 1.0, high=1.0),
                   readout_ms=_opt_num(opts, "readout_ms", spec, DEFAULT_READOUT_MS, low_open=False),
                   master=_opt_bool(opts, "master", spec, False),
                   drop=_opt_num(opts, "drop", spec, 0.0, high=1.0, low_open=False),
                   fault_seed=_opt_int(opts, "fault_seed", spec, 0))


def replace_target(o: SimOptions, target: str = "chart", patch: int | None = None) -> SimOptions:
    """``o`` looking at calibration target ``target`` instead of its sample."""
    from dataclasses import replace

    return replace(o, target=target, patch=patch, material=None, maps=None, shadows=False)


def check_target(camera: str, target: str | None, patch: int | None, spec: str) -> None:
    """``InputError`` naming ``spec`` unless camera ``camera`` can look at calibration target
    ``target`` (:data:`TARGETS`; ``None``: a sample) with ColorChecker ``patch`` (0..23, the
    patch centred under the micro camera; ``None``: the chart centred)."""
    if target is None:
        return
    if target not in TARGETS:
        raise InputError(f"camera {spec!r}: target={target!r}: one of {', '.join(TARGETS)}")
    if target in ("dot_grid", "polarization") and camera != "micro":
        raise InputError(f"camera {spec!r}: the {target} target is imaged by the micro camera only")
    if patch is not None:
        if target != "chart":
            raise InputError(f"camera {spec!r}: patch= places a ColorChecker patch: it needs target=chart")
        if camera != "micro":
            raise InputError(f"camera {spec!r}: patch= moves the chart under the micro camera; the {camera} camera "
                             f"images the whole chart (leave patch out)")
        if not 0 <= patch < 24:
            raise InputError(f"camera {spec!r}: patch={patch}: a ColorChecker patch is 0..23")


# ---- the scene: sample, camera geometry, sensor --------------------------------------------------

class _LightSum:
    """What both scenes share: the raw camera signal of a light state as the sum of each light's
    signal at full intensity times its drive level (the renderer and the sensor's raw signal are
    linear in the light), cached per (lights, analyser) state, and one exposure of it.
    Subclasses give ``camera``, ``exposer``, ``_analyser(polarizer_cdeg)`` and
    ``_one(kind, index, cdeg)`` (``(H, W, 3)`` float64 raw signal of one light at full intensity)."""

    _cache: OrderedDict
    renders: int
    render_s: float

    def _analyser(self, polarizer_cdeg: int | None) -> int | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _one(self, kind: str, index: int | None, cdeg: int | None) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def raw(self, lights: Lights, polarizer_cdeg: int | None) -> np.ndarray:
        """The raw signal ``(H, W, 3)`` for ``lights`` ((rm.Source kind, index, intensity register
        value), ...) with the analyser at ``polarizer_cdeg`` [centidegrees] (ignored where the
        camera or target has none)."""
        cdeg = self._analyser(polarizer_cdeg)
        key = (lights, cdeg)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        t0 = time.perf_counter()
        out = np.zeros((self.camera.height, self.camera.width, 3))
        for kind, index, intensity in lights:
            name = SOURCE_KIND.get(kind)
            if name is None or intensity <= 0:
                continue
            out = out + self._one(name, index if name != "diffuse" else None, cdeg) * (intensity / rm.INTENSITY_MAX)
        self.renders += 1
        self.render_s += time.perf_counter() - t0
        self._cache[key] = out
        while len(self._cache) > RADIANCE_CACHE:
            self._cache.popitem(last=False)
        return out

    def expose(self, raw: np.ndarray, exposure_s: float, shot: object = None) -> np.ndarray:
        """One exposure of ``raw`` for ``exposure_s`` [s]: float32 normalised DN ``(H, W, 3)``;
        ``shot`` the shot's identity, which fixes its noise (:class:`~dualscale.sim.targets.Exposer`)."""
        return np.asarray(self.exposer(raw, exposure_s, shot), dtype=np.float32)


class Scene(_LightSum):
    """What the camera looks at and how it records it: the sample's maps on the dome, the camera's
    geometry (:mod:`dualscale.geometry.cameras`) and its sensor (:func:`~dualscale.sim.targets.rig_exposer`).

    :meth:`raw` is the raw camera signal ``(H, W, 3)`` float64 of a light state (cached);
    :meth:`expose` one exposure of it in normalised DN."""

    def __init__(self, o: SimOptions, spec: str):
        import torch

        from dualscale.geometry.cameras import micro_camera, mid_camera, polar_camera
        from dualscale.geometry.dome import DomeGeometry
        from dualscale.sim.targets import Defects, SynthConfig, rig_exposer

        self.options = o
        geometry = None
        if o.maps is not None:
            from dualscale.formats.maps import load_maps

            maps, meta = load_maps(o.maps, dtype=torch.float32)
            h, w = maps.shape
            meta_texel_um = float(meta["texel_mm"]) * 1000.0 if meta.get("texel_mm") else None
            if o.camera == "micro":
                if h != w:
                    raise InputError(f"camera {spec!r}: the micro camera needs square maps, {o.maps} is {h}x{w}")
                if o.size is not None and o.size != w:
                    raise InputError(f"camera {spec!r}: size={o.size}, but the micro camera images the map grid "
                                     f"and {o.maps} is {w} texels wide (leave size out)")
            if o.shadows:
                from dualscale.formats.relief import load_geometry

                path = Path(o.maps) / "geometry.exr"
                if not path.is_file():
                    raise InputError(f"camera {spec!r}: shadows=1 needs the relief {path}")
                geometry = load_geometry(path)
            texel_um = o.texel_um or meta_texel_um or 1.8
            source = f"maps:{Path(o.maps).resolve()}"
            size = w if o.camera == "micro" else (o.size or 256)
        else:
            from dualscale.sim.materials import generate

            size = o.size or (512 if o.camera == "micro" else 256)
            texel_um = o.texel_um or (1.8 if o.camera == "micro" else o.field_mm * 1000.0 / size)
            mat = generate(o.material or DEFAULT_MATERIAL, size, texel_um / 1000.0, o.seed)
            maps, meta = mat.maps, mat.meta
            geometry = mat.geometry if o.shadows else None
            source = f"material:{o.material}"
        if o.shadows and geometry is None:
            raise InputError(f"camera {spec!r}: shadows=1, but the material has no relief")
        if o.camera == "micro":
            cam, texel_mm = micro_camera(maps.shape[1], texel_um), None
        elif o.camera == "mid":
            cam, texel_mm = mid_camera(size, field_mm=o.field_mm), texel_um / 1000.0
        else:
            cam, texel_mm = polar_camera(int(o.camera[-1]), size, field_mm=o.field_mm), texel_um / 1000.0
        self.maps, self.meta, self.geometry, self.camera, self.texel_mm = maps, meta, geometry, cam, texel_mm
        self.texel_um, self.source = texel_um, source
        self.dome = DomeGeometry.from_regmap()
        self.cfg = SynthConfig(white_level=o.white_level)
        self.defects = Defects()
        self.exposer = rig_exposer(cam, self.cfg, self.defects, noise=o.noise)
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.renders = 0
        self.render_s = 0.0

    def identity(self) -> str:
        """The sample and sensor geometry the serial is made from."""
        o = self.options
        return f"{self.source}|seed={o.seed}|size={self.camera.width}|texel_um={self.texel_um:g}|field_mm={o.field_mm:g}"

    def _analyser(self, polarizer_cdeg: int | None) -> int | None:
        return polarizer_cdeg if self.camera.has_analyzer else None

    def _one(self, kind: str, index: int | None, cdeg: int | None) -> np.ndarray:
        """One light at full intensity, rendered (:func:`dualscale.sim.render.render`) and made
        the camera's raw signal (:func:`dualscale.sim.targets.raw_signal`)."""
        import torch

        from dualscale.sim.render import Analyzer, LightRealism, LightState, render
        from dualscale.sim.targets import raw_signal

        an = None if cdeg is None else Analyzer(cdeg / 100.0, relative=True)
        state = (LightState.led(index) if kind == "led" else
                 LightState.backlight(index) if kind == "backlight" else LightState.diffuse_group())
        rad = render(self.maps, self.camera, state, self.dome, an, texel_mm=self.texel_mm, geometry=self.geometry,
                     realism=LightRealism(shadows=self.geometry is not None))
        with torch.no_grad():
            rad_np = rad.detach().double().cpu().numpy()
        return raw_signal(rad_np, self.camera, kind, index, self.cfg, self.defects)


class TargetScene(_LightSum):
    """A calibration target on the virtual rig's holder, as :func:`dualscale.sim.targets.write_session`
    renders it (``dualscale synth-targets``), seen by one camera; the same interface as :class:`Scene`.

    The radiance is :mod:`dualscale.sim.targets`' own, with its :class:`~dualscale.sim.targets.SynthConfig`
    (this camera's white level) and :class:`~dualscale.sim.targets.Defects` (seed ``seed``): the white
    sheet and the ColorChecker through :func:`~dualscale.sim.targets.true_radiance` (the chart centred;
    with a ``patch`` the micro camera sees that patch filling its field, target ``patch``); the dot
    grid (:func:`~dualscale.sim.targets.dot_albedo` of :func:`~dualscale.sim.targets.dot_grid_truth`,
    dots of reflectance ``DOT_R`` on ``DOT_BG_R``) and the glossy dark polarisation target (reflectance
    0.05, ``pol_roughness``) composed as ``_dot_grid`` and ``_polarization`` compose them.  Summed over
    the lights that are on, each times its intensity register / ``INTENSITY_MAX``.  What differs from
    a sample scene, as in ``write_session``:

    * the analyser: only the micro camera's (the servo-turned one) is rendered, at the servo angle
      relative to each LED's polariser, except on the polarisation target, where the angle is
      absolute (the image's +x) plus ``analyzer_offset`` [deg] (the analyser's misalignment, what
      ``evaluate-device`` measures); the dot grid is rendered without it (as ``_dot_grid``); the
      mid and polar cameras see the targets without an analyser;
    * the sensor (:class:`~dualscale.sim.targets.Exposer`): :func:`~dualscale.sim.targets.rig_exposer`
      for the white sheet and the chart, seed 99 without vignetting for the dot grid, seed 77 for the
      polarisation target (``write_session``'s sensors, hence its dark patterns);
    * no exposure jitter: ``Defects.diffuse_jitter`` models a DSLR's shutter, not a gate-triggered
      exposure, so the mid camera's diffuse captures are not scaled by it;
    * the dot grid and the polarisation target are black to a back light (opaque); the LED gains and
      collimation ramps apply to the dot grid under an LED (``true_radiance``'s rule), not to the
      polarisation target (``_polarization`` has none).

    :meth:`place` is the virtual operator: it puts another target on the holder (or moves the chart
    so that ``patch`` fills the micro field)."""

    def __init__(self, o: SimOptions, spec: str, camera=None, exposer=None):
        from dualscale.calib.chart import ChartLayout
        from dualscale.geometry.cameras import micro_camera, mid_camera, polar_camera
        from dualscale.geometry.dome import DomeGeometry
        from dualscale.sim.targets import MICRO_FIELD_MM, Defects, SynthConfig

        self.options, self.spec = o, spec
        if camera is None:
            if o.camera == "micro":
                size = o.size or 512
                camera = micro_camera(size, o.texel_um or MICRO_FIELD_MM * 1000.0 / size)
            elif o.camera == "mid":
                camera = mid_camera(o.size or 256, field_mm=o.field_mm)
            else:
                camera = polar_camera(int(o.camera[-1]), o.size or 256, field_mm=o.field_mm)
        self.camera = camera
        self.texel_um = camera.pixel_mm[0] * 1000.0
        self.dome = DomeGeometry.from_regmap()
        self.layout = ChartLayout()
        self.cfg = SynthConfig(white_level=o.white_level)
        self.defects = Defects(analyzer_offset_deg=o.analyzer_offset, seed=o.seed)
        self._exposers: dict[str, Any] = {} if exposer is None else {"rig": exposer}
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._dots: np.ndarray | None = None
        self.renders = 0
        self.render_s = 0.0
        self.target, self.patch = "", None
        self.place(o.target or "white_sheet", o.patch)

    @property
    def source(self) -> str:
        """``target:NAME`` (``target:chart/patchNN`` with a patch under the micro camera)."""
        return f"target:{self.target}" + ("" if self.patch is None else f"/patch{self.patch:02d}")

    def identity(self) -> str:
        """The target and sensor geometry the serial is made from."""
        o = self.options
        return (f"target:{o.target}|patch={o.patch}|seed={o.seed}|size={self.camera.width}|texel_um={self.texel_um:g}"
                f"|field_mm={o.field_mm:g}")

    def place(self, target: str, patch: int | None = None) -> None:
        """Put ``target`` (:data:`TARGETS`) on the holder; ``patch`` (0..23, ``target`` ``chart``,
        micro camera): move the chart so that this patch fills the micro camera's field."""
        check_target(self.camera.name, target, patch, self.spec)
        if (target, patch) != (self.target, self.patch):
            self.target, self.patch = target, patch
            self._cache.clear()

    @property
    def exposer(self):
        """The sensor of the current target (class doc)."""
        from dataclasses import replace

        from dualscale.sim.targets import Exposer, rig_exposer

        kind = self.target if self.target in ("dot_grid", "polarization") else "rig"
        ex = self._exposers.get(kind)
        if ex is None:
            noise = self.options.noise
            ex = (Exposer(self.camera, self.cfg, replace(self.defects, vignetting=0.0), 99, noise=noise)
                  if kind == "dot_grid" else Exposer(self.camera, self.cfg, self.defects, 77, noise=noise)
                  if kind == "polarization" else rig_exposer(self.camera, self.cfg, self.defects, noise=noise))
            self._exposers[kind] = ex
        return ex

    def _one(self, kind: str, light_id: int | None, cdeg: int | None) -> np.ndarray:
        """The radiance of the current target under one light at full intensity (class doc)."""
        from dualscale.calib import colourref as cr
        from dualscale.sim.render import Analyzer
        from dualscale.sim.targets import (DOT_BG_R, DOT_R, collimation_ramp, dot_albedo, dot_grid_truth,
                                           geometry_factors, led_gains, true_radiance)

        cam, cfg, d = self.camera, self.cfg, self.defects
        micro = cam.name == "micro"
        if self.target in ("white_sheet", "chart"):
            an = Analyzer(cdeg / 100.0, relative=True) if micro and cdeg is not None else None
            name = "patch" if self.patch is not None else self.target
            return true_radiance(name, cam, kind, light_id, cfg, d, self.dome, self.layout, patch=self.patch, analyzer=an)
        if kind == "backlight":  # opaque targets
            return np.zeros((cam.height, cam.width, 3))
        sens, ill = cfg.sens(cam.name), cfg.illum(kind)
        white = cr.camera_raw([cr.flat_spectrum(1.0, 1.0)], sens, ill)[0]
        if self.target == "dot_grid":
            if self._dots is None:
                _, sig = dot_grid_truth(cam.width, self.texel_um, d)
                self._dots = dot_albedo(cam.width, self.texel_um, sig)
            w = self._dots[..., None]
            cols = cr.camera_raw([cr.flat_spectrum(DOT_BG_R, DOT_BG_R), cr.flat_spectrum(DOT_R, DOT_R)], sens, ill)
            g_d, g_s = geometry_factors(cam, kind, light_id, None, cfg.roughness, self.dome)
            rad = (cols[0] * (1 - w) + cols[1] * w) * g_d[..., None] + white * g_s[..., None]
            if kind == "led":
                rad = rad * led_gains(self.dome.n_leds, d)[light_id] * collimation_ramp(cam, light_id, d)[..., None]
            return rad
        an = None if cdeg is None else Analyzer(cdeg / 100.0 + d.analyzer_offset_deg)
        col = cr.camera_raw([cr.flat_spectrum(0.05, 0.05)], sens, ill)[0]
        g_d, g_s = geometry_factors(cam, kind, light_id, an, cfg.pol_roughness, self.dome)
        return col * g_d[..., None] + white * g_s[..., None]

    def _analyser(self, polarizer_cdeg: int | None) -> int | None:
        return polarizer_cdeg if self.camera.name == "micro" and self.target != "dot_grid" else None

    def holder(self) -> dict[str, Any]:
        """What the rig's operator reads off this camera's view of the holder, as ``write_session``
        records it: ``markers`` (the mid camera: pixel boxes ``[row0, row1, col0, col1]`` inside the
        holder's white markers, :func:`~dualscale.sim.targets.marker_boxes`) and ``chart_corners``
        (the polar cameras: the centred chart's swatch-area corners TL, TR, BR, BL as image ``(x, y)``,
        :func:`~dualscale.sim.targets.chart_corners`).  Empty for the micro camera."""
        from dualscale.sim.targets import chart_corners, marker_boxes

        if self.camera.name == "mid":
            return {"markers": {"mid": marker_boxes(self.camera)}}
        if self.camera.name.startswith("polar"):
            return {"chart_corners": {self.camera.name: chart_corners(self.camera, self.layout).tolist()}}
        return {}

# ---- the camera ----------------------------------------------------------------------------------

@dataclass
class _Exposure:
    """One exposure waiting for the render worker."""

    generation: int
    index: int
    t_us: int
    exposure_s: float
    lights: Lights
    polarizer_cdeg: int
    info: TriggerInfo
    source: str                      # "edge", "gate", "software" or "master"
    exact: bool                      # t_us is a side-channel time (not an estimate)
    extra: dict[str, Any] = field(default_factory=dict)


class SimCamera:
    """A camera of the simulated rig (module docstring).  Implements
    :class:`dualscale.capture.camera.Camera`; open it with ``open_camera("sim:...")``."""

    def __init__(self, rest: str):
        self.spec = f"sim:{rest}"
        o = SimOptions.parse(rest)
        self.options = o
        self.name = o.camera
        self.bit = rm.TRIGGER_NAMES.index(o.camera)
        self.camera_index = rm.CAMERA_NAMES.index(o.camera)
        self.scene: Scene | TargetScene = TargetScene(o, self.spec) if o.target else Scene(o, self.spec)
        digest = hashlib.sha1(self.scene.identity().encode()).hexdigest()[:8].upper()
        self.serial = f"SIM-{o.camera}-{digest}"
        self.readout_s = o.readout_ms / 1000.0
        self._rng = np.random.default_rng(o.fault_seed)
        self._cond = threading.Condition()
        self._send_lock = threading.Lock()
        # live state (reader thread)
        self._lights: dict[tuple[int, int], int] = {}
        self._polarizer = 0
        self._level: int | None = None
        self._last_t_us = 0
        self._last_mono = time.monotonic()
        self._rate = 1.0
        self._hello: dict[str, Any] | None = None
        self._syncs = 0
        self._edge_events: list[dict[str, Any]] = []
        self._disconnected: str | None = None
        self._failed: str | None = None  # a frame that could not be rendered (a bug, not the link)
        self._stop = False
        # acquisition
        self._info: TriggerInfo | None = None
        self._armed = False
        self._generation = 0
        self._exposed = 0            # exposures started this acquisition (dropped ones included)
        self._pending = 0            # exposures queued and not yet rendered
        self._busy_until_us = -1     # device time until which the sensor is exposing / reading out
        self._soft_busy_until_us = -1  # the same, of the last internal-trigger exposure (arm() waits for it)
        self._gate: tuple[int, Lights, int] | None = None
        self._frames: list[Frame] = []
        self._counters = {"ignored_triggers": 0, "busy_triggers": 0, "dropped_frames": 0, "unarmed_triggers": 0}
        self._jobs: queue.Queue[_Exposure | None] = queue.Queue()
        self._sock = self._connect(o.hw)
        self._reader = threading.Thread(target=self._read_loop, name=f"sim-camera-{o.camera}-sidechan", daemon=True)
        self._worker = threading.Thread(target=self._render_loop, name=f"sim-camera-{o.camera}-render", daemon=True)
        self._reader.start()
        self._worker.start()
        deadline = Deadline(HELLO_S)
        with self._cond:
            while self._hello is None and self._disconnected is None and not deadline.expired():
                self._cond.wait(deadline.remaining())
            hello = self._hello
        if hello is None:
            why = self._disconnected or f"no hello within {HELLO_S:g} s"
            self.close()
            raise CameraDisconnected(f"camera {self.spec!r}: the simulator's side channel {o.hw} did not greet ({why})")

    # -- the side channel ----------------------------------------------------------------------
    def _connect(self, path: str) -> socket.socket:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(path)
        except OSError as e:
            s.close()
            raise CameraDisconnected(f"camera {self.spec!r}: cannot connect to the simulator's side channel "
                                     f"{path} ({e.strerror or e}); start it with `dualscale sim --hw-socket {path}`") from e
        s.settimeout(0.2)
        return s

    def _send(self, line: dict[str, Any]) -> None:
        data = (json.dumps(line, separators=(",", ":")) + "\n").encode()
        try:
            with self._send_lock:
                self._sock.sendall(data)
        except OSError as e:
            self._lost(f"sending failed: {e}")
            raise CameraDisconnected(f"camera {self.spec!r}: the simulator's side channel {self.options.hw} "
                                     f"is gone ({e})") from e

    def _lost(self, why: str) -> None:
        with self._cond:
            if self._disconnected is None:
                self._disconnected = why
            self._cond.notify_all()

    def _read_loop(self) -> None:
        buf = b""
        while not self._stop:
            try:
                chunk = self._sock.recv(65536)
            except socket.timeout:
                continue
            except OSError as e:
                self._lost(f"read failed: {e}")
                return
            if not chunk:
                self._lost("the simulator closed the side channel")
                return
            buf += chunk
            *lines, buf = buf.split(b"\n")
            with self._cond:
                for ln in lines:
                    if ln.strip():
                        try:
                            self._handle(json.loads(ln))
                        except (ValueError, KeyError, TypeError):
                            continue  # not a line of ours to judge; the state is unchanged
                self._cond.notify_all()

    def _handle(self, o: dict[str, Any]) -> None:
        """One side-channel line, under ``self._cond``."""
        ev = o.get("ev")
        if "t_us" in o:
            t = int(o["t_us"])
            if t >= self._last_t_us:
                self._last_t_us, self._last_mono = t, time.monotonic()
        if ev == "light":
            key = (int(o["kind"]), int(o["index"]))
            if int(o["intensity"]) > 0:
                self._lights[key] = int(o["intensity"])
            else:
                self._lights.pop(key, None)
        elif ev == "polarizer":
            self._polarizer = int(o["cdeg"])
        elif ev == "triggers":
            self._on_triggers(int(o["mask"]), int(o["t_us"]))
        elif ev == "event":
            if int(o["kind"]) == rm.Event.CAMERA_EDGE and (int(o["arg"]) & ~rm.EDGE_IGNORED) == self.camera_index:
                self._edge_events.append({k: o[k] for k in ("t_us", "seq", "step", "arg")}
                                         | {"ignored": bool(int(o["arg"]) & rm.EDGE_IGNORED)})
        elif ev in ("error", "pong"):  # the answer to a synchronising line (_sync)
            self._syncs += 1
        elif ev == "hello":
            speed = float(o.get("speed", 1.0))
            self._rate = speed if speed > 0 else 1.0  # speed 0 runs at 1x between jumps (sim.h)
            self._hello = o

    def _snapshot(self) -> Lights:
        return tuple(sorted((k, i, v) for (k, i), v in self._lights.items()))

    def _on_triggers(self, mask: int, t_us: int) -> None:
        level = (mask >> self.bit) & 1
        prev, self._level = self._level, level
        if prev is None or level == prev:
            return
        info = self._info
        hw_mode = info is not None and info.mode in (TriggerMode.EDGE, TriggerMode.GATE)
        if level:  # rising edge
            if not (self._armed and hw_mode):
                self._counters["unarmed_triggers"] += 1
                return
            if self._exposed >= info.frames:
                self._counters["ignored_triggers"] += 1
                return
            if t_us < self._busy_until_us:
                self._counters["busy_triggers"] += 1
                return
            if info.mode == TriggerMode.EDGE:
                self._busy_until_us = t_us + round(info.exposure_s * 1e6 + self.readout_s * 1e6)
                self._queue(t_us, info.exposure_s, self._snapshot(), "edge", True)
            else:
                self._gate = (t_us, self._snapshot(), self._polarizer)
                self._busy_until_us = 2 ** 63  # exposing until the gate falls
        elif self._gate is not None and self._armed and info is not None and info.mode == TriggerMode.GATE:
            t0, lights, cdeg = self._gate
            self._gate = None
            self._busy_until_us = t_us + round(self.readout_s * 1e6)
            exposure = max((t_us - t0) / 1e6, EXPOSURE_RANGE_S[0])
            self._queue(t0, exposure, lights, "gate", True, polarizer_cdeg=cdeg)

    def _queue(self, t_us: int, exposure_s: float, lights: Lights, source: str, exact: bool,
               polarizer_cdeg: int | None = None, extra: dict[str, Any] | None = None) -> None:
        """Start exposure number ``self._exposed`` (under ``self._cond``); ``drop`` may lose it."""
        index = self._exposed
        self._exposed += 1
        if self.options.drop > 0 and self._rng.random() < self.options.drop:
            self._counters["dropped_frames"] += 1
            return
        self._pending += 1
        self._jobs.put(_Exposure(self._generation, index, int(t_us), float(exposure_s), lights,
                                 self._polarizer if polarizer_cdeg is None else polarizer_cdeg, self._info,
                                 source, exact, dict(extra or {})))

    def _device_now_us(self) -> int:
        """The device clock now [µs], estimated (under ``self._cond``)."""
        return self._last_t_us + int((time.monotonic() - self._last_mono) * self._rate * 1e6)

    def _sync(self) -> None:
        """Wait until every line the simulator published before now has been handled: send a line
        the simulator answers (it answers anything but an edge with an ``error`` line, and handles
        a client's lines in order, after publishing what they caused).  ``CameraDisconnected`` if
        the side channel is gone or silent for :data:`SYNC_S`."""
        with self._cond:
            n0 = self._syncs
        self._send({"ev": "ping"})
        deadline = Deadline(SYNC_S)
        with self._cond:
            while self._syncs <= n0 and self._disconnected is None and not deadline.expired():
                self._cond.wait(deadline.remaining())
            if self._syncs <= n0:
                why = self._disconnected or f"no answer within {SYNC_S:g} s"
                raise CameraDisconnected(f"camera {self.spec!r}: the simulator's side channel {self.options.hw} "
                                         f"stopped answering ({why})")

    # -- rendering -----------------------------------------------------------------------------
    def _render_loop(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                raw = self.scene.raw(job.lights, job.polarizer_cdeg)
                # the noise is drawn per shot identity, so a resumed capture equals an uninterrupted one;
                # a dark frame's (no light on) does not depend on where the analyser happens to be
                # (after a resume the servo starts elsewhere: issue 27's adaptive capture takes darks
                # between rounds)
                dark = not any(int(v) > 0 for _k, _i, v in job.lights)
                image = self.scene.expose(raw, job.exposure_s, (self.scene.identity(), job.lights,
                                                                None if dark else job.polarizer_cdeg,
                                                                round(job.exposure_s, 9)))
                error = None
            except Exception as e:  # noqa: BLE001 - reported through collect(), never lost silently
                image, error = None, f"{type(e).__name__}: {e}"
            with self._cond:
                self._pending -= 1
                if error is not None:
                    self._failed = self._failed or f"rendering frame {job.index} failed: {error}"
                elif job.generation == self._generation:
                    meta = frame_metadata(self, job.info)
                    meta.update({"device_t_us": job.t_us, "device_t_exact": job.exact,
                                 "lights": [list(x) for x in job.lights],
                                 "polarizer_cdeg": job.polarizer_cdeg if self.scene.camera.has_analyzer else None,
                                 "trigger_source": job.source, **job.extra})
                    self._frames.append(Frame(image=image, index=job.index, timestamp_s=job.t_us / 1e6,
                                              exposure_s=job.exposure_s, metadata=meta))
                self._cond.notify_all()

    # -- the virtual operator ------------------------------------------------------------------
    def place(self, target: str, patch: int | None = None) -> None:
        """The virtual rig's operator at the holder: put calibration target ``target``
        (:data:`TARGETS`) in front of this camera, or move the chart so that ColorChecker ``patch``
        (0..23) fills the micro camera's field (:meth:`TargetScene.place`); a camera that looked at
        a sample now looks at the target, through the same geometry and sensor.  Waits for the
        frames still being rendered; ``CameraError`` while armed, ``InputError`` for a target this
        camera cannot image."""
        deadline = Deadline(30.0)
        with self._cond:
            while self._pending and not deadline.expired():
                self._cond.wait(deadline.remaining())
            if self._armed or self._pending:
                raise CameraError(f"camera {self.spec!r}: the target cannot be moved during an acquisition")
            if isinstance(self.scene, TargetScene):
                self.scene.place(target, patch)
            else:
                check_target(self.options.camera, target, patch, self.spec)
                self.scene = TargetScene(replace_target(self.options, target, patch), self.spec,
                                         camera=self.scene.camera, exposer=self.scene.exposer)

    def holder(self) -> dict[str, Any]:
        """The holder as seen by this camera, for the capture set (:meth:`TargetScene.holder`:
        the mid camera's white-marker boxes, a polar camera's chart corners)."""
        with self._cond:
            scene = self.scene
        if not isinstance(scene, TargetScene):
            scene = TargetScene(replace_target(self.options), self.spec, camera=scene.camera)
        return scene.holder()

    # -- the contract --------------------------------------------------------------------------
    def geometry(self):
        """The camera's geometry on the rig (:class:`dualscale.geometry.cameras.Camera`: name,
        projection, size, field [mm], analyser), the one its frames are rendered with: what a
        dataset records for this camera."""
        return self.scene.camera

    def sensor(self) -> SensorInfo:
        """The simulated sensor: the camera's size, pixel pitch [µm] (the micro camera's texel, a
        mid/polar camera's field / size), 12 bits, black level 0 (the dark signal is measured from
        dark frames, as on the rig), white level ``SynthConfig.white_level``."""
        cam = self.scene.camera
        return SensorInfo(width=cam.width, height=cam.height, pixel_um=cam.pixel_mm[0] * 1000.0,
                          bit_depth=self.scene.cfg.sensor().bits, black_level=0.0,
                          white_level=float(np.min(self.scene.cfg.white_level)), pixel_format="RGB12")

    def settings(self) -> dict[str, Any]:
        o = self.options
        with self._cond:
            counters = dict(self._counters)
        return {"backend": "sim", "camera": o.camera, "hw": o.hw, "sample": self.scene.source,
                "size": self.scene.camera.width, "texel_um": self.scene.texel_um,
                "field_mm": None if o.camera == "micro" else o.field_mm, "seed": o.seed, "shadows": o.shadows,
                "noise": o.noise, "white_level": o.white_level, "readout_s": self.readout_s, "master": o.master,
                "trigger_bit": self.bit, "sensitivity": self.scene.cfg.sens(o.camera),
                "drop": o.drop, "fault_seed": o.fault_seed, **counters}

    def supported_modes(self) -> tuple[TriggerMode, ...]:
        return (TriggerMode.INTERNAL, TriggerMode.EDGE, TriggerMode.GATE)

    def prepare(self, info: TriggerInfo) -> None:
        """Declare the acquisition; ``InputError`` for an exposure outside 1 µs .. 60 s, or a
        hardware-trigger mode on a camera-master camera (it is triggered by :meth:`trigger`)."""
        lo, hi = EXPOSURE_RANGE_S
        if not lo <= info.exposure_s <= hi:
            raise InputError(f"camera {self.spec!r}: exposure {info.exposure_s!r} s outside {lo:g} .. {hi:g} s")
        if self.options.master and info.mode != TriggerMode.INTERNAL:
            raise InputError(f"camera {self.spec!r}: a camera-master camera (master=1) takes internal triggers only "
                             f"(each trigger() sends its edge to the rig), not {info.mode.value!r}")
        with self._cond:
            self._armed = False
            self._gate = None
            self._info = info

    def arm(self) -> None:
        """Start the acquisition :meth:`prepare` declared.  For the rig's edges (``edge``/``gate``)
        first wait until an internal-trigger exposure still running on the device clock (its
        frame came at once, when rendered) and its readout have ended: edges inside it would be
        missed as ``busy_triggers``, which a real camera, whose frame comes only after the
        exposure, never shows a host that waited for its frame."""
        with self._cond:
            if self._info is None:
                raise InputError(f"camera {self.spec!r}: arm() before prepare()")
            if self._info.mode in (TriggerMode.EDGE, TriggerMode.GATE):
                while not self._stop and self._disconnected is None:
                    left_us = self._soft_busy_until_us - self._device_now_us()
                    if left_us <= 0:
                        break
                    self._cond.wait(min(left_us / 1e6 / self._rate, 0.5))
            self._generation += 1
            self._frames = []
            self._exposed = 0
            self._gate = None
            self._counters = {k: 0 for k in self._counters}
            self._armed = True

    def trigger(self) -> None:
        """``internal`` mode: expose now (blocks until the sensor is free of its previous
        exposure and readout, in device time).  With ``master=1`` first send the camera-master
        edge and expose the state the firmware latched on it."""
        with self._cond:
            info = self._info
            if info is None or not self._armed:
                raise InputError(f"camera {self.spec!r}: trigger() while not armed (prepare() and arm() first)")
            if info.mode != TriggerMode.INTERNAL:
                raise InputError(f"camera {self.spec!r}: trigger() in {info.mode.value} mode (the rig's trigger "
                                 "line starts the exposures)")
            if self._exposed >= info.frames:
                raise InputError(f"camera {self.spec!r}: trigger() beyond the {info.frames} frame(s) armed for")
            if self._disconnected is not None:
                raise CameraDisconnected(f"camera {self.spec!r}: the simulator's side channel is gone "
                                         f"({self._disconnected})")
            wait_us = self._busy_until_us - self._device_now_us()
            rate = self._rate
        if wait_us > 0:
            time.sleep(wait_us / 1e6 / rate)
        with self._cond:
            n_edges = len(self._edge_events)
        if self.options.master:
            self._send({"ev": "edge", "camera": self.camera_index})
        self._sync()
        with self._cond:
            extra: dict[str, Any] = {}
            edges = self._edge_events[n_edges:] if self.options.master else []
            if self.options.master:
                extra["master_edge"] = edges[0] if edges else None  # None: the rig did not count it
            if edges:
                t_us, exact = int(edges[0]["t_us"]), True
            else:
                t_us, exact = max(self._device_now_us(), self._busy_until_us, self._last_t_us), False
            self._busy_until_us = t_us + round((info.exposure_s + self.readout_s) * 1e6)
            self._soft_busy_until_us = self._busy_until_us
            self._queue(t_us, info.exposure_s, self._snapshot(), "master" if self.options.master else "software",
                        exact, extra=extra)

    def collect(self, timeout_s: float | None = None) -> list[Frame]:
        """The armed frames, in order.  Fewer by ``timeout_s`` (default
        ``TriggerInfo.total_timeout()``, from this call) raise ``CameraTimeout`` carrying those that
        arrived (at once when every armed exposure was taken and the rest were lost to ``drop``);
        a side channel that closed raises ``CameraDisconnected`` (its ``frames`` likewise)
        once the exposures taken before are rendered; a frame that could not be rendered raises
        ``CameraError`` (with ``frames``) at once."""
        info, wait, deadline = collect_deadline(self.spec, self._info, timeout_s)
        with self._cond:
            while len(self._frames) < info.frames and not deadline.expired() and self._failed is None:
                if self._pending == 0 and (self._disconnected is not None or self._exposed >= info.frames):
                    break  # nothing more can come: the link is gone, or every armed exposure is done
                self._cond.wait(min(deadline.remaining(), 0.5))
            frames = sorted(self._frames, key=lambda f: f.index)
            gone, failed, counters = self._disconnected, self._failed, dict(self._counters)
            done = self._exposed >= info.frames and self._pending == 0
        if len(frames) < info.frames:
            seen = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counters.items() if v)
            msg = (f"camera {self.spec!r}: {len(frames)} of {info.frames} frame(s)"
                   + (f"; {seen}" if seen else ""))
            err: CameraError
            if failed is not None:
                err = CameraError(f"{msg}; {failed}")
            elif gone is not None:
                err = CameraDisconnected(f"{msg}; the simulator's side channel is gone ({gone})")
            elif done:  # lost frames (drop=): known at once, as a real camera knows a frame-id gap
                raise CameraTimeout(f"{msg}; all {info.frames} armed exposure(s) taken, the missing frame(s) "
                                    f"were lost", frames=frames)
            else:
                raise CameraTimeout(f"{msg} within {wait:.3g} s", frames=frames)
            err.frames = frames  # never drop what arrived
            raise err
        return frames

    def disarm(self) -> None:
        with self._cond:
            self._armed = False
            self._gate = None

    def close(self) -> None:
        """Stop both threads and close the socket; safe to call more than once."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._jobs.put(None)
        for th in (getattr(self, "_reader", None), getattr(self, "_worker", None)):
            if th is not None and th.is_alive() and th is not threading.current_thread():
                th.join(timeout=10.0)
        self._sock.close()

    def __enter__(self) -> SimCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_sim_camera(rest: str) -> SimCamera:
    """The ``sim`` backend's factory: ``rest`` is the spec after ``sim:`` (module docstring)."""
    return SimCamera(rest)


register_backend("sim", open_sim_camera)
