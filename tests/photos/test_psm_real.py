"""Real photographs (../shared/data/psm-12lights, skipped when absent): chrome-sphere lights,
import, and the leave-one-light-out comparison with the Lambertian baseline."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualscale.cli import main
from dualscale.fit.holdout import leave_one_light_out, sample_pixels
from dualscale.fit.observations import load_observations
from dualscale.fit.presets import get_preset
from dualscale.fit.select import select_components
from dualscale.formats.lightfile import read_lights
from photoset import PSM, ROOT, skip_without_psm


@pytest.fixture(scope="module")
def lights(tmp_path_factory):
    skip_without_psm()
    out = tmp_path_factory.mktemp("psm") / "lights"
    assert main(["lights", "sphere", str(PSM / "chrome"), "-o", str(out)]) == 0
    return out.with_name("lights.lp")


def test_chrome_lights_are_all_on_one_side_above_the_horizon(lights):
    recs = read_lights(lights)
    d = np.array([r.direction for r in recs])
    assert len(recs) == 12 and (d[:, 2] > 0.7).all() and (d[:, 1] > 0).all()
    assert [r.file for r in recs] == [f"chrome.{k}.png" for k in range(12)]


def test_import_and_fast_fit_beat_the_baseline(lights, tmp_path):
    torch.set_num_threads(1)
    wins, results = 0, {}
    for name in ("cat", "owl"):
        ds = tmp_path / name
        assert main(["import", str(PSM / name), "--lights", str(lights), "-o", str(ds), "--transfer", "srgb"]) == 0
        obs = load_observations(ds, camera="photo")
        assert obs.valid is not None and int(obs.fitted_pixels.sum()) > 20000  # the mask
        sub = obs.pixels(sample_pixels(obs, 300, seed=1))
        comps, _ = select_components(sub)  # once, on every light (the bench chooses per fold)
        rep = leave_one_light_out(sub, get_preset("standard").scaled(0.5), comps, pixels=None)
        assert np.isfinite(rep.ours).all() and np.isfinite(rep.baseline).all()
        s = rep.summary()
        results[name] = (s["ours_mean"], s["baseline_mean"])
        wins += s["ours_mean"] < s["baseline_mean"]
    assert wins >= 1, results


@pytest.mark.slow
def test_bench_beats_the_baseline_on_every_object(tmp_path):
    skip_without_psm()
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_photos", ROOT / "bench" / "bench_photos.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--pixels", "1500", "--no-ablation", "--decodings", "srgb,auto", "--out", str(tmp_path)]) == 0
    import json

    objs = json.loads((tmp_path / "results.json").read_text())["objects"]
    assert [o["object"] for o in objs] == ["cat", "buddha", "owl"]
    for o in objs:
        for key, rec in o["rows"].items():  # ours beats the baseline under the same decoding
            s = rec["loo"]
            assert np.isfinite(s["ours"]).all() and np.isfinite(s["baseline"]).all()
            assert s["ours_codes_mean"] < s["baseline_codes_mean"], (o["object"], key)
        # the estimated decoding predicts held-out photographs better than sRGB (code values)
        assert o["rows"]["auto"]["loo"]["ours_codes_mean"] < o["rows"]["srgb"]["loo"]["ours_codes_mean"], o["object"]
        assert np.isfinite(o["full_fit"]["normal_angle_mean_deg"])
        assert (tmp_path / o["object"] / "normals_ours.png").is_file()
