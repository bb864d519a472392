"""``uvc``: USB (UVC / V4L2) cameras through OpenCV's ``VideoCapture`` (issue 14 §2, kept thin).

Specs:

* ``uvc:N`` -- video device index ``N`` (``/dev/videoN`` on Linux);
* ``uvc:PATH`` -- an image sequence (a ``printf`` pattern such as ``frames/f_%03d.png``, read
  through OpenCV's ``CAP_IMAGES``, or one image file) or a video file (``CAP_FFMPEG``): a
  recorded camera, which is how this backend is tested (no ``/dev/video*`` on the build machine).

Options follow a ``?``: ``uvc:0?pixel_um=3.0`` (the pixel pitch [um]; UVC does not report it --
without it ``SensorInfo.pixel_um`` is 1.0 and ``settings()["pixel_um_known"]`` is False).

Trigger: ``internal`` only; each :meth:`~HostTriggeredCamera.trigger` grabs one frame (UVC has no
trigger input).  Exposure: ``CAP_PROP_EXPOSURE`` in V4L2 units of 100 us after switching
``CAP_PROP_AUTO_EXPOSURE`` to manual, where the device accepts it; a source that does not (every
file source) records the exposure as requested and says so: ``settings()["exposure_applied"]``
is False and every frame's metadata carries ``"exposure_applied": False``.

Sensor: the frame size of the source; 8-bit (``uint8`` frames, ``DN/255``) unless the source
delivers ``uint16`` frames (16-bit PNG/TIFF sequences: ``DN/65535``).  Colour frames are RGB
``(H, W, 3)`` (OpenCV's BGR reordered), grey ones ``(H, W)``.

A source that stops delivering (device unplugged, files gone, end of a recording) raises
:class:`~dualscale.errors.CameraDisconnected` naming the source; a recording never loops.

:class:`~dualscale.capture.camera.HostTriggeredCamera` is the lifecycle shared by the backends whose frames are grabbed by
the host, one per ``trigger()`` (``uvc``, ``gphoto2``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.capture.camera import HostTriggeredCamera, SensorInfo, option_float, register_backend, split_options
from dualscale.errors import CameraDisconnected, CameraError, InputError

IMAGE_EXTS = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm", ".exr", ".webp"}


def normalise(raw: np.ndarray, source: str) -> tuple[np.ndarray, int]:
    """An OpenCV frame (``uint8``/``uint16``; 1, 3 (BGR) or 4 (BGRA) channels) -> float32
    normalised DN ``(H, W)`` or RGB ``(H, W, 3)`` in [0, 1], and its bit depth (8 or 16)."""
    if raw.dtype == np.uint8:
        bits = 8
    elif raw.dtype == np.uint16:
        bits = 16
    else:
        raise CameraError(f"{source}: frames of dtype {raw.dtype} are not 8- or 16-bit DN")
    img = raw
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, 2::-1]  # BGR(A) -> RGB
    elif img.ndim != 2:
        raise CameraError(f"{source}: frame of shape {raw.shape} is neither grey nor BGR")
    out = np.ascontiguousarray(img, dtype=np.float32)
    out *= np.float32(1.0 / (2 ** bits - 1))
    return out, bits


class UVCCamera(HostTriggeredCamera):
    """A UVC camera or a recorded one through ``cv2.VideoCapture`` (module docstring)."""

    def __init__(self, rest: str):
        super().__init__()
        import cv2  # a project dependency; imported here to keep ``import dualscale.capture`` light

        self._cv2 = cv2
        self.spec = f"uvc:{rest}"
        target, opts = split_options(rest)
        if not target:
            raise InputError(f"camera {self.spec!r}: give uvc:N (device index) or uvc:PATH (image sequence or video)")
        self._pixel_um = option_float(opts, "pixel_um", self.spec)
        if target.isdigit():
            self._source: int | str = int(target)
            self._api = cv2.CAP_ANY
            self.serial = _device_serial(int(target))
        else:
            path = os.path.abspath(os.path.expanduser(target))
            self._source = path
            self._api = cv2.CAP_IMAGES if ("%" in path or Path(path).suffix.lower() in IMAGE_EXTS) else cv2.CAP_FFMPEG
            self.serial = path
            # CAP_IMAGES starts a pattern at 0, else at 1 (OpenCV's icvExtractPattern)
            self._first = 0 if "%" not in path or os.path.exists(path % 0) else 1
        self._cap = None
        self._exposure_s = 0.0
        self._exposure_applied = False
        self._grabbed = 0
        self._open()
        probe = self._read()  # the size and depth of the frames, before any acquisition
        image, bits = normalise(probe, self.spec)
        self._sensor = SensorInfo(width=image.shape[1], height=image.shape[0], pixel_um=self._pixel_um or 1.0,
                                  bit_depth=bits, pixel_format=("Mono" if image.ndim == 2 else "RGB") + str(bits))
        self._open()  # rewind: the probe is not a frame of any acquisition
        self._grabbed = 0

    def _open(self) -> None:
        cv2 = self._cv2
        if self._cap is not None:
            self._cap.release()
        if isinstance(self._source, str) and "%" not in self._source and not os.path.exists(self._source):
            raise CameraDisconnected(f"camera {self.spec!r}: {self._source} does not exist (check the path)")
        # OpenCV logs its own attempts (V4L2 probes, "can't open camera by index") on stderr
        # before our one-line error: quiet it while opening
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        try:
            cap = cv2.VideoCapture(self._source, self._api)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not cap.isOpened():
            cap.release()
            what = (f"no video device {self._source} (check /dev/video{self._source}, the cable and permissions)"
                    if isinstance(self._source, int) else f"OpenCV cannot read {self._source} (check the path/pattern)")
            raise CameraDisconnected(f"camera {self.spec!r}: {what}")
        self._cap = cap

    def _read(self) -> np.ndarray:
        if self._cap is None:
            raise CameraDisconnected(f"camera {self.spec!r}: closed")
        ok, raw = self._cap.read()
        if not ok or raw is None:
            raise CameraDisconnected(f"camera {self.spec!r}: no frame after {self._grabbed} grabbed "
                                     f"(device unplugged, files removed or end of the recording)")
        self._grabbed += 1
        return raw

    # -- reports -----------------------------------------------------------------------------------
    def sensor(self) -> SensorInfo:
        return self._sensor

    def settings(self) -> dict[str, Any]:
        return {"source": self._source, "opencv_backend": self._cap.getBackendName() if self._cap else None,
                "exposure_s": self._exposure_s, "exposure_applied": self._exposure_applied,
                "pixel_um_known": self._pixel_um is not None}

    # -- lifecycle hooks ---------------------------------------------------------------------------
    def _apply_exposure(self, exposure_s: float) -> None:
        cv2, cap = self._cv2, self._cap
        self._exposure_s = float(exposure_s)
        self._exposure_applied = False
        if cap is None or isinstance(self._source, str):
            return  # a recording cannot change its exposure: recorded as requested (settings say so)
        # V4L2 (what OpenCV uses for UVC on Linux): auto exposure 1 = manual, exposure in 100 us units
        cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
        if cap.set(cv2.CAP_PROP_EXPOSURE, exposure_s * 1e4):
            got = cap.get(cv2.CAP_PROP_EXPOSURE)
            if got > 0:
                self._exposure_s = got / 1e4
                self._exposure_applied = True

    def _frame_file(self, k: int) -> str | None:
        """The file behind the ``k``-th frame (0-based) of a recording; ``None`` for a device."""
        if not isinstance(self._source, str):
            return None
        if "%" not in self._source:
            return self._source
        return self._source % (self._first + k)

    def _grab(self) -> tuple[np.ndarray, float, float, dict[str, Any]]:
        ts = time.monotonic()
        k = self._grabbed
        raw = self._read()
        # OpenCV decodes a recording's first frame when it opens it: a file removed since must still
        # read as a camera gone, not as a frame
        f = self._frame_file(k)
        if f is not None and not os.path.exists(f):
            raise CameraDisconnected(f"camera {self.spec!r}: {f} is gone (frame {k})")
        image, _ = normalise(raw, self.spec)
        if image.shape[:2] != (self._sensor.height, self._sensor.width):
            raise CameraError(f"camera {self.spec!r}: frame {image.shape[1]}x{image.shape[0]} differs from the "
                              f"sensor {self._sensor.width}x{self._sensor.height} it opened with")
        return image, ts, self._exposure_s, {"exposure_applied": self._exposure_applied}

    def close(self) -> None:
        self.disarm()
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _device_serial(index: int) -> str:
    """``uvcN`` plus the USB serial of ``/dev/videoN`` where sysfs has one."""
    for rel in ("device/../serial", "device/serial"):
        p = Path(f"/sys/class/video4linux/video{index}") / rel
        try:
            s = p.read_text().strip()
        except OSError:
            continue
        if s:
            return f"uvc{index}:{s}"
    return f"uvc{index}"


register_backend("uvc", UVCCamera)
