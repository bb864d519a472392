"""The ``genicam`` backend against Aravis's GigE Vision camera emulator (issue 14 §2).

Each camera here is a real ``arv-fake-gv-camera-0.8`` process on loopback, reached through
Aravis's GigE Vision control and stream protocols (no mocks).  `make deps` installs both
(Debian ``aravis-tools``, ``gir1.2-aravis-0.8``; PyPI ``PyGObject``); without them the module
skips and says which is missing.

The emulator draws a known image: pixel (x, y) of the frame with id ``fid`` is
``clip(((x + y + fid) mod 255) * s, 0, 255)`` in Mono8 and
``clip((256 (x + y + fid) mod 65535) * s, 0, 65535)`` in Mono16, with
``s = 1 + gain + log10(exposure / 10 ms)`` (Aravis's ``arvfakecamera.c``).  The tests compare
whole frames with it, so exposure, gain, pixel format *and which frame arrived* are all checked
end to end.  The emulator cannot fire its Line0 input: the edge mode is checked as far as the
device's trigger registers (``exposure_scales`` stays False: the image grows with
log10(exposure), checked exactly instead).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import socket
import subprocess
import time

import numpy as np
import pytest

from tests.capture.contract import CameraContract, acquire

FAKE = shutil.which("arv-fake-gv-camera-0.8")
try:
    from dualscale.capture import genicam
    genicam.aravis()
    _why = None
except Exception as e:  # ToolError: gi / Aravis missing
    _why = f"Aravis GObject introspection unavailable (`make deps` installs it): {e}"

pytestmark = [
    pytest.mark.skipif(FAKE is None, reason="arv-fake-gv-camera-0.8 not installed (Debian aravis-tools; "
                                            "`make deps` installs it)"),
    pytest.mark.skipif(_why is not None, reason=_why or ""),
]

from dualscale.capture.camera import TriggerInfo, TriggerMode, open_camera  # noqa: E402
from dualscale.errors import CameraDisconnected, CameraTimeout, InputError  # noqa: E402

GVCP_PORT = 3956
ADDRESS = "127.0.0.1"
SPEC = f"genicam:{ADDRESS}"  # by address: no discovery round (~1 s each)
_started = 0


def _gvcp_bound() -> bool:
    """Whether some process has a UDP socket on 127.0.0.1:3956 (an emulator's control port)."""
    with open("/proc/net/udp") as f:
        return any(line.split()[1] == f"0100007F:{GVCP_PORT:04X}" for line in list(f)[1:])


def _die_with_parent() -> None:
    """In the emulator's child process: SIGKILL when this test process dies (PR_SET_PDEATHSIG),
    so that a crashed run leaves no emulator holding 127.0.0.1:3956."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1


class Emulator:
    """One ``arv-fake-gv-camera-0.8 -i 127.0.0.1 -s SERIAL [args]`` process, bound when started."""

    def __init__(self, *args: str):
        global _started
        # every emulator binds 127.0.0.1:3956 (SO_REUSEADDR): two at once would answer each
        # other's control packets, so one runs at a time; wait out another run's (< 30 s)
        end = time.monotonic() + 60
        while _gvcp_bound():
            if time.monotonic() > end:
                pytest.skip("another GigE Vision emulator held 127.0.0.1:3956 for 60 s (a concurrent run?)")
            time.sleep(0.1)
        _started += 1
        self.serial = f"DS{os.getpid() % 100000:05d}{_started:03d}"
        self.proc = subprocess.Popen([FAKE, "-i", ADDRESS, "-s", self.serial, *args], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, preexec_fn=_die_with_parent)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            if _gvcp_bound():
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.01)
        self.kill()
        pytest.fail(f"emulator {self.serial} did not bind {ADDRESS}:{GVCP_PORT} within 5 s")

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
    c = open_camera(SPEC)
    yield c
    c.disarm()
    c.close()


def expected_image(fid: int, exposure_s: float, gain: float, pixel_format: str = "Mono8") -> np.ndarray:
    """The emulator's frame ``fid`` (module docstring), normalised like the backend's frames."""
    y, x = np.mgrid[:512, :512].astype(np.float64)
    s = 1 + gain + np.log10(exposure_s / 0.01)
    if pixel_format == "Mono8":
        return (np.clip(((x + y + fid) % 255) * s, 0, 255).astype(np.uint8) / 255).astype(np.float32)
    return (np.clip(((256 * (x + y + fid)) % 65535) * s, 0, 65535).astype(np.uint16) / 65535).astype(np.float32)


def assert_is_frame(f, exposure_s, gain, pixel_format="Mono8"):
    """``f`` is, pixel for pixel, the emulator frame its GVSP frame id names."""
    want = expected_image(f.metadata["frame_id"], exposure_s, gain, pixel_format)
    np.testing.assert_allclose(f.image, want, atol=1e-6, err_msg=f"frame {f.index} (id {f.metadata['frame_id']})")


class TestGenICamContract(CameraContract):
    exposure_scales = False  # log10(exposure) brightness in the emulator, checked exactly below instead

    @pytest.fixture(autouse=True)
    def _emulators(self):
        self._emus = []
        yield
        for e in self._emus:
            e.kill()

    def make(self):
        e = Emulator()
        self._emus.append(e)
        c = open_camera(SPEC)
        c._emulator = e
        return c

    def disconnect(self, cam):
        cam._emulator.kill()


def _acquire(cam, n, exposure_s=0.005):
    return acquire(cam, n, exposure_s, timeout_s=5)


def test_open_by_serial_address_and_first_and_unknown(emulator):
    c = open_camera(f"genicam:{emulator.serial}")  # discovery by serial
    try:
        assert c.serial == emulator.serial and c.spec == f"genicam:{emulator.serial}"
        s = c.sensor()
        assert (s.width, s.height, s.pixel_format, s.bit_depth) == (512, 512, "Mono8", 8)
        assert s.pixel_um == genicam.DEFAULT_PIXEL_UM  # the emulator has no SensorPixelWidth
        assert c.settings()["pixel_um_source"].startswith("default")
    finally:
        c.close()
    for spec in (SPEC, "genicam:"):  # by address, and the first camera found
        c = open_camera(spec)
        assert c.serial == emulator.serial
        c.close()
    with pytest.raises(CameraDisconnected, match="NOSUCH"):
        open_camera("genicam:NOSUCH?discovery_timeout_s=0.3")
    with pytest.raises(InputError, match="unknown option"):
        open_camera(f"{SPEC}?colour=1")


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


def test_exposure_gain_and_pixel_format_reach_the_image(cam):
    """Each frame equals, pixel for pixel, the emulator's image for its exposure, gain, pixel
    format and frame id; Mono16 keeps levels that Mono8 cannot hold; the metadata says so."""
    for pf in ("Mono8", "Mono16"):
        cam.set_pixel_format(pf)
        assert cam.sensor().pixel_format == pf and cam.sensor().bit_depth == {"Mono8": 8, "Mono16": 16}[pf]
        for exposure_s, gain in ((0.005, 0), (0.02, 0), (0.005, 1)):
            cam.set_gain(gain)
            f = _acquire(cam, 1, exposure_s)[0]
            assert f.image.dtype == np.float32 and f.image.shape == (512, 512)
            assert f.exposure_s == pytest.approx(exposure_s)
            assert f.metadata["pixel_format"] == pf and f.metadata["settings"]["gain"] == pytest.approx(gain)
            assert f.metadata["sensor"]["bit_depth"] == cam.sensor().bit_depth
            assert_is_frame(f, exposure_s, gain, pf)
            levels = len(np.unique(f.image))
            assert levels > 256 if pf == "Mono16" else levels <= 256
    with pytest.raises(InputError, match="PixelFormat"):
        cam.set_pixel_format("RGB8")


def test_timestamps_follow_the_software_triggers(cam):
    """Device timestamps (ns -> s; the emulator's clock is the host's wall clock) step with the
    host's software triggers: each frame is stamped after its trigger was sent and by the
    emulator's next look at its trigger register (a 40 ms tick; 100 ms before the first frame),
    each trigger is sent after the frame before it, and the frame ids follow each other.  (The
    emulator stamps a frame when it draws it: it does not take the exposure time, so frames may
    be closer than the exposure.)"""
    frames = _acquire(cam, 4, 0.005)
    ts = np.array([f.timestamp_s for f in frames])
    sent = np.array([f.metadata["trigger_host_s"] for f in frames])
    assert (np.diff(ts) > 0).all(), np.diff(ts)
    lag = ts - sent
    assert (lag > -0.002).all() and (lag < 0.1 + 0.1).all(), lag
    assert (sent[1:] > ts[:-1] - 0.002).all(), (sent, ts)  # a trigger waits for the frame before it
    ids = [f.metadata["frame_id"] for f in frames]
    assert ids == list(range(ids[0], ids[0] + 4))
    assert all(f.metadata["system_timestamp_s"] >= f.timestamp_s - 0.002 for f in frames)


def _stream_rcvbuf(port: int) -> int:
    """SO_RCVBUF of this process's UDP socket on ``port``, found through /proc (independently
    of the backend's own lookup)."""
    rows = [r.split() for r in open("/proc/net/udp").read().splitlines()[1:]]
    inodes = {r[9] for r in rows if int(r[1].split(":")[1], 16) == port}
    for fd in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{fd}")[8:-1] in inodes:
                with socket.socket(fileno=os.dup(int(fd))) as s:
                    return s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        except OSError:
            continue
    raise AssertionError(f"no UDP socket of this process on port {port}")


def test_stream_socket_holds_whole_frames_before_the_first_packet(emulator):
    """The root cause of the lost first frames (docs/CAPTURE.md): Aravis enlarges the stream's
    receive buffer only when a frame's first packet arrives, and the emulator sends the whole
    frame (512 KiB in Mono16, 375 packets) in one burst into Linux's 208 KiB default.  Sized at
    prepare(), before AcquisitionStart, the socket holds several frames."""
    c = open_camera(f"{SPEC}?pixel_format=Mono16")
    try:
        c.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.005))
        payload = 512 * 512 * 2
        with open("/proc/sys/net/core/rmem_max") as f:
            rmem_max = int(f.read())
        forced = os.geteuid() == 0  # CAP_NET_ADMIN: SO_RCVBUFFORCE passes net.core.rmem_max
        if not forced and rmem_max < 2 * payload:
            pytest.skip(f"net.core.rmem_max = {rmem_max} and no CAP_NET_ADMIN: no process can get a socket "
                        f"buffer of 2 frames ({2 * payload} B); raise net.core.rmem_max (docs/CAPTURE.md)")
        rb = _stream_rcvbuf(int(c._stream.get_port()))
        assert rb >= 2 * payload, rb
        assert c.stats()["socket_buffer_bytes"] == rb
    finally:
        c.close()


def test_single_frame_acquisitions_arrive_whole(emulator):
    """The lost-trigger symptom of issue 14: each prepare() opens a new stream, and its first
    frame lost its tail packets in about one acquisition in four (Mono16; RcvbufErrors in
    /proc/net/snmp).  15 acquisitions in a row now all deliver their frame, whole."""
    c = open_camera(f"{SPEC}?pixel_format=Mono16")
    try:
        for i in range(15):
            c.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.002, timeout_s=3))
            c.arm()
            c.trigger()
            f = c.collect()[0]
            st = c.stats()
            c.disarm()
            assert st["failures"] == 0 and st["dropped"] == 0, (i, st)
            assert_is_frame(f, 0.002, 0, "Mono16")
    finally:
        c.close()


def test_damaged_frames_leave_gaps_and_later_frames_keep_their_index(monkeypatch):
    """The emulator drops 3 GVSP packets in 1000 (``-r 3``) and answers no resend, so about 4
    frames in 10 arrive damaged.  Each is counted lost and leaves its index empty; every frame
    that does arrive is the one its trigger started (image and frame id), never shifted onto an
    earlier trigger; collect() says which frames are missing without waiting out its timeout."""
    monkeypatch.setattr(genicam, "FRAME_RETENTION_US", 150_000)  # report damage quicker (Aravis: 100 ms)
    e = Emulator("-r", "3")
    try:
        c = open_camera(SPEC)
        try:
            for attempt in range(4):  # until some frames are damaged and some are whole
                n = 10
                c.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=n, exposure_s=0.01, timeout_s=30))
                c.arm()
                for _ in range(n):
                    c.trigger()
                t0 = time.monotonic()
                try:
                    frames = c.collect()
                except CameraTimeout as err:
                    frames, message = err.frames, str(err)
                else:
                    message = ""
                took = time.monotonic() - t0
                st = c.stats()
                c.disarm()
                if 0 < len(frames) < n:
                    break
            else:
                pytest.fail(f"4 acquisitions without both whole and damaged frames ({st})")
            idx = [f.index for f in frames]
            missing = sorted(set(range(n)) - set(idx))
            assert idx == sorted(idx) and st["failures"] == len(missing) and st["dropped"] == len(missing), st
            assert f"{missing} lost" in message and took < 5, (message, took)
            first_id = frames[0].metadata["frame_id"] - frames[0].index
            for f in frames:
                assert f.metadata["frame_id"] - f.index == first_id  # one GVSP id per trigger, in order
                assert_is_frame(f, 0.01, 0)
        finally:
            c.close()
    finally:
        e.kill()


def test_an_unanswered_trigger_ends_the_acquisition_and_rearming_recovers(cam, monkeypatch):
    """A software trigger the camera ignores (here: its TriggerSource switched to Line0 behind
    the backend's back) gets no frame: the next trigger() raises CameraTimeout keeping the
    frames so far, and so does everything until the camera is re-armed -- a late frame could
    no longer be told from the next trigger's.  prepare() + arm() starts clean."""
    monkeypatch.setattr(genicam, "READOUT_WAIT_S", 0.4)
    cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=3, exposure_s=0.002, timeout_s=3))
    cam.arm()
    cam.trigger()
    with pytest.raises(CameraTimeout) as err:
        cam.collect(timeout_s=1.0)  # frame 0 arrives; 1 and 2 are not triggered yet
    assert [f.index for f in err.value.frames] == [0]
    cam._dev.set_string_feature_value("TriggerSource", "Line0")
    cam.trigger()  # trigger 1, which the camera ignores
    t0 = time.monotonic()
    with pytest.raises(CameraTimeout, match="trigger 1 got no frame") as err:
        cam.trigger()
    assert time.monotonic() - t0 < 1.5 and [f.index for f in err.value.frames] == [0]
    with pytest.raises(CameraTimeout, match="disarm and arm again"):
        cam.collect()
    assert cam.stats()["lost_triggers"] == 1
    cam.disarm()
    frames = _acquire(cam, 3, 0.002)
    assert [f.index for f in frames] == [0, 1, 2] and cam.stats()["dropped"] == 0


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
    for f in frames:
        assert_is_frame(f, 0.001, 0)
    assert cam.stats() == st  # kept after disarm
    with pytest.raises(InputError):
        cam.trigger()  # free run: no software trigger


def test_edge_mode_writes_line0_rising_edge_and_times_out_without_edges(emulator):
    """The emulator cannot fire Line0: the edge mapping is checked at the registers, and an edge
    acquisition with no edges is a CameraTimeout with no frames, not a hang."""
    c = open_camera(SPEC)
    assert TriggerMode.EDGE not in c.supported_modes()
    with pytest.raises(InputError, match="edge"):
        c.prepare(TriggerInfo(TriggerMode.EDGE, frames=1))
    c.close()
    c = open_camera(f"{SPEC}?edge=1")
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
    """The camera dies after two of three frames: the next trigger fails within Aravis's GVCP
    retries (~2.5 s) as CameraDisconnected, the frames that came are whole and indexed, and
    closing the dead camera does not wait for Aravis's own teardown (~10 s of GVCP timeouts)."""
    c = open_camera(SPEC)
    try:
        c.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=3, exposure_s=0.002, timeout_s=3))
        c.arm()
        c.trigger()
        c.trigger()  # waits for frame 0
        time.sleep(0.2)  # frame 1 arrives
        emulator.kill()
        t0 = time.monotonic()
        with pytest.raises(CameraDisconnected, match="TriggerSoftware") as err:
            c.trigger()  # takes frame 1, then the trigger write gets no answer
        assert time.monotonic() - t0 < 4
        assert [f.index for f in err.value.frames] == [0, 1]
        with pytest.raises(CameraDisconnected) as err:
            c.collect()
        assert [f.index for f in err.value.frames] == [0, 1]
        for f in err.value.frames:
            assert_is_frame(f, 0.002, 0)
    finally:
        t0 = time.monotonic()
        c.close()
        assert time.monotonic() - t0 < 0.5
