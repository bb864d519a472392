"""GenICam / GigE Vision cameras through Aravis 0.8 (issue 14 §2, ``genicam:SERIAL``).

The usual micro and polar cameras of the rig (spec Sections 3-4) are GenICam machine-vision
cameras.  This backend drives them through Aravis's GObject-introspection binding
(``gi.repository.Aravis`` 0.8: Debian ``gir1.2-aravis-0.8`` + PyGObject) and implements the
camera contract of :mod:`dualscale.capture.camera`:

* **spec** ``genicam:SERIAL`` opens the camera whose serial number (or Aravis device id) is
  ``SERIAL`` (found by discovery, ~1 s a round); ``genicam:192.168.1.20`` the camera at that IPv4
  address, asked directly; ``genicam:`` the first camera found.  Options follow a ``?``:
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
* **frames**: a GigE Vision stream with a buffer pool sized to the armed frames and a receive
  socket sized before the first packet (:func:`size_stream_socket`); images are
  ``DN / (2^bits - 1)`` as float32 ``(H, W)``; ``timestamp_s`` is the buffer's device timestamp
  (ns -> s); the metadata adds the GVSP ``frame_id``, the host's arrival time and, for software
  triggers, the host time the trigger was sent (``trigger_host_s``).
* **frame accounting**: a frame's ``index`` is the trigger it answers (software trigger: the
  order of :meth:`GenICamCamera.trigger` calls; edge: the GVSP block-id distance from the first
  frame).  A frame that arrives damaged (packets lost; Aravis 0.8 asks Aravis's emulator for no
  resends) is counted lost and leaves a gap in the indices; it is never delivered half-filled,
  and the frames after it keep their own indices.  Frames no trigger asked for are counted, not
  delivered.  Counters in :meth:`GenICamCamera.stats`.
* **faults**: ``collect`` raises :class:`~dualscale.errors.CameraTimeout` with the frames that
  arrived when some are missing (past its deadline, or at once when they are known lost); a
  software trigger the camera never answers ends the acquisition (:meth:`GenICamCamera.trigger`);
  a camera whose control channel stops answering raises
  :class:`~dualscale.errors.CameraDisconnected` (from a failed register access, ~2.5 s of GVCP
  retries, or Aravis's ``control-lost`` heartbeat signal; from ``trigger``/``collect`` it carries
  the frames that arrived in ``.frames``), and closing it does not wait.
"""

from __future__ import annotations

import copy
import ctypes
import ipaddress
import os
import socket
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
#: Smallest receive-socket buffer given to a GVSP stream [bytes]; it grows to
#: :data:`SOCKET_BUFFER_FRAMES` frames of payload, up to :data:`SOCKET_BUFFER_MAX_BYTES`.  It is
#: set on the stream's socket *before* AcquisitionStart (:func:`size_stream_socket`): Aravis 0.8
#: sizes it only when the first packet of the first frame arrives, and a frame larger than
#: Linux's 208 KiB default, sent in one burst, loses its tail packets before that (the lost
#: first frame of issue 14; docs/CAPTURE.md).
SOCKET_BUFFER_BYTES = 8 << 20
#: Frames of payload the stream socket holds (the kernel counts each UDP packet's full
#: allocation, ~1.7x its payload for 1400-byte packets on loopback).
SOCKET_BUFFER_FRAMES = 4
#: Largest receive-socket buffer requested [bytes].
SOCKET_BUFFER_MAX_BYTES = 256 << 20
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux; needs CAP_NET_ADMIN
#: Pause after AcquisitionStart before the first trigger [s] (see :meth:`GenICamCamera.arm`).
ARM_SETTLE_S = 0.05
#: How long an incomplete GVSP frame is kept open for late or resent packets [us].
FRAME_RETENTION_US = 1_000_000
#: Longest wait for the previous software-triggered frame before the next trigger [s], beyond
#: the exposure (a trigger sent while the camera is busy is ignored under GenICam's overlap
#: rules).  Longer than :data:`FRAME_RETENTION_US`, so that a frame that arrived damaged is
#: reported (as lost) within it rather than taken for a trigger the camera never answered.
READOUT_WAIT_S = 2.0
#: GVSP block ids (16 bit) run 1..65535 and wrap to 1.
_GVSP_IDS = 65535

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
                            "gir1.2-aravis-0.8 and PyGObject>=3.50,<3.51 (`make deps` installs both)") from e
        _ARAVIS = Aravis
    return _ARAVIS


def _gerror(e: Exception) -> bool:
    """Whether ``e`` is a GLib error raised through the binding (``GLib.Error``/``GLib.GError``)."""
    from gi.repository import GLib
    return isinstance(e, GLib.Error)


def _socket_fd(port: int) -> int | None:
    """The file descriptor of this process's UDP socket bound to ``port`` (Linux ``/proc``),
    or None where it cannot be found."""
    inodes = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as f:
                rows = list(f)[1:]
        except OSError:
            continue
        for row in rows:
            cols = row.split()
            if len(cols) > 9 and int(cols[1].rsplit(":", 1)[1], 16) == port:
                inodes.add(cols[9])
    if not inodes:
        return None
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return None
    for fd in fds:
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:[") and link[8:-1] in inodes:
            return int(fd)
    return None


def size_stream_socket(port: int, nbytes: int) -> int | None:
    """Set the receive buffer of the UDP socket on ``port`` (an Aravis GVSP stream of this
    process) to ``nbytes`` before any packet arrives: ``SO_RCVBUFFORCE`` where the process may
    (CAP_NET_ADMIN), else ``SO_RCVBUF``, which the kernel caps at ``net.core.rmem_max``.
    Returns the buffer the kernel granted [bytes] (``SO_RCVBUF`` read back), None where the
    socket cannot be found (not Linux)."""
    fd = _socket_fd(port)
    if fd is None:
        return None
    sk = socket.socket(fileno=os.dup(fd))  # a duplicate: closing it leaves Aravis's socket open
    try:
        try:
            sk.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, nbytes)
        except OSError:  # EPERM without CAP_NET_ADMIN
            sk.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, nbytes)
        return int(sk.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    finally:
        sk.close()


def _keep_forever(obj) -> None:
    """Leak one reference to ``obj``: it is never freed, not even at interpreter exit (where a
    module-level list would be cleared, tearing the objects down then).  For the Aravis device
    of a camera that stopped answering (:meth:`GenICamCamera._release`): a few KiB and two
    sockets per dead camera."""
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))


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
        self._lost_handler = None
        try:  # Aravis's heartbeat thread emits it
            self._lost_handler = self._dev.connect("control-lost", lambda *_: self._lost.set())
        except TypeError:  # not a GigE Vision device: no heartbeat signal
            pass
        if self._cam.is_gv_device():
            self._cam.gv_set_stream_options(A.GvStreamOption.PACKET_SOCKET_DISABLED)
        self.serial = self._call(self._cam.get_device_serial_number) or serial or device_id
        self._stream = None
        self._info: TriggerInfo | None = None
        self._exposure_s = 0.0
        self._armed = False
        self._free_run = False
        self._reset_acquisition()
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
        """The Aravis device id to open: an IPv4 address as it is (Aravis asks that address
        directly, no discovery), else the discovered device whose serial or id is ``serial``
        (each discovery round waits ~1 s for answers)."""
        try:
            ipaddress.IPv4Address(serial)
            return serial
        except ValueError:
            pass
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
            fn = args = None  # the traceback must not keep the camera alive (see _release)
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
        self._meta = None  # the frames' metadata is read again
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
        alone (``buffers``: the pool size, default ``frames``).  :meth:`collect` then returns the
        first ``frames`` frames that arrive whole, numbered in arrival order; the frames the
        camera sent that did not arrive are counted (``stats()["id_gaps"]``), not numbered.
        Returns the :class:`TriggerInfo` recorded in the frames' metadata."""
        info = TriggerInfo(TriggerMode.INTERNAL, frames=frames, exposure_s=exposure_s, timeout_s=timeout_s)
        self.prepare(info)
        if buffers is not None and buffers != frames:
            self._release("_stream")
            self._open_stream(int(buffers))
        self._set_enum("TriggerMode", "Off")
        self._free_run = True
        return info

    def _open_stream(self, n_buffers: int) -> None:
        A = self._A
        stream = self._call(self._cam.create_stream, None, None, what="create stream")
        if stream is None:
            raise CameraDisconnected(f"{self.spec}: cannot open a stream")
        payload = int(self._call(self._cam.get_payload, what="read PayloadSize"))
        self._socket_bytes = None
        if self._cam.is_gv_device():
            want = min(max(SOCKET_BUFFER_BYTES, SOCKET_BUFFER_FRAMES * payload), SOCKET_BUFFER_MAX_BYTES)
            self._socket_bytes = size_stream_socket(int(stream.get_port()), want)
            stream.set_property("socket-buffer", A.GvStreamSocketBuffer.FIXED)
            # sized above: size 0 tells Aravis to leave the socket alone (it would set it only at
            # the first frame's first packet, and only up to net.core.rmem_max); where the socket
            # was not found, Aravis's late sizing is the fallback
            stream.set_property("socket-buffer-size", 0 if self._socket_bytes else want)
            # a loaded host may read a frame's packets late: keep an open frame 1 s (Aravis: 100 ms)
            # before declaring it incomplete, and ask for resends after 40 ms without a packet
            stream.set_property("frame-retention", FRAME_RETENTION_US)
            stream.set_property("packet-timeout", 40_000)
        for _ in range(n_buffers):
            stream.push_buffer(A.Buffer.new_allocate(payload))
        self._stream = stream
        self._reset_acquisition()

    def _reset_acquisition(self) -> None:
        """Forget the frames and the trigger accounting of the last acquisition."""
        self._frames: list[Frame] = []
        self._sent: list[float] = []      # wall-clock time of each software trigger, by ordinal
        self._resolved = 0                # software triggers answered by a buffer, whole or not
        self._missing: list[int] = []     # frame indices that arrived damaged or not at all
        self._edge_next = 0               # edge trigger: the next index expected
        self._first_id: int | None = None
        self._last_id: int | None = None
        self._id_gaps = self._incomplete = self._unanswered = self._unsolicited = 0
        self._broken: str | None = None
        self._meta: dict[str, Any] | None = None

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
        self._reset_acquisition()
        self._meta = frame_metadata(self, self._info)  # read once, not per frame
        self._call(self._cam.start_acquisition, what="AcquisitionStart")
        self._armed = True
        # a camera may ignore a trigger that arrives before its acquisition runs, and not every
        # camera has AcquisitionStatus to ask: settle one short interval first (Aravis's emulator
        # would not need it: it keeps a software trigger until its next frame tick)
        time.sleep(ARM_SETTLE_S)

    def _software(self) -> bool:
        return self._info is not None and self._info.mode is TriggerMode.INTERNAL and not self._free_run

    def trigger(self) -> None:
        """One software trigger (``TriggerSoftware``); the frame it starts gets the next index.

        Triggers are one at a time: this first waits (up to the exposure +
        :data:`READOUT_WAIT_S`) for the previous trigger's frame, since a camera ignores a
        trigger that arrives while it is busy (GenICam overlap rules).  Whatever answers a
        trigger -- a whole frame, or a damaged one, counted lost -- belongs to it, so a lost frame
        leaves a gap in the indices and never shifts the later frames onto the wrong trigger.
        A previous trigger with no answer at all raises :class:`~dualscale.errors.CameraTimeout`
        (with the frames so far) and ends the acquisition: a late frame could no longer be told
        from the next trigger's, so ``disarm()`` and ``arm()`` again.  ``InputError`` outside an
        armed software-trigger acquisition or past its frames."""
        if self._info is None or not self._software():
            raise InputError(f"{self.spec}: trigger() needs an armed internal (software) trigger")
        if not self._armed:
            raise InputError(f"{self.spec}: trigger() before arm()")
        self._raise_if_broken()
        if len(self._sent) >= self._info.frames:
            raise InputError(f"{self.spec}: trigger() past the {self._info.frames} armed frame(s)")
        try:
            self._trigger()
        except CameraDisconnected as e:
            raise self._with_frames(e)

    def _with_frames(self, e: CameraDisconnected) -> CameraDisconnected:
        """``e`` carrying the frames that arrived (``e.frames``, as :class:`CameraTimeout` does)."""
        e.frames = sorted(self._frames, key=lambda f: f.index)
        return e

    def _trigger(self) -> None:
        if self._resolved < len(self._sent):
            wait = Deadline(self._exposure_s + READOUT_WAIT_S)
            while self._resolved < len(self._sent) and not wait.expired():
                self._pop(wait.remaining())
            if self._resolved < len(self._sent):
                k = self._resolved
                self._unanswered += 1
                self._missing.append(k)
                self._broken = (f"{self.spec}: software trigger {k} got no frame, whole or damaged, within "
                                f"{self._exposure_s + READOUT_WAIT_S:g} s (the camera did not answer it); "
                                f"{len(self._frames)} frame(s) kept; disarm and arm again")
                self._raise_if_broken()
        self._call(self._cam.software_trigger, what="TriggerSoftware")
        self._sent.append(time.time())

    def _raise_if_broken(self) -> None:
        if self._broken is not None:
            raise CameraTimeout(self._broken, frames=list(self._frames))

    def _pop(self, wait_s: float) -> bool:
        """Pop one buffer within ``wait_s`` and account for it (:meth:`_index_for`): a whole one
        becomes a Frame, a damaged one is counted lost; its buffer is requeued.  False when
        nothing came."""
        if self._lost.is_set():
            raise CameraDisconnected(f"{self.spec}: control channel lost (heartbeat)")
        buf = self._stream.timeout_pop_buffer(max(1, int(min(wait_s, 0.1) * 1e6)))
        if buf is None:
            return False
        try:
            whole = buf.get_status() == self._A.BufferStatus.SUCCESS
            fid = int(buf.get_frame_id())
            index = self._index_for(fid, whole)
            if not whole:
                self._incomplete += 1
                if index is not None:
                    self._missing.append(index)
            elif index is None:
                self._unsolicited += 1
            else:
                self._frames.append(self._to_frame(buf, index))
            return True
        finally:
            self._stream.push_buffer(buf)

    def _index_for(self, fid: int, whole: bool) -> int | None:
        """The index of the buffer with GVSP block id ``fid`` (``whole``: not damaged); None for a
        frame no trigger asked for, and for a damaged one in free run.

        * software trigger: the oldest trigger not yet answered (one is outstanding at a time);
        * edge trigger: the block-id distance from the acquisition's first frame (a camera
          numbers every exposure, so frames lost whole still advance the index);
        * free run: the whole frames in arrival order.
        Block ids that skip ahead are counted (``id_gaps``) in every mode; a damaged frame
        reported after later ones (Aravis holds it for the frame retention) is not a gap."""
        if fid:
            ahead = (fid - self._last_id) % _GVSP_IDS if self._last_id is not None else 1
            if 0 < ahead < _GVSP_IDS // 2:
                self._id_gaps += ahead - 1
                self._last_id = fid
            if self._first_id is None:
                self._first_id = fid
        if self._software():
            if self._resolved >= len(self._sent):
                return None
            self._resolved += 1
            return self._resolved - 1
        if self._info is not None and self._info.mode is TriggerMode.EDGE and fid and self._first_id is not None:
            index = (fid - self._first_id) % _GVSP_IDS
            self._missing.extend(range(self._edge_next, index))  # numbered by the camera, never arrived
            self._edge_next = max(self._edge_next, index + 1)
            return index
        return len(self._frames) if whole else None

    def _to_frame(self, buf, index: int) -> Frame:
        w, h = buf.get_image_width(), buf.get_image_height()
        pf = self._pf_name(buf.get_image_pixel_format())
        bits = PIXEL_BITS[pf]
        raw = np.frombuffer(buf.get_data(), dtype=np.uint8 if bits == 8 else "<u2", count=w * h).reshape(h, w)
        image = (raw.astype(np.float32) / np.float32(2 ** bits - 1))
        np.clip(image, 0.0, 1.0, out=image)
        ts = buf.get_timestamp() or buf.get_system_timestamp()
        if self._meta is None:
            self._meta = frame_metadata(self, self._info)
        meta = copy.deepcopy(self._meta)
        meta.update({"frame_id": int(buf.get_frame_id()), "system_timestamp_s": buf.get_system_timestamp() * 1e-9,
                     "pixel_format": pf})
        if self._software() and index < len(self._sent):
            meta["trigger_host_s"] = self._sent[index]
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

    def _complete(self, n: int) -> bool:
        """Whether every one of the ``n`` armed frames has arrived or is known lost."""
        if self._software():
            return self._resolved >= n
        if self._free_run:
            return len(self._frames) >= n
        return len(self._frames) + len(set(i for i in self._missing if i < n)) >= n

    def collect(self, timeout_s: float | None = None) -> list[Frame]:
        """The armed frames, in index order.  ``CameraTimeout`` (with the frames that came, each
        with its own index) when some are missing: not there after ``timeout_s`` (default
        ``info.total_timeout()``), or known lost (arrived damaged, or never answered, see
        :meth:`trigger`) -- then at once, without waiting out the timeout.
        ``CameraDisconnected`` when the control channel is lost."""
        if self._info is None or not self._armed:
            raise InputError(f"{self.spec}: collect() before arm()")
        self._raise_if_broken()
        n = self._info.frames
        deadline = Deadline(self._info.total_timeout() if timeout_s is None else timeout_s)
        try:
            while not self._complete(n) and not deadline.expired():
                self._pop(deadline.remaining())
        except CameraDisconnected as e:
            raise self._with_frames(e)
        frames = sorted((f for f in self._frames if f.index < n), key=lambda f: f.index)
        if len(frames) < n:
            st = self.stats()
            lost = sorted(set(i for i in self._missing if i < n))
            why = (f"frame(s) {lost} lost (damaged in transfer: {st['failures']}, no answer: "
                   f"{st['lost_triggers']})" if lost else "the rest not there before the timeout")
            raise CameraTimeout(f"{self.spec}: {len(frames)} of {n} frames; {why}; dropped {st['dropped']}",
                                frames=frames)
        return frames[:n]

    def stats(self) -> dict[str, int]:
        """Counters of the current (or last) stream, in frames unless named otherwise: Aravis's
        ``completed_buffers``, ``failures`` (frames that arrived damaged), ``missing_frames`` and
        ``underrun_packets`` (packets that found no free buffer -- Aravis counts them in packets);
        ``id_gaps`` (frames the camera numbered between two that arrived but that never arrived
        at all: exact, from the GVSP block ids), ``lost_triggers`` (software triggers no frame
        answered), ``unsolicited`` (frames no trigger asked for: counted, not delivered),
        ``dropped`` = max(``id_gaps``, ``failures`` + ``missing_frames``) + ``lost_triggers``,
        and ``socket_buffer_bytes`` (the stream socket's receive buffer the kernel granted,
        0 where it was left to Aravis)."""
        if self._stream is not None:
            s = self._stream
            self._last_stats = {k: int(s.get_info_uint64_by_name(f"n_{k}"))
                                for k in ("completed_buffers", "failures", "missing_frames", "underruns")}
            self._last_stats["underrun_packets"] = self._last_stats.pop("underruns")
        st = dict(self._last_stats or {"completed_buffers": 0, "failures": 0, "missing_frames": 0,
                                       "underrun_packets": 0})
        st["failures"] = max(st["failures"], self._incomplete)
        st["id_gaps"] = self._id_gaps
        st["lost_triggers"] = self._unanswered
        st["unsolicited"] = self._unsolicited
        st["dropped"] = max(st["id_gaps"], st["failures"] + st["missing_frames"]) + st["lost_triggers"]
        st["socket_buffer_bytes"] = int(getattr(self, "_socket_bytes", None) or 0)
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
        self._release("_stream")

    def _release(self, *attrs: str) -> None:
        """Set the attributes ``attrs`` (Aravis objects) to None and drop the objects.

        For a camera that stopped answering, Aravis's teardown (stop the stream channel, leave
        control) waits out its GVCP timeouts, ~10 s, which no caller should wait for: the stream
        and camera objects are dropped in a background thread (the binding releases the GIL).
        Its *device* is never torn down in this process (:func:`_keep_forever`): Aravis 0.8's
        heartbeat thread emits ``control-lost`` holding a reference to it, and when that
        reference is the last one, the device's teardown runs in the heartbeat thread, joins
        that same thread and aborts the process (GLib-ERROR "Resource deadlock avoided" in
        ``pthread_join``, a SIGTRAP: 1 test run in 40 under load)."""
        doomed = [getattr(self, a, None) for a in attrs]
        for a in attrs:
            setattr(self, a, None)
        if self._lost.is_set() and any(o is not None for o in doomed):
            # (indices, not a loop variable: a name left holding an object would make this frame,
            # not the thread, drop its last reference)
            for i in [i for i, o in enumerate(doomed) if isinstance(o, self._A.Device)]:
                _keep_forever(doomed[i])
                doomed[i] = None
            threading.Thread(target=doomed.clear, name=f"{self.spec} release", daemon=True).start()
        else:
            doomed.clear()

    def close(self) -> None:
        """Disarm and release the device (at once, also for a camera that stopped answering)."""
        self.disarm()
        if self._dev is not None and self._lost_handler is not None:
            self._dev.disconnect(self._lost_handler)  # no Python callback from a device being torn down
            self._lost_handler = None
        self._release("_cam", "_dev")


def _factory(rest: str) -> GenICamCamera:
    return GenICamCamera.open(rest)


register_backend("genicam", _factory)
