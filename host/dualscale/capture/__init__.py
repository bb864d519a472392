"""Capture: cameras on the rig's triggers (issue 14).  :mod:`.camera` is the one camera
contract (prepare / arm / collect / disarm) and the registry of backends by spec."""

from .camera import (BACKENDS, Camera, Frame, SensorInfo, TriggerInfo, TriggerMode, frame_metadata, open_camera,
                     parse_spec, register_backend)

__all__ = ["BACKENDS", "Camera", "Frame", "SensorInfo", "TriggerInfo", "TriggerMode", "frame_metadata",
           "open_camera", "parse_spec", "register_backend"]

from . import gphoto2cam  # noqa: E402,F401  registers "gphoto2" (python-gphoto2 is loaded on open)
from . import uvc  # noqa: E402,F401  registers "uvc"
from . import genicam  # noqa: E402,F401  registers "genicam" (Aravis is loaded on open)
