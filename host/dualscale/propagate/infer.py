"""Tiled onnxruntime inference over a large guidance image.

* The guidance (:mod:`.guidance`: linear RGB, refused when it has non-finite pixels) is
  processed in ``tile`` x ``tile`` tiles overlapping by ``overlap`` pixels.
* Blending: each tile's output is weighted by a separable window that is 0 on a ``margin`` of
  ``overlap / 4`` px at inner tile edges (where zero padding hurts the network), then rises as a
  raised cosine over the rest of the overlap, and is 1 inside; sides on the image border keep
  weight 1.  Outputs are divided by the summed weights.  Normals are renormalised; the axial
  tangent map is blended as the doubled angle ``(cos 2 pi v, sin 2 pi v)`` so that 0.02 and 0.98
  average to 0 and not to 0.5.
* Memory: the blend accumulator holds one strip of ``tile + stride`` rows; finished rows go to
  the output maps, which are held whole (``C * H * W * 4`` bytes: 0.73 GB for 7 maps at 4072^2)
  and written by the one maps writer, :func:`dualscale.formats.maps.save_maps`, with the
  guidance's ``texel_mm``.
* Exposure: ``exposure="auto"`` scales the guidance so its mean luminance (over a given box,
  else the whole image) equals the model's ``input_reference`` (mean of the training diffuse
  images); a number is used as is.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dualscale.bsdf import MAP_CHANNELS
from dualscale.errors import FormatError

from .unet import MULTIPLE

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
PREVIEW_MAX_PIXELS = 2048 * 2048  # larger maps get no PNG previews by default (memory)
MARGIN_FRACTION = 0.25  # share of the overlap where an inner tile edge gets weight 0


@dataclass
class OnnxModel:
    """An onnxruntime session plus the metadata ``run`` needs."""

    session: object
    maps: list[str]
    input_reference: list[float] | None
    half: bool

    @classmethod
    def open(cls, path: str | Path, threads: int | None = None) -> "OnnxModel":
        from .export import session
        from dualscale.formats.model import COMPATIBLE

        sess = session(path, threads)
        meta = sess.get_modelmeta().custom_metadata_map
        if "dualscale:maps" not in meta:
            raise FormatError(f"{path}: not a dualscale propagation ONNX model (no dualscale:maps metadata)")
        ver = int(meta.get("dualscale:version", -1))
        if ver not in COMPATIBLE:
            raise FormatError(f"{path}: model version {ver} is incompatible (this dualscale reads {COMPATIBLE}); "
                             "re-export it with 'dualscale propagate export'")
        ref = json.loads(meta["dualscale:input_reference"]) if "dualscale:input_reference" in meta else None
        return cls(sess, json.loads(meta["dualscale:maps"]), ref,
                   sess.get_inputs()[0].type == "tensor(float16)")

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``(N, 3, H, W)`` float32 -> ``(N, C, H, W)`` float32."""
        inp = self.session.get_inputs()[0].name
        return self.session.run(None, {inp: x.astype(np.float16 if self.half else np.float32)})[0].astype(np.float32)


def tile_positions(n: int, tile: int, stride: int) -> list[int]:
    """Tile origins covering ``[0, n)``; the last tile ends exactly at ``n``."""
    if n <= tile:
        return [0]
    pos = list(range(0, n - tile, stride))
    return pos + [n - tile]


def window_1d(tile: int, overlap: int, lo_border: bool, hi_border: bool) -> np.ndarray:
    """Blend weights along one tile axis (see the module docstring)."""
    w = np.ones(tile, np.float32)
    margin = int(overlap * MARGIN_FRACTION)
    ramp = overlap - margin
    if ramp > 0:
        t = (np.arange(ramp, dtype=np.float32) + 0.5) / ramp
        r = np.concatenate([np.zeros(margin, np.float32), 0.5 - 0.5 * np.cos(np.pi * t)])
        if not lo_border:
            w[:overlap] = np.minimum(w[:overlap], r)
        if not hi_border:
            w[tile - overlap:] = np.minimum(w[tile - overlap:], r[::-1])
    return w


def _acc_layout(maps: list[str]) -> dict[str, slice]:
    """Accumulator channels: the maps, with ``tangent`` as 2 (doubled-angle cos, sin)."""
    out, c = {}, 0
    for m in maps:
        n = 2 if m == "tangent" else MAP_CHANNELS[m]
        out[m] = slice(c, c + n)
        c += n
    return out


def _encode(maps: list[str], y: np.ndarray) -> np.ndarray:
    parts, c = [], 0
    for m in maps:
        n = MAP_CHANNELS[m]
        v = y[:, c:c + n]
        if m == "tangent":
            a = 2 * np.pi * v
            v = np.concatenate([np.cos(a), np.sin(a)], 1)
        parts.append(v)
        c += n
    return np.concatenate(parts, 1)


def _decode(maps: list[str], acc: np.ndarray) -> dict[str, np.ndarray]:
    """Normalised accumulator ``(C', rows, W)`` -> ``{map: (rows, W, C)}``."""
    out = {}
    for m, s in _acc_layout(maps).items():
        v = acc[s]
        if m == "tangent":
            v = (np.mod(np.arctan2(v[1], v[0]), 2 * np.pi) / (2 * np.pi))[None]
        elif m == "normal":
            v = v / np.maximum(np.linalg.norm(v, axis=0, keepdims=True), 1e-12)
        out[m] = np.moveaxis(v, 0, -1)
    return out


def _pad_to(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """Reflect-pad ``(rows, cols, 3)`` at the bottom/right to ``(h, w, 3)``."""
    ph, pw = h - a.shape[0], w - a.shape[1]
    if ph <= 0 and pw <= 0:
        return a
    mode = "reflect" if ph < a.shape[0] and pw < a.shape[1] else "edge"
    return np.pad(a, ((0, max(ph, 0)), (0, max(pw, 0)), (0, 0)), mode=mode)


def exposure_gain(model: OnnxModel, guidance_lum: np.ndarray, exposure: str | float = "auto",
                  box: tuple[float, float, float, float] | None = None) -> float:
    """The gain applied to the guidance: ``exposure="auto"`` matches the mean luminance of the
    guidance (inside ``box`` = ``(x, y, w, h)`` pixels when given: the registered micro field, as
    the paper calibrates the mid camera on the area the micro camera sees) to the model's
    ``input_reference``; a number is used as is."""
    if exposure != "auto":
        g = float(exposure)
        if not (np.isfinite(g) and g > 0):
            raise ValueError(f"exposure gain must be a positive number or 'auto', got {exposure!r}")
        return g
    if model.input_reference is None:
        raise ValueError("the model has no input reference; pass an explicit exposure")
    region = guidance_lum
    if box is not None:
        x, y, w, h = box
        x0, y0 = max(0, int(round(x))), max(0, int(round(y)))
        x1, y1 = min(guidance_lum.shape[1], int(round(x + w))), min(guidance_lum.shape[0], int(round(y + h)))
        if x1 > x0 and y1 > y0:
            region = guidance_lum[y0:y1, x0:x1]
    mean = float(region.mean(dtype=np.float64))
    if not mean > 0:
        raise ValueError(f"the guidance is black (mean luminance {mean:g}): no exposure can match the training images")
    return float(np.dot(model.input_reference, LUMA)) / mean


def propagate_image(model: OnnxModel, rgb: np.ndarray, tile: int = 512, overlap: int = 64, gain: float = 1.0,
                    batch: int = 1, progress: bool = True) -> tuple[dict[str, np.ndarray], dict]:
    """Run ``model`` tiled over ``rgb`` ``(H, W, 3)`` linear radiance times ``gain``.

    Returns ``({map: (H, W, C) float32}, summary)``.  Tiling and blending: module docstring.
    """
    from tqdm import tqdm

    if tile % MULTIPLE or overlap < 0 or overlap >= tile // 2:
        raise ValueError(f"tile must be a multiple of {MULTIPLE} and 0 <= overlap < tile/2 (got {tile}, {overlap})")
    H, W = rgb.shape[:2]
    th = min(tile, math.ceil(H / MULTIPLE) * MULTIPLE)
    tw = min(tile, math.ceil(W / MULTIPLE) * MULTIPLE)
    stride_y, stride_x = th - overlap, tw - overlap
    ys, xs = tile_positions(H, th, stride_y), tile_positions(W, tw, stride_x)
    maps = model.maps
    layout = _acc_layout(maps)
    nacc = max(s.stop for s in layout.values())
    out = {m: np.empty((H, W, MAP_CHANNELS[m]), np.float32) for m in maps}
    base = 0  # first row held in the accumulator
    acc = np.zeros((nacc, 0, W), np.float32)
    wsum = np.zeros((0, W), np.float32)
    bar = tqdm(total=len(ys) * len(xs), disable=not progress, desc="propagate run", unit="tile")
    try:
        for k, y0 in enumerate(ys):
            y1 = min(H, y0 + th)
            strip = _pad_to(rgb[y0:y1] * np.float32(gain), th, max(W, tw))
            need = y0 + th - base
            if acc.shape[1] < need:
                grow = need - acc.shape[1]
                acc = np.concatenate([acc, np.zeros((nacc, grow, W), np.float32)], 1)
                wsum = np.concatenate([wsum, np.zeros((grow, W), np.float32)], 0)
            wy = window_1d(th, overlap, k == 0, k == len(ys) - 1)
            for j in range(0, len(xs), batch):
                group = xs[j:j + batch]
                x = np.stack([strip[:, x0:x0 + tw].transpose(2, 0, 1) for x0 in group])
                y = _encode(maps, model(np.ascontiguousarray(x)))
                for i, x0 in enumerate(group):
                    jj = j + i
                    wgt = wy[:, None] * window_1d(tw, overlap, jj == 0, jj == len(xs) - 1)[None, :]
                    x1 = min(W, x0 + tw)
                    r0, r1 = y0 - base, y0 - base + (y1 - y0)
                    acc[:, r0:r1, x0:x1] += (y[i] * wgt)[:, :y1 - y0, :x1 - x0]
                    wsum[r0:r1, x0:x1] += wgt[:y1 - y0, :x1 - x0]
                bar.update(len(group))
            done = H if k == len(ys) - 1 else ys[k + 1]  # rows no later tile touches
            n = done - base
            for m, v in _decode(maps, acc[:, :n] / np.maximum(wsum[:n], 1e-12)).items():
                out[m][base:done] = v
            acc, wsum, base = acc[:, n:].copy(), wsum[n:].copy(), done
    finally:
        bar.close()
    return out, {"height": H, "width": W, "tiles": len(ys) * len(xs), "tile": (th, tw), "overlap": overlap,
                 "gain": float(gain), "maps": list(maps), "precision": "fp16" if model.half else "fp32"}


def run_tiled(model: OnnxModel, guidance, out_dir: str | Path, tile: int = 512, overlap: int = 64,
              exposure: str | float = "auto", batch: int = 1, progress: bool = True, *, transfer: str | None = None,
              texel_mm: float | None = None, box: tuple[float, float, float, float] | None = None,
              meta: dict | None = None, previews: bool | None = None) -> dict:
    """Propagate maps over ``guidance`` and write them to ``out_dir`` (``dualscale-maps``, through
    :func:`dualscale.formats.maps.save_maps`); returns a summary.

    ``guidance``: a :class:`~dualscale.propagate.guidance.Guidance`, or a path read with
    :func:`~dualscale.propagate.guidance.read_guidance` (``transfer``, ``texel_mm``; its refusals
    happen before anything is written).  ``texel_mm``: recorded in the maps (the guidance's;
    ``None`` = unknown, with a warning in the summary).  ``box``: the region for the ``auto``
    exposure (the registered micro field).  ``previews``: PNG previews beside the EXR maps; by
    default only up to :data:`PREVIEW_MAX_PIXELS` (the preview writer works in float64 and would
    add ~1.5 GB at 4072^2: peak 3.4 GB instead of 1.9 GB).
    """
    from dualscale.bsdf import MaterialMaps
    from dualscale.formats.maps import save_maps

    from .guidance import Guidance, read_guidance

    g = guidance if isinstance(guidance, Guidance) else read_guidance(guidance, transfer, texel_mm)
    tex = g.texel_mm if texel_mm is None else float(texel_mm)
    warnings = list(g.warnings)
    if tex is None:
        warnings.append(f"the texel size of {g.file.name} is unknown (pass --texel-mm): the maps record texel_mm "
                        "null")
    gain = exposure_gain(model, g.luminance(), exposure, box)
    maps, summary = propagate_image(model, g.rgb, tile, overlap, gain, batch, progress)
    record = {"guidance": str(g.file), "transfer": g.transfer, "gain": gain, "tile": tile, "overlap": overlap,
              "precision": summary["precision"], **(meta or {})}
    if previews is None:
        previews = g.shape[0] * g.shape[1] <= PREVIEW_MAX_PIXELS
    save_maps(out_dir, MaterialMaps(**{k: torch.from_numpy(v) for k, v in maps.items()}), {"propagate": record},
              texel_mm=tex, previews=previews)
    return {**summary, "texel_mm": tex, "transfer": g.transfer, "previews": previews, "warnings": warnings}
