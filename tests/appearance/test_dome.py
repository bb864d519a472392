"""Virtual dome: geometry, cameras, polarised rendering, realism and the dataset format."""

import json
import math

import numpy as np
import pytest
import torch

from dualscale.bsdf import MaterialMaps, evaluate
from dualscale.geometry.cameras import micro_camera, mid_camera, polar_camera, rig_cameras
from dualscale.formats.dataset import DatasetWriter, read_dataset
from dualscale.geometry.dome import DomeGeometry, led_directions, polarizer_axis
from dualscale.sim.render import Analyzer, LightRealism, LightState, render
from dualscale.sim.sensor import SensorModel, capture, spectral_matrix
from dualscale.protocol import regmap

D64 = torch.float64


def flat_maps(size=8, albedo=(0.4, 0.3, 0.2), rough=0.3, **kw):
    return MaterialMaps(albedo=torch.tensor(albedo, dtype=D64).expand(size, size, 3).clone(),
                        roughness=torch.full((size, size, 1), rough, dtype=D64), **kw)


# --- geometry ------------------------------------------------------------------------------

def test_led_layout_from_regmap():
    d = led_directions(D64)
    assert d.shape == (regmap.N_LEDS, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(regmap.N_LEDS, dtype=D64))
    th = torch.rad2deg(torch.acos(d[:, 2]))
    start = 0
    for count, theta in zip(regmap.DOME_COUNTS, regmap.DOME_THETA_DEG):
        torch.testing.assert_close(th[start:start + count], torch.full((count,), float(theta), dtype=D64))
        start += count
    dome = DomeGeometry.from_regmap()
    assert dome.diffuse_weights().sum().item() == pytest.approx(2 * math.pi)


def test_polarizer_is_s():
    d = led_directions(D64)[1:]
    s = polarizer_axis(d, "s")
    torch.testing.assert_close((s * d).sum(-1), torch.zeros(len(d), dtype=D64), atol=1e-12, rtol=0)
    assert (s[:, 2] == 0).all()
    torch.testing.assert_close(s.norm(dim=-1), torch.ones(len(d), dtype=D64))
    with pytest.raises(ValueError):
        polarizer_axis(d, "x")


def test_calibration_round_trip_and_errors(tmp_path):
    dome = DomeGeometry.from_regmap()
    dirs = dome.led_dirs.clone()
    dirs[5] = torch.nn.functional.normalize(dirs[5] + 0.01, dim=0)
    p = tmp_path / "cal.json"
    DomeGeometry(dirs).to_calibration(p)
    back = DomeGeometry.from_calibration(p)
    torch.testing.assert_close(back.led_dirs, dirs)
    with pytest.raises(FileNotFoundError):
        DomeGeometry.from_calibration(tmp_path / "missing.json")
    data = json.loads(p.read_text())
    data["leds"] = data["leds"][:-1]
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="expected LED ids"):
        DomeGeometry.from_calibration(p)
    p.write_text("{not json")
    with pytest.raises(ValueError):
        DomeGeometry.from_calibration(p)


# --- cameras -------------------------------------------------------------------------------

def test_cameras():
    cams = rig_cameras(micro_size=16, other_size=16)
    assert tuple(cams) == regmap.CAMERA_NAMES
    pts, v = cams["micro"].pixel_geometry()
    assert v.shape == (3,) and pts.shape == (16, 16, 2)
    assert pts[0, 0, 0] < 0 < pts[0, 0, 1]  # row 0 is the top (+y), column 0 the left (-x)
    mid = mid_camera(32)
    pts, v = mid.pixel_geometry()
    assert pts.abs().max().item() == pytest.approx(50 - 100 / 64, rel=1e-9)  # 10 cm field
    assert v.shape == (32, 32, 3) and (v[..., 2] > 0.9).all()
    pol = polar_camera(0, 32, theta_deg=60)
    pts, v = pol.pixel_geometry()
    c = pts[15:17, 15:17].mean((0, 1))
    assert c.norm().item() < 2.0  # looks at the centre
    assert torch.allclose(v[16, 16, 2], torch.tensor(0.5, dtype=D64), atol=0.02)
    right, up, fwd = pol.basis()
    assert abs(float(right @ up)) < 1e-12 and abs(float(right @ fwd)) < 1e-12


# --- polarised rendering -------------------------------------------------------------------

@pytest.mark.parametrize("led", [0, 3, 40, 100])
def test_polarised_specular_and_depolarised_diffuse(led):
    cam = micro_camera(8)
    maps = flat_maps()
    light = LightState.led(led)
    nopol = render(maps, cam, light)
    p0 = render(maps, cam, light, analyzer=Analyzer(0.0, relative=True))
    p90 = render(maps, cam, light, analyzer=Analyzer(90.0, relative=True))
    # diffuse only, no analyser, and specular only with S-polarised Fresnel
    dome = DomeGeometry.from_regmap()
    l = dome.led_dirs[led:led + 1]
    v = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    spec = evaluate(maps, l, v, w_s=1.0, w_p=0.0, diffuse_weight=0.0)[0]
    diff = evaluate(maps, l, v, w_s=0.0, w_p=0.0, diffuse_weight=1.0)[0]
    torch.testing.assert_close(nopol, diff + spec)
    torch.testing.assert_close(p90, 0.5 * diff)  # crossed: specular blocked, half the diffuse
    torch.testing.assert_close(p0, 0.5 * diff + spec)  # aligned: all the specular passes
    assert (spec > 0).all()


def test_absolute_analyzer_follows_malus():
    cam = micro_camera(4)
    maps = flat_maps(4, albedo=(0.0, 0.0, 0.0))  # specular only
    dome = DomeGeometry.from_regmap()
    led = 10
    phi = float(dome.led_theta_phi_deg()[led, 1])
    ref = render(maps, cam, LightState.led(led), analyzer=Analyzer(0.0, relative=True))
    for delta in (0.0, 30.0, 60.0, 90.0):
        img = render(maps, cam, LightState.led(led), analyzer=phi + 90.0 + delta)
        torch.testing.assert_close(img, ref * math.cos(math.radians(delta)) ** 2, atol=1e-12, rtol=1e-9)


def test_unpolarised_sources_and_backlight():
    cam = micro_camera(4)
    t = torch.full((4, 4, 3), 0.3, dtype=D64)
    op = torch.full((4, 4, 1), 0.8, dtype=D64)
    maps = flat_maps(4, transmittance=t, opacity=op)
    img = render(maps, cam, LightState.backlight(0, 2.0))
    torch.testing.assert_close(img, 2.0 * (t * op + (1 - op)))
    half = render(maps, cam, LightState.backlight(0, 2.0), analyzer=45.0)
    torch.testing.assert_close(half, 0.5 * img)
    # uniform dome on a white Lambert-like surface: close to its directional albedo
    white = flat_maps(4, albedo=(1.0, 1.0, 1.0), rough=1.0)  # rough: no delta-like peak to undersample
    dif = render(white, cam, LightState.diffuse_group(1.0), comps=None)
    assert 0.8 < dif.mean().item() < 1.3
    with pytest.raises(ValueError):
        render(maps, cam, LightState.backlight(regmap.N_BACKLIGHTS))
    with pytest.raises(ValueError):
        render(maps, mid_camera(8), LightState.led(0), analyzer=0.0)


def test_mid_camera_resampling_and_falloff():
    maps = flat_maps(8)
    cam = mid_camera(16)
    far = render(maps, cam, LightState.led(0), texel_mm=1.0)
    near = render(maps, cam, LightState.led(0), texel_mm=1.0, realism=LightRealism(near_field=True, beam_exponent=4))
    assert near[8, 8].mean() > near[0, 0].mean()  # inverse square + beam: the centre is brighter
    assert (near[0, 0] < far[0, 0]).all()
    with pytest.raises(ValueError, match="texel_mm"):
        render(maps, cam, LightState.led(0))


def test_led_gain_is_seeded():
    r1, r2 = LightRealism(led_gain_sigma=0.05, seed=3), LightRealism(led_gain_sigma=0.05, seed=4)
    g1 = r1.led_gains(127)
    torch.testing.assert_close(g1, r1.led_gains(127))
    assert not torch.equal(g1, r2.led_gains(127))
    assert 0.02 < float(g1.std()) < 0.08


# --- sensor --------------------------------------------------------------------------------

def test_sensor_effects():
    cam = micro_camera(32)
    rad = torch.full((32, 32, 3), 0.05, dtype=D64)
    s = SensorModel()
    clean = capture(rad, cam, s)
    torch.testing.assert_close(clean, rad * s.exposure_s * s.gain_e / s.full_well_e)
    noisy = capture(rad, cam, SensorModel(shot_noise=True), seed=1)
    e_mean = 0.05 * s.exposure_s * s.gain_e
    var_e = float((noisy * s.full_well_e).var())
    assert var_e == pytest.approx(e_mean, rel=0.15)  # Poisson: variance = mean
    torch.testing.assert_close(noisy, capture(rad, cam, SensorModel(shot_noise=True), seed=1))
    sat = capture(rad * 1000, cam, SensorModel(saturate=True))
    assert float(sat.max()) == 1.0
    q = capture(rad, cam, SensorModel(quantize=True, bits=8))
    assert torch.allclose(q * 255, torch.round(q * 255))
    vig = capture(rad, cam, SensorModel(vignetting=0.5))
    assert vig[0, 0, 0] < vig[16, 16, 0]
    white = capture(torch.ones(32, 32, 3, dtype=D64) * 0.05, cam, SensorModel(spectral_camera="Nikon 5100 (NPL)"))
    m = spectral_matrix("Nikon 5100 (NPL)")
    torch.testing.assert_close(white[0, 0], clean[0, 0] * torch.from_numpy(m.sum(1)))
    with pytest.raises(ValueError):
        capture(rad[:5], cam, s)
    with pytest.raises(ValueError):
        capture(rad * float("nan"), cam, s)


# --- dataset -------------------------------------------------------------------------------

def test_dataset_round_trip_and_errors(tmp_path):
    cam = micro_camera(6)
    dome = DomeGeometry.from_regmap()
    g = np.random.default_rng(0)
    imgs = []
    with DatasetWriter(tmp_path / "ds", dome={"source": dome.source}) as w:
        for led in (0, 7):
            img = g.random((6, 6, 3)).astype(np.float32)
            imgs.append(img)
            w.add(img, cam, "led", led, [float(x) for x in dome.led_dirs[led]], analyzer_deg=0.0,
                  analyzer_relative=True, exposure_s=0.01)
        with pytest.raises(ValueError):
            w.add(np.zeros((5, 6, 3)), cam, "led", 1)
        with pytest.raises(ValueError):
            w.add(np.full((6, 6, 3), np.nan), cam, "led", 2)
    ds = read_dataset(tmp_path / "ds")
    assert len(ds.records) == 2 and ds.records[1].light_id == 7
    assert ds.manifest["units"] == "relative_radiance" and ds.manifest["colour_space"] == "linear_rec709"
    np.testing.assert_array_equal(ds.load(1), imgs[1])
    assert ds.select(light_id=7) == [1]
    (tmp_path / "ds" / ds.records[0].file).unlink()
    with pytest.raises(FileNotFoundError):
        read_dataset(tmp_path / "ds")
    with pytest.raises(FileNotFoundError):
        read_dataset(tmp_path / "nothing")
