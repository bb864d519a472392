"""The ``genicam`` backend against Aravis's GigE Vision camera emulator (issue 14 §2).

Each camera here is a real ``arv-fake-gv-camera-0.8`` process on loopback with a unique serial,
reached through Aravis's GigE Vision control and stream protocols (no mocks).  The emulator
draws a fixed diagonal ramp whose brightness grows with log10(exposure) and with gain, and it
cannot fire its Line0 input: ``exposure_scales`` is False and the edge mode is checked only as
far as the device's trigger registers.
"""

from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import time

import numpy as np
import pytest

from tests.capture.contract import CameraContract

FAKE = shutil.which("arv-fake-gv-camera-0.8")
try:
    from dualscale.capture import genicam
    genicam.aravis()
    _why = None
except Exception as e:  # ToolError: gi / Aravis missing
    _why = f"Aravis GObject introspection unavailable: {e}"

pytestmark = [
    pytest.mark.skipif(FAKE is None, reason="arv-fake-gv-camera-0.8 not installed (Debian aravis-tools)"),
    pytest.mark.skipif(_why is not None, reason=_why or ""),
    # not yet reliable: under load the emulator loses a software trigger in about one module run in
    # three (a test then gets one frame fewer); the Aravis packages are not in `make deps` until then
    pytest.mark.skipif(os.environ.get("DUALSCALE_GENICAM") != "1",
                       reason="genicam tests are opt-in (DUALSCALE_GENICAM=1) until a lost software trigger "
                              "under load is fixed (issue 14)"),
]

from dualscale.capture.camera import TriggerInfo, TriggerMode, open_camera  # noqa: E402
from dualscale.errors import CameraDisconnected, CameraTimeout, InputError  # noqa: E402

_serials = itertools.count()
GVCP_PORT = 3956


def _gvcp_bound() -> bool:
    """Whether some process has a UDP socket on 127.0.0.1:3956 (an emulator's control port)."""
    with open("/proc/net/udp") as f:
        return any(line.split()[1] == f"0100007F:{GVCP_PORT:04X}" for line in list(f)[1:])


class Emulator:
    """One ``arv-fake-gv-camera-0.8 -i 127.0.0.1 -s SERIAL`` process, discoverable when started."""

    def __init__(self):
        # every emulator binds 127.0.0.1:3956 (SO_REUSEADDR): two at once would answer each
        # other's control packets, so a test runs one at a time and waits out a leftover one
        end = time.monotonic() + 10
        while _gvcp_bound():
            if time.monotonic() > end:
                pytest.skip("another GigE Vision emulator holds 127.0.0.1:3956 (a concurrent test run?)")
            time.sleep(0.1)
        self.serial = f"DS{os.getpid() % 100000:05d}{next(_serials):03d}"
        self.proc = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", self.serial],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            if _gvcp_bound():
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        self.kill()
        pytest.fail(f"emulator {self.serial} did not bind 127.0.0.1:{GVCP_PORT} within 5 s")

    def kill(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(5)


@pytest.fixture
def emulator():
    e = Emulator()
    yield e
    e.kill()


@pytest.fixture
def cam(emulator):
    c = open_camera(f"genicam:{emulator.serial}")
    yield c
    c.disarm()
    c.close()


class TestGenICamContract(CameraContract):
    exposure_scales = False  # log10(exposure) brightness in the emulator, checked below instead

    @pytest.fixture(autouse=True)
    def _emulators(self):
        self._emus = []
        yield
        for e in self._emus:
            e.kill()

    def make(self):
        e = Emulator()
        self._emus.append(e)
        c = open_camera(f"genicam:{e.serial}")
        c._emulator = e
        return c

    def disconnect(self, cam):
        cam._emulator.kill()


def _acquire(cam, n, exposure_s=0.005):
    cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=n, exposure_s=exposure_s, timeout_s=5))
    cam.arm()
    t = []
    for _ in range(n):
        cam.trigger()
        t.append(time.time())
    frames = cam.collect()
    cam.disarm()
    return frames, t


def test_open_by_serial_and_first_and_unknown(emulator):
    c = open_camera(f"genicam:{emulator.serial}")
    try:
        assert c.serial == emulator.serial and c.spec == f"genicam:{emulator.serial}"
        s = c.sensor()
        assert (s.width, s.height, s.pixel_format, s.bit_depth) == (512, 512, "Mono8", 8)
        assert s.pixel_um == genicam.DEFAULT_PIXEL_UM  # the emulator has no SensorPixelWidth
        assert c.settings()["pixel_um_source"].startswith("default")
    finally:
        c.close()
    first = open_camera("genicam:")
    assert first.serial  # some camera (this emulator or another test's)
    first.close()
    with pytest.raises(CameraDisconnected, match="NOSUCH"):
        open_camera("genicam:NOSUCH?discovery_timeout_s=0.3")
    with pytest.raises(InputError, match="unknown option"):
        open_camera(f"genicam:{emulator.serial}?colour=1")


def test_exposure_and_gain_read_back_and_range_checked(cam):
    lo, hi = cam.exposure_bounds_s()
    assert (lo, hi) == pytest.approx((10e-6, 10.0))
    cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.0123))
    assert cam.settings()["exposure_us"] == pytest.approx(12300)
    assert cam.settings()["TriggerSource"] == "Software" and cam.settings()["TriggerMode"] == "On"
    assert cam.set_gain(3) == pytest.approx(3)
    assert cam.settings()["gain"] == pytest.approx(3)
    with pytest.raises(InputError, match="Gain"):
        cam.set_gain(1000)
    for bad in (5e-6, 11.0):
        with pytest.raises(InputError, match="ExposureTime"):
            cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=bad))


def test_exposure_and_gain_change_the_image(cam):
    """The emulator's ramp scales by 1 + gain + log10(exposure / 10 ms): longer exposure and
    more gain both brighten it, by the emulator's law."""
    m = {}
    for exp, gain in ((0.005, 0), (0.02, 0), (0.005, 1)):
        cam.set_gain(gain)
        f = _acquire(cam, 1, exp)[0][0]
        assert f.exposure_s == pytest.approx(exp) and f.metadata["settings"]["gain"] == pytest.approx(gain)
        m[exp, gain] = float(f.image.mean())
    y, x = np.mgrid[:512, :512]
    law = {e: np.clip(((x + y) % 255) * (1 + np.log10(e / 0.01)), 0, 255).mean() for e in (0.005, 0.02)}
    ratio = m[0.02, 0] / m[0.005, 0]  # ~1.77: the 4x exposure brightens by the log law, clipped at 255
    assert ratio == pytest.approx(law[0.02] / law[0.005], rel=0.03)
    assert m[0.005, 1] > 1.5 * m[0.005, 0]


def test_pixel_format_mono8_vs_mono16(cam):
    f8 = _acquire(cam, 1)[0][0]
    cam.set_pixel_format("Mono16")
    assert cam.sensor().bit_depth == 16 and cam.sensor().pixel_format == "Mono16"
    f16 = _acquire(cam, 1)[0][0]
    for f in (f8, f16):
        assert f.image.dtype == np.float32 and f.image.shape == (512, 512)
        assert 0 <= f.image.min() and f.image.max() <= 1
    assert f8.metadata["pixel_format"] == "Mono8" and f16.metadata["pixel_format"] == "Mono16"
    # the same ramp: normalised by 255 and 65535 the two agree to within one 8-bit step
    assert abs(float(f16.image.mean()) - float(f8.image.mean())) < 2 / 255
    # Mono16 keeps more levels than 8 bits hold
    assert len(np.unique(f16.image)) > 256 >= len(np.unique(f8.image))
    with pytest.raises(InputError, match="PixelFormat"):
        cam.set_pixel_format("RGB8")


def test_timestamps_increase_with_the_trigger_period(cam):
    """Camera timestamps (device ns -> s) step with the host's software triggers: each trigger
    waits for the previous frame, and the emulator starts a frame at its next frame-period tick
    (25 Hz), so the steps are >= the exposure and match the host's trigger times within a period."""
    frames, t_host = _acquire(cam, 4, 0.005)
    ts = np.array([f.timestamp_s for f in frames])
    assert (np.diff(ts) >= 0.005).all(), np.diff(ts)
    period = 1 / cam.settings()["frame_rate_hz"]
    # a frame is stamped after its trigger and before the next one is sent
    assert (ts - np.array(t_host) > -0.01).all() and (ts - np.array(t_host) < period + 0.05).all(), ts - t_host
    assert [f.metadata["frame_id"] for f in frames] == list(range(frames[0].metadata["frame_id"],
                                                                   frames[0].metadata["frame_id"] + 4))


def test_dropped_frames_are_counted_not_delivered(cam):
    """Free-running at 100 Hz into a pool of 3 buffers: the host drains nothing for 0.3 s, so the
    ~27 frames the camera sends meanwhile find no buffer.  The 6 delivered frames are whole, and
    the frames missing between them are counted (GVSP block-id gaps), never passed off as
    consecutive."""
    cam.set_frame_rate(100)
    cam.prepare_free_run(6, 0.001, timeout_s=3, buffers=3)
    cam.arm()
    time.sleep(0.3)
    frames = cam.collect()
    st = cam.stats()
    cam.disarm()
    ids = [f.metadata["frame_id"] for f in frames]
    assert len(frames) == 6 and [f.index for f in frames] == list(range(6))
    gaps = sum((b - a - 1) % 65535 for a, b in zip(ids, ids[1:]))
    assert st["id_gaps"] == gaps and 15 <= gaps <= 40, (ids, st)
    assert st["dropped"] >= gaps and st["underrun_packets"] > 0, st
    assert cam.stats() == st  # kept after disarm
    with pytest.raises(InputError):
        cam.trigger()  # free run: no software trigger


def test_edge_mode_writes_line0_rising_edge_and_times_out_without_edges(emulator):
    """The emulator cannot fire Line0: the edge mapping is checked at the registers, and an edge
    acquisition with no edges is a CameraTimeout with no frames, not a hang."""
    c = open_camera(f"genicam:{emulator.serial}")
    assert TriggerMode.EDGE not in c.supported_modes()
    with pytest.raises(InputError, match="edge"):
        c.prepare(TriggerInfo(TriggerMode.EDGE, frames=1))
    c.close()
    c = open_camera(f"genicam:{emulator.serial}?edge=1")
    try:
        c.prepare(TriggerInfo(TriggerMode.EDGE, frames=2, exposure_s=0.002, timeout_s=0.5))
        s = c.settings()
        assert (s["TriggerMode"], s["TriggerSource"], s["TriggerActivation"]) == ("On", "Line0", "RisingEdge")
        c.arm()
        with pytest.raises(InputError):
            c.trigger()
        t0 = time.monotonic()
        with pytest.raises(CameraTimeout) as e:
            c.collect()
        assert e.value.frames == [] and time.monotonic() - t0 < 1.5
    finally:
        c.close()


def test_killed_emulator_mid_acquisition_keeps_the_frames_that_came(emulator):
    c = open_camera(f"genicam:{emulator.serial}")
    try:
        c.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=3, exposure_s=0.002, timeout_s=3))
        c.arm()
        c.trigger()
        c.trigger()  # waits for frame 0
        time.sleep(0.2)  # frame 1 arrives
        emulator.kill()
        t0 = time.monotonic()
        with pytest.raises((CameraDisconnected, CameraTimeout)) as e:
            c.trigger()
            c.collect()
        assert time.monotonic() - t0 < 10
        if isinstance(e.value, CameraTimeout):
            assert [f.index for f in e.value.frames] == [0, 1]
    finally:
        c.close()
