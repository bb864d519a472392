"""Fitting: accuracy, robustness, checkpoints, output format."""

import json
import shutil

import numpy as np
import pytest
import torch

from dualscale.fit.checkpoint import FitInterrupted
from dualscale.fit.core import fit_observations, split_holdout
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import PRESETS
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)


def _finite(res):
    for name, t in res.maps.items():
        assert torch.isfinite(t).all(), name


def test_observation_weights(datasets):
    obs = load_observations(datasets("twill"))  # the synth output dir: micro/ is found
    assert obs.n == 254 and obs.shape == (16, 16)
    assert obs.backlight is not None and float(obs.backlight.abs().max()) == 0.0  # opaque: a black back-lit image
    p0 = obs.w_s > 0.5
    assert int(p0.sum()) == 127
    assert torch.all(obs.w_s[~p0] < 1e-9) and torch.all(obs.w_p == 0) and torch.all(obs.w_d == 0.5)
    assert obs.pixel_mm == pytest.approx(0.009)
    tr, ho = split_holdout(obs, 8)
    assert set(tr.led_ids.tolist()).isdisjoint(ho.led_ids.tolist()) and tr.n + ho.n == obs.n
    assert ho.n == 2 * 16


@pytest.mark.parametrize("name", ["standard", "coarse-to-fine"])
def test_lm_presets_recover_ground_truth(datasets, name):
    root = datasets("twill")
    obs = load_observations(root)
    gt, _ = load_maps(root / "maps")
    train, held = split_holdout(obs)
    res = fit_observations(train, PRESETS[name], TWILL, held_out=held)
    _finite(res)
    e = map_errors(res.maps, gt)
    assert e["normal_mean_deg"] < 1.0 and e["albedo_rmse"] < 0.01 and e["roughness_mae"] < 0.02
    assert res.losses["heldout_ssim"] > 0.99


def test_paper_procedure_short_run_lowers_loss(datasets):
    obs = load_observations(datasets("twill")).crop(0, 8, 0, 8)
    res = fit_observations(obs, PRESETS["paper"].scaled(0.03), TWILL)
    _finite(res)
    from dualscale.fit.init import initial_params
    from dualscale.fit.metrics import image_losses
    from dualscale.fit.params import to_maps

    start = image_losses(to_maps(initial_params(obs, TWILL)), TWILL, obs)["l1"]
    assert res.losses["train_l1"] < 0.5 * start
    assert [h[1] for h in res.history][:21] == ["diffuse"] * 21


def _corrupt(obs):
    """Black, saturated and grazing-shadowed pixels."""
    imgs = obs.images.clone()
    imgs[:, 0:2, 0:2] = 0.0  # fully black
    imgs[:, 3:5, 3:5] = 1e4  # saturated far beyond the clamp
    grazing = obs.dirs[:, 2] < 0.45
    imgs[grazing, 6:10, 6:10] = 0.0  # shadows under grazing lights
    obs.images = imgs
    return obs


@pytest.mark.parametrize("preset", ["standard", "adam-fast"])
def test_no_nan_with_black_saturated_shadowed_pixels(datasets, preset):
    obs = _corrupt(load_observations(datasets("twill")).crop(0, 12, 0, 12))
    p = PRESETS[preset] if preset == "standard" else PRESETS[preset].scaled(0.2)
    res = fit_observations(obs, p, TWILL)
    _finite(res)
    assert all(np.isfinite(v) for v in res.losses.values())
    assert float(res.maps.albedo[0:2, 0:2].max()) < 0.05  # black pixels fit black


def test_dataset_missing_lights_fits(datasets, tmp_path):
    src = datasets("leather")
    dst = tmp_path / "ds"
    shutil.copytree(src / "micro", dst)
    man = json.loads((dst / "manifest.json").read_text())
    keep = [r for r in man["images"] if r["light"]["id"] is None or r["light"]["id"] % 3 != 0
            or r["analyzer_deg"] == 0.0]  # drop P90 of every third LED
    keep = [r for r in keep if r["light"]["id"] not in range(40, 70)]  # and whole LEDs
    man["images"] = keep
    (dst / "manifest.json").write_text(json.dumps(man))
    obs = load_observations(dst)
    assert obs.n < 200
    res = fit_observations(obs, PRESETS["draft"], fit_components(True, True, False))
    _finite(res)


def test_missing_and_corrupt_files_give_clear_errors(datasets, tmp_path):
    with pytest.raises(FileNotFoundError, match="dataset not found"):
        load_observations(tmp_path / "nope")
    dst = tmp_path / "ds"
    shutil.copytree(datasets("leather") / "micro", dst)
    victim = sorted((dst / "images").glob("*.exr"))[5]
    victim.write_bytes(b"not an exr at all")
    from dualscale.errors import FormatError

    with pytest.raises(FormatError, match=victim.name):  # bad input naming the file (issue 24 §2)
        load_observations(dst)
    victim.unlink()
    with pytest.raises(FileNotFoundError, match="missing"):
        load_observations(dst)
    (dst / "manifest.json").write_text("{broken")
    with pytest.raises(ValueError, match="invalid JSON"):
        load_observations(dst)


@pytest.mark.parametrize("preset,stop", [("standard", 7), ("adam-fast", 23)])
def test_interrupt_and_resume_equals_uninterrupted(datasets, tmp_path, preset, stop):
    obs = load_observations(datasets("twill")).crop(0, 10, 0, 10)
    p = PRESETS[preset] if preset == "standard" else PRESETS[preset].scaled(0.25)
    full = fit_observations(obs, p, TWILL)
    ck = tmp_path / "ck.pt"
    with pytest.raises(FitInterrupted):
        fit_observations(obs, p, TWILL, checkpoint=ck, checkpoint_every=5, stop_after=stop)
    assert ck.is_file()
    resumed = fit_observations(obs, p, TWILL, checkpoint=ck, checkpoint_every=5)
    assert resumed.resumed_from == stop
    for (name, a), (_, b) in zip(full.maps.items(), resumed.maps.items()):
        assert torch.allclose(a, b, atol=1e-6, rtol=0), name
    # a checkpoint of a different fit is refused
    with pytest.raises(ValueError, match="different fit"):
        fit_observations(obs, p.scaled(2.0), TWILL, checkpoint=ck)
