import pytest
import torch

from dualscale.propagate.unet import PropagationUNet, UNetConfig, count_parameters, map_slices

ALL = ("albedo", "roughness", "anisotropy", "tangent", "normal", "ior", "specular_tint", "transmittance", "opacity")


@pytest.mark.parametrize("maps", [("albedo", "roughness"), ("albedo", "roughness", "normal"), ALL])
def test_shapes_and_ranges(maps):
    m = PropagationUNet(UNetConfig(maps, width=8))
    x = torch.rand(2, 3, 48, 32) * 3
    y = m(x)
    cfg = m.config
    assert y.shape == (2, cfg.out_channels, 48, 32)
    parts = m.split(y)
    assert list(parts) == list(maps) and set(m.decoders) == set(maps)
    for name, t in parts.items():
        if name == "normal":
            assert torch.allclose(t.norm(dim=1), torch.ones(2, 48, 32), atol=1e-5)
            assert bool((t[:, 2] > 0).all())
        else:
            assert bool(((t >= 0) & (t <= 1)).all())


def test_one_decoder_per_map_only():
    small = count_parameters(PropagationUNet(UNetConfig(("albedo", "roughness"), 8)))
    big = count_parameters(PropagationUNet(UNetConfig(("albedo", "roughness", "normal"), 8)))
    enc = count_parameters(PropagationUNet(UNetConfig(("roughness",), 8)))
    assert big - small == small - enc > 0  # one more 3-channel decoder each time


def test_gradients_reach_every_parameter():
    m = PropagationUNet(UNetConfig(("albedo", "tangent", "normal"), width=8))
    y = m(torch.rand(2, 3, 32, 32))
    (y ** 2).mean().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert float(p.grad.abs().sum()) > 0, name


def test_architecture_pieces():
    m = PropagationUNet(UNetConfig(("albedo",), width=16))
    mods = list(m.modules())
    assert sum(isinstance(x, torch.nn.ConvTranspose2d) for x in mods) == 4
    assert any(isinstance(x, torch.nn.GroupNorm) for x in mods)
    assert m.enc[0].skip.kernel_size == (1, 1)
    assert m.config.encoder_widths == [16, 32, 64, 128] and m.config.decoder_widths == [8, 16, 32, 64]


@pytest.mark.parametrize("kw", [dict(maps=()), dict(maps=("colour",)), dict(maps=("albedo",), width=12),
                                dict(maps=("albedo",), decoder_ratio=0)])
def test_bad_config(kw):
    with pytest.raises(ValueError):
        UNetConfig(**kw)


def test_map_slices():
    assert map_slices(("albedo", "roughness", "normal")) == {"albedo": slice(0, 3), "roughness": slice(3, 4),
                                                            "normal": slice(4, 7)}
