"""Clipped pixels and pixels outside the sample mask are masked, never fitted as valid: the LM
rows, the Adam loss, the photometric-stereo start and the held-out metrics give them no weight."""

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.cli import main
from dualscale.fit.core import fit_observations
from dualscale.fit.metrics import image_losses, map_errors, rerender_ssim
from dualscale.fit.observations import load_observations
from dualscale.fit.presets import PRESETS
from dualscale.formats.exr import read_exr, write_exr
from dualscale.formats.maps import load_maps

from .helpers import edit_manifest, led_records

CLIP_SHARE = 0.2  # the brightest 20 % of the LED samples are clipped


@pytest.fixture(scope="module")
def leather(tmp_path_factory):
    """Ground truth and a relative_radiance dataset: leather, 12 x 12 texels, every 4th LED."""
    root = tmp_path_factory.mktemp("leather")
    assert main(["synth", "leather", "-o", str(root), "--size", "12", "--texel-um", "9", "--dataset",
                 "--no-previews", "--lights", "mod4"]) == 0
    return root


def _clipped_copy(src: Path, dst: Path, level: float, record_saturation: bool) -> Path:
    """The dataset with every LED image clipped at ``level`` (as a sensor would), with or
    without ``saturation`` recorded."""
    shutil.copytree(src, dst)

    def clip(m):
        for r in led_records(m):
            write_exr(dst / r["file"], np.minimum(read_exr(dst / r["file"]), level))
            r["saturation"] = level if record_saturation else None
    edit_manifest(dst, clip)
    return dst


def _level(ds: Path) -> float:
    m = json.loads((ds / "manifest.json").read_text())
    vals = np.concatenate([read_exr(ds / r["file"]).max(-1).ravel() for r in led_records(m)])
    return float(np.quantile(vals, 1.0 - CLIP_SHARE))


def _errors(ds: Path, gt, preset=PRESETS["draft"]):
    obs = load_observations(ds)
    res = fit_observations(obs, preset, gt.components())
    return map_errors(res.maps, gt), obs


def test_clipped_pixels_are_masked_not_fitted(leather, tmp_path):
    gt, _ = load_maps(leather / "maps")
    level = _level(leather / "micro")
    masked = _clipped_copy(leather / "micro", tmp_path / "masked", level, True)
    blind = _clipped_copy(leather / "micro", tmp_path / "blind", level, False)
    truth, _ = _errors(leather / "micro", gt)
    good, obs = _errors(masked, gt)
    bad, obs_blind = _errors(blind, gt)
    assert obs_blind.valid is None
    assert obs.valid is not None and obs.valid.shape == obs.images.shape[:3]
    assert 1.0 - float(obs.valid.float().mean()) == pytest.approx(CLIP_SHARE, abs=0.01)
    # with the mask the fit is that of the unclipped truth; fitting the clipped values is not
    assert good["roughness_mae"] < truth["roughness_mae"] + 0.005 and good["roughness_mae"] < 0.01
    assert good["normal_mean_deg"] < 0.1 and good["albedo_rmse"] < 0.002
    assert bad["roughness_mae"] > 5 * good["roughness_mae"] and bad["roughness_mae"] > 0.04
    assert bad["normal_mean_deg"] > 2 * good["normal_mean_deg"]


def test_adam_loss_gives_invalid_samples_no_weight(leather, tmp_path):
    gt, _ = load_maps(leather / "maps")
    level = _level(leather / "micro")
    masked = load_observations(_clipped_copy(leather / "micro", tmp_path / "m", level, True)).crop(0, 6, 0, 6)
    blind = load_observations(_clipped_copy(leather / "micro", tmp_path / "b", level, False)).crop(0, 6, 0, 6)
    p = PRESETS["adam-fast"].scaled(0.25)
    e_m = map_errors(fit_observations(masked, p, gt.components()).maps, gt.crop(0, 6, 0, 6))
    e_b = map_errors(fit_observations(blind, p, gt.components()).maps, gt.crop(0, 6, 0, 6))
    assert e_m["roughness_mae"] < 0.5 * e_b["roughness_mae"], (e_m, e_b)


def test_outside_the_mask_is_ignored(leather, tmp_path):
    """Garbage outside the sample mask changes nothing inside it, in the fit and the metrics."""
    gt, _ = load_maps(leather / "maps")
    ds = tmp_path / "masked"
    shutil.copytree(leather / "micro", ds)
    mask = np.ones((12, 12), np.float32)
    mask[:, :4] = 0.0
    write_exr(ds / "mask.exr", mask, ("Y",))
    g = np.random.default_rng(1)

    def spoil(m):
        m["mask"] = "mask.exr"
        for r in led_records(m):
            img = read_exr(ds / r["file"])
            img[:, :4] = g.uniform(0.0, 5.0, img[:, :4].shape)  # a background the model cannot explain
            write_exr(ds / r["file"], img)
    edit_manifest(ds, spoil)
    obs = load_observations(ds)
    clean = load_observations(leather / "micro")
    assert not obs.valid[:, :, :4].any() and obs.valid[:, :, 4:].all()
    assert obs.fitted_pixels is not None and int(obs.fitted_pixels.sum()) == 12 * 8
    a = fit_observations(obs, PRESETS["draft"], gt.components())
    b = fit_observations(clean, PRESETS["draft"], gt.components())
    for name, t in a.maps.items():
        assert torch.isfinite(t).all(), name
        torch.testing.assert_close(t[:, 4:], getattr(b.maps, name)[:, 4:], atol=2e-3, rtol=0), name
    # held-out metrics skip the invalid samples: the same as the clean data over the same pixels
    losses = image_losses(b.maps, b.comps, obs)
    ref = image_losses(b.maps.crop(0, 12, 4, 12), b.comps, clean.crop(0, 12, 4, 12))
    assert losses["l1"] == pytest.approx(ref["l1"], rel=1e-5)
    blind = image_losses(b.maps, b.comps, replace(obs, valid=None))  # what skipping them avoids
    assert losses["l1"] < 0.1 * blind["l1"]
    assert rerender_ssim(b.maps, b.comps, obs) > 0.99


def test_valid_mask_follows_select_crop_pixels(leather, tmp_path):
    obs = load_observations(_clipped_copy(leather / "micro", tmp_path / "c", _level(leather / "micro"), True))
    v = obs.valid
    assert torch.equal(obs.select([3, 1]).valid, v[[3, 1]])
    assert torch.equal(obs.crop(2, 7, 1, 5).valid, v[:, 2:7, 1:5])
    flat = torch.tensor([0, 13, 50, 143])
    assert torch.equal(obs.pixels(flat).valid[:, 0], v.reshape(v.shape[0], -1)[:, flat])
    assert obs.to(torch.float64).valid.dtype == torch.bool
    with pytest.raises(ValueError, match="valid mask"):
        replace(obs, valid=v[:, :3])


def test_exposure_is_honoured(leather, tmp_path):
    """An image taken with exposure t holds t x the radiance: the fit divides it out."""
    ds = tmp_path / "exp"
    shutil.copytree(leather / "micro", ds)
    g = np.random.default_rng(2)

    def expose(m):
        for r in led_records(m):
            t = float(g.choice([0.05, 0.2, 1.0, 2.5]))
            write_exr(ds / r["file"], read_exr(ds / r["file"]) * t)
            r["exposure_s"] = t
    edit_manifest(ds, expose)
    torch.testing.assert_close(load_observations(ds).images, load_observations(leather / "micro").images,
                               rtol=1e-6, atol=1e-7)
