"""White level (issue 13, section 5): a sensor that clips below nominal full scale must not have
its clipped samples merged as valid.  The white level is declared per camera in the captures or
measured from the brackets, carried by the calibration, and used per channel by the HDR merge
and by the dataset clipping mask of ``calib.apply``."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from dualscale.calib.hdr import (WHITE_MARGIN, WhiteLevel, measure_white_level, merge_debevec, meter,
                                 plan_brackets)
from dualscale.errors import CalibrationError
from dualscale.geometry.cameras import micro_camera
from dualscale.sim.sensor import SensorModel, capture


def _scene(n=64, seed=0, colour=(1.0, 0.8, 0.6)):
    """The merge tests' scene: three decades of radiance [DN/s], one warm colour."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.uniform(np.log(0.01), np.log(10.0), (n, n, 1))) * np.array(colour)


def highlight_errors(merged, truth, q=0.95):
    """``(mean |relative error|, colour cast)`` over the brightest ``1 - q`` of the pixels; the
    cast is the largest mean relative error of a channel ratio (R/G, B/G, R/B)."""
    lum = truth.mean(-1)
    hi = lum >= np.quantile(lum, q)
    m, t = merged[hi], truth[hi]
    err = float(np.abs(m / t - 1).mean())
    cast = max(float(np.abs((m[:, a] / m[:, b]) / (t[:, a] / t[:, b]) - 1).mean()) for a, b in ((0, 1), (2, 1), (0, 2)))
    return err, cast


def test_sensor_clipping_at_095_is_merged_right_with_its_white_level():
    """The issue's case restated: brackets planned as the rig plans them, a sensor that clips
    at 0.95.  Before: highlights 35.0 % off and a 20.0 % colour cast (R/B) with the fixed
    0.98 threshold (the issue measured 36 % / 22 %).  After: exact, as at full scale."""
    e = _scene()
    times = plan_brackets(e * 0.05, 0.05)
    imgs = [np.clip(e * t, 0.0, 0.95) for t in times]
    old = merge_debevec(imgs, times).radiance  # the code path without a white level
    err, cast = highlight_errors(old, e)
    assert err > 0.30 and cast > 0.15, (err, cast)

    measured = measure_white_level([(imgs, times, None)])
    assert measured.source == "measured"
    assert np.allclose(measured.level, 0.95, atol=1e-9)
    for wl in (measured, WhiteLevel.uniform(0.95)):
        res = merge_debevec(imgs, times, white_level=wl)
        assert res.valid.all() and not res.saturated.any()
        assert np.allclose(res.radiance, e, rtol=1e-9)  # as test_linear_merge_recovers_radiance_and_flags


def _shoot(e, sensor, cam, t, seed):
    """A capture of radiance ``e`` [DN/s at full well] by the simulated sensor at ``t`` s."""
    x = torch.from_numpy(e * sensor.full_well_e / sensor.gain_e)
    return capture(x, cam, replace(sensor, exposure_s=t), seed=seed).numpy()


def _noisy_brackets(level, spread=0.0, n=64):
    """Metered, planned brackets of the scene on a noisy 12-bit sensor clipping at ``level``."""
    e = _scene(n)
    cam = micro_camera(n)
    s = SensorModel(shot_noise=True, read_noise=True, saturate=True, quantize=True, white_level=level,
                    white_level_spread=spread)
    sat = level * (1 - WHITE_MARGIN)
    m, t0 = meter(lambda t: _shoot(e, s, cam, t, 1), saturation=sat)
    times = plan_brackets(m, t0, high=0.8 * level, saturation=sat)
    return e, times, [_shoot(e, s, cam, t, 10 + k) for k, t in enumerate(times)]


@pytest.mark.parametrize("spread", [0.0, 0.005])
@pytest.mark.parametrize("level", [0.80, 0.90, 0.95, 1.0])
def test_measured_white_level_and_merge_on_noisy_sensors(level, spread):
    """Measured within 0.002 DN (shot and read noise, 12 bits, with and without a 0.5 % spread
    of the wells); the merge with it is within the merge's normal error (the same scene on a
    sensor clipping at full scale: 0.77 % in the highlights, 1.2 % cast) while the fixed 0.98
    threshold is 17-49 % off (cast 9-14 %) below full scale."""
    e, times, imgs = _noisy_brackets(level, spread)
    wl = measure_white_level([(imgs, times, None)])
    assert wl.source == "measured" and min(wl.n_clipped) >= 50
    assert np.abs(np.asarray(wl.level) - level).max() <= 0.002, wl
    e1, times1, imgs1 = _noisy_brackets(1.0)
    normal = highlight_errors(merge_debevec(imgs1, times1).radiance, e1)
    new = highlight_errors(merge_debevec(imgs, times, white_level=wl).radiance, e)
    assert new[0] <= normal[0] + 0.003 and new[1] <= normal[1] + 0.005, (new, normal)
    if level < 1.0:
        old = highlight_errors(merge_debevec(imgs, times).radiance, e)
        assert old[0] > 0.1 and old[1] > 0.05, old


def test_clipped_channel_is_excluded_alone():
    """Red clips in the long bracket, green and blue are only above noise there: red comes from
    the short bracket, green and blue from the long one (excluding the whole pixel would lose
    them), and a channel's own white level counts for that channel only."""
    e = np.ones((4, 4, 1)) * np.array([20.0, 0.05, 0.02])
    times = [0.03, 1.0]
    imgs = [np.clip(e * t, 0.0, 0.9) for t in times]  # short: 0.6, 0.0015, 0.0006; long: 0.9 (clipped), 0.05, 0.02
    res = merge_debevec(imgs, times, white_level=WhiteLevel.uniform(0.9))
    assert res.valid.all() and not res.saturated.any() and not res.underexposed.any()
    assert np.allclose(res.radiance, e, rtol=1e-9)
    old = merge_debevec(imgs, times).radiance
    assert abs(old[0, 0, 0] / 20.0 - 1) > 0.1  # the clipped red merged as valid
    # per-channel levels: green near 0.95 is valid on a camera whose red alone clips at 0.9
    e2 = np.ones((4, 4, 1)) * np.array([2.0, 0.93, 0.5])
    imgs2 = [np.clip(e2 * t, 0.0, [0.9, 1.0, 1.0]) for t in (0.1, 1.0)]
    res2 = merge_debevec(imgs2, [0.1, 1.0], white_level=WhiteLevel((0.9, 1.0, 1.0)), domain="linear")
    assert np.allclose(res2.radiance, e2, rtol=1e-9)


def test_white_level_record_is_checked():
    with pytest.raises(ValueError, match="white level"):
        WhiteLevel((1.2, 1.0, 1.0))
    wl = WhiteLevel((0.95, 0.95, 0.95), "measured", spread=(0.001,) * 3, n_clipped=(100,) * 3)
    j = wl.to_json()
    assert j["clip"] == pytest.approx([0.946] * 3) and j["threshold"] == pytest.approx([0.931] * 3)
    assert WhiteLevel.from_record(j) == wl
    # nothing clipped anywhere: nominal full scale, said so
    e = _scene() * 1e-3
    nominal = measure_white_level([([e * 1.0, e * 4.0], [1.0, 4.0], None)])
    assert nominal.source == "nominal" and nominal.level == (1.0, 1.0, 1.0)


# ---- captures, calibration, apply -----------------------------------------------------------

def _session(root, level=0.95, declare=False, parts=("white_sheet",)):
    from dualscale.sim.targets import Defects, SynthConfig, write_session

    cfg = SynthConfig(led_step=64, cameras=("micro", "mid"), white_level=level, declare_white_level=declare)
    truth = write_session(root, cfg, Defects(), parts=parts)
    return root, truth


def test_declared_and_measured_white_level_agree(tmp_path):
    from dualscale.calib.pipeline import Session
    from dualscale.formats.captures import read_captures

    declared = read_captures(_session(tmp_path / "d", declare=True)[0])
    measured = read_captures(_session(tmp_path / "m", declare=False)[0])
    for cam in ("micro", "mid"):
        assert declared.white_level(cam) == [0.95] * 3
        assert measured.white_level(cam) is None
        d, m = Session(declared).white_level(cam), Session(measured).white_level(cam)
        assert d.source == "declared" and m.source == "measured"
        assert np.abs(np.asarray(m.level) - np.asarray(d.level)).max() <= 0.002, (cam, m)


def test_old_capture_file_without_white_level_loads_and_is_measured(tmp_path):
    from dualscale.calib.pipeline import Session
    from dualscale.formats.captures import read_captures

    root = _session(tmp_path / "c", declare=True)[0]
    path = root / "captures.json"
    m = json.loads(path.read_text())
    assert m["version"] == 2
    m["version"] = 1
    for rec in m["cameras"].values():
        del rec["white_level"]
    path.write_text(json.dumps(m))
    cs = read_captures(root)
    assert cs.white_level("micro") is None and cs.camera("micro").width > 0
    wl = Session(cs).white_level("micro")
    assert wl.source == "measured" and np.abs(np.asarray(wl.level) - 0.95).max() <= 0.002
    m["version"] = 3
    path.write_text(json.dumps(m))
    with pytest.raises(CalibrationError, match="version 3"):
        read_captures(root)
    m["version"] = 2
    m["cameras"]["micro"]["white_level"] = [0.9, 1.3, 0.9]
    path.write_text(json.dumps(m))
    with pytest.raises(CalibrationError, match="cameras.micro.white_level"):
        read_captures(root)


@pytest.mark.slow
def test_calibration_of_a_clipping_sensor_carries_its_white_level(tmp_path):
    """End to end on a session whose sensors clip at 0.95, undeclared: the calibration measures
    and records the level, and the white-sheet irradiance ``r_c`` stays within 1 % of the truth
    in every channel up to one scale per camera (the fixed 0.98 threshold tints it by 4 %)."""
    from dualscale.calib.pipeline import calibrate
    from dualscale.formats.calibration import read_calibration, white_level, write_calibration
    from dualscale.formats.captures import read_captures

    root, truth = _session(tmp_path / "c", parts=("white_sheet", "chart"))
    path = write_calibration(tmp_path / "rig.calib.json", calibrate(read_captures(root)))
    data = read_calibration(path)
    for cam in ("micro", "mid"):
        rec = white_level(data, cam, path)
        assert rec["source"] == "measured" and np.abs(np.asarray(rec["level"]) - 0.95).max() <= 0.002
        assert all(t <= c <= v for t, c, v in zip(rec["threshold"], rec["clip"], rec["level"]))
    worst = 0.0
    for cam, per_light in data["r_c"].items():
        keys = [k for k in per_light if not (cam == "mid" and k == "diffuse")]  # that one uses markers
        ratio = np.array([per_light[k] for k in keys]) / np.array([truth.white_sheet[(cam, k)] for k in keys])
        worst = max(worst, float(np.abs(ratio / ratio.mean() - 1).max()))  # one scale per camera: colour counts
    assert worst < 0.01, worst  # 0.25 % measured; 4.0 % with the fixed 0.98 threshold


def test_dataset_clipping_mask_uses_the_calibrations_white_level(tmp_path):
    """A raw dataset from a sensor clipping at 0.95 (plateau with read noise), recorded with
    the nominal ``saturation`` 1.0: with the calibration's white level its clipped pixels are
    carried as clipped; without one (a file from before) none would be."""
    from dualscale.calib.apply import to_radiance
    from dualscale.formats.calibration import write_calibration
    from dualscale.formats.dataset import DatasetWriter, read_dataset
    from dualscale.geometry.dome import DomeGeometry

    n = 16
    cam = micro_camera(n)
    dome = DomeGeometry.from_regmap()
    rng = np.random.default_rng(0)
    e = np.exp(rng.uniform(np.log(0.05), np.log(3.0), (n, n, 1))) * np.array([1.0, 0.7, 0.5])
    raw = np.minimum(e, 0.95) + np.where(e >= 0.95, 2.5e-4 * rng.standard_normal(e.shape), 0.0)
    rig = {"id": "rig-A", "layout": "127leds"}
    with DatasetWriter(tmp_path / "raw", units="dn_normalized", colour_space="camera_raw:Nikon 5100 (NPL)",
                       dome={"source": dome.source, "polarizer": dome.polarizer, "radius_mm": dome.radius_mm},
                       rig=rig) as w:
        w.add(raw, cam, "led", 0, [float(x) for x in dome.led_dirs[0]], 1.0, exposure_s=1.0, saturation=1.0)
    wl = WhiteLevel((0.95,) * 3, "measured", spread=(2.5e-4,) * 3, n_clipped=(500,) * 3)
    base = {"rig": rig, "r_ws": [0.5] * 3, "r_c": {"micro": {"led000": [1.0] * 3}},
            "ccm": {"micro": {"led": {"matrix": np.eye(3).tolist()}}},
            "dark": {"micro": {"bias": [0.0] * 3, "rate": [0.0] * 3}}}
    expected = (raw >= np.asarray(wl.clip)).any(-1)
    assert expected.sum() >= 20 and expected.sum() >= (e >= 0.95).any(-1).sum()
    for name, calib, want in (("with", {**base, "white_level": {"micro": wl.to_json()}}, expected),
                              ("without", base, np.zeros((n, n), bool))):
        cal = write_calibration(tmp_path / f"{name}.calib.json", calib)
        s = to_radiance(tmp_path / "raw", tmp_path / name, cal)
        out = read_dataset(tmp_path / name)
        clipped = out.clipped(0, out.load(0))
        got = np.zeros((n, n), bool) if clipped is None else clipped
        assert np.array_equal(got, want), name
        assert s["clipped_share"] == pytest.approx(want.mean())
    bad = write_calibration(tmp_path / "bad.calib.json", {**base, "white_level": {"micro": {"level": [0.95] * 3}}})
    with pytest.raises(CalibrationError, match="white_level.micro"):
        to_radiance(tmp_path / "raw", tmp_path / "bad", bad)
