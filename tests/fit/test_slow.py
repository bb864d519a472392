"""Long runs: the full paper preset and the whole light-subset study (``-m slow``)."""

import pytest

from dualscale.fit.core import fit_observations, split_holdout
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.presets import PRESETS
from dualscale.fit.select import select_components
from dualscale.fit.study import builtin_subsets, study_observations
from dualscale.formats.maps import load_maps

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("material", ["twill", "leather", "brick"])
def test_paper_preset_meets_acceptance_bounds(datasets, material):
    root = datasets(material, 32)
    obs = load_observations(root)
    gt, _ = load_maps(root / "maps")
    train, held = split_holdout(obs)
    comps, _ = select_components(train)
    res = fit_observations(train, PRESETS["paper"], comps, held_out=held)
    e = map_errors(res.maps, gt, comps.ior)
    assert e["normal_mean_deg"] < 3.0 and e["albedo_rmse"] < 0.02 and res.losses["heldout_ssim"] > 0.95
    std = fit_observations(train, PRESETS["standard"], comps, held_out=held)
    assert std.seconds < 0.1 * res.seconds
    assert std.losses["heldout_ssim"] >= 0.95 * res.losses["heldout_ssim"]


def test_full_light_study(datasets):
    root = datasets("twill", 16)
    gt, _ = load_maps(root / "maps")
    rep = study_observations(load_observations(root), builtin_subsets(), "standard", gt, "twill")
    ssim = {r["subset"]: r["heldout_ssim"] for r in rep["rows"]}
    assert set(ssim) == {"ALL", "MOD2", "MOD3", "ROW2+4", "ROW2+5", "MINIMAL"}
    assert ssim["ALL"] >= ssim["MINIMAL"] - 1e-3
