"""Training data: micro photometric datasets paired with their fitted maps.

Layout of one training source (``dualscale synth MAT -o DIR --dataset`` writes exactly this;
``dualscale fit`` output works as the maps folder)::

    DIR/micro/manifest.json     photometric dataset (dualscale.formats.dataset format)
    DIR/maps/material.json      maps in the dualscale-maps format (dualscale.formats.maps),
    DIR/maps/<map>.exr          one EXR per map, same size as the micro images

A source may also be given as the micro dataset folder itself; its maps are then looked up in
``--maps DIR`` (paired in order), else ``<dataset>/maps``, else ``<dataset>/../maps``.

Which maps to propagate: when ``material.json`` carries fit metadata (``meta.fit.components``,
written by ``dualscale fit``), the maps those components require; otherwise every map found.

Images per light (LEDs and back lights): P0 (relative analyser 0), P90 (relative 90) and their
mean; a light captured without analyser contributes its single image.  A black back-lit image
(an opaque sample) is left out.  The diffuse light is
the dataset's ``diffuse`` capture when there is one; otherwise it is synthesised as
``sum_i w_i (P0_i + P90_i) / 2`` over all dome LEDs with the dome's solid-angle weights
``w_i`` (what the renderer does for the diffuse group, except that the specular part is
weighted by ``R_s`` instead of ``(R_s + R_p) / 2``).  Images are linear RGB radiance, stored
as float16 ``(L, 2, 3, H, W)`` (P0, P90).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dualscale.bsdf import MAP_NAMES, Components

MODES = 3  # P0, P90, mean


@dataclass
class Source:
    """One micro dataset with its maps, in memory."""

    name: str
    pairs: Tensor  # (L, 2, 3, H, W) float16: P0, P90 per light
    maps: dict[str, Tensor]  # name -> (C, H, W) float32
    light_names: list[str]
    texel_mm: float | None = None  # pixel pitch on the sample (maps' texel_mm, else the dataset camera's)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.pairs.shape[-2]), int(self.pairs.shape[-1])

    def diffuse_image(self) -> Tensor:
        """``(3, H, W)`` float32: the diffuse light's mean image, else the mean of every image."""
        if "diffuse" in self.light_names:
            return self.pairs[self.light_names.index("diffuse")].float().mean(0)
        return self.pairs.float().mean((0, 1))

    def diffuse_mean(self) -> list[float]:
        """Mean linear RGB of the diffuse light's mean image (the exposure reference)."""
        i = self.light_names.index("diffuse")
        return self.pairs[i].float().mean(0).mean((1, 2)).tolist()


def resolve_source(path: str | Path, maps: str | Path | None = None) -> tuple[Path, Path]:
    """``(micro dataset dir, maps dir)`` for a training source; see the module docstring."""
    p = Path(path)
    if (p / "micro" / "manifest.json").is_file():
        micro = p / "micro"
        cands = [Path(maps)] if maps else [p / "maps"]
    elif (p / "manifest.json").is_file():
        micro = p
        cands = [Path(maps)] if maps else [p / "maps", p.parent / "maps"]
    else:
        raise FileNotFoundError(f"{p}: no micro photometric dataset (expected {p}/micro/manifest.json "
                                f"or {p}/manifest.json)")
    for c in cands:
        if (c / "material.json").is_file():
            return micro, c
    raise FileNotFoundError(f"dataset {p} has no fitted maps: looked for material.json in "
                            f"{', '.join(str(c) for c in cands)} (pass --maps DIR)")


def required_maps(maps_dir: Path, present: list[str]) -> list[str]:
    """Maps to propagate: from fit metadata when present, else all maps found (MAP_NAMES order)."""
    doc = json.loads((maps_dir / "material.json").read_text())
    comps = ((doc.get("meta") or {}).get("fit") or {}).get("components")
    if comps:
        need = list(Components(**comps).required_maps())
        missing = [m for m in need if m not in present]
        if missing:
            raise ValueError(f"{maps_dir}: the fit's components need maps {missing}, which are missing")
        return [m for m in MAP_NAMES if m in need]
    return [m for m in MAP_NAMES if m in present]


def _light_images(ds) -> dict[str, list]:
    """Group records by light: ``{name: [P0 index, P90 index]}`` (or one nopol index twice)."""
    groups: dict[str, dict] = {}
    for i, r in enumerate(ds.records):
        if r.light_kind == "off":
            continue
        name = r.light_kind if r.light_id is None else f"{r.light_kind}{r.light_id:03d}"
        g = groups.setdefault(name, {})
        if r.analyzer_deg is None:
            g["nopol"] = i
        elif r.analyzer_relative and abs(r.analyzer_deg) < 1e-6:
            g["p0"] = i
        elif r.analyzer_relative and abs(r.analyzer_deg - 90) < 1e-6:
            g["p90"] = i
    out = {}
    for name, g in groups.items():
        if "p0" in g and "p90" in g:
            out[name] = [g["p0"], g["p90"]]
        elif "nopol" in g:
            out[name] = [g["nopol"], g["nopol"]]
    return out


def _synth_diffuse(ds, names: list[str], pairs: np.ndarray) -> np.ndarray | None:
    """Diffuse image from all dome LEDs (see module docstring), or None if LEDs are missing."""
    from dualscale.geometry.dome import DomeGeometry

    dome = DomeGeometry.from_regmap()
    idx = {n: k for k, n in enumerate(names)}
    keys = [f"led{i:03d}" for i in range(dome.n_leds)]
    if any(k not in idx for k in keys) or (ds.manifest.get("dome") or {}).get("source", "regmap") != "regmap":
        return None
    w = dome.diffuse_weights().numpy().astype(np.float32)
    acc = np.zeros(pairs.shape[2:], np.float32)
    for wi, k in zip(w, keys):
        acc += wi * pairs[idx[k]].astype(np.float32).mean(0)
    return acc


def load_source(path: str | Path, maps: str | Path | None = None) -> Source:
    """Read one training source (micro dataset + maps) into memory; clear errors on bad input."""
    from dualscale.formats.dataset import read_dataset
    from dualscale.formats.maps import load_maps

    micro, maps_dir = resolve_source(path, maps)
    mm, mmeta = load_maps(maps_dir)
    present = [n for n, _ in mm.items()]
    names = required_maps(maps_dir, present)
    ds = read_dataset(micro)
    groups = _light_images(ds)
    if not groups:
        raise ValueError(f"{micro}: no usable images (need P0/P90 relative-analyser pairs or unpolarised images)")
    light_names = sorted(groups)
    first = ds.load(groups[light_names[0]][0])
    h, w = first.shape[:2]
    if (h, w) != mm.shape:
        raise ValueError(f"{micro}: images are {(h, w)} but the maps in {maps_dir} are {mm.shape}")
    pairs = np.empty((len(light_names), 2, 3, h, w), np.float16)
    for k, n in enumerate(light_names):
        for j, i in enumerate(groups[n]):
            pairs[k, j] = ds.load(i).transpose(2, 0, 1)
    # the rig takes a back-lit image of every sample; an opaque one's is black, with nothing to learn
    black = [k for k, n in enumerate(light_names) if n.startswith("backlight") and not np.any(pairs[k])]
    if black:
        keep = [k for k in range(len(light_names)) if k not in black]
        pairs, light_names = pairs[keep], [light_names[k] for k in keep]
    if "diffuse" not in groups:
        d = _synth_diffuse(ds, light_names, pairs)
        if d is not None:
            pairs = np.concatenate([pairs, np.broadcast_to(d.astype(np.float16), (1, 2) + d.shape)], 0)
            light_names.append("diffuse")
    tmaps = {n: getattr(mm, n).permute(2, 0, 1).contiguous().float() for n in names}
    return Source(str(path), torch.from_numpy(np.ascontiguousarray(pairs)), tmaps, light_names,
                  _texel_mm(ds, groups[light_names[0]][0], mmeta.get("texel_mm")))


def _texel_mm(ds, index: int, maps_texel: float | None) -> float | None:
    """Pixel pitch of the micro images: the maps' ``texel_mm``, else the camera's ``field_mm /
    width`` from the dataset manifest; ``None`` when neither says.  A disagreement over 1 % is an
    error (maps from another capture)."""
    rec = ds.records[index]
    cam = (ds.manifest.get("cameras") or {}).get(rec.camera) or {}
    cam_texel = None
    if cam.get("field_mm") and cam.get("width"):
        cam_texel = float(cam["field_mm"][0]) / float(cam["width"])
    if maps_texel and cam_texel and abs(maps_texel - cam_texel) > 0.01 * cam_texel:
        raise ValueError(f"{ds.root}: the maps' texel_mm {maps_texel:g} disagrees with the micro camera's "
                         f"{cam_texel:g} mm (field_mm / width in manifest.json)")
    return float(maps_texel) if maps_texel else cam_texel


def check_sources(sources: list[Source]) -> list[str]:
    """All sources must propagate the same maps; returns that list."""
    if not sources:
        raise ValueError("need at least one training dataset")
    first = list(sources[0].maps)
    for s in sources[1:]:
        if list(s.maps) != first:
            raise ValueError(f"datasets propagate different maps: {sources[0].name} has {first}, "
                             f"{s.name} has {list(s.maps)}")
    return first


def sample_batch(sources: list[Source], batch: int, crop: int,
                 gen: torch.Generator) -> tuple[Tensor, dict[str, Tensor]]:
    """Random crops: per element a random source, light, mode (P0, P90, mean) and position.

    Returns ``(images (B, 3, crop, crop) float32, {map: (B, C, crop, crop)})``.
    """
    names = list(sources[0].maps)
    xs, ys = [], {n: [] for n in names}
    for _ in range(batch):
        s = sources[int(torch.randint(len(sources), (1,), generator=gen))]
        h, w = s.size
        if h < crop or w < crop:
            raise ValueError(f"{s.name}: images are {(h, w)}, smaller than the {crop}px crop")
        li = int(torch.randint(s.pairs.shape[0], (1,), generator=gen))
        mode = int(torch.randint(MODES, (1,), generator=gen))
        y = int(torch.randint(h - crop + 1, (1,), generator=gen))
        x = int(torch.randint(w - crop + 1, (1,), generator=gen))
        p = s.pairs[li, :, :, y:y + crop, x:x + crop].float()
        xs.append(p.mean(0) if mode == 2 else p[mode])
        for n in names:
            ys[n].append(s.maps[n][:, y:y + crop, x:x + crop])
    return torch.stack(xs), {n: torch.stack(v) for n, v in ys.items()}
