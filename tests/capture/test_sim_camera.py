"""The ``sim`` camera backend on the POSIX firmware simulator's hardware side channel (issue 14 §2):
the contract suite, frames that show the light the firmware latched, gate exposures, camera-master
edges that advance the sequence, and equality with ``synth --dataset --realistic``."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

import dualscale.sim.camera  # noqa: F401  (registers "sim")
from dualscale.capture.camera import TriggerInfo, TriggerMode, open_camera
from dualscale.errors import CameraDisconnected, CameraError, CameraTimeout, InputError
from dualscale.protocol import regmap as rm
from dualscale.rig.client import RigClient
from dualscale.rig.launcher import SimulatedRig, sim_binary
from dualscale.rig.sequence import Step

try:  # tests/capture may or may not be a package
    from .contract import CameraContract
except ImportError:
    from contract import CameraContract

pytestmark = pytest.mark.skipif(not sim_binary().exists(), reason="build the simulator: make -C firmware posix")

MICRO = 1 << rm.TRIGGER_NAMES.index("micro")
FULL = rm.INTENSITY_MAX


class Rig:
    """A simulated rig with its side channel in ``folder``; ``client()`` opens a RigClient."""

    def __init__(self, folder, speed: float):
        self.link, self.hw = folder / "tty", folder / "hw.sock"
        self.sim = SimulatedRig("posix", link=self.link, speed=speed, hw_socket=self.hw).start()

    def client(self) -> RigClient:
        return RigClient(str(self.link))

    def camera(self, name: str = "micro", **opts) -> dualscale.sim.camera.SimCamera:
        q = "&".join(f"{k}={v}" for k, v in {"hw": self.hw, "size": 32, **opts}.items())
        return open_camera(f"sim:{name}?{q}")

    def stop(self) -> None:
        self.sim.stop()


@pytest.fixture
def rig0(tmp_path):
    """A rig at --speed 0 (device time jumps from deadline to deadline)."""
    r = Rig(tmp_path, 0)
    yield r
    r.stop()


@pytest.fixture
def rig1(tmp_path):
    """A rig in real time: manual lights stay on (at speed 0 device time jumps to the moment their
    on-time bucket fills, and the firmware switches them off with LED_LIMIT)."""
    r = Rig(tmp_path, 1)
    with r.client() as c:
        c.write_register(rm.HR.LED_MAX_ON_MS, 60000)
    yield r
    r.stop()


def expected(cam, lights, cdeg: int | None, exposure_s: float) -> np.ndarray:
    """What ``synth --realistic`` makes of these lights, composed independently of the camera:
    render per light + :func:`raw_signal` + :func:`rig_exposer` (noise off) at ``exposure_s``."""
    from dualscale.geometry.dome import DomeGeometry
    from dualscale.sim.render import Analyzer, LightState, render
    from dualscale.sim.targets import raw_signal, rig_exposer

    sc = cam.scene
    raw = np.zeros((sc.camera.height, sc.camera.width, 3))
    for kind, index, level in lights:
        name = {1: "led", 2: "backlight", 3: "diffuse"}[kind]
        state = {"led": LightState.led, "backlight": LightState.backlight}[name](index, level / FULL) \
            if name != "diffuse" else LightState.diffuse_group(level / FULL)
        an = None if cdeg is None else Analyzer(cdeg / 100.0, relative=True)
        rad = render(sc.maps, sc.camera, state, DomeGeometry.from_regmap(), an, texel_mm=sc.texel_mm)
        raw = raw + raw_signal(rad.detach().double().numpy(), sc.camera, name, None if name == "diffuse" else index)
    return rig_exposer(sc.camera, noise=False)(raw, exposure_s).astype(np.float32)


# ---- the contract ------------------------------------------------------------------------------

class TestSimContract(CameraContract):
    exposure_s = 0.05  # the diffuse group on twill: ~0.4 DN/s, far above the 0.004 DN dark signal

    @pytest.fixture(autouse=True)
    def _rig(self, tmp_path):
        self.rig = Rig(tmp_path, 1)  # real time: a manual light stays on (its bucket fills in 10 s)
        with self.rig.client() as c:
            c.write_register(rm.HR.LED_MAX_ON_MS, 60000)
            c.set_intensity(FULL)
            c.set_light(rm.Source.DIFFUSE, 0, True)
        yield
        self.rig.stop()

    def make(self):
        return self.rig.camera()

    def fire(self, cam, n):
        """The rig raises the camera's trigger line ``n`` times: a device-master sequence of ``n``
        steps, each pulsing the micro trigger for 100 µs, 100 ms apart."""
        steps = [Step(rm.Source.DIFFUSE, 0, FULL, None, 1000, 100_000, 100, 1, 0, MICRO)] * n
        with self.rig.client() as c:
            res = c.run(steps)
        assert sum(e.kind == rm.Event.TRIGGER for e in res.events) == n

    def disconnect(self, cam):
        self.rig.stop()


# ---- what the frames show ----------------------------------------------------------------------

def test_edge_frames_show_the_light_the_step_latched(rig0):
    """Device-master, edge trigger: each frame is the step's LED (metadata and pixels, exactly
    as the independent composition gives it with noise off); an unlit step is a dark frame."""
    steps = [Step(rm.Source.LED, 5, FULL, 0, 250_000, 300_000, 100, 1, 0, MICRO),
             Step(rm.Source.LED, 40, FULL // 2, 9000, 250_000, 300_000, 100, 1, 0, MICRO),
             Step(rm.Source.OFF, 0, 0, None, 1000, 300_000, 100, 1, 0, MICRO)]
    with rig0.camera(noise=0) as cam:
        cam.prepare(TriggerInfo(TriggerMode.EDGE, frames=3, exposure_s=0.25, timeout_s=20))
        cam.arm()
        with rig0.client() as c:
            res = c.run(steps, watchdog_ms=0)  # at speed 0 device time jumps past any host watchdog
        frames = cam.collect()
    trig = [e.ts_us for e in res.events if e.kind == rm.Event.TRIGGER]
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.metadata["device_t_us"] for f in frames] == trig  # exposure start = the rising edge
    assert [f.metadata["lights"] for f in frames] == [[[1, 5, FULL]], [[1, 40, FULL // 2]], []]
    assert [f.metadata["polarizer_cdeg"] for f in frames] == [0, 9000, 9000]
    assert all(f.exposure_s == 0.25 and f.metadata["trigger_source"] == "edge" for f in frames)
    want = [expected(cam, [(1, 5, FULL)], 0, 0.25), expected(cam, [(1, 40, FULL // 2)], 9000, 0.25),
            expected(cam, [], 9000, 0.25)]
    for f, w in zip(frames, want):
        np.testing.assert_array_equal(f.image, w)
    assert frames[0].image.mean() > 3 * frames[2].image.mean()  # LED 5 at P0 is lit, the OFF step dark
    assert not np.array_equal(want[0], expected(cam, [(1, 40, FULL)], 0, 0.25))  # the check tells LEDs apart


def test_gate_exposure_is_the_gate_and_brackets_reuse_one_render(rig0):
    """Gate mode (PULSE_US = 0): each frame's exposure is its bracket's (EV-stepped) gate, timed
    on the device clock; the brackets of one step render the scene once."""
    steps = [Step(rm.Source.LED, 12, FULL, 0, 1000, 50_000, 0, 3, 1, MICRO),
             Step(rm.Source.LED, 30, FULL, None, 1000, 7_000, 0, 1, 0, MICRO)]
    with rig0.camera(noise=0) as cam:
        cam.prepare(TriggerInfo(TriggerMode.GATE, frames=4, exposure_s=0.05, timeout_s=20))
        cam.arm()
        with rig0.client() as c:
            c.write_registers(rm.HR.FRAME_GAP_US, [0, 10_000])  # >= the camera's 5 ms readout
            res = c.run(steps, watchdog_ms=0)
        frames = cam.collect()
        renders = cam.scene.renders
        dark = [float(expected(cam, [], 0, f.exposure_s).mean()) for f in frames[:3]]
        want = expected(cam, [(1, 12, FULL)], 0, 0.2)
    assert [f.exposure_s for f in frames] == pytest.approx([0.05, 0.1, 0.2, 0.007], abs=1e-9)
    assert [f.metadata["device_t_us"] for f in frames] == [e.ts_us for e in res.events if e.kind == rm.Event.TRIGGER]
    assert renders == 2  # one per (lights, analyser) state
    signal = [float(f.image.mean()) - d for f, d in zip(frames, dark)]
    assert signal[1] / signal[0] == pytest.approx(2, rel=0.05) and signal[2] / signal[1] == pytest.approx(2, rel=0.05)
    np.testing.assert_array_equal(frames[2].image, want)


def test_an_edge_during_readout_is_missed_as_on_a_real_camera(rig0):
    """Two brackets 100 µs apart: the second rises while the camera still reads out (5 ms), so it
    is not a frame; collect() times out with the first and says why."""
    steps = [Step(rm.Source.LED, 3, FULL, None, 1000, 2_000, 0, 2, 0, MICRO)]
    with rig0.camera(readout_ms=5) as cam:
        cam.prepare(TriggerInfo(TriggerMode.GATE, frames=2, exposure_s=0.002, timeout_s=1))
        cam.arm()
        with rig0.client() as c:
            c.write_registers(rm.HR.FRAME_GAP_US, [0, 100])
            c.run(steps, watchdog_ms=0)
        with pytest.raises(CameraTimeout, match="busy triggers 1") as e:
            cam.collect()
    assert [f.index for f in e.value.frames] == [0]


def test_edges_right_after_a_long_software_exposure_are_taken(rig0):
    """A software-triggered 0.8 s dark then, at once, a device-master sequence (the adaptive
    capture's darks at a round's end, then the next round's metering): arming for the edges
    waits until the dark's exposure and readout ended on the device clock, so the sequence's
    edges find the sensor free.  (Without the wait the dark, delivered when rendered, left the
    sensor busy 0.8 device seconds and the sequence's frames were missed as busy triggers: 0
    frames, a retake.)"""
    steps = [Step(rm.Source.LED, 12, FULL, None, 1000, 5_000, 0, 2, 0, MICRO)]
    with rig0.camera(size=8, readout_ms=1, noise=0) as cam, rig0.client() as c:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.8, timeout_s=10))
        cam.arm()
        cam.trigger()
        (dark,) = cam.collect()
        cam.disarm()
        cam.prepare(TriggerInfo(TriggerMode.GATE, frames=2, exposure_s=0.005, timeout_s=10))
        cam.arm()
        assert c.status().uptime_us >= dark.metadata["device_t_us"] + 0.8e6
        c.write_registers(rm.HR.FRAME_GAP_US, [0, 2_000])
        res = c.run(steps, watchdog_ms=0)
        frames = cam.collect(timeout_s=5)
        busy = cam.settings()["busy_triggers"]
    assert busy == 0 and [f.metadata["device_t_us"] for f in frames] == [
        e.ts_us for e in res.events if e.kind == rm.Event.TRIGGER]


def test_camera_master_edges_advance_the_firmware(tmp_path):
    """Camera-master (PROTOCOL.md §3.2): each trigger() sends the camera's edge; the firmware
    latches the next step on it (CAMERA_EDGE events, in the frames' metadata), the frame shows
    that step's light, and the edge after the last step ends the sequence (SEQ_DONE, dark)."""
    rig = Rig(tmp_path, 1)  # real time: at speed 0 the camera timeout would be jumped to at once
    try:
        steps = [Step(rm.Source.LED, 5, FULL, None, 0, 10_000, 0, 1, 0, 0),
                 Step(rm.Source.LED, 20, FULL, None, 0, 10_000, 0, 2, 0, 0)]
        with rig.client() as c, rig.camera(master=1) as cam:
            c.write_register(rm.HR.MASTER_CAMERA, rm.CAMERA_NAMES.index("micro"))
            c.upload(steps)
            c.sync_events()
            c.start(rm.TriggerMode.CAMERA_MASTER)
            cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=4, exposure_s=0.01, timeout_s=10))
            cam.arm()
            for _ in range(4):
                cam.trigger()
            frames = cam.collect()
            events = c.poll_events()
            state = c.status().state
    finally:
        rig.stop()
    edges = [e for e in events if e.kind == rm.Event.CAMERA_EDGE]
    assert [(e.step, bool(e.arg & rm.EDGE_IGNORED)) for e in edges] == [(0, False), (1, False), (1, False), (1, True)]
    assert [f.metadata["master_edge"]["seq"] for f in frames] == [e.seq for e in edges]
    assert [f.metadata["device_t_us"] for f in frames] == [e.ts_us for e in edges]
    assert all(f.metadata["device_t_exact"] for f in frames)
    assert [f.metadata["lights"] for f in frames] == [[[1, 5, FULL]], [[1, 20, FULL]], [[1, 20, FULL]], []]
    assert any(e.kind == rm.Event.SEQ_DONE for e in events) and state == rm.State.DONE


def test_master_edge_the_rig_does_not_count_is_reported_not_invented(rig0):
    """A camera-master camera whose edge the rig ignores (no sequence running) still exposes, and
    its frame says that no CAMERA_EDGE came back."""
    with rig0.camera(master=1) as cam:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.001))
        cam.arm()
        cam.trigger()
        (f,) = cam.collect()
    assert f.metadata["master_edge"] is None and f.metadata["device_t_exact"] is False


# ---- equality with synth -----------------------------------------------------------------------

def test_micro_frame_equals_the_synth_sensor_path_exactly_without_noise(rig1):
    """noise=0: the camera's frame of LED 17 at P90 for 0.3 s is, pixel for pixel, render +
    raw_signal + rig_exposer at 0.3 s on the same material and seed."""
    with rig1.client() as c:
        c.set_polarizer(9000)
        c.set_intensity(FULL)
        c.set_light(rm.Source.LED, 17, True)
    with rig1.camera(material="satin", seed=4, noise=0) as cam:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.3))
        cam.arm()
        cam.trigger()
        (f,) = cam.collect()
        from dualscale.sim.materials import generate
        mat = generate("satin", 32, 0.0018, 4)
        assert torch.equal(mat.maps.albedo, cam.scene.maps.albedo)  # the same sample as synth's
        want = expected(cam, [(1, 17, FULL)], 9000, 0.3)
    assert f.metadata["lights"] == [[1, 17, FULL]] and f.metadata["polarizer_cdeg"] == 9000
    np.testing.assert_array_equal(f.image, want)


def _sigma(dn: np.ndarray) -> np.ndarray:
    """The sensor's noise [normalised DN] at level ``dn``: shot, read and quantisation."""
    from dualscale.sim.targets import SENSOR

    fw = SENSOR.full_well_e
    return np.sqrt(np.clip(dn, 0, None) / fw + (SENSOR.read_noise_e / fw) ** 2 + 1 / (12 * (2 ** SENSOR.bits - 1) ** 2))


def test_dataset_through_the_simulated_rig_equals_synth_within_noise(rig0, tmp_path):
    """``synth --dataset --realistic`` for twill, seed 3, LEDs 0 and 64 at P0/P90, the back light
    and the dark frames; then the same images taken through the firmware: one device-master
    sequence whose steps light each image's source at full intensity, turn the analyser and open
    the micro camera's gate for each image's exposure.  Every frame equals synth's image within
    the sensor noise (the difference, in units of its predicted sigma, has mean ~0 and std ~1)."""
    from dualscale.cli import main
    from dualscale.formats.dataset import read_dataset

    out = tmp_path / "synth"
    assert main(["synth", "twill", "-o", str(out), "--dataset", "--realistic", "--size", "32", "--lights", "mod64",
                 "--seed", "3", "--no-previews"]) == 0
    ds = read_dataset(out / "micro")
    src = {"led": rm.Source.LED, "backlight": rm.Source.BACKLIGHT, "off": rm.Source.OFF}
    steps = []
    for r in ds.records:
        lit = r.light_kind != "off"
        cdeg = None if r.analyzer_deg is None else round(r.analyzer_deg * 100)
        steps.append(Step(src[r.light_kind], r.light_id or 0, FULL if lit else 0, cdeg, 250_000,
                          round(r.exposure_s * 1e6), 0, 1, 0, MICRO))
    with rig0.camera(material="twill", seed=3) as cam:
        cam.prepare(TriggerInfo(TriggerMode.GATE, frames=len(steps), exposure_s=1.0, timeout_s=60))
        cam.arm()
        with rig0.client() as c:
            c.run(steps, watchdog_ms=0)
        frames = cam.collect()
    assert len(frames) == len(ds.records) == 8  # LEDs 0, 64 and the back light at P0, P90; 2 darks
    for i, (r, f) in enumerate(zip(ds.records, frames)):
        a = ds.load(i)
        assert f.exposure_s == pytest.approx(r.exposure_s, abs=1e-9), r.file
        z = (f.image - a) / np.sqrt(_sigma(a) ** 2 + _sigma(f.image) ** 2)
        assert abs(float(z.mean())) < 0.1 and 0.9 < float(z.std()) < 1.12, (r.file, float(z.mean()), float(z.std()))
        assert abs(float(f.image.mean()) / float(a.mean()) - 1) < 0.01, r.file


# ---- faults and the spec -----------------------------------------------------------------------

def test_drop_loses_frames_and_their_indices_show_it(rig0):
    """drop=P loses exposed frames; the indices of the rest show the gaps, and collect() knows at
    once that nothing more can come (all armed exposures taken), without waiting for the timeout."""
    with rig0.camera(drop=0.5, fault_seed=1) as cam:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=8, exposure_s=0.001, timeout_s=30))
        cam.arm()
        for _ in range(8):
            cam.trigger()
        t0 = time.monotonic()
        with pytest.raises(CameraTimeout, match="were lost") as e:
            cam.collect()
        assert time.monotonic() - t0 < 5
        dropped = cam.settings()["dropped_frames"]
    got = [f.index for f in e.value.frames]
    assert 0 < dropped < 8 and len(got) == 8 - dropped and got == sorted(got) and set(got) < set(range(8))


def test_a_closed_side_channel_is_a_disconnect_keeping_the_frames(tmp_path):
    rig = Rig(tmp_path, 0)
    with rig.camera() as cam:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=3, exposure_s=0.001, timeout_s=10))
        cam.arm()
        cam.trigger()
        rig.stop()
        t0 = time.monotonic()
        with pytest.raises(CameraDisconnected) as e:
            cam.collect()
        assert time.monotonic() - t0 < 3  # not the 10 s timeout
        assert [f.index for f in e.value.frames] == [0]
        with pytest.raises(CameraDisconnected):
            cam.trigger()


def test_spec_errors_name_the_option(tmp_path):
    with pytest.raises(InputError, match="one of micro, mid"):
        open_camera("sim:macro?hw=/x")
    with pytest.raises(InputError, match="hw=SOCKET"):
        open_camera("sim:micro")
    with pytest.raises(InputError, match="unknown option.*colour"):
        open_camera("sim:micro?hw=/x&colour=1")
    with pytest.raises(InputError, match="drop"):
        open_camera("sim:micro?hw=/x&drop=2")
    with pytest.raises(InputError, match="shadows"):
        open_camera("sim:mid?hw=/x&shadows=1")
    with pytest.raises(CameraDisconnected, match="dualscale sim --hw-socket"):
        open_camera(f"sim:micro?hw={tmp_path / 'none.sock'}&size=16")


def test_mid_and_polar_cameras_and_the_serial(rig1, tmp_path):
    """The mid camera (no analyser) and a polar camera (with one) see the diffuse group; the
    serial is stable for the same sample and differs for another seed; maps folders work."""
    from dualscale.sim.materials import generate
    from dualscale.sim.materials.io import save_material

    with rig1.client() as c:
        c.set_intensity(FULL)
        c.set_light(rm.Source.DIFFUSE, 0, True)
    save_material(tmp_path / "maps", generate("leather", 32, 0.05, 0), previews=False)
    cams = [rig1.camera("mid", size=24, field_mm=5), rig1.camera("polar1", size=24),
            rig1.camera("mid", size=24, field_mm=5, seed=1), rig1.camera("micro", maps=tmp_path / "maps")]
    try:
        mid, polar, mid1, mm = cams
        assert mid.sensor().width == 24 and mid.sensor().pixel_um == pytest.approx(5000 / 24)
        assert mid.settings()["texel_um"] == pytest.approx(5000 / 24)  # synth --mid's texel
        with rig1.camera("mid", size=24, field_mm=5) as again:
            assert again.serial == mid.serial and mid.serial.startswith("SIM-mid-")
        assert mid.serial != mid1.serial and polar.serial.startswith("SIM-polar1-")
        assert mm.sensor().width == 32 and mm.settings()["texel_um"] == pytest.approx(50.0)
        assert [c.geometry().name for c in cams] == ["mid", "polar1", "mid", "micro"]
        assert polar.geometry().has_analyzer and not mid.geometry().has_analyzer
        assert mm.geometry().field_mm == pytest.approx((1.6, 1.6))  # 32 texels of 50 um
        for cam in cams:
            cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.05))
            cam.arm()
            cam.trigger()
            (f,) = cam.collect()
            assert f.image.shape == (cam.sensor().height, cam.sensor().width, 3) and f.image.mean() > 0.01
            assert f.metadata["polarizer_cdeg"] == (None if cam.name == "mid" else 0)
    finally:
        for cam in cams:
            cam.close()


def test_spec_is_json_safe_in_metadata(rig0):
    with rig0.camera() as cam:
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.001))
        cam.arm()
        cam.trigger()
        (f,) = cam.collect()
    json.dumps(f.metadata)
    assert f.metadata["serial"] == cam.serial and f.metadata["settings"]["readout_s"] == 0.005


def test_a_frame_that_cannot_be_rendered_is_an_error_not_a_timeout(rig0):
    """The renderer refusing a state (here: stood in by a scene that raises) ends collect() at
    once with a CameraError naming the frame, not after the timeout."""
    def broken(lights, cdeg):
        raise ValueError("LED ids must be in 0..126")

    with rig0.camera() as cam:
        cam.scene.raw = broken
        cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.001, timeout_s=30))
        cam.arm()
        cam.trigger()
        t0 = time.monotonic()
        with pytest.raises(CameraError, match="rendering frame 0 failed: ValueError") as e:
            cam.collect()
    assert time.monotonic() - t0 < 5 and not isinstance(e.value, CameraTimeout) and e.value.frames == []


def test_shadows_darken_a_grazing_led(rig1):
    """shadows=1 casts the relief's shadows (as ``synth --shadows``): under a grazing LED the
    frame is darker than without them, and equal to the independent composition with shadows."""
    from dualscale.geometry.dome import DomeGeometry
    from dualscale.sim.render import Analyzer, LightRealism, LightState, render
    from dualscale.sim.targets import raw_signal, rig_exposer

    led = rm.N_LEDS - 1  # the outer ring, 72 degrees from the normal
    with rig1.client() as c:
        c.set_intensity(FULL)
        c.set_light(rm.Source.LED, led, True)
    images = []
    for shadows in (0, 1):
        with rig1.camera(noise=0, shadows=shadows, material="denim") as cam:
            cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=0.5))
            cam.arm()
            cam.trigger()
            (f,) = cam.collect()
            images.append(f.image)
            sc = cam.scene
    rad = render(sc.maps, sc.camera, LightState.led(led), DomeGeometry.from_regmap(), Analyzer(0.0, True),
                 geometry=sc.geometry, realism=LightRealism(shadows=True))
    want = rig_exposer(sc.camera, noise=False)(raw_signal(rad.double().numpy(), sc.camera, "led", led), 0.5)
    np.testing.assert_array_equal(images[1], want.astype(np.float32))
    assert images[1].mean() < 0.9 * images[0].mean()  # 0.71 here: the relief shadows a grazing light
