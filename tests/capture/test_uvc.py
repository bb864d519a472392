"""The ``uvc`` backend on recorded cameras: 8- and 16-bit PNG sequences written here (there is no
/dev/video* on the build machine, so the V4L2 device path and its exposure control are untested;
docs/CAPTURE.md "UVC")."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import dualscale.capture.uvc  # noqa: F401  (registers "uvc")
from dualscale.capture.camera import TriggerInfo, TriggerMode, open_camera
from dualscale.capture.camera import split_options
from dualscale.errors import CameraDisconnected, InputError

try:  # tests/capture may or may not be a package
    from .contract import CameraContract
except ImportError:
    from contract import CameraContract


def write_sequence(folder, n=8, h=24, w=32, dtype=np.uint8, channels=3):
    """``n`` frames with a known value per frame: frame k's pixel (y, x) = (k*7 + y + x) mod 200 (x 256 for 16-bit)."""
    folder.mkdir(parents=True, exist_ok=True)
    scale = 256 if dtype == np.uint16 else 1
    y, x = np.mgrid[0:h, 0:w]
    frames = []
    for k in range(n):
        grey = ((k * 7 + y + x) % 200).astype(np.int64) * scale
        img = grey.astype(dtype) if channels == 1 else np.dstack([grey, grey // 2, grey // 4]).astype(dtype)  # BGR
        assert cv2.imwrite(str(folder / f"f_{k:03d}.png"), img)
        frames.append(img)
    return str(folder / "f_%03d.png"), frames


class TestUVCContract(CameraContract):
    exposure_scales = False  # a recording cannot respond to exposure: the suite checks the reported exposure

    @pytest.fixture(autouse=True)
    def _seq(self, tmp_path):
        self.pattern, _ = write_sequence(tmp_path / "seq")
        self.folder = tmp_path / "seq"

    def make(self):
        return open_camera(f"uvc:{self.pattern}")

    def disconnect(self, cam):
        for p in self.folder.iterdir():
            p.unlink()


def test_frames_are_the_sequence_normalised_rgb_8bit(tmp_path):
    pattern, frames = write_sequence(tmp_path / "s")
    cam = open_camera(f"uvc:{pattern}?pixel_um=2.5")
    try:
        s = cam.sensor()
        assert (s.width, s.height, s.bit_depth, s.pixel_format, s.pixel_um) == (32, 24, 8, "RGB8", 2.5)
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=2, exposure_s=0.01))
        cam.arm()
        cam.trigger()
        cam.trigger()
        got = cam.collect()
        for k in range(2):  # the probe at open is not frame 0: the acquisition starts at the first file
            np.testing.assert_allclose(got[k].image, frames[k][:, :, ::-1] / 255.0, rtol=0, atol=1e-7)
        assert cam.settings()["exposure_applied"] is False and got[0].metadata["exposure_applied"] is False
        assert got[0].metadata["settings"]["pixel_um_known"] is True
    finally:
        cam.close()


def test_16bit_source_normalises_by_65535(tmp_path):
    pattern, frames = write_sequence(tmp_path / "s16", n=2, dtype=np.uint16, channels=1)
    cam = open_camera(f"uvc:{pattern}")
    try:
        s = cam.sensor()
        assert (s.bit_depth, s.pixel_format) == (16, "Mono16")
        cam.prepare(TriggerInfo(frames=1))
        cam.arm()
        cam.trigger()
        img = cam.collect()[0].image
        assert img.shape == (24, 32) and img.dtype == np.float32
        np.testing.assert_allclose(img, frames[0] / 65535.0, rtol=0, atol=1e-7)
        assert frames[0].max() > 255 and img.max() <= 1  # divided by 255 it would exceed 1
    finally:
        cam.close()


def test_end_of_recording_is_a_disconnect_not_a_loop(tmp_path):
    pattern, _ = write_sequence(tmp_path / "s", n=2)
    cam = open_camera(f"uvc:{pattern}")
    try:
        cam.prepare(TriggerInfo(frames=3))
        cam.arm()
        cam.trigger()
        cam.trigger()
        with pytest.raises(CameraDisconnected, match="after 2 grabbed"):
            cam.trigger()
    finally:
        cam.close()


def test_only_internal_trigger_and_clear_open_errors(tmp_path):
    pattern, _ = write_sequence(tmp_path / "s", n=1)
    cam = open_camera(f"uvc:{pattern}")
    try:
        with pytest.raises(InputError, match="edge"):
            cam.prepare(TriggerInfo(TriggerMode.EDGE))
        with pytest.raises(InputError, match="not armed"):
            cam.trigger()
    finally:
        cam.close()
    with pytest.raises(InputError, match="uvc:N"):
        open_camera("uvc:")
    with pytest.raises(CameraDisconnected, match="does not exist"):
        open_camera(f"uvc:{tmp_path}/missing.mp4")
    with pytest.raises(CameraDisconnected, match="no video device 7"):
        open_camera("uvc:7")  # no /dev/video7 here (nor on most machines)
    with pytest.raises(InputError, match="pixel_um"):
        open_camera(f"uvc:{pattern}?pixel_um=-1")


def test_split_options():
    assert split_options("0?pixel_um=3&a=b") == ("0", {"pixel_um": "3", "a": "b"})
    assert split_options("/x/what?.png") == ("/x/what?.png", {})
    assert split_options("0") == ("0", {})
