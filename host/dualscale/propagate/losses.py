"""Loss ``L = sum_p lambda_p L1_p + lambda_style L_style`` (seed Section 7.3/7.4).

* ``L1_p``: mean absolute error of map ``p``.  The tangent map is axial (value 0 and 1 are
  the same axis), so its distance is ``min(|d|, 1 - |d|)``.
* ``L_style`` (Chambon, Heitz & Belcour 2021): all map channels are stacked (normals mapped
  to [0, 1] as ``n/2 + 1/2``) and random channel triplets are passed, as RGB images, to a
  3-channel perceptual loss.
* Perceptual losses (``method=`` registry :data:`PERCEPTUAL`):
  - ``"gram"`` (default, needs no weights): Gram matrices of a *fixed random* multi-scale CNN
    (Ustyuzhaninov et al. 2016): filters of size 3, 5 and 7, 16 each, drawn from a fixed
    seed, applied at scales 1, 1/2 and 1/4; the loss is the mean absolute Gram difference.
  - ``"lpips_alex"``: LPIPS with an AlexNet trunk.  Its ImageNet weights are *not* shipped and
    never downloaded: put a state dict at ``$DUALSCALE_LPIPS_ALEX`` or
    ``~/.cache/dualscale/lpips_alex.pt`` with torchvision AlexNet keys
    ``features.{0,3,6,8,10}.{weight,bias}`` plus the LPIPS heads ``lin{0..4}.model.1.weight``.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

WEIGHTS: dict[str, float] = {
    "normal": 3.0, "ior": 1.0, "roughness": 1.0, "albedo": 3.0, "tangent": 3.0, "anisotropy": 1.0,
    "specular_tint": 1.0, "transmittance": 3.0, "opacity": 1.0,
}
STYLE_WEIGHT = 0.25
GRAM_SEED = 20210513


def map_l1(name: str, pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute error; axial wrap-around for ``tangent``."""
    d = (pred - target).abs()
    if name == "tangent":
        d = torch.minimum(d, 1 - d)
    return d.mean()


class RandomGramLoss(nn.Module):
    """Gram statistics of a fixed random multi-scale CNN; input ``(B, 3, H, W)`` in ~[0, 1]."""

    def __init__(self, sizes: tuple[int, ...] = (3, 5, 7), filters: int = 16, scales: int = 3,
                 seed: int = GRAM_SEED) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        for k in sizes:
            w = torch.randn(filters, 3, k, k, generator=g)
            w = w - w.mean((1, 2, 3), keepdim=True)  # zero-mean: responds to texture, not level
            self.register_buffer(f"w{k}", w / w.flatten(1).norm(dim=1)[:, None, None, None])
        self.sizes, self.scales = sizes, scales

    def grams(self, x: Tensor) -> list[Tensor]:
        out = []
        x = x - 0.5
        for s in range(self.scales):
            if s:
                x = F.avg_pool2d(x, 2)
            for k in self.sizes:
                f = F.relu(F.conv2d(x, getattr(self, f"w{k}").to(x.dtype), padding=k // 2)).flatten(2)
                out.append(f @ f.transpose(1, 2) / f.shape[-1])
        return out

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        return sum((a - b).abs().mean() for a, b in zip(self.grams(pred), self.grams(target.detach())))


def lpips_weights_path() -> Path:
    """Where the LPIPS-AlexNet weights are looked for (never downloaded)."""
    env = os.environ.get("DUALSCALE_LPIPS_ALEX")
    return Path(env) if env else Path.home() / ".cache" / "dualscale" / "lpips_alex.pt"


class LpipsAlex(nn.Module):
    """LPIPS (Zhang et al. 2018) on an AlexNet trunk, weights from :func:`lpips_weights_path`."""

    _CONVS = ((3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1), (384, 256, 3, 1, 1), (256, 256, 3, 1, 1))
    _KEYS = (0, 3, 6, 8, 10)

    def __init__(self, path: str | Path | None = None) -> None:
        super().__init__()
        path = Path(path) if path else lpips_weights_path()
        if not path.is_file():
            raise FileNotFoundError(f"LPIPS-AlexNet weights not found at {path} (set DUALSCALE_LPIPS_ALEX); "
                                    "they are never downloaded, use the default 'gram' perceptual loss instead")
        sd = torch.load(path, map_location="cpu", weights_only=True)
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, s, p) for i, o, k, s, p in self._CONVS)
        self.lins = nn.ModuleList(nn.Conv2d(c[1], 1, 1, bias=False) for c in self._CONVS)
        try:
            for conv, key in zip(self.convs, self._KEYS):
                conv.weight.data.copy_(sd[f"features.{key}.weight"])
                conv.bias.data.copy_(sd[f"features.{key}.bias"])
            for i, lin in enumerate(self.lins):
                lin.weight.data.copy_(sd[f"lin{i}.model.1.weight"])
        except (KeyError, RuntimeError) as e:
            raise ValueError(f"{path}: not an LPIPS-AlexNet state dict ({e})") from e
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])
        self.requires_grad_(False)

    def features(self, x: Tensor) -> list[Tensor]:
        x = ((2 * x - 1) - self.shift.to(x)) / self.scale.to(x)
        out = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            out.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return out

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        loss = pred.new_zeros(())
        for lin, a, b in zip(self.lins, self.features(pred), self.features(target.detach())):
            loss = loss + lin((a - b) ** 2).mean()
        return loss


PERCEPTUAL = {"gram": RandomGramLoss, "lpips_alex": LpipsAlex}


def stack_channels(maps: dict[str, Tensor]) -> Tensor:
    """``{map: (B, C, H, W)}`` -> ``(B, sum C, H, W)`` in [0, 1] (normals remapped)."""
    return torch.cat([0.5 * t + 0.5 if n == "normal" else t for n, t in maps.items()], 1)


def random_triplets(channels: int, count: int, gen: torch.Generator) -> list[list[int]]:
    """``count`` random channel triplets (distinct channels when ``channels >= 3``)."""
    out = []
    for _ in range(count):
        if channels >= 3:
            out.append(torch.randperm(channels, generator=gen)[:3].tolist())
        else:
            out.append(torch.randint(channels, (3,), generator=gen).tolist())
    return out


class PropagationLoss(nn.Module):
    """Weighted per-map L1 plus the multi-channel style term; returns ``(total, parts)``."""

    def __init__(self, maps: list[str], perceptual: str = "gram", style_weight: float = STYLE_WEIGHT,
                 triplets: int = 2) -> None:
        super().__init__()
        if perceptual not in PERCEPTUAL:
            raise ValueError(f"perceptual loss must be one of {sorted(PERCEPTUAL)}, got {perceptual!r}")
        self.maps, self.style_weight, self.triplets = list(maps), style_weight, triplets
        self.perceptual = PERCEPTUAL[perceptual]() if style_weight > 0 else None

    def forward(self, pred: dict[str, Tensor], target: dict[str, Tensor],
                gen: torch.Generator) -> tuple[Tensor, dict[str, float]]:
        parts: dict[str, float] = {}
        total = pred[self.maps[0]].new_zeros((), dtype=torch.float32)
        for m in self.maps:
            l1 = map_l1(m, pred[m].float(), target[m].float())
            parts[m] = float(l1.detach())
            total = total + WEIGHTS[m] * l1
        if self.perceptual is not None:
            p, t = stack_channels(pred).float(), stack_channels(target).float()
            trip = random_triplets(p.shape[1], self.triplets, gen)
            style = sum(self.perceptual(p[:, c], t[:, c]) for c in trip) / len(trip)
            parts["style"] = float(style.detach())
            total = total + self.style_weight * style
        return total, parts
