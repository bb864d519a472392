"""The fit on imported photographs: the Lambertian baseline, leave-one-light-out, the specular
choice for unpolarised captures, fitting only the sample, and the LED stride on few lights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualscale.calib.photo_import import import_photos
from dualscale.fit.observations import stride_leds
from dualscale.fit.holdout import fit_sample, leave_one_light_out, relative_l1, sample_pixels
from dualscale.fit.lambertian import fit_lambertian, render_lambertian
from dualscale.fit.observations import load_observations
from dualscale.fit.presets import get_preset
from dualscale.fit.select import diffuse_only, has_specular, select_components
from photoset import angle_deg, lights_one_side, render_sphere


def imported(tmp_path, roughness=None, n=12, size=32):
    s = render_sphere(tmp_path / "ball", lights_one_side(n, seed=1), size=size, roughness=roughness, gain=2.0)
    import_photos(s.folder, s.lp, tmp_path / "ds", "srgb")
    return s, load_observations(tmp_path / "ds", camera="photo")


def test_lambertian_baseline_is_exact_on_lambertian_data():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(500, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dirs = lights_one_side(12)
    albedo = rng.uniform(0.1, 0.9, (500, 3))
    imgs = np.clip(dirs @ n.T, 0, None)[..., None] * albedo
    lit = (dirs @ n.T > 0).all(0)  # no attached shadow: the linear least squares is exact there
    m = fit_lambertian(imgs, dirs)
    assert angle_deg(m.normal[lit], n[lit]).max() < 1e-4
    assert np.allclose(m.albedo[lit], albedo[lit], atol=1e-9)
    assert np.allclose(render_lambertian(m, dirs)[:, lit], imgs[:, lit], atol=1e-9)
    valid = np.ones((12, 500), bool)
    valid[:10] = False  # 2 valid lights: unsolved, n = +z, finite
    m2 = fit_lambertian(imgs, dirs, valid)
    assert not m2.solved.any() and np.isfinite(m2.albedo).all() and np.allclose(m2.normal, [0, 0, 1])


def test_relative_l1():
    cap = np.ones((2, 2, 3))
    pred = cap * 1.5
    assert relative_l1(pred, cap, None) == pytest.approx(0.5)
    v = np.array([[True, False], [False, False]])
    pred[1] = 9.0
    assert relative_l1(pred, cap, v) == pytest.approx(0.5)
    assert np.isnan(relative_l1(pred, cap, np.zeros((2, 2), bool)))


def test_leave_one_light_out_beats_the_baseline_on_a_diffuse_sphere(tmp_path):
    s, obs = imported(tmp_path)
    rep = leave_one_light_out(obs, get_preset("standard").scaled(0.5), diffuse_only(), pixels=150)
    assert rep.light_ids == list(range(12)) and rep.pixels == 150
    assert np.isfinite(rep.ours).all() and np.isfinite(rep.baseline).all()
    # attached shadows bias the linear least squares; the fit's max(0, n.l) does not mind them
    assert rep.summary()["ours_mean"] < 0.7 * rep.summary()["baseline_mean"]
    assert rep.summary()["ours_mean"] < 0.03


@pytest.mark.parametrize("roughness,chosen", [(None, False), (0.3, True)], ids=["matte", "glossy"])
def test_specular_lobe_is_chosen_by_held_out_lights_on_unpolarised_captures(tmp_path, roughness, chosen):
    _, obs = imported(tmp_path, roughness)
    assert not obs.has_polarisation
    comps, rep = select_components(obs)
    ev = rep["specular"]["evidence"]
    assert rep["specular"]["chosen"] is chosen and has_specular(comps) is chosen
    assert ev["folds"] == 4 and (ev["relative_gain"] > 0.1 if chosen else ev["relative_gain"] < 0.02)
    if not chosen:
        assert comps == diffuse_only() and rep["anisotropy"]["reason"] == "no specular lobe"
    forced, rep2 = select_components(obs, {"specular": True, "anisotropy": False, "tint": False})
    assert has_specular(forced) and rep2["specular"]["overridden"]


def test_fit_sample_fits_only_the_mask_and_matches_the_whole_image_fit(tmp_path):
    from dualscale.fit.core import fit_observations

    s, obs = imported(tmp_path, size=20)
    p = get_preset("standard").scaled(0.3)
    maps = fit_sample(obs, p, diffuse_only())
    whole = fit_observations(obs, p, diffuse_only()).maps
    m = torch.from_numpy(s.mask)
    assert torch.equal(obs.fitted_pixels, m)
    assert torch.allclose(maps.normal[m], whole.normal[m], atol=1e-4)
    assert torch.allclose(maps.albedo[m], whole.albedo[m], atol=1e-4)
    assert torch.equal(maps.normal[~m], torch.tensor([0.0, 0.0, 1.0]).expand(int((~m).sum()), 3))
    assert angle_deg(maps.normal[m].double().numpy(), s.normal[s.mask]).mean() < 3.0
    assert sample_pixels(obs, 10).numel() == 10


def test_led_stride_keeps_every_light_of_a_small_set(tmp_path):
    _, obs = imported(tmp_path, size=8)
    assert stride_leds(obs, 2).n == 12
    many = obs.select([k % 12 for k in range(127)])
    many.led_ids = torch.arange(127)
    assert stride_leds(many, 2).n == 64 and stride_leds(many, 8).n == 43  # stride 3: >= 32 left


def test_fit_warns_when_the_albedo_would_leave_its_box(tmp_path):
    from dualscale.fit.init import initial_params

    s = render_sphere(tmp_path / "ball", lights_one_side(12, seed=1), size=16, gain=2.5)  # albedo x 2.5 > 1
    import_photos(s.folder, s.lp, tmp_path / "raw", "srgb", scale=1.0)
    with pytest.warns(RuntimeWarning, match="albedo >= 1"):
        initial_params(load_observations(tmp_path / "raw"), diffuse_only())
    import_photos(s.folder, s.lp, tmp_path / "scaled", "srgb")  # the importer's light scale
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = initial_params(load_observations(tmp_path / "scaled"), diffuse_only())
    assert float(p["albedo"][torch.from_numpy(s.mask)].max()) < 0.95


def test_unpolarised_lights_weigh_both_fresnel_terms(tmp_path):
    _, obs = imported(tmp_path, size=8)
    assert torch.equal(obs.w_s, torch.full((12,), 0.5)) and torch.equal(obs.w_p, obs.w_s)
    assert torch.equal(obs.w_d, torch.ones(12))
