"""LM through the compiled BSDF kernels (``Preset.compiled``, ``standard-compiled``)."""

from dataclasses import replace

import pytest
import torch

from dualscale.fit.core import fit_observations
from dualscale.fit.metrics import map_errors
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import PRESETS, Preset
from dualscale.formats.maps import load_maps

TWILL = fit_components(opaque=True, isotropic=False, tinted=True)


def test_compiled_fit_matches_eager(datasets):
    """Same fit, other kernels: the maps agree to float32 round-off amplified by LM's per-pixel
    accept test, and so do their errors against ground truth."""
    root = datasets("twill")
    obs = load_observations(root).crop(0, 8, 0, 8)
    gt = load_maps(root / "maps")[0].crop(0, 8, 0, 8)
    p = PRESETS["standard"].scaled(0.4)
    eager = fit_observations(obs, replace(p, kernel="eager"), TWILL)
    comp = fit_observations(obs, replace(p, kernel="compiled"), TWILL)
    for name, t in comp.maps.items():
        assert torch.isfinite(t).all(), name
    assert torch.allclose(comp.maps.albedo, eager.maps.albedo, atol=5e-3)
    assert torch.allclose(comp.maps.normal, eager.maps.normal, atol=5e-3)
    e, c = map_errors(eager.maps, gt), map_errors(comp.maps, gt)
    for k in ("albedo_rmse", "normal_mean_deg", "roughness_mae"):
        assert c[k] <= 1.2 * e[k] + 1e-4, k


def test_compiled_preset_settings():
    assert PRESETS["standard-compiled"] == replace(PRESETS["standard"], name="standard-compiled", kernel="compiled")
    assert PRESETS["standard-compiled"].compiled and not PRESETS["standard"].compiled
    with pytest.raises(ValueError, match="compiled"):
        Preset("x", "adam", (1, 1, 1), kernel="compiled")
    assert Preset("x", "adam", (1, 1, 1), kernel="fused").kernel == "fused"
    with pytest.raises(ValueError, match="unknown kernel"):
        Preset("x", "lm", (1, 1, 1), kernel="gpu")


def test_failed_compile_falls_back_to_eager_with_a_warning(monkeypatch):
    import dualscale.bsdf.model as model
    from dualscale.bsdf import evaluate
    from dualscale.sim.materials import generate

    def broken(fn, **kw):
        def run(*a, **k):
            raise RuntimeError("no C++ compiler")
        return run

    monkeypatch.setattr(model, "_COMPILED", {})
    monkeypatch.setattr(torch, "compile", broken)
    maps = generate("twill", 8, 0.009).maps
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866]])
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
        got = evaluate(maps, dirs, torch.tensor([0.0, 0.0, 1.0]), compiled=True)
    want = evaluate(maps, dirs, torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(got, want)
    assert torch.equal(evaluate(maps, dirs, torch.tensor([0.0, 0.0, 1.0]), compiled=True), want)  # stays eager
