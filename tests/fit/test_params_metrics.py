import math

import pytest
import torch

from dualscale.bsdf import Components, normal_from_square
from dualscale.fit.metrics import map_errors, normal_angle_deg, ssim_images
from dualscale.fit.params import PAPER_BOUNDS, bounds_at, params_from_maps, project, to_maps
from dualscale.fit.presets import PRESETS, get_preset


def test_paper_bounds_schedule():
    assert bounds_at(0.0, PAPER_BOUNDS) == {"roughness": (0.3, 1.0), "ior": (0.1, 1.0), "anisotropy": (0.1, 0.9)}
    assert bounds_at(0.59, PAPER_BOUNDS)["roughness"] == (0.3, 1.0)
    assert "roughness" not in bounds_at(0.6, PAPER_BOUNDS)
    assert bounds_at(0.79, PAPER_BOUNDS)["anisotropy"] == (0.1, 0.9)
    b = bounds_at(0.85, PAPER_BOUNDS)
    assert b == {"anisotropy": (0.1, 1.0)}
    assert bounds_at(0.9, PAPER_BOUNDS) == {}


def test_paper_preset_is_the_papers_procedure():
    p = get_preset("paper")
    assert p.optimizer == "adam" and p.iterations == (700, 500, 600) and p.total == 1800
    assert p.light_batch is None
    with pytest.raises(ValueError, match="unknown preset"):
        get_preset("nope")
    assert set(PRESETS) >= {"draft", "standard", "paper"}


def test_project_clamps_wraps_and_repairs():
    p = {"roughness": torch.tensor([[[0.1], [0.5], [1.4]]]), "tangent": torch.tensor([[[1.25], [-0.25], [0.5]]]),
         "normal": torch.tensor([[[2.0, -3.0], [0.1, 0.2], [float("nan"), 0.0]]])}
    project(p, bounds_at(0.0, PAPER_BOUNDS))
    assert p["roughness"].flatten().tolist() == pytest.approx([0.3, 0.5, 1.0])
    assert p["tangent"].flatten().tolist() == pytest.approx([0.25, 0.75, 0.5])
    assert torch.isfinite(p["normal"]).all() and p["normal"].abs().max() <= 1.0


def test_params_roundtrip_through_elliptical_mapping():
    g = torch.Generator().manual_seed(0)
    n = normal_from_square(torch.rand(4, 5, 2, generator=g, dtype=torch.float64) * 1.6 - 0.8)
    from dualscale.bsdf import MaterialMaps

    maps = MaterialMaps(albedo=torch.rand(4, 5, 3, dtype=torch.float64), roughness=torch.rand(4, 5, 1, dtype=torch.float64),
                        normal=n)
    comps = Components(normal_mapped=True, ior_mapped=True)
    back = to_maps(params_from_maps(maps, comps))
    assert torch.allclose(back.normal, n, atol=1e-9)
    assert torch.allclose(back.ior, torch.full((4, 5, 1), 0.25, dtype=torch.float64))


def test_normal_angle_and_map_errors():
    a = torch.tensor([[0.0, 0.0, 1.0]])
    b = torch.tensor([[math.sin(math.radians(3)), 0.0, math.cos(math.radians(3))]])
    assert float(normal_angle_deg(a, b)) == pytest.approx(3.0, abs=1e-5)
    from dualscale.sim.materials import generate

    gt = generate("twill", 16, 0.009).maps
    e = map_errors(gt, gt)
    assert all(v == pytest.approx(0.0, abs=1e-6) for v in e.values())
    worse = generate("twill", 16, 0.009, seed=1).maps
    assert map_errors(worse, gt)["albedo_rmse"] > 0.01


def test_albedo_opacity_error_sees_only_the_reflected_product():
    from dualscale.sim.materials import generate

    gt = generate("sheer", 16, 0.009).maps
    gt.opacity = torch.where(gt.opacity > 0.5, 0.9, 0.0)
    assert "albedo_opacity_rmse" not in map_errors(generate("twill", 16, 0.009).maps, generate("twill", 16, 0.009).maps)
    fit = generate("sheer", 16, 0.009).maps
    fit.opacity = torch.where(gt.opacity > 0.5, torch.ones_like(gt.opacity), gt.opacity)  # 0.9 -> 1 ...
    fit.albedo = gt.albedo * gt.opacity / fit.opacity.clamp(min=1e-6)  # ... and a darker albedo: same reflection
    e = map_errors(fit, gt)
    assert e["albedo_rmse"] > 0.005
    assert e["albedo_opacity_rmse"] == pytest.approx(0.0, abs=1e-6)
    fit.albedo = fit.albedo * 1.1
    assert map_errors(fit, gt)["albedo_opacity_rmse"] > 0.01


def test_ssim_identical_is_one_and_detects_difference():
    x = torch.rand(2, 16, 16, 3, generator=torch.Generator().manual_seed(1))
    assert ssim_images(x, x) == pytest.approx([1.0, 1.0])
    assert (ssim_images(x * 0.5 + 0.25, x) < 0.99).all()
