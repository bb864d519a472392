"""One camera contract for the rig and every backend (issue 14 §1).

The lifecycle follows ophyd-async's detector protocol and Micro-Manager's sequence acquisition:

1. ``prepare(TriggerInfo)`` -- the trigger (``internal``: the camera times itself, or the host
   calls :meth:`Camera.trigger`; ``edge``: one frame per rising edge of its trigger input;
   ``gate``: the exposure lasts while the input is high), the number of frames, the exposure and
   the dead time are declared *before* arming; a camera refuses what it cannot do
   (``InputError``) here, never later;
2. ``arm()`` -- ready for the first trigger;
3. ``collect(timeout_s)`` -- wait for the armed frames; fewer than armed by the timeout raises
   :class:`~dualscale.errors.CameraTimeout` carrying the frames that did arrive;
4. ``disarm()`` -- stop; safe to call at any time and more than once.

What a camera reports (:meth:`Camera.sensor`, :meth:`Camera.settings`, ``serial``) goes into
every :class:`Frame`'s metadata (:meth:`Camera.frame_metadata`).  Pixel values are raw
digital numbers normalised to the sensor's full scale, ``DN / (2^bits - 1)`` in [0, 1], as
``float32`` ``(H, W)`` (mono/raw Bayer) or ``(H, W, 3)`` (RGB): the units the calibration reads
(``dn_normalized``, docs/CALIBRATION.md).

Backends are chosen by a URL-like spec, ``scheme:rest`` (``sim:micro``, ``genicam:SERIAL``,
``gphoto2:``, ``uvc:0``), through :data:`BACKENDS` (:func:`register_backend`,
:func:`open_camera`).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict, dataclass, field
from enum import Enum
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from dualscale.errors import CameraTimeout, InputError


class TriggerMode(str, Enum):
    """How exposures start: the camera's own timing, an input edge, or an input gate."""

    INTERNAL = "internal"
    EDGE = "edge"
    GATE = "gate"


@dataclass(frozen=True)
class TriggerInfo:
    """What an acquisition will be, declared before arming.

    ``frames``: how many frames to collect (>= 1); ``exposure_s``: exposure per frame [s] (for
    ``gate`` the gate sets it and this is the expected length); ``deadtime_s``: the minimum time
    between the end of one exposure and the next trigger [s] the caller promises to leave;
    ``timeout_s``: the longest wait for the whole acquisition in :meth:`Camera.collect` (``None``:
    ``frames * (exposure_s + deadtime_s) + 5 s``).
    """

    mode: TriggerMode = TriggerMode.INTERNAL
    frames: int = 1
    exposure_s: float = 0.01
    deadtime_s: float = 0.0
    timeout_s: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", TriggerMode(self.mode))
        if not (isinstance(self.frames, int) and self.frames >= 1):
            raise InputError(f"TriggerInfo.frames must be a positive integer, got {self.frames!r}")
        for name in ("exposure_s", "deadtime_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"TriggerInfo.{name} must be a finite number of seconds >= 0, got {v!r}")
        if self.exposure_s <= 0:
            raise InputError(f"TriggerInfo.exposure_s must be > 0 s, got {self.exposure_s!r}")
        if self.timeout_s is not None and not (math.isfinite(self.timeout_s) and self.timeout_s > 0):
            raise InputError(f"TriggerInfo.timeout_s must be > 0 s, got {self.timeout_s!r}")

    def total_timeout(self) -> float:
        """The wait for the whole acquisition [s] (see the class docstring)."""
        if self.timeout_s is not None:
            return float(self.timeout_s)
        return self.frames * (self.exposure_s + self.deadtime_s) + 5.0


@dataclass(frozen=True)
class SensorInfo:
    """A camera's sensor: ``width`` x ``height`` pixels of ``pixel_um`` [um], ``bit_depth`` bits,
    ``black_level`` and ``white_level`` in normalised DN ([0, 1]; the white level is where it
    clips, issue 13 §5), ``pixel_format`` (GenICam names: ``Mono8``, ``Mono16``,
    ``BayerRG16``, ``RGB8``, ...)."""

    width: int
    height: int
    pixel_um: float
    bit_depth: int
    black_level: float = 0.0
    white_level: float = 1.0
    pixel_format: str = "Mono16"

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.bit_depth <= 0 or not self.pixel_um > 0:
            raise InputError(f"sensor size, bit depth and pixel pitch must be positive: {self}")
        if not (0.0 <= self.black_level < self.white_level <= 1.0):
            raise InputError(f"need 0 <= black_level < white_level <= 1 (normalised DN): {self}")


@dataclass
class Frame:
    """One exposure: ``image`` float32 normalised DN ``(H, W)`` or ``(H, W, 3)``; ``index`` its
    number in the acquisition (0-based); ``timestamp_s`` the camera's exposure-start time [s] on
    its own clock; ``exposure_s`` the exposure it actually had; ``metadata`` the camera's
    identity, sensor and settings (:meth:`Camera.frame_metadata`)."""

    image: np.ndarray
    index: int
    timestamp_s: float
    exposure_s: float
    metadata: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """The contract every backend implements (module docstring)."""

    spec: str      # the spec it was opened with ("sim:micro", "genicam:SERIAL", ...)
    serial: str    # the device's serial number (or the backend's stable id)

    def sensor(self) -> SensorInfo: ...

    def settings(self) -> dict[str, Any]: ...

    def supported_modes(self) -> tuple[TriggerMode, ...]: ...

    def prepare(self, info: TriggerInfo) -> None: ...

    def arm(self) -> None: ...

    def trigger(self) -> None:
        """A software trigger (``internal`` mode: one frame now; otherwise ``InputError``)."""

    def collect(self, timeout_s: float | None = None) -> list[Frame]: ...

    def disarm(self) -> None: ...

    def close(self) -> None: ...


def frame_metadata(camera: Camera, info: TriggerInfo | None = None) -> dict[str, Any]:
    """The metadata every frame of ``camera`` carries: spec, serial, sensor, settings and the
    prepared trigger (JSON-able)."""
    meta: dict[str, Any] = {"camera": camera.spec, "serial": camera.serial, "sensor": asdict(camera.sensor()),
                            "settings": dict(camera.settings())}
    if info is not None:
        meta["trigger"] = {**asdict(info), "mode": info.mode.value}
    return meta


class Deadline:
    """A monotonic deadline (``remaining()`` in s, never negative)."""

    def __init__(self, seconds: float):
        self.end = time.monotonic() + float(seconds)

    def remaining(self) -> float:
        return max(0.0, self.end - time.monotonic())

    def expired(self) -> bool:
        return time.monotonic() >= self.end


def collect_deadline(spec: str, info: TriggerInfo | None, timeout_s: float | None) -> tuple[TriggerInfo, float, Deadline]:
    """The start of every ``collect()``: ``(the prepared info, the wait [s], its Deadline)``; the
    wait is ``timeout_s`` or, when None, ``info.total_timeout()``; ``InputError`` before ``prepare()``."""
    if info is None:
        raise InputError(f"camera {spec!r}: collect() before prepare()")
    wait = info.total_timeout() if timeout_s is None else float(timeout_s)
    return info, wait, Deadline(wait)


def split_options(rest: str) -> tuple[str, dict[str, str]]:
    """``"0?pixel_um=3&x=1"`` -> ``("0", {"pixel_um": "3", "x": "1"})``; a ``?`` not followed by
    ``key=value`` pairs stays part of the target (a path may contain one)."""
    target, sep, query = rest.rpartition("?")
    if not sep or not query or not all("=" in kv and kv.split("=", 1)[0].isidentifier() for kv in query.split("&")):
        return rest, {}
    return target, dict(kv.split("=", 1) for kv in query.split("&"))


def option_float(opts: dict[str, str], key: str, spec: str, default: float | None = None) -> float | None:
    """A positive float option, ``InputError`` naming the spec and key otherwise."""
    if key not in opts:
        return default
    try:
        v = float(opts[key])
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"camera {spec!r}: option {key}={opts[key]!r} must be a positive number")
    return v


class HostTriggeredCamera:
    """The lifecycle of a camera whose frames the host grabs, one per :meth:`trigger`
    (``internal`` trigger only).  Subclasses implement ``_apply_exposure(exposure_s)`` (at
    :meth:`prepare`) and ``_grab() -> (image, timestamp_s, exposure_s, extra_metadata)``, raising
    ``CameraDisconnected`` when the source is gone."""

    spec: str = ""
    serial: str = ""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._info: TriggerInfo | None = None
        self._armed = False
        self._frames: list[Frame] = []

    # -- to implement ------------------------------------------------------------------------------
    def _apply_exposure(self, exposure_s: float) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _grab(self) -> tuple[np.ndarray, float, float, dict[str, Any]]:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- the contract ------------------------------------------------------------------------------
    def supported_modes(self) -> tuple[TriggerMode, ...]:
        return (TriggerMode.INTERNAL,)

    def prepare(self, info: TriggerInfo) -> None:
        """Declare the acquisition; ``InputError`` for a mode other than ``internal`` or an
        exposure the camera cannot take."""
        if info.mode not in self.supported_modes():
            raise InputError(f"camera {self.spec!r}: trigger mode {info.mode.value!r} is not supported "
                             f"(only {', '.join(m.value for m in self.supported_modes())}: the host grabs each frame)")
        with self._cond:
            self._armed = False
        self._apply_exposure(info.exposure_s)
        self._info = info

    def arm(self) -> None:
        if self._info is None:
            raise InputError(f"camera {self.spec!r}: arm() before prepare()")
        with self._cond:
            self._frames = []
            self._armed = True

    def trigger(self) -> None:
        """Grab one frame now (blocks for its exposure and readout)."""
        info = self._info
        if info is None or not self._armed:
            raise InputError(f"camera {self.spec!r}: trigger() while not armed (prepare() and arm() first)")
        if len(self._frames) >= info.frames:
            raise InputError(f"camera {self.spec!r}: trigger() beyond the {info.frames} frame(s) armed for")
        image, ts, exposure, extra = self._grab()
        meta = {**frame_metadata(self, info), **extra}  # type: ignore[arg-type]
        with self._cond:
            self._frames.append(Frame(image=image, index=len(self._frames), timestamp_s=ts, exposure_s=exposure,
                                      metadata=meta))
            self._cond.notify_all()

    def collect(self, timeout_s: float | None = None) -> list[Frame]:
        """The armed frames; fewer by ``timeout_s`` (default ``TriggerInfo.total_timeout()``, counted
        from this call) raises ``CameraTimeout`` carrying those that arrived."""
        info, wait, deadline = collect_deadline(self.spec, self._info, timeout_s)
        with self._cond:
            while len(self._frames) < info.frames and not deadline.expired():
                self._cond.wait(deadline.remaining())
            frames = list(self._frames)
        if len(frames) < info.frames:
            raise CameraTimeout(f"camera {self.spec!r}: {len(frames)} of {info.frames} frame(s) within {wait:.3g} s "
                                f"(each needs a trigger())", frames=frames)
        return frames

    def disarm(self) -> None:
        with self._cond:
            self._armed = False


Factory = Callable[[str], Camera]
BACKENDS: dict[str, Factory] = {}


def register_backend(scheme: str, factory: Factory) -> None:
    """Make ``scheme:rest`` specs open with ``factory(rest)``."""
    if not scheme.isidentifier():
        raise ValueError(f"backend scheme must be an identifier, got {scheme!r}")
    BACKENDS[scheme] = factory


def parse_spec(spec: str) -> tuple[str, str]:
    """``"genicam:ABC123"`` -> ``("genicam", "ABC123")``; ``InputError`` for a spec without a
    known scheme (naming the known ones)."""
    scheme, sep, rest = str(spec).partition(":")
    if not sep or scheme not in BACKENDS:
        raise InputError(f"camera {spec!r}: give SCHEME:ID with a scheme of {', '.join(sorted(BACKENDS)) or '(none)'}"
                         " (e.g. sim:micro, genicam:SERIAL, gphoto2:, uvc:0)")
    return scheme, rest


def open_camera(spec: str) -> Camera:
    """Open the camera named by ``spec`` through its backend."""
    scheme, rest = parse_spec(spec)
    cam = BACKENDS[scheme](rest)
    cam.spec = spec
    return cam
