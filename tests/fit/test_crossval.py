"""The final maps are fitted on every light; the held-out figure comes from a cross-validation
pass over the lights on a pixel sample (dualscale.fit.holdout.cross_validate): the folds
(leave-one-light-out for a dozen lights, k-fold round-robin for the dome), every light scored
once by a fit that never saw it, the record in fit.json, resume, and the command line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.fit import api
from dualscale.fit import holdout
from dualscale.fit.holdout import (CV_PIXELS, KFOLD, LOO_MAX_LIGHTS, cross_validate, light_folds, parse_folds,
                                   pixel_preset)
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import PRESETS

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)
TWELVE = set(range(0, 127, 11))  # 12 LEDs spread over the rings, like a dozen photographs


def test_light_folds_loo_for_few_lights_round_robin_k_fold_for_many():
    assert light_folds(list(range(12))) == [[i] for i in range(12)]  # auto: leave-one-light-out
    assert len(light_folds(list(range(LOO_MAX_LIGHTS)))) == LOO_MAX_LIGHTS
    ids = list(range(0, 127, 4))[::-1] + [0, 4]  # 32 distinct, unordered, repeated (P0 and P90)
    folds = light_folds(ids)
    assert len(folds) == KFOLD == 8 and folds[0] == [0, 32, 64, 96] and folds[7] == [28, 60, 92, 124]
    assert sorted(i for f in folds for i in f) == sorted(set(ids))  # every light in exactly one fold
    dome = light_folds(range(127))
    assert len(dome) == 8 and {len(f) for f in dome} == {15, 16} and dome[3][:3] == [3, 11, 19]
    for f in dome:  # round-robin in id order: each fold spans the rings (ids run ring by ring)
        assert max(f) - min(f) >= 112
    assert light_folds(range(17), "loo") == [[i] for i in range(17)]
    assert light_folds(range(12), 4) == [[0, 4, 8], [1, 5, 9], [2, 6, 10], [3, 7, 11]]
    assert light_folds(range(3), 8) == [[0], [1], [2]]  # k lowered to the lights
    with pytest.raises(ValueError, match="at least two distinct lights"):
        light_folds([5, 5])
    for bad in ("1", 0, "two", "k=3"):
        with pytest.raises(ValueError, match="folds"):
            parse_folds(bad)
    assert parse_folds("LOO") == "loo" and parse_folds("auto") == "auto" and parse_folds("5") == 5


def test_pixel_preset_drops_only_the_coarse_level():
    p = pixel_preset(PRESETS["coarse-to-fine"])
    assert p.coarse_factor == 1 and p.iterations == PRESETS["coarse-to-fine"].iterations
    assert pixel_preset(PRESETS["standard"]) is PRESETS["standard"]


def _spy_fits(monkeypatch):
    """Record the LED ids of every fit ``cross_validate`` runs."""
    seen: list[set[int]] = []
    real = holdout.fit_observations

    def spy(obs, *a, **k):
        seen.append(set(obs.led_ids.tolist()))
        return real(obs, *a, **k)

    monkeypatch.setattr(holdout, "fit_observations", spy)
    return seen


@pytest.mark.parametrize("leds,scheme,nfolds", [(TWELVE, "leave-one-light-out", 12), (None, "8-fold", 8)])
def test_every_light_is_scored_by_a_fit_that_never_saw_it(datasets, monkeypatch, leds, scheme, nfolds):
    obs = load_observations(datasets("twill")).crop(0, 8, 0, 8)
    if leds is not None:
        obs = obs.select_leds(leds)
    all_ids = set(obs.led_ids.tolist())
    seen = _spy_fits(monkeypatch)
    rep = cross_validate(obs, PRESETS["standard"].scaled(0.3), TWILL, pixels=40, seed=1)
    assert rep.scheme == scheme and len(rep.folds) == nfolds and rep.pixels == 40
    assert rep.light_ids == sorted(all_ids) and len(rep.ours) == len(all_ids) == len(rep.directions)
    assert np.isfinite(rep.ours).all() and np.isfinite(rep.baseline).all() and (rep.ours > 0).all()
    assert len(seen) == nfolds
    for fold, trained in zip(rep.folds, seen):
        assert trained == all_ids - set(fold)  # the fold's lights were held out of its fit, no other
    assert [rep.fold[rep.light_ids.index(i)] for i in rep.folds[1]] == [1] * len(rep.folds[1])
    dirs = np.asarray(rep.directions)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0) and (dirs[:, 2] > 0).all()
    doc = rep.as_json()
    json.dumps(doc, allow_nan=False)
    assert doc["scheme"] == scheme and doc["folds"] == nfolds and doc["lights"] == len(all_ids)
    assert doc["ours_mean"] == pytest.approx(float(np.mean(rep.ours)))


def test_final_fit_uses_every_light_and_cv_is_recorded(datasets, tmp_path, monkeypatch):
    """fit_dataset: the final fit's observations are all the dataset's images (none held out);
    the cross-validation record (fit.json, extra) scores every light, with the components chosen
    once on all lights."""
    obs = load_observations(datasets("twill")).select_leds(TWELVE)
    finals: list[int] = []
    real = api.fit_observations

    def spy(o, *a, **k):
        finals.append(o.n)
        return real(o, *a, **k)

    monkeypatch.setattr(api, "fit_observations", spy)
    res, extra = api.fit_dataset("twelve", tmp_path / "maps", PRESETS["standard"].scaled(0.3), comps=TWILL,
                                 obs=obs, previews=False, cv_pixels=60)
    assert finals == [obs.n] == [24]  # 12 LEDs x P0/P90: every image, no light held out
    assert extra["lights"] == {"images": 24, "leds": 12, "fitted_images": 24, "fitted_leds": 12}
    cv = extra["cross_validation"]
    assert cv["scheme"] == "leave-one-light-out" and cv["light_ids"] == sorted(TWELVE) and cv["pixels"] == 60
    assert all(isinstance(x, float) and x > 0 for x in cv["ours"]) and math.isfinite(cv["relative_l1"])
    assert cv["relative_l1"] == pytest.approx(float(np.mean(cv["ours"])))
    assert cv["components"] == [{"lights": f, **TWILL.__dict__} for f in cv["fold_lights"]]
    assert set(res.losses) == {"train_l1", "train_rmse"}  # the final fit reports no held-out loss
    rec = json.loads((tmp_path / "maps" / "fit.json").read_text())
    assert rec["cross_validation"]["light_ids"] == cv["light_ids"] and rec["lights"]["images"] == 24
    assert not (tmp_path / "maps" / "crossval.json").exists()


def test_no_pass_and_too_few_lights(datasets, tmp_path):
    obs = load_observations(datasets("twill")).crop(0, 6, 0, 6)
    _, extra = api.fit_dataset("x", tmp_path / "a", "draft", comps=TWILL, obs=obs, previews=False, cv_pixels=0)
    assert extra["cross_validation"] is None
    one = obs.select_leds({3})
    _, extra = api.fit_dataset("x", tmp_path / "b", "draft", comps=TWILL, obs=one, previews=False)
    assert "at least two distinct lights" in extra["cross_validation"]["skipped"]
    assert "not measured" in holdout.describe(extra["cross_validation"]) and "--cv-pixels 0" in holdout.describe(None)
    with pytest.raises(ValueError, match="folds"):
        api.fit_dataset("x", tmp_path / "c", "draft", comps=TWILL, obs=obs, cv_folds=1)


def test_resumed_fit_does_not_redo_the_cross_validation(datasets, tmp_path, monkeypatch):
    from dualscale.fit.checkpoint import FitInterrupted

    obs = load_observations(datasets("twill")).crop(0, 6, 0, 6).select_leds(TWELVE)
    calls: list[int] = []
    real = api.cross_validate
    monkeypatch.setattr(api, "cross_validate", lambda *a, **k: calls.append(1) or real(*a, **k))
    kw = dict(comps=TWILL, obs=obs, previews=False, cv_pixels=20, checkpoint_every=2)
    with pytest.raises(FitInterrupted):
        api.fit_dataset("x", tmp_path / "m", "standard", stop_after=4, **kw)
    assert calls == [1] and (tmp_path / "m" / "crossval.json").is_file()
    _, first = api.fit_dataset("x", tmp_path / "m", "standard", **kw)
    assert calls == [1]  # reused from crossval.json
    _, again = api.fit_dataset("x", tmp_path / "n", "standard", **{**kw, "cv_pixels": 21})
    assert calls == [1, 1] and again["cross_validation"]["pixels"] == 21  # other parameters: computed anew
    assert first["cross_validation"]["pixels"] == 20


def test_cli_fit_cv_options_and_summary(datasets, tmp_path, capsys):
    ds = datasets("leather")
    base = ["fit", str(ds), "--preset", "draft", "--threads", "1", "--no-previews"]
    assert main(base + ["-o", str(tmp_path / "a"), "--cv-pixels", "48", "--cv-folds", "4"]) == 0
    out = capsys.readouterr().out
    assert "fitted on 128 of 254 images (64 of 127 lights); the draft preset's led_stride thins the lights" in out
    assert "held-out relative L1" in out and "(cross-validated, 4-fold over 127 lights on 48 sample pixels" in out
    rec = json.loads((tmp_path / "a" / "fit.json").read_text())["cross_validation"]
    assert rec["folds"] == 4 and len(rec["ours"]) == 127 and rec["requested_folds"] == 4
    # issue 24 trial: the per-pixel constant predictor (a prediction that ignores the light), on the same folds
    assert len(rec["constant"]) == 127 and rec["constant_relative_l1"] == pytest.approx(np.mean(rec["constant"]))
    assert rec["relative_l1"] < 0.8 * rec["constant_relative_l1"]
    assert f"per-pixel constant predictor {rec['constant_relative_l1']:.4g}" in out
    assert main(base + ["-o", str(tmp_path / "b"), "--cv-pixels", "0"]) == 0
    assert "held-out error: not measured (--cv-pixels 0" in capsys.readouterr().out
    for bad, words in ((["--cv-folds", "1"], "--cv-folds"), (["--cv-pixels", "-3"], "--cv-pixels -3")):
        assert main(base + ["-o", str(tmp_path / "c"), *bad]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "c").exists()


def test_cli_default_pixels_agree_with_the_library():
    from dualscale.cli import fit as cli_fit

    assert cli_fit.CV_PIXELS == CV_PIXELS


def test_the_chosen_loss_is_used_by_the_final_fit_and_every_fold(datasets, tmp_path, monkeypatch):
    """The selection's loss (here an override, as photographs choose it) reaches the final fit and
    the cross-validation folds alike: the held-out figure measures the fit that is delivered."""
    obs = load_observations(datasets("twill")).crop(0, 6, 0, 6).select_leds(TWELVE)
    losses: list[tuple[str, str]] = []
    for mod, name in ((api, "final"), (holdout, "fold")):
        real = mod.fit_observations
        monkeypatch.setattr(mod, "fit_observations",
                            lambda o, p, *a, _real=real, _name=name, **k: losses.append((_name, p.loss)) or
                            _real(o, p, *a, **k))
    over = {"loss": "l2", "anisotropy": False, "tint": False, "transmittance": False}
    res, extra = api.fit_dataset("x", tmp_path / "m", "standard", overrides=over, obs=obs, previews=False,
                                 cv_pixels=20)
    assert losses == [("fold", "l2")] * 12 + [("final", "l2")] and res.preset.loss == "l2"
    assert json.loads((tmp_path / "m" / "fit.json").read_text())["preset"]["loss"] == "l2"


def test_constant_prediction_is_each_pixels_mean_over_its_valid_training_samples():
    """The per-pixel constant predictor (issue 24 trial): every held-out image of a pixel is that
    pixel's mean over the training images' valid samples, clamped at 2 like the captures."""
    import torch

    from dualscale.fit.holdout import constant_prediction

    class Obs:  # the two fields constant_prediction reads, and n
        def __init__(self, images, valid):
            self.images, self.valid, self.n = images, valid, images.shape[0]

    x = torch.tensor([[[[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]]], [[[3.0, 2.0, 1.0], [9.0, 9.0, 9.0]]],
                      [[[5.0, 2.0, 2.0], [0.1, 0.1, 0.1]]]])  # (3, 1, 2, 3)
    valid = torch.tensor([[[True, True]], [[True, False]], [[False, False]]])
    pred = constant_prediction(Obs(x, valid), Obs(x[:2], None))
    assert pred.shape == (2, 2, 3)
    np.testing.assert_allclose(pred[0], [[1.5, 2.0, 1.5], [0.5, 0.5, 0.5]])  # 3 and 5 clamped to 2; invalid left out
    np.testing.assert_allclose(pred[1], pred[0])  # the same for every held-out light
    none = constant_prediction(Obs(x, torch.zeros_like(valid)), Obs(x[:1], None))
    assert (none == 0).all()
