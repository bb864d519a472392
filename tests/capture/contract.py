"""The camera contract test suite (issue 14 §1): every backend passes it.

A backend's test module subclasses :class:`CameraContract` as ``TestXxxContract`` and provides:

* ``make(self) -> Camera`` -- a freshly opened camera (closed by the suite);
* ``fire(self, cam, n)`` -- deliver ``n`` trigger edges to its trigger input (``edge``/``gate``
  modes; skip what the backend cannot do by leaving the mode out of ``supported_modes``);
* ``disconnect(self, cam)`` -- make the camera stop answering (kill its emulator, close its
  device), or ``pytest.skip`` with the reason;
* ``exposure_scales`` -- whether the image's mean grows with the exposure (an emulator that
  draws a fixed pattern sets it False, and the suite then checks the reported exposure only).
"""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.capture.camera import Camera, Frame, SensorInfo, TriggerInfo, TriggerMode
from dualscale.errors import CameraDisconnected, CameraError, CameraTimeout, InputError


def acquire(cam: Camera, n: int, exposure_s: float, timeout_s: float = 10.0) -> list[Frame]:
    """``n`` software-triggered frames of ``exposure_s`` (prepare, arm, trigger n times, collect,
    disarm)."""
    cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=n, exposure_s=exposure_s, timeout_s=timeout_s))
    cam.arm()
    for _ in range(n):
        cam.trigger()
    frames = cam.collect()
    cam.disarm()
    return frames


class CameraContract:
    exposure_scales = True
    exposure_s = 0.005

    def make(self) -> Camera:  # pragma: no cover - provided by the backend's test
        raise NotImplementedError

    def fire(self, cam: Camera, n: int) -> None:  # pragma: no cover
        raise NotImplementedError

    def disconnect(self, cam: Camera) -> None:  # pragma: no cover
        raise NotImplementedError

    @pytest.fixture
    def cam(self):
        c = self.make()
        try:
            yield c
        finally:
            try:
                c.disarm()
            finally:
                c.close()

    def _acquire(self, cam: Camera, n: int, exposure_s: float | None = None) -> list[Frame]:
        return acquire(cam, n, exposure_s or self.exposure_s)

    # -- what a camera reports -------------------------------------------------------------------
    def test_reports_sensor_serial_and_settings(self, cam):
        assert isinstance(cam, Camera)
        s = cam.sensor()
        assert isinstance(s, SensorInfo) and s.width > 0 and s.height > 0 and s.bit_depth > 0
        assert cam.serial and cam.spec
        assert isinstance(cam.settings(), dict)
        assert TriggerMode.INTERNAL in cam.supported_modes()

    # -- internal trigger, frame counts, metadata ------------------------------------------------
    def test_internal_trigger_delivers_exactly_the_armed_frames(self, cam):
        frames = self._acquire(cam, 3)
        s = cam.sensor()
        assert [f.index for f in frames] == [0, 1, 2]
        ts = [f.timestamp_s for f in frames]
        assert all(b > a for a, b in zip(ts, ts[1:])), ts
        for f in frames:
            assert f.image.dtype == np.float32 and f.image.shape[:2] == (s.height, s.width)
            assert np.isfinite(f.image).all() and f.image.min() >= 0 and f.image.max() <= 1
            assert f.exposure_s == pytest.approx(self.exposure_s, rel=0.05, abs=2e-5)
            assert f.metadata["serial"] == cam.serial and f.metadata["sensor"]["width"] == s.width
            assert f.metadata["trigger"]["frames"] == 3

    def test_exposure_is_applied(self, cam):
        short = self._acquire(cam, 1, self.exposure_s)[0]
        long = self._acquire(cam, 1, 4 * self.exposure_s)[0]
        assert long.exposure_s == pytest.approx(4 * short.exposure_s, rel=0.05)
        if self.exposure_scales:
            m_s, m_l = float(short.image.mean()), float(long.image.mean())
            assert m_l > 2.5 * m_s, (m_s, m_l)

    def test_rearm_after_disarm(self, cam):
        assert len(self._acquire(cam, 1)) == 1
        cam.disarm()  # idempotent
        assert len(self._acquire(cam, 2)) == 2

    # -- hardware trigger modes ------------------------------------------------------------------
    def test_edge_trigger_one_frame_per_edge(self, cam):
        if TriggerMode.EDGE not in cam.supported_modes():
            pytest.skip(f"{cam.spec} has no edge trigger")
        cam.prepare(TriggerInfo(TriggerMode.EDGE, frames=2, exposure_s=self.exposure_s, timeout_s=10))
        cam.arm()
        self.fire(cam, 2)
        frames = cam.collect()
        assert [f.index for f in frames] == [0, 1]

    def test_unsupported_mode_is_refused_at_prepare(self, cam):
        missing = [m for m in TriggerMode if m not in cam.supported_modes()]
        if not missing:
            pytest.skip("supports every trigger mode")
        with pytest.raises(InputError):
            cam.prepare(TriggerInfo(missing[0], frames=1, exposure_s=self.exposure_s))

    # -- faults ----------------------------------------------------------------------------------
    def test_fewer_frames_than_armed_times_out_and_keeps_what_arrived(self, cam):
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=3, exposure_s=self.exposure_s, timeout_s=1.5))
        cam.arm()
        cam.trigger()
        cam.trigger()
        with pytest.raises(CameraTimeout) as e:
            cam.collect()
        assert [f.index for f in e.value.frames] == [0, 1]

    def test_a_camera_that_stops_answering_is_an_error_not_a_hang(self, cam):
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=self.exposure_s, timeout_s=3))
        cam.arm()
        self.disconnect(cam)
        with pytest.raises(CameraError) as e:
            cam.trigger()
            cam.collect()
        assert isinstance(e.value, (CameraDisconnected, CameraTimeout))
