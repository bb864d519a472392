"""GenICam / GigE Vision cameras through Aravis 0.8 (issue 14 §2, ``genicam:SERIAL``).

The usual micro and polar cameras of the rig (spec Sections 3-4) are GenICam machine-vision
cameras.  This backend drives them through Aravis's GObject-introspection binding
(``gi.repository.Aravis`` 0.8: Debian ``gir1.2-aravis-0.8`` + PyGObject) and implements the
camera contract of :mod:`dualscale.capture.camera`:

* **spec** ``genicam:SERIAL`` opens the camera whose serial number (or Aravis device id) is
  ``SERIAL``; ``genicam:`` opens the first camera found.  Options follow a ``?``:
  ``genicam:SERIAL?pixel_format=Mono16&gain=2&edge=1`` (``edge=1`` enables the ``edge`` trigger
  mode, see below).
* **sensor**: ``Width`` x ``Height`` (the current region), bit depth from ``PixelFormat``
  (``Mono8`` 8 bits, ``Mono10/12/14/16`` unpacked in 16-bit words), pixel pitch [um] from
  ``SensorPixelWidth`` when the device has it, else :data:`DEFAULT_PIXEL_UM` (3.45 um, the pitch
  of Sony's IMX250/264 global-shutter sensors common in GigE cameras -- a stated default, not a
  measurement; set it per camera in the rig's calibration when it matters).
* **trigger**: ``prepare`` writes ``TriggerSelector=FrameStart``, ``TriggerMode=On`` and
  ``AcquisitionMode=Continuous``; ``internal`` maps to ``TriggerSource=Software`` (the host calls
  :meth:`GenICamCamera.trigger`, which issues ``TriggerSoftware``), ``edge`` to
  ``TriggerSource=Line0`` with ``TriggerActivation=RisingEdge``.  ``gate`` is refused.
  ``edge`` is listed in :meth:`GenICamCamera.supported_modes` only when opened with ``edge=1``:
  Aravis's camera emulator cannot fire its Line0 input, so that path is tested only as far as
  the device registers (docs/CAPTURE.md).
* **exposure** in us (``ExposureTime``/``ExposureTimeAbs``, through Aravis), range-checked
  against the device's bounds (``InputError`` outside); the frames report the exposure read back.
* **frames**: a GigE Vision stream with a buffer pool sized to the armed frames; images are
  ``DN / (2^bits - 1)`` as float32 ``(H, W)``; ``timestamp_s`` is the buffer's device timestamp
  (ns -> s).  Frames that arrive incomplete, or with no free buffer, are *dropped* and counted
  (:meth:`GenICamCamera.stats`), never delivered half-filled.
* **faults**: ``collect`` past its deadline raises :class:`~dualscale.errors.CameraTimeout` with
  the frames that arrived; a camera whose control channel stops answering raises
  :class:`~dualscale.errors.CameraDisconnected` (from a failed register access, or Aravis's
  ``control-lost`` heartbeat signal); no call waits past its deadline.
"""

from __future__ import annotations

import threading
import time
from typing import Any
from urllib.parse import parse_qsl

import numpy as np

from dualscale.capture.camera import (Deadline, Frame, SensorInfo, TriggerInfo, TriggerMode, frame_metadata,
                                      register_backend)
from dualscale.errors import CameraDisconnected, CameraError, CameraTimeout, InputError, ToolError

#: Pixel pitch [um] assumed when the device has no ``SensorPixelWidth`` feature (see module doc).
DEFAULT_PIXEL_UM = 3.45
#: Bits per pixel of the pixel formats this backend decodes (GenICam PFNC names).
PIXEL_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}
#: Receive-socket buffer requested for the GVSP stream [bytes] (the kernel caps it at
#: net.core.rmem_max); Linux's 208 KiB default drops packets of a 512x512 frame on loopback.
SOCKET_BUFFER_BYTES = 8 << 20
#: Pause after AcquisitionStart before the first trigger [s] (see :meth:`GenICamCamera.arm`).
ARM_SETTLE_S = 0.05
#: How long an incomplete GVSP frame is kept open for late or resent packets [us].
FRAME_RETENTION_US = 1_000_000
#: Longest wait for the previous software-triggered frame before the next trigger [s], beyond
#: the exposure (a trigger sent while the camera is busy is ignored under GenICam's overlap rules).
READOUT_WAIT_S = 1.0

_ARAVIS = None


def aravis():
    """The ``gi.repository.Aravis`` 0.8 module (``ToolError`` naming the packages when missing)."""
    global _ARAVIS
    if _ARAVIS is None:
        try:
            import gi
            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as e:
            raise ToolError(f"genicam: Aravis 0.8 GObject introspection unavailable ({e}); install Debian "
                            "gir1.2-aravis-0.8 and PyGObject (pip install 'PyGObject<3.51')") from e
        _ARAVIS = Aravis
    return _ARAVIS


def _gerror(e: Exception) -> bool:
    """Whether ``e`` is a GLib error raised through the binding (``GLib.Error``/``GLib.GError``)."""
    from gi.repository import GLib
    return isinstance(e, GLib.Error)


def list_devices() -> list[dict[str, str]]:
    """The GenICam devices Aravis discovers now: ``[{"id", "serial", "model", "address"}]``."""
    A = aravis()
    A.update_device_list()
    return [{"id": A.get_device_id(i) or "", "serial": A.get_device_serial_nbr(i) or "",
             "model": A.get_device_model(i) or "", "address": A.get_device_address(i) or ""}
            for i in range(A.get_n_devices())]


class GenICamCamera:
    """One GenICam camera through Aravis (module docstring).  ``serial``: serial number or Aravis
    device id, ``""`` for the first camera; ``discovery_timeout_s``: how long to look for it;
    ``pixel_format``/``gain``: applied at open; ``edge``: offer the (emulator-untested) edge mode."""

    def __init__(self, serial: str = "", *, discovery_timeout_s: float = 3.0, pixel_format: str | None = None,
                 gain: float | None = None, edge: bool = False, spec: str | None = None):
        A = aravis()
        self._A = A
        self.spec = spec or f"genicam:{serial}"
        self._edge = bool(edge)
        device_id = self._find(serial, discovery_timeout_s)
        try:
            self._cam = A.Camera.new(device_id)
        except Exception as e:
            if _gerror(e):
                raise CameraDisconnected(f"{self.spec}: cannot open GenICam device {device_id!r}: {e}") from e
            raise
        self._dev = self._cam.get_device()
        self._lost = threading.Event()
        try:
            self._dev.connect("control-lost", lambda *_: self._lost.set())
        except TypeError:  # not a GigE Vision device: no heartbeat signal
            pass
        if self._cam.is_gv_device():
            self._cam.gv_set_stream_options(A.GvStreamOption.PACKET_SOCKET_DISABLED)
        self.serial = self._call(self._cam.get_device_serial_number) or serial or device_id
        self._stream = None
        self._info: TriggerInfo | None = None
        self._exposure_s = 0.0
        self._armed = False
        self._frames: list[Frame] = []
        self._triggered = 0
        self._incomplete = self._lost_triggers = 0
        self._last_stats: dict[str, int] = {}
        if pixel_format is not None:
            self.set_pixel_format(pixel_format)
        if gain is not None:
            self.set_gain(gain)

    @classmethod
    def open(cls, rest: str) -> "GenICamCamera":
        """Open from the part of a spec after ``genicam:`` (``SERIAL[?key=value&...]``)."""
        serial, _, query = rest.partition("?")
        opts = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=False))
        unknown = set(opts) - {"pixel_format", "gain", "edge", "discovery_timeout_s"}
        if unknown:
            raise InputError(f"camera genicam:{rest}: unknown option(s) {sorted(unknown)} "
                             "(pixel_format, gain, edge, discovery_timeout_s)")
        try:
            return cls(serial, pixel_format=opts.get("pixel_format"),
                       gain=float(opts["gain"]) if "gain" in opts else None,
                       edge=opts.get("edge", "0") not in ("0", "", "false", "no"),
                       discovery_timeout_s=float(opts.get("discovery_timeout_s", 3.0)),
                       spec=f"genicam:{rest}")
        except ValueError as e:
            if isinstance(e, InputError):
                raise
            raise InputError(f"camera genicam:{rest}: bad option value ({e})") from e

    # -- discovery and register access ----------------------------------------------------------
    def _find(self, serial: str, timeout_s: float) -> str:
        deadline = Deadline(timeout_s)
        while True:
            devices = list_devices()
            for d in devices:
                if not serial or serial in (d["serial"], d["id"]):
                    return d["id"]
            if deadline.expired():
                found = ", ".join(f"{d['serial']} ({d['address']})" for d in devices) or "none"
                raise CameraDisconnected(f"{self.spec}: no GenICam camera with serial {serial!r} after "
                                         f"{timeout_s:g} s (found: {found})")
            time.sleep(0.1)

    def _call(self, fn, *args, what: str = ""):
        """Call an Aravis function; a GError (no answer, bad access) becomes ``CameraDisconnected``
        when the control channel is gone, else ``CameraError`` naming the feature."""
        try:
            return fn(*args)
        except Exception as e:
            if not _gerror(e):
                raise
            msg = f"{self.spec}: {what or getattr(fn, '__name__', 'register access')}: {e}"
            if self._lost.is_set() or "timeout" in str(e).lower() or "lost" in str(e).lower():
                self._lost.set()  # no further register access waits on a dead control channel
                raise CameraDisconnected(msg) from e
            raise CameraError(msg) from e

    def _feature(self, name: str) -> str | None:
        if not self._dev.is_feature_available(name):
            return None
        return self._call(self._dev.get_string_feature_value, name, what=f"read {name}") \
            if self._is_enum(name) else str(self._call(self._feature_value, name, what=f"read {name}"))

    def _is_enum(self, name: str) -> bool:
        node = self._dev.get_feature(name)
        return node is not None and type(node).__name__ == "GcEnumeration"

    def _feature_value(self, name: str):
        node = self._dev.get_feature(name)
        return node.get_value_as_string()

    def _set_enum(self, name: str, value: str) -> None:
        values = self._call(self._dev.dup_available_enumeration_feature_values_as_strings, name,
                            what=f"list {name}") or []
        if value not in values:
            raise InputError(f"{self.spec}: {name}={value!r} not offered by the device (it offers {list(values)})")
        self._call(self._dev.set_string_feature_value, name, value, what=f"write {name}={value}")

    # -- what the camera reports ----------------------------------------------------------------
    def pixel_format(self) -> str:
        return self._call(self._cam.get_pixel_format_as_string, what="read PixelFormat")

    def sensor(self) -> SensorInfo:
        """Sensor of the current region and pixel format (module docstring)."""
        _, _, w, h = self._call(self._cam.get_region, what="read Width/Height")
        pf = self.pixel_format()
        pitch = DEFAULT_PIXEL_UM
        if self._dev.is_feature_available("SensorPixelWidth"):
            pitch = float(self._call(self._dev.get_float_feature_value, "SensorPixelWidth",
                                     what="read SensorPixelWidth"))
        return SensorInfo(width=int(w), height=int(h), pixel_um=pitch, bit_depth=PIXEL_BITS.get(pf, 8),
                          pixel_format=pf)

    def settings(self) -> dict[str, Any]:
        """Exposure [us], gain, pixel format, trigger and acquisition features, frame rate [Hz],
        the device's vendor/model and its pixel pitch source (JSON-able)."""
        c = self._cam
        out: dict[str, Any] = {
            "vendor": self._call(c.get_vendor_name) or "", "model": self._call(c.get_model_name) or "",
            "device_id": self._call(c.get_device_id) or "",
            "exposure_us": float(self._call(c.get_exposure_time, what="read ExposureTime")),
            "gain": float(self._call(c.get_gain, what="read Gain")) if c.is_gain_available() else None,
            "pixel_format": self.pixel_format(),
            "pixel_um_source": "SensorPixelWidth" if self._dev.is_feature_available("SensorPixelWidth")
            else f"default {DEFAULT_PIXEL_UM} um",
        }
        for name in ("TriggerSelector", "TriggerMode", "TriggerSource", "TriggerActivation", "AcquisitionMode"):
            out[name] = self._feature(name)
        out["frame_rate_hz"] = float(self._call(c.get_frame_rate)) if c.is_frame_rate_available() else None
        return out

    def supported_modes(self) -> tuple[TriggerMode, ...]:
        """``internal`` (software trigger), plus ``edge`` when opened with ``edge=1``."""
        return (TriggerMode.INTERNAL, TriggerMode.EDGE) if self._edge else (TriggerMode.INTERNAL,)

    def exposure_bounds_s(self) -> tuple[float, float]:
        lo, hi = self._call(self._cam.get_exposure_time_bounds, what="read ExposureTime bounds")
        return lo * 1e-6, hi * 1e-6

    # -- settings outside the trigger -------------------------------------------------------------
    def set_gain(self, gain: float) -> float:
        """Set the gain (the device's units: dB for ``Gain``, raw counts for ``GainRaw``), range
        checked (``InputError``); returns the value read back."""
        lo, hi = self._call(self._cam.get_gain_bounds, what="read Gain bounds")
        if not (lo <= gain <= hi):
            raise InputError(f"{self.spec}: Gain {gain} outside the device range [{lo}, {hi}]")
        self._call(self._cam.set_gain, float(gain), what=f"write Gain={gain}")
        return float(self._call(self._cam.get_gain, what="read Gain"))

    def set_pixel_format(self, name: str) -> None:
        """Set ``PixelFormat`` (one of :data:`PIXEL_BITS` the device offers; ``InputError`` else)."""
        if self._armed:
            raise InputError(f"{self.spec}: PixelFormat cannot change while armed")
        offered = list(self._call(self._cam.dup_available_pixel_formats_as_strings) or [])
        if name not in PIXEL_BITS or name not in offered:
            raise InputError(f"{self.spec}: PixelFormat {name!r} not supported (device offers {offered}; "
                             f"this backend decodes {sorted(PIXEL_BITS)})")
        self._call(self._cam.set_pixel_format_from_string, name, what=f"write PixelFormat={name}")

    def set_frame_rate(self, hz: float) -> float:
        """Set ``AcquisitionFrameRate`` [Hz] (free-running rate; used by the bench); returns it."""
        lo, hi = self._call(self._cam.get_frame_rate_bounds)
        if not (lo <= hz <= hi):
            raise InputError(f"{self.spec}: AcquisitionFrameRate {hz} outside [{lo}, {hi}] Hz")
        self._call(self._cam.set_frame_rate, float(hz), what="write AcquisitionFrameRate")
        return float(self._call(self._cam.get_frame_rate))

    # -- lifecycle ------------------------------------------------------------------------------
    def prepare(self, info: TriggerInfo) -> None:
        """Write exposure and trigger features and allocate the stream's buffer pool (``frames``
        buffers); ``InputError`` for an unsupported mode or an exposure outside the device range."""
        if info.mode not in self.supported_modes():
            raise InputError(f"{self.spec}: trigger mode {info.mode.value!r} unsupported "
                             f"(supported: {[m.value for m in self.supported_modes()]})")
        lo, hi = self.exposure_bounds_s()
        if not (lo <= info.exposure_s <= hi):
            raise InputError(f"{self.spec}: ExposureTime {info.exposure_s * 1e6:g} us outside the device range "
                             f"[{lo * 1e6:g}, {hi * 1e6:g}] us")
        self.disarm()
        A = self._A
        self._call(self._cam.set_exposure_time, info.exposure_s * 1e6, what="write ExposureTime")
        self._exposure_s = float(self._call(self._cam.get_exposure_time)) * 1e-6
        self._call(self._cam.set_acquisition_mode, A.AcquisitionMode.CONTINUOUS, what="write AcquisitionMode")
        if self._dev.is_feature_available("TriggerSelector"):
            self._set_enum("TriggerSelector", "FrameStart")
        self._set_enum("TriggerMode", "On")
        if info.mode is TriggerMode.INTERNAL:
            self._set_enum("TriggerSource", "Software")
        else:
            self._set_enum("TriggerSource", "Line0")
            self._set_enum("TriggerActivation", "RisingEdge")
        self._open_stream(info.frames)
        self._free_run = False
        self._info = info

    def prepare_free_run(self, frames: int, exposure_s: float, timeout_s: float | None = None,
                         buffers: int | None = None) -> TriggerInfo:
        """Like :meth:`prepare` with ``TriggerMode=Off``: the camera streams at its
        ``AcquisitionFrameRate`` (no :meth:`trigger`); for the bench and for checks of the stream
        alone (``buffers``: the pool size, default ``frames``).  Returns the :class:`TriggerInfo` recorded in the frames' metadata."""
        info = TriggerInfo(TriggerMode.INTERNAL, frames=frames, exposure_s=exposure_s, timeout_s=timeout_s)
        self.prepare(info)
        if buffers is not None and buffers != frames:
            self._stream = None
            self._open_stream(int(buffers))
        self._set_enum("TriggerMode", "Off")
        self._free_run = True
        return info

    def _open_stream(self, n_buffers: int) -> None:
        A = self._A
        stream = self._call(self._cam.create_stream, None, None, what="create stream")
        if stream is None:
            raise CameraDisconnected(f"{self.spec}: cannot open a stream")
        if self._cam.is_gv_device():
            stream.set_property("socket-buffer", A.GvStreamSocketBuffer.FIXED)
            stream.set_property("socket-buffer-size", SOCKET_BUFFER_BYTES)
            # a loaded host may read a frame's packets late: keep an open frame 1 s (Aravis: 100 ms)
            # before declaring it incomplete, and ask for resends after 40 ms without a packet
            stream.set_property("frame-retention", FRAME_RETENTION_US)
            stream.set_property("packet-timeout", 40_000)
        payload = int(self._call(self._cam.get_payload, what="read PayloadSize"))
        for _ in range(n_buffers):
            stream.push_buffer(A.Buffer.new_allocate(payload))
        self._stream = stream
        self._last_id = None
        self._id_gaps = 0
        self._incomplete = self._lost_triggers = 0

    def arm(self) -> None:
        """Start the acquisition (``AcquisitionStart``); after :meth:`disarm` it re-arms the same
        prepared acquisition with a fresh buffer pool."""
        if self._info is None:
            raise InputError(f"{self.spec}: arm() before prepare()")
        if self._lost.is_set():
            raise CameraDisconnected(f"{self.spec}: control channel lost")
        if self._armed:
            return
        if self._stream is None:  # re-arming after disarm(): the same prepared acquisition
            self._open_stream(self._info.frames)
        self._frames, self._triggered, self._incomplete, self._lost_triggers = [], 0, 0, 0
        self._call(self._cam.start_acquisition, what="AcquisitionStart")
        self._armed = True
        # the emulator (and cameras whose AcquisitionStatus we cannot read) drop a trigger that
        # arrives before their acquisition thread runs: settle one short interval first
        time.sleep(ARM_SETTLE_S)

    def trigger(self) -> None:
        """One software trigger (``TriggerSoftware``).  Waits first (up to exposure +
        :data:`READOUT_WAIT_S`) for the previous triggered frame, since a trigger the camera
        receives while busy is ignored; a previous frame that does not come is counted dropped."""
        if self._info is None or self._info.mode is not TriggerMode.INTERNAL or getattr(self, "_free_run", False):
            raise InputError(f"{self.spec}: trigger() needs an armed internal (software) trigger")
        if not self._armed:
            raise InputError(f"{self.spec}: trigger() before arm()")
        pending = lambda: self._triggered > len(self._frames) + self._incomplete + self._lost_triggers  # noqa: E731
        if pending():
            wait = Deadline(self._exposure_s + READOUT_WAIT_S)
            while pending() and not wait.expired():
                self._pop(wait.remaining())
            if pending():
                self._lost_triggers += 1
        self._call(self._cam.software_trigger, what="TriggerSoftware")
        self._triggered += 1

    def _pop(self, wait_s: float) -> bool:
        """Pop one buffer within ``wait_s``: a complete one becomes a Frame; an incomplete one is
        counted dropped and its buffer requeued.  False when nothing came."""
        if self._lost.is_set():
            raise CameraDisconnected(f"{self.spec}: control channel lost (heartbeat)")
        buf = self._stream.timeout_pop_buffer(max(1, int(min(wait_s, 0.1) * 1e6)))
        if buf is None:
            return False
        try:
            if buf.get_status() != self._A.BufferStatus.SUCCESS:
                self._incomplete += 1
                return True
            fid = int(buf.get_frame_id())
            if self._last_id is not None:  # GVSP block ids run 1..65535 and wrap
                self._id_gaps += (fid - self._last_id - 1) % 65535
            self._last_id = fid
            self._frames.append(self._to_frame(buf, len(self._frames)))
            return True
        finally:
            self._stream.push_buffer(buf)

    def _to_frame(self, buf, index: int) -> Frame:
        w, h = buf.get_image_width(), buf.get_image_height()
        pf = self._pf_name(buf.get_image_pixel_format())
        bits = PIXEL_BITS[pf]
        raw = np.frombuffer(buf.get_data(), dtype=np.uint8 if bits == 8 else "<u2", count=w * h).reshape(h, w)
        image = (raw.astype(np.float32) / np.float32(2 ** bits - 1))
        np.clip(image, 0.0, 1.0, out=image)
        ts = buf.get_timestamp() or buf.get_system_timestamp()
        meta = frame_metadata(self, self._info)
        meta.update({"frame_id": int(buf.get_frame_id()), "system_timestamp_s": buf.get_system_timestamp() * 1e-9,
                     "pixel_format": pf})
        return Frame(image=image, index=index, timestamp_s=ts * 1e-9, exposure_s=self._exposure_s, metadata=meta)

    def _pf_name(self, code: int) -> str:
        cached = getattr(self, "_pf_cache", {})
        if code not in cached:
            for name in PIXEL_BITS:
                if code == getattr(self._A, f"PIXEL_FORMAT_MONO_{name[4:]}", None):
                    cached[code] = name
            self._pf_cache = cached
        if code not in cached:
            raise CameraError(f"{self.spec}: buffer PixelFormat 0x{code:08x} not decodable "
                              f"(this backend decodes {sorted(PIXEL_BITS)})")
        return cached[code]

    def collect(self, timeout_s: float | None = None) -> list[Frame]:
        """The armed frames, in order; ``CameraTimeout`` (with the frames that came) after
        ``timeout_s`` (default ``info.total_timeout()``), ``CameraDisconnected`` when the
        control channel is lost."""
        if self._info is None or not self._armed:
            raise InputError(f"{self.spec}: collect() before arm()")
        n = self._info.frames
        deadline = Deadline(self._info.total_timeout() if timeout_s is None else timeout_s)
        while len(self._frames) < n and not deadline.expired():
            self._pop(deadline.remaining())
        if len(self._frames) < n:
            stats = self.stats()
            raise CameraTimeout(f"{self.spec}: {len(self._frames)} of {n} frames before the timeout "
                                f"(dropped {stats['dropped']})", frames=list(self._frames))
        return list(self._frames[:n])

    def stats(self) -> dict[str, int]:
        """Counters of the current (or last) stream: Aravis's ``completed_buffers``,
        ``failures`` (incomplete frames), ``missing_frames`` and ``underrun_packets`` (packets that
        found no free buffer -- Aravis counts them in packets, not frames); ``id_gaps`` (frames
        the camera numbered between two delivered ones but never delivered: exact, from the GVSP
        block ids), ``lost_triggers`` (software triggers whose frame never came) and
        ``dropped`` = max(``id_gaps``, ``failures`` + ``missing_frames``) + ``lost_triggers``,
        in frames."""
        if self._stream is not None:
            s = self._stream
            self._last_stats = {k: int(s.get_info_uint64_by_name(f"n_{k}"))
                                for k in ("completed_buffers", "failures", "missing_frames", "underruns")}
            self._last_stats["underrun_packets"] = self._last_stats.pop("underruns")
        st = dict(self._last_stats or {"completed_buffers": 0, "failures": 0, "missing_frames": 0,
                                       "underrun_packets": 0})
        st["failures"] = max(st["failures"], self._incomplete)
        st["id_gaps"] = getattr(self, "_id_gaps", 0)
        st["lost_triggers"] = self._lost_triggers
        st["dropped"] = max(st["id_gaps"], st["failures"] + st["missing_frames"]) + st["lost_triggers"]
        return st

    def disarm(self) -> None:
        """Stop the acquisition and free the stream (idempotent; a camera whose control channel
        is lost gets no ``AcquisitionStop``, which would only wait out the GVCP timeouts)."""
        if self._stream is not None:
            self.stats()
        if self._armed and not self._lost.is_set():
            try:
                self._cam.stop_acquisition()
            except Exception as e:
                if not _gerror(e):
                    raise
            self._armed = False
        self._stream = None

    def close(self) -> None:
        """Disarm and release the device."""
        self.disarm()
        self._cam = self._dev = None  # type: ignore[assignment]


def _factory(rest: str) -> GenICamCamera:
    return GenICamCamera.open(rest)


register_backend("genicam", _factory)
