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

A source larger than :data:`IN_MEMORY_BYTES` is a :class:`DiskSource`: every training crop is
read from the EXR files (:meth:`Dataset.load` with a box), with the same values, so training
is bit for bit the in-memory one's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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

    @property
    def map_names(self) -> list[str]:
        return list(self.maps)

    @property
    def n_lights(self) -> int:
        return int(self.pairs.shape[0])

    def crop_image(self, li: int, mode: int, y: int, x: int, crop: int) -> Tensor:
        """``(3, crop, crop)`` float32: light ``li``'s P0 (mode 0), P90 (1) or their mean (2)."""
        p = self.pairs[li, :, :, y:y + crop, x:x + crop].float()
        return p.mean(0) if mode == 2 else p[mode]

    def crop_maps(self, y: int, x: int, crop: int) -> dict[str, Tensor]:
        return {n: m[:, y:y + crop, x:x + crop] for n, m in self.maps.items()}

    def mean_rgb(self) -> list[float]:
        return self.pairs.float().mean((0, 1, 3, 4)).tolist()

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


def _synth_diffuse(ds, names: list[str], pair) -> np.ndarray | None:
    """Diffuse image from all dome LEDs (see module docstring), or None if LEDs are missing.
    ``pair(k)``: light ``k``'s ``(2, 3, H, W)`` float16 images (from memory or read from disk:
    the same arithmetic either way)."""
    from dualscale.geometry.dome import DomeGeometry

    dome = DomeGeometry.from_regmap()
    idx = {n: k for k, n in enumerate(names)}
    keys = [f"led{i:03d}" for i in range(dome.n_leds)]
    if any(k not in idx for k in keys) or (ds.manifest.get("dome") or {}).get("source", "regmap") != "regmap":
        return None
    w = dome.diffuse_weights().numpy().astype(np.float32)
    acc = None
    for wi, k in zip(w, keys):
        term = wi * pair(idx[k]).astype(np.float32).mean(0)
        acc = term if acc is None else acc + term
    return acc


IN_MEMORY_BYTES = 512 * 2**20
"""A training source whose images and maps would take more than this in memory (float16
images, float32 maps) is read crop by crop from its EXR files (:class:`DiskSource`);
``$DUALSCALE_PROPAGATE_IN_MEMORY_MB`` overrides it (``0``: always from disk)."""

MAPS_SHARE = 0.25
"""A :class:`DiskSource` still holds its maps in memory when they take at most this share of the
threshold (float32; 128 MiB by default: 7 woven-fabric maps up to ~1750 px square)."""


def in_memory_limit() -> float:
    import os

    v = os.environ.get("DUALSCALE_PROPAGATE_IN_MEMORY_MB")
    return IN_MEMORY_BYTES if v in (None, "") else float(v) * 2**20


def _read_pair(ds, indices, box=None) -> np.ndarray:
    """``(2, 3, h, w)`` float16: the P0 and P90 images (one unpolarised image twice) of a light,
    as :class:`Source` holds them; ``box`` ``(y0, y1, x0, x1)``: only that region."""
    a = ds.load(indices[0], box).transpose(2, 0, 1).astype(np.float16)
    b = a if indices[1] == indices[0] else ds.load(indices[1], box).transpose(2, 0, 1).astype(np.float16)
    return np.stack([a, b])


def _check_maps_streamed(maps_dir: Path, doc: dict, names: list[str], rows: int = 256) -> None:
    """What :func:`~dualscale.formats.maps.load_maps` checks of the maps to propagate (size,
    finite values, unit normals with z >= 0), reading ``rows`` rows at a time."""
    from dualscale.errors import FormatError
    from dualscale.formats.exr import read_exr
    from dualscale.formats.maps import channel_names, check_normals

    H, W = int(doc["height"]), int(doc["width"])
    for n in names:
        f = maps_dir / f"{n}.exr"
        for y0 in range(0, H, rows):
            try:
                a = read_exr(f, channel_names(n), box=(y0, min(H, y0 + rows), 0, W), size=(H, W))
            except ValueError as e:
                raise FormatError(str(e) if f.name in str(e) else f"{f}: {e}") from None
            if not np.isfinite(a).all():
                raise FormatError(f"{f}: {int((~np.isfinite(a)).sum())} non-finite values")
            if n == "normal":
                check_normals(a, str(f))


@dataclass
class DiskSource:
    """One micro dataset with its maps, read crop by crop from its EXR files.

    Holds the file lists and, in memory, only images that have no file (a synthesised diffuse
    light: one ``(2, 3, H, W)`` float16 entry).  Every crop has exactly the values of the same
    crop of the in-memory :class:`Source` (images cast to float16 as it stores them)."""

    name: str
    dataset: Any  # dualscale.formats.dataset.Dataset
    maps_dir: Path
    lights: list  # per light: [P0 record, P90 record] indices, or an in-memory (2, 3, H, W) float16 array
    map_names: list[str]
    light_names: list[str]
    shape: tuple[int, int]
    texel_mm: float | None = None
    maps: dict[str, Tensor] | None = None  # name -> (C, H, W) float32 when held in memory, else read per crop

    @property
    def size(self) -> tuple[int, int]:
        return self.shape

    @property
    def n_lights(self) -> int:
        return len(self.lights)

    def pair(self, li: int, box=None) -> np.ndarray:
        v = self.lights[li]
        if isinstance(v, np.ndarray):
            return v if box is None else v[:, :, box[0]:box[1], box[2]:box[3]]
        return _read_pair(self.dataset, v, box)

    def crop_image(self, li: int, mode: int, y: int, x: int, crop: int) -> Tensor:
        v = self.lights[li]
        box = (y, y + crop, x, x + crop)
        if mode < 2 and not isinstance(v, np.ndarray):  # one image read, not two
            a = self.dataset.load(v[mode], box).transpose(2, 0, 1).astype(np.float16)
            return torch.from_numpy(np.ascontiguousarray(a)).float()
        p = torch.from_numpy(np.ascontiguousarray(self.pair(li, box))).float()
        return p.mean(0) if mode == 2 else p[mode]

    def crop_maps(self, y: int, x: int, crop: int) -> dict[str, Tensor]:
        from dualscale.formats.exr import read_exr
        from dualscale.formats.maps import channel_names

        if self.maps is not None:
            return {n: m[:, y:y + crop, x:x + crop] for n, m in self.maps.items()}
        out = {}
        for n in self.map_names:
            a = read_exr(self.maps_dir / f"{n}.exr", channel_names(n), box=(y, y + crop, x, x + crop), size=self.shape)
            out[n] = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1))).float()
        return out

    def diffuse_image(self) -> Tensor:
        if "diffuse" in self.light_names:
            return torch.from_numpy(self.pair(self.light_names.index("diffuse"))).float().mean(0)
        return torch.tensor(self.mean_rgb(per_pixel=True))

    def diffuse_mean(self) -> list[float]:
        i = self.light_names.index("diffuse")
        return torch.from_numpy(self.pair(i)).float().mean(0).mean((1, 2)).tolist()

    def mean_rgb(self, per_pixel: bool = False):
        """Mean of every image, accumulated one light at a time in float64 (the in-memory mean
        over the whole array can differ in the last float32 bits)."""
        acc = np.zeros((3,) + self.shape, np.float64)
        for li in range(self.n_lights):
            acc += self.pair(li).astype(np.float64).sum(0)
        acc /= 2 * self.n_lights
        return acc.astype(np.float32) if per_pixel else acc.mean((1, 2)).tolist()


def source_bytes(n_lights: int, h: int, w: int, map_channels: int) -> int:
    """Memory of an in-memory :class:`Source`: float16 ``(L, 2, 3, H, W)`` images, float32 maps."""
    return n_lights * 2 * 3 * h * w * 2 + map_channels * h * w * 4


def load_source(path: str | Path, maps: str | Path | None = None,
                in_memory_bytes: float | None = None) -> "Source | DiskSource":
    """Read one training source (micro dataset + maps); clear errors on bad input.

    In memory (:class:`Source`) when it takes at most ``in_memory_bytes`` (default
    :func:`in_memory_limit`, :data:`IN_MEMORY_BYTES`), else a :class:`DiskSource` that reads its
    crops from the EXR files (the same crops: training is bit for bit the same)."""
    from dualscale.formats.dataset import read_dataset
    from dualscale.formats.maps import MAP_CHANNELS, read_material_json

    micro, maps_dir = resolve_source(path, maps)
    doc = read_material_json(maps_dir)
    present = [n for n in doc["maps"] if n in MAP_CHANNELS]
    names = required_maps(maps_dir, present)
    ds = read_dataset(micro)
    groups = _light_images(ds)
    if not groups:
        raise ValueError(f"{micro}: no usable images (need P0/P90 relative-analyser pairs or unpolarised images)")
    light_names = sorted(groups)
    rec = ds.records[groups[light_names[0]][0]]
    h, w = int(rec.height), int(rec.width)
    n_lights = len(light_names) + (0 if "diffuse" in groups else 1)
    limit = in_memory_limit() if in_memory_bytes is None else in_memory_bytes
    if source_bytes(n_lights, h, w, sum(MAP_CHANNELS[n] for n in names)) <= limit:
        return _load_in_memory(path, micro, maps_dir, names, ds, groups, light_names)
    if (h, w) != (int(doc["height"]), int(doc["width"])):
        raise ValueError(f"{micro}: images are {(h, w)} but the maps in {maps_dir} are "
                         f"{(int(doc['height']), int(doc['width']))}")
    tmaps = None
    if sum(MAP_CHANNELS[n] for n in names) * h * w * 4 <= limit * MAPS_SHARE:
        # the maps alone fit: held in memory (load_maps checks them), one file read per crop instead of 1 + maps
        from dualscale.formats.maps import load_maps

        mm, _ = load_maps(maps_dir)
        tmaps = {n: getattr(mm, n).permute(2, 0, 1).contiguous().float() for n in names}
        del mm
    else:
        if "albedo" not in present or "roughness" not in present:
            from dualscale.errors import FormatError

            raise FormatError(f"{maps_dir}: albedo and roughness maps are required")
        _check_maps_streamed(maps_dir, doc, names)
    lights: list = [list(groups[n]) for n in light_names]
    # an opaque sample's back-lit image is black (as float16), with nothing to learn
    black = [k for k, n in enumerate(light_names) if n.startswith("backlight") and not np.any(_read_pair(ds, lights[k]))]
    if black:
        keep = [k for k in range(len(light_names)) if k not in black]
        lights, light_names = [lights[k] for k in keep], [light_names[k] for k in keep]
    if "diffuse" not in groups:
        d = _synth_diffuse(ds, light_names, lambda k: _read_pair(ds, lights[k]))
        if d is not None:
            lights.append(np.ascontiguousarray(np.broadcast_to(d.astype(np.float16), (2,) + d.shape)))
            light_names.append("diffuse")
    maps_texel = doc.get("texel_mm", (doc.get("meta") or {}).get("texel_mm"))
    return DiskSource(str(path), ds, maps_dir, lights, names, light_names, (h, w),
                      _texel_mm(ds, groups[light_names[0]][0], maps_texel), tmaps)


def _load_in_memory(path, micro, maps_dir, names, ds, groups, light_names) -> Source:
    from dualscale.formats.maps import load_maps

    mm, mmeta = load_maps(maps_dir)
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
        d = _synth_diffuse(ds, light_names, lambda k: pairs[k])
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
    first = list(sources[0].map_names)
    for s in sources[1:]:
        if list(s.map_names) != first:
            raise ValueError(f"datasets propagate different maps: {sources[0].name} has {first}, "
                             f"{s.name} has {list(s.map_names)}")
    return first


def sample_batch(sources: list[Source], batch: int, crop: int, gen: torch.Generator,
                 diffuse_fraction: float = 0.0) -> tuple[Tensor, dict[str, Tensor]]:
    """Random crops: per element a random source, light, mode (P0, P90, mean) and position.

    ``diffuse_fraction``: the probability that an element is the source's diffuse light without
    analyser (its mean mode), the lighting of the guidance image (the dome's diffuse group,
    docs/PROPAGATION.md "Sampling"); the rest draw a light and mode uniformly as before.  A source
    without a diffuse light always draws uniformly.  At ``0`` the random stream is that of the
    uniform sampler (no extra draws).

    Returns ``(images (B, 3, crop, crop) float32, {map: (B, C, crop, crop)})``.
    """
    names = list(sources[0].map_names)
    xs, ys = [], {n: [] for n in names}
    for _ in range(batch):
        s = sources[int(torch.randint(len(sources), (1,), generator=gen))]
        h, w = s.size
        if h < crop or w < crop:
            raise ValueError(f"{s.name}: images are {(h, w)}, smaller than the {crop}px crop")
        if diffuse_fraction > 0 and float(torch.rand((), generator=gen)) < diffuse_fraction \
                and "diffuse" in s.light_names:
            li, mode = s.light_names.index("diffuse"), 2
        else:
            li = int(torch.randint(s.n_lights, (1,), generator=gen))
            mode = int(torch.randint(MODES, (1,), generator=gen))
        y = int(torch.randint(h - crop + 1, (1,), generator=gen))
        x = int(torch.randint(w - crop + 1, (1,), generator=gen))
        xs.append(s.crop_image(li, mode, y, x, crop))
        m = s.crop_maps(y, x, crop)
        for n in names:
            ys[n].append(m[n])
    return torch.stack(xs), {n: torch.stack(v) for n, v in ys.items()}
