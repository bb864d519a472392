import pytest
import torch

from dualscale.propagate.augment import augment, random_blur, random_colour
from dualscale.propagate.losses import (WEIGHTS, LpipsAlex, PropagationLoss, RandomGramLoss, map_l1,
                                        random_triplets, stack_channels)


def test_paper_weights():
    assert WEIGHTS == {"normal": 3, "ior": 1, "roughness": 1, "albedo": 3, "tangent": 3, "anisotropy": 1,
                       "specular_tint": 1, "transmittance": 3, "opacity": 1}


def test_tangent_l1_is_axial():
    a, b = torch.full((1, 1, 2, 2), 0.01), torch.full((1, 1, 2, 2), 0.99)
    assert map_l1("tangent", a, b) == pytest.approx(0.02, abs=1e-6)
    assert map_l1("roughness", a, b) == pytest.approx(0.98, abs=1e-6)


def test_gram_loss():
    g = RandomGramLoss()
    x = torch.rand(2, 3, 32, 32)
    assert float(g(x, x)) == 0.0
    y = torch.rand(2, 3, 32, 32, requires_grad=True)
    loss = g(y, x)
    loss.backward()
    assert float(loss.detach()) > 0 and torch.isfinite(y.grad).all() and float(y.grad.abs().sum()) > 0
    # texture statistics, not positions: a shifted copy of the same texture scores far lower
    i = torch.arange(64.0)
    tex = (0.5 + 0.4 * torch.sin(i / 2))[None, None, None, :].expand(1, 3, 64, 64)  # vertical stripes
    other = tex.transpose(-1, -2)  # horizontal stripes: same pixel histogram, other structure
    assert float(g(torch.roll(tex, 3, -1), tex)) < 0.2 * float(g(other, tex))
    assert torch.equal(RandomGramLoss().w3, g.w3)  # fixed seed: identical across instances


def test_triplets_and_stack():
    gen = torch.Generator().manual_seed(0)
    for t in random_triplets(7, 20, gen):
        assert len(set(t)) == 3 and all(0 <= c < 7 for c in t)
    assert all(len(t) == 3 for t in random_triplets(2, 5, gen))
    s = stack_channels({"albedo": torch.zeros(1, 3, 2, 2), "normal": -torch.ones(1, 3, 2, 2)})
    assert s.shape == (1, 6, 2, 2) and float(s.min()) == 0.0


def test_total_loss_and_gradient():
    maps = ["albedo", "roughness", "normal"]
    fn = PropagationLoss(maps)
    gen = torch.Generator().manual_seed(0)
    tgt = {"albedo": torch.rand(2, 3, 16, 16), "roughness": torch.rand(2, 1, 16, 16),
           "normal": torch.nn.functional.normalize(torch.rand(2, 3, 16, 16), dim=1)}
    pred = {k: v.clone().requires_grad_(True) for k, v in tgt.items()}
    total, parts = fn(pred, tgt, gen)
    assert float(total.detach()) == 0.0 and set(parts) == {*maps, "style"}
    pred["albedo"] = (tgt["albedo"] + 0.1).requires_grad_(True)
    total, parts = fn(pred, tgt, gen)
    assert float(total.detach()) >= 3 * 0.1 - 1e-5
    total.backward()
    assert float(pred["albedo"].grad.abs().sum()) > 0
    with pytest.raises(ValueError):
        PropagationLoss(maps, perceptual="vgg")


def _fake_lpips(path):
    sd = {}
    for key, (i, o, k, _, _) in zip(LpipsAlex._KEYS, LpipsAlex._CONVS):
        sd[f"features.{key}.weight"] = 0.05 * torch.randn(o, i, k, k)
        sd[f"features.{key}.bias"] = torch.zeros(o)
    for i, c in enumerate(LpipsAlex._CONVS):
        sd[f"lin{i}.model.1.weight"] = torch.rand(1, c[1], 1, 1)
    torch.save(sd, path)


def test_lpips_local_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("DUALSCALE_LPIPS_ALEX", str(tmp_path / "none.pt"))
    with pytest.raises(FileNotFoundError, match="never downloaded"):
        PropagationLoss(["albedo"], perceptual="lpips_alex")
    _fake_lpips(tmp_path / "w.pt")
    monkeypatch.setenv("DUALSCALE_LPIPS_ALEX", str(tmp_path / "w.pt"))
    lp = LpipsAlex()
    x = torch.rand(1, 3, 64, 64)
    assert float(lp(x, x)) == 0.0 and float(lp(torch.rand(1, 3, 64, 64), x)) > 0
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not an LPIPS"):
        LpipsAlex(tmp_path / "bad.pt")


def test_blur_probability_and_range():
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(200, 3, 16, 16)
    y = random_blur(x, gen)
    changed = ((y - x).abs().flatten(1).max(1).values > 1e-3).float().mean()
    assert 0.35 < float(changed) < 0.65  # p = 0.5, minus the sigma ~ 0.1 draws that barely blur
    assert torch.allclose(y.mean((2, 3)), x.mean((2, 3)), atol=0.02)  # a blur keeps the mean


def test_colour_only_for_one_dataset():
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(64, 3, 16, 16) + 0.5
    ratio = lambda t: t.mean((2, 3)) / x.mean((2, 3))  # noqa: E731
    assert float((ratio(augment(x, gen, 2)) - 1).abs().max()) < 0.03
    assert float((ratio(augment(x, gen, 1)) - 1).abs().max()) > 0.3
    g = ratio(random_colour(x, gen))
    assert float(g.min()) >= 0.5 * 0.8 - 1e-4 and float(g.max()) <= 2 * 1.25 + 1e-4
