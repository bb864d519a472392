"""Lightweight multi-decoder U-Net for mesoscale propagation (seed Section 7.4, Fig. 9).

* One shared encoder and one decoder per propagated map (``MAP_NAMES`` order).
* Every block is residual: two 3x3 convolutions with Group Normalization, and a 1x1
  convolution on the skip path.
* Four levels (encoder widths ``W, 2W, 4W, 8W``), 2x2 max pooling down, 2x2 transposed
  convolution up; a bottleneck block at ``8W`` and 1/16 resolution.
* Decoders are ``decoder_ratio`` (default 1/2) as wide as the encoder.  The full-resolution
  decoder levels dominate the cost (one decoder per map), and halving them cuts training and
  4072^2 inference time ~3x on a CPU; ``decoder_ratio=1`` gives the symmetric U-Net.
* Input: linear RGB radiance ``(B, 3, H, W)``, ``H`` and ``W`` multiples of 16.
  Output: ``(B, C, H, W)`` with the map channels concatenated in ``maps`` order, already in
  each map's convention (see :mod:`dualscale.bsdf.maps`): sigmoid for [0, 1] maps, unit
  vectors with ``z > 0`` for ``normal``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from dualscale.bsdf import MAP_CHANNELS, MAP_NAMES

LEVELS = 4
MULTIPLE = 2 ** LEVELS  # input sides must be multiples of this


def _groups(c: int) -> int:
    """GroupNorm groups: 8 channels per group, at least 1."""
    return max(1, c // 8)


class ResBlock(nn.Module):
    """``act(GN(conv3(act(GN(conv3(x))))) + conv1(x))``."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1, bias=False)
        self.norm1 = nn.GroupNorm(_groups(cout), cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.norm2 = nn.GroupNorm(_groups(cout), cout)
        self.skip = nn.Conv2d(cin, cout, 1, bias=False)
        self.act = nn.LeakyReLU(0.1)

    def forward(self, x: Tensor) -> Tensor:
        h = self.act(self.norm1(self.conv1(x)))
        return self.act(self.norm2(self.conv2(h)) + self.skip(x))


class Decoder(nn.Module):
    """Four up-steps (transposed conv, concat encoder skip, ResBlock) and a 1x1 head.

    Level ``i`` has ``dec[i]`` channels; the encoder skip brings ``enc[i]``.
    """

    def __init__(self, enc: list[int], dec: list[int], out_channels: int) -> None:
        super().__init__()
        self.ups = nn.ModuleList()
        self.blocks = nn.ModuleList()
        cin = enc[-1]
        for e, d in zip(reversed(enc), reversed(dec)):
            self.ups.append(nn.ConvTranspose2d(cin, d, 2, stride=2))
            self.blocks.append(ResBlock(d + e, d))
            cin = d
        self.head = nn.Conv2d(dec[0], out_channels, 1)

    def forward(self, x: Tensor, skips: list[Tensor]) -> Tensor:
        for up, block, s in zip(self.ups, self.blocks, reversed(skips)):
            x = block(torch.cat([up(x), s], 1))
        return self.head(x)


@dataclass(frozen=True)
class UNetConfig:
    """Architecture hyper-parameters stored in the model file."""

    maps: tuple[str, ...]
    width: int = 16
    decoder_ratio: float = 0.5
    in_channels: int = 3

    def __post_init__(self) -> None:
        bad = [m for m in self.maps if m not in MAP_CHANNELS]
        if bad or not self.maps:
            raise ValueError(f"maps must be a non-empty subset of {MAP_NAMES}, got {self.maps}")
        if self.width < 8 or self.width % 8:
            raise ValueError(f"width must be a positive multiple of 8, got {self.width}")
        if not 0 < self.decoder_ratio <= 1:
            raise ValueError(f"decoder_ratio must be in (0, 1], got {self.decoder_ratio}")

    @property
    def encoder_widths(self) -> list[int]:
        """``W, 2W, 4W, 8W``."""
        return [self.width * 2 ** i for i in range(LEVELS)]

    @property
    def decoder_widths(self) -> list[int]:
        """Encoder widths times ``decoder_ratio`` (at least 8 channels)."""
        return [max(8, int(round(w * self.decoder_ratio))) for w in self.encoder_widths]

    @property
    def out_channels(self) -> int:
        return sum(MAP_CHANNELS[m] for m in self.maps)

    def to_json(self) -> dict:
        d = asdict(self)
        d["maps"] = list(self.maps)
        return d


def map_slices(maps: tuple[str, ...]) -> dict[str, slice]:
    """Channel slice of each map in the concatenated output."""
    out, c = {}, 0
    for m in maps:
        out[m] = slice(c, c + MAP_CHANNELS[m])
        c += MAP_CHANNELS[m]
    return out


def activate(name: str, raw: Tensor) -> Tensor:
    """Head output -> map convention: unit normals (z > 0), everything else in [0, 1]."""
    if name == "normal":
        v = torch.cat([torch.tanh(raw[:, :2]), torch.sigmoid(raw[:, 2:3]) + 1e-3], 1)
        return v / torch.sqrt((v * v).sum(1, keepdim=True))
    return torch.sigmoid(raw)


class PropagationUNet(nn.Module):
    """Image -> concatenated maps; see the module docstring for shapes and conventions."""

    def __init__(self, config: UNetConfig) -> None:
        super().__init__()
        self.config = config
        ws = config.encoder_widths
        self.enc = nn.ModuleList()
        cin = config.in_channels
        for w in ws:
            self.enc.append(ResBlock(cin, w))
            cin = w
        self.pool = nn.MaxPool2d(2)
        self.bottleneck = ResBlock(ws[-1], ws[-1])
        self.decoders = nn.ModuleDict({m: Decoder(ws, config.decoder_widths, MAP_CHANNELS[m]) for m in config.maps})

    def forward(self, x: Tensor) -> Tensor:
        skips = []
        for block in self.enc:
            x = block(x)
            skips.append(x)
            x = self.pool(x)
        x = self.bottleneck(x)
        return torch.cat([activate(m, self.decoders[m](x, skips)) for m in self.config.maps], 1)

    def split(self, out: Tensor) -> dict[str, Tensor]:
        """Concatenated output ``(B, C, H, W)`` -> ``{map: (B, C_map, H, W)}``."""
        return {m: out[:, s] for m, s in map_slices(self.config.maps).items()}


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
