import json
import shutil

import numpy as np
import pytest
import torch

from dualscale.propagate.data import load_source, resolve_source, sample_batch


def test_load_source(twill):
    s = load_source(twill)
    assert list(s.maps) == ["albedo", "roughness", "anisotropy", "tangent", "normal", "ior", "specular_tint"]
    n_leds = len(range(0, 127, 16))
    assert s.pairs.shape == (n_leds, 2, 3, 32, 32)  # not all LEDs -> no synthesised diffuse
    assert "diffuse" not in s.light_names
    # P0 = diffuse/2 + specular >= P90 = diffuse/2
    assert float((s.pairs[:, 0].float() - s.pairs[:, 1].float()).min()) > -1e-3
    assert s.maps["albedo"].shape == (3, 32, 32)


def test_micro_folder_and_explicit_maps(twill, tmp_path):
    micro, maps = resolve_source(twill / "micro")
    assert maps == twill / "maps"
    shutil.copytree(twill / "maps", tmp_path / "elsewhere")
    assert resolve_source(twill / "micro", tmp_path / "elsewhere")[1] == tmp_path / "elsewhere"


def test_dataset_without_maps(twill, tmp_path):
    shutil.copytree(twill / "micro", tmp_path / "cap" / "micro")
    with pytest.raises(FileNotFoundError, match="no fitted maps"):
        load_source(tmp_path / "cap")
    with pytest.raises(FileNotFoundError, match="no micro photometric dataset"):
        load_source(tmp_path)


def test_fit_metadata_selects_maps(twill, tmp_path):
    root = tmp_path / "fit"
    shutil.copytree(twill, root)
    doc = json.loads((root / "maps" / "material.json").read_text())
    comps = {"opaque": True, "isotropic": True, "tinted": False, "normal_mapped": True, "ior_mapped": False,
             "ior": 1.5}
    doc["meta"] = {"fit": {"components": comps}}
    (root / "maps" / "material.json").write_text(json.dumps(doc))
    assert list(load_source(root).maps) == ["albedo", "roughness", "normal"]
    doc["meta"]["fit"]["components"]["opaque"] = False  # needs transmittance/opacity: absent
    (root / "maps" / "material.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="missing"):
        load_source(root)


def test_synthesised_diffuse(tmp_path):
    from dualscale.cli import main
    from dualscale.geometry.cameras import micro_camera
    from dualscale.sim.render import Analyzer, LightState, render
    from dualscale.formats.maps import load_maps

    assert main(["synth", "leather", "-o", str(tmp_path / "l"), "--size", "16", "--dataset", "--no-previews"]) == 0
    s = load_source(tmp_path / "l")
    assert s.light_names[-1] == "diffuse" and s.pairs.shape[0] == 128
    maps, _ = load_maps(tmp_path / "l" / "maps")
    ref = render(maps, micro_camera(16), LightState.diffuse_group(), analyzer=Analyzer(0.0, True))
    got = s.pairs[-1, 0].float().permute(1, 2, 0)
    # exact up to the specular polarisation weighting (R_s vs (R_s + R_p)/2) and float16 storage
    assert float((got - ref).abs().mean() / ref.mean()) < 0.05


def test_sample_batch(twill):
    s = load_source(twill)
    gen = torch.Generator().manual_seed(0)
    x, y = sample_batch([s], 5, 16, gen)
    assert x.shape == (5, 3, 16, 16) and x.dtype == torch.float32
    assert y["normal"].shape == (5, 3, 16, 16) and y["roughness"].shape == (5, 1, 16, 16)
    with pytest.raises(ValueError, match="smaller than"):
        sample_batch([s], 1, 64, gen)


def test_sample_batch_pairs_image_and_maps(twill):
    """A crop's maps are the maps at the crop position (checked by re-locating the crop)."""
    s = load_source(twill)
    x, y = sample_batch([s], 3, 16, torch.Generator().manual_seed(3))
    full = s.maps["albedo"].numpy()
    for b in range(3):
        crop = y["albedo"][b].numpy()
        hits = [(i, j) for i in range(17) for j in range(17) if np.array_equal(full[:, i:i + 16, j:j + 16], crop)]
        assert hits


def test_sample_batch_diffuse_fraction(twill):
    """diffuse_fraction=1 takes every crop from the diffuse light's mean image (the guidance's
    lighting); 0 keeps the uniform sampler's stream exactly; a source without a diffuse light
    samples uniformly whatever the fraction."""
    from dataclasses import replace

    s = load_source(twill)
    assert "diffuse" not in s.light_names  # every 16th LED: no synthesised diffuse light
    x0, _ = sample_batch([s], 6, 16, torch.Generator().manual_seed(2))
    x1, _ = sample_batch([s], 6, 16, torch.Generator().manual_seed(2), diffuse_fraction=0.0)
    assert torch.equal(x0, x1)
    x2, _ = sample_batch([s], 6, 16, torch.Generator().manual_seed(2), diffuse_fraction=1.0)
    assert x2.shape == x0.shape  # no diffuse light: uniform draws (another stream, same shapes)
    # give the source a diffuse light: a constant image, so every diffuse crop is that constant
    d = torch.full((1, 2, 3, *s.size), 0.25, dtype=s.pairs.dtype)
    sd = replace(s, pairs=torch.cat([s.pairs, d]), light_names=[*s.light_names, "diffuse"])
    xd, _ = sample_batch([sd], 8, 16, torch.Generator().manual_seed(2), diffuse_fraction=1.0)
    assert torch.all(xd == 0.25)
    xh, _ = sample_batch([sd], 64, 16, torch.Generator().manual_seed(2), diffuse_fraction=0.5)
    share = float((xh == 0.25).flatten(1).all(1).float().mean())
    assert 0.3 < share < 0.7
