"""Tiled onnxruntime inference over a large guidance image.

* The guidance (:mod:`.guidance`: linear RGB, refused when it has non-finite pixels) is
  processed in tiles of at most ``tile`` x ``tile`` px overlapping by at least ``overlap`` px:
  per axis the fewest tiles that cover the image, each as small as that count allows
  (:func:`fit_tile`, :class:`TilePlan`).
* Blending: each tile's output is weighted by a separable window that is 0 on a ``margin`` of
  ``overlap / 4`` px at inner tile edges (where zero padding hurts the network), then rises as a
  raised cosine over the rest of the overlap, and is 1 inside; sides on the image border keep
  weight 1.  Outputs are divided by the summed weights.  Normals are renormalised; the axial
  tangent map is blended as the doubled angle ``(cos 2 pi v, sin 2 pi v)`` so that 0.02 and 0.98
  average to 0 and not to 0.5.
* Memory: the blend accumulator holds one strip of ``tile`` rows.  :func:`run_tiled` streams:
  finished rows go to the maps writer (:class:`dualscale.formats.maps.MapsWriter`, the files of
  ``save_maps``, with the guidance's ``texel_mm``) while the next strip computes, so the maps
  are never held whole (they would be ``C * H * W * 4`` bytes: 0.73 GB for 7 maps at 4072^2).
  ``stream=False`` keeps the earlier way (maps held whole, then ``save_maps``) for comparison.
* Threads: with ``stream=True`` the main thread runs onnxruntime (which releases the GIL) and
  one worker thread blends, decodes and writes; a bounded queue (:data:`QUEUE_TILES` tile
  outputs) keeps the memory flat.  An error or Ctrl-C in either stops both, and the writer
  deletes its temporary files: no partial map appears.
* Precision: ``fp32`` (default), ``fp16`` and ``int8`` (dynamic quantisation, opt-in only:
  :meth:`OnnxModel.open` with ``precision="int8"``; docs/PROPAGATION.md states its loss).
* Exposure: ``exposure="auto"`` scales the guidance so its mean luminance (over a given box,
  else the whole image) equals the model's ``input_reference`` (mean of the training diffuse
  images); a number is used as is.
"""

from __future__ import annotations

import hashlib
import json
import math
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from dualscale.bsdf import MAP_CHANNELS
from dualscale.errors import FormatError, InputError

from .unet import MULTIPLE

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
PREVIEW_MAX_PIXELS = 2048 * 2048  # larger maps get no PNG previews by default (memory)
MARGIN_FRACTION = 0.25  # share of the overlap where an inner tile edge gets weight 0
QUEUE_TILES = 4  # tile outputs waiting for the blend/write thread (12.6 MB each at 512^2, 7 maps)
PRECISIONS = ("fp32", "fp16", "int8")


@dataclass
class OnnxModel:
    """An onnxruntime session plus the metadata ``run`` needs.

    ``precision``: ``"fp32"``, ``"fp16"`` (float16 input and output) or ``"int8"`` (dynamic
    quantisation of the fp32 graph: float32 input and output, int8 convolutions), from the
    file's ``dualscale:precision``."""

    session: object
    maps: list[str]
    input_reference: list[float] | None
    half: bool
    precision: str = "fp32"

    @classmethod
    def open(cls, path: str | Path, threads: int | None = None, precision: str | None = None,
             optimization: str = "all") -> "OnnxModel":
        """Open an exported ONNX file (``dualscale.propagate.export``).

        ``path``: the ONNX file, or a model file (``.dsp``) whose export of ``precision`` lies
        next to it (:func:`~dualscale.propagate.export.onnx_path`).  ``precision``: ``None``
        takes the file as it is; a name (:data:`PRECISIONS`) is checked against the file, so an
        explicit ``"int8"`` is refused (``InputError``/``FormatError`` naming the file and how
        to make it) when the quantised file is absent, is another precision, or was quantised
        from another fp32 export than the one beside it.  ``threads``: onnxruntime intra-op
        threads; ``optimization``: the graph optimisation level (:func:`~.export.session`).
        """
        from .export import onnx_path, session
        from dualscale.formats.model import COMPATIBLE

        if precision is not None and precision not in PRECISIONS:
            raise InputError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        path = Path(path)
        if path.suffix != ".onnx":
            if precision is None:
                raise InputError(f"{path}: not an ONNX file; pass precision= to open its export")
            path = onnx_path(path, precision)
        if not path.is_file():
            how = (" (make it with 'dualscale propagate export MODEL --int8', or export_model(MODEL, int8=True))"
                   if precision == "int8" else " (export the model with 'dualscale propagate export')")
            raise InputError(f"ONNX model not found: {path}{how}")
        sess = session(path, threads, optimization)
        meta = sess.get_modelmeta().custom_metadata_map
        if "dualscale:maps" not in meta:
            raise FormatError(f"{path}: not a dualscale propagation ONNX model (no dualscale:maps metadata)")
        ver = int(meta.get("dualscale:version", -1))
        if ver not in COMPATIBLE:
            raise FormatError(f"{path}: model version {ver} is incompatible (this dualscale reads {COMPATIBLE}); "
                             "re-export it with 'dualscale propagate export'")
        half = sess.get_inputs()[0].type == "tensor(float16)"
        prec = meta.get("dualscale:precision", "fp16" if half else "fp32")
        if precision is not None and prec != precision:
            raise FormatError(f"{path} is a {prec} model, not {precision}"
                              + ("; the int8 model is made by export_model(MODEL, int8=True)"
                                 if precision == "int8" else ""))
        if prec == "int8":
            _check_int8_source(path, meta)
        ref = json.loads(meta["dualscale:input_reference"]) if "dualscale:input_reference" in meta else None
        return cls(sess, json.loads(meta["dualscale:maps"]), ref, half, prec)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``(N, 3, H, W)`` float32 -> ``(N, C, H, W)`` float32."""
        inp = self.session.get_inputs()[0].name
        return self.session.run(None, {inp: x.astype(np.float16 if self.half else np.float32)})[0].astype(np.float32)


def _check_int8_source(path: Path, meta: dict) -> None:
    """Refuse an int8 file quantised from another fp32 export than the one beside it (stale)."""
    src = meta.get("dualscale:quantised_from")
    digest = meta.get("dualscale:quantised_from_sha256")
    if not src or not digest:
        raise FormatError(f"{path}: int8 model without its source record (dualscale:quantised_from); "
                          "re-make it with export_model(MODEL, int8=True)")
    fp32 = path.parent / src
    if fp32.is_file() and hashlib.sha256(fp32.read_bytes()).hexdigest() != digest:
        raise FormatError(f"{path} was quantised from another export than {fp32} (stale); re-make it with "
                          "export_model(MODEL, int8=True)")


def fit_tile(n: int, tile: int, overlap: int) -> int:
    """The tile side (a multiple of 16, at most ``tile``; an image smaller than a tile: the image
    rounded up to 16) for which the fewest tiles cover ``n`` px with at least ``overlap``."""
    if n <= tile:
        return min(tile, math.ceil(n / MULTIPLE) * MULTIPLE)
    count = math.ceil((n - overlap) / (tile - overlap))
    return min(tile, math.ceil((n + (count - 1) * overlap) / count / MULTIPLE) * MULTIPLE)


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


@dataclass(frozen=True)
class TilePlan:
    """Where the tiles go: tile size ``(th, tw)`` (a multiple of 16, at most the image padded to
    one), row and column origins ``ys``, ``xs``, and the overlap."""

    height: int
    width: int
    th: int
    tw: int
    overlap: int
    ys: tuple[int, ...]
    xs: tuple[int, ...]

    @classmethod
    def make(cls, height: int, width: int, tile: int, overlap: int) -> "TilePlan":
        """Tiles of at most ``tile`` px: per axis the fewest tiles that cover the image with
        ``overlap``, then the smallest multiple of 16 that lets that many cover it
        (:func:`fit_tile`), so that no tile is spent on a last tile overlapping its neighbour
        by far more than ``overlap`` (4072 px with 1024 px tiles: 5 tiles of 880 px, not 5 of
        1024)."""
        if tile % MULTIPLE or overlap < 0 or overlap >= tile // 2:
            raise ValueError(f"tile must be a multiple of {MULTIPLE} and 0 <= overlap < tile/2 (got {tile}, {overlap})")
        th, tw = fit_tile(height, tile, overlap), fit_tile(width, tile, overlap)
        return cls(height, width, th, tw, overlap, tuple(tile_positions(height, th, th - overlap)),
                   tuple(tile_positions(width, tw, tw - overlap)))

    @property
    def tiles(self) -> int:
        return len(self.ys) * len(self.xs)


def _tile_outputs(model: OnnxModel, rgb: np.ndarray, plan: TilePlan, gain: float,
                  batch: int) -> Iterator[tuple[int, int, np.ndarray]]:
    """``(k, j, y)``: the network's raw output ``y`` ``(n, C, th, tw)`` for the tiles ``j ..
    j + n - 1`` of tile row ``k``, in order."""
    W = plan.width
    for k, y0 in enumerate(plan.ys):
        y1 = min(plan.height, y0 + plan.th)
        strip = _pad_to(rgb[y0:y1] * np.float32(gain), plan.th, max(W, plan.tw))
        for j in range(0, len(plan.xs), batch):
            x = np.stack([strip[:, x0:x0 + plan.tw].transpose(2, 0, 1) for x0 in plan.xs[j:j + batch]])
            yield k, j, model(np.ascontiguousarray(x))


class _Blender:
    """Blends tile outputs (in the order of :func:`_tile_outputs`) into finished rows."""

    def __init__(self, plan: TilePlan, maps: list[str]) -> None:
        self.plan, self.maps = plan, maps
        self.nacc = max(s.stop for s in _acc_layout(maps).values())
        self.base = 0  # first row held in the accumulator
        self.acc = np.zeros((self.nacc, 0, plan.width), np.float32)
        self.wsum = np.zeros((0, plan.width), np.float32)

    def add(self, k: int, j: int, y: np.ndarray) -> tuple[int, dict[str, np.ndarray]] | None:
        """Blend one batch; returns ``(first row, {map: (rows, W, C)})`` when tile row ``k`` is
        complete (the rows no later tile touches), else ``None``."""
        p, W = self.plan, self.plan.width
        y0 = p.ys[k]
        y1 = min(p.height, y0 + p.th)
        if j == 0:
            need = y0 + p.th - self.base
            if self.acc.shape[1] < need:
                grow = need - self.acc.shape[1]
                self.acc = np.concatenate([self.acc, np.zeros((self.nacc, grow, W), np.float32)], 1)
                self.wsum = np.concatenate([self.wsum, np.zeros((grow, W), np.float32)], 0)
        wy = window_1d(p.th, p.overlap, k == 0, k == len(p.ys) - 1)
        y = _encode(self.maps, y)
        for i in range(y.shape[0]):
            jj = j + i
            x0 = p.xs[jj]
            wgt = wy[:, None] * window_1d(p.tw, p.overlap, jj == 0, jj == len(p.xs) - 1)[None, :]
            x1 = min(W, x0 + p.tw)
            r0, r1 = y0 - self.base, y0 - self.base + (y1 - y0)
            self.acc[:, r0:r1, x0:x1] += (y[i] * wgt)[:, :y1 - y0, :x1 - x0]
            self.wsum[r0:r1, x0:x1] += wgt[:y1 - y0, :x1 - x0]
        if j + y.shape[0] < len(p.xs):
            return None
        done = p.height if k == len(p.ys) - 1 else p.ys[k + 1]  # rows no later tile touches
        n, first = done - self.base, self.base
        rows = _decode(self.maps, self.acc[:, :n] / np.maximum(self.wsum[:n], 1e-12))
        self.acc, self.wsum, self.base = self.acc[:, n:].copy(), self.wsum[n:].copy(), done
        return first, rows


def _summary(model: OnnxModel, plan: TilePlan, gain: float) -> dict:
    return {"height": plan.height, "width": plan.width, "tiles": plan.tiles, "tile": (plan.th, plan.tw),
            "overlap": plan.overlap, "gain": float(gain), "maps": list(model.maps), "precision": model.precision}


def propagate_image(model: OnnxModel, rgb: np.ndarray, tile: int = 512, overlap: int = 64, gain: float = 1.0,
                    batch: int = 1, progress: bool = True) -> tuple[dict[str, np.ndarray], dict]:
    """Run ``model`` tiled over ``rgb`` ``(H, W, 3)`` linear radiance times ``gain``, in this
    thread, holding the maps whole.

    Returns ``({map: (H, W, C) float32}, summary)``.  Tiling and blending: module docstring.
    """
    from tqdm import tqdm

    H, W = rgb.shape[:2]
    plan = TilePlan.make(H, W, tile, overlap)
    out = {m: np.empty((H, W, MAP_CHANNELS[m]), np.float32) for m in model.maps}
    blender = _Blender(plan, model.maps)
    with tqdm(total=plan.tiles, disable=not progress, desc="propagate run", unit="tile") as bar:
        for k, j, y in _tile_outputs(model, rgb, plan, gain, batch):
            rows = blender.add(k, j, y)
            bar.update(y.shape[0])
            if rows is not None:
                for m, v in rows[1].items():
                    out[m][rows[0]:rows[0] + v.shape[0]] = v
    return out, _summary(model, plan, gain)


def _stream(model: OnnxModel, rgb: np.ndarray, plan: TilePlan, gain: float, batch: int, progress: bool,
            writer) -> None:
    """Tile outputs from this thread (onnxruntime) to a worker thread that blends them and
    hands finished rows to ``writer`` (a :class:`~dualscale.formats.maps.MapsWriter`)."""
    from tqdm import tqdm

    q: queue.Queue = queue.Queue(maxsize=QUEUE_TILES)
    failed: list[BaseException] = []
    blender = _Blender(plan, model.maps)

    def work() -> None:
        try:
            while (item := q.get()) is not None:
                rows = blender.add(*item)
                if rows is not None:
                    writer.write(*rows)
        except BaseException as e:  # handed to the main thread
            failed.append(e)

    def put(item) -> None:
        while True:
            try:
                q.put(item, timeout=0.2)
                return
            except queue.Full:
                if not worker.is_alive():
                    raise failed[0] if failed else RuntimeError("propagate: the writer thread stopped")

    worker = threading.Thread(target=work, name="propagate-writer", daemon=True)
    worker.start()
    try:
        with tqdm(total=plan.tiles, disable=not progress, desc="propagate run", unit="tile") as bar:
            for item in _tile_outputs(model, rgb, plan, gain, batch):
                if failed:
                    raise failed[0]
                put(item)
                bar.update(item[2].shape[0])
        put(None)
        worker.join()
        if failed:
            raise failed[0]
    except BaseException:
        while True:  # stop the worker: drop what waits, then the end mark
            try:
                q.get_nowait()
            except queue.Empty:
                break
        q.put_nowait(None)
        worker.join()
        raise


def run_tiled(model: OnnxModel, guidance, out_dir: str | Path, tile: int = 512, overlap: int = 64,
              exposure: str | float = "auto", batch: int = 1, progress: bool = True, *, transfer: str | None = None,
              texel_mm: float | None = None, box: tuple[float, float, float, float] | None = None,
              meta: dict | None = None, previews: bool | None = None, stream: bool = True) -> dict:
    """Propagate maps over ``guidance`` and write them to ``out_dir`` (``dualscale-maps``, through
    :class:`dualscale.formats.maps.MapsWriter`); returns a summary.

    ``guidance``: a :class:`~dualscale.propagate.guidance.Guidance`, or a path read with
    :func:`~dualscale.propagate.guidance.read_guidance` (``transfer``, ``texel_mm``; its refusals
    happen before anything is written).  ``texel_mm``: recorded in the maps (the guidance's;
    ``None`` = unknown, with a warning in the summary).  ``box``: the region for the ``auto``
    exposure (the registered micro field).  ``previews``: PNG previews beside the EXR maps; by
    default only up to :data:`PREVIEW_MAX_PIXELS` (they cost time: ~8-bit PNG encoding of every
    map).  ``stream``: write finished rows while the next ones compute (default; module
    docstring); ``False``: hold the maps whole and write them at the end with
    :func:`~dualscale.formats.maps.save_maps` (the earlier way, kept for the benchmark; its
    previews convert whole maps to float64: +1.5 GB at 4072^2).  An error or an interrupt
    leaves no new map file under ``out_dir`` (an earlier ``material.json`` is removed first).
    """
    from dualscale.bsdf import MaterialMaps
    from dualscale.formats.maps import MapsWriter, save_maps

    from .guidance import Guidance, read_guidance

    g = guidance if isinstance(guidance, Guidance) else read_guidance(guidance, transfer, texel_mm)
    tex = g.texel_mm if texel_mm is None else float(texel_mm)
    warnings = list(g.warnings)
    if tex is None:
        warnings.append(f"the texel size of {g.file.name} is unknown (pass --texel-mm): the maps record texel_mm "
                        "null")
    gain = exposure_gain(model, g.luminance(), exposure, box)
    plan = TilePlan.make(*g.shape, tile, overlap)
    record = {"guidance": str(g.file), "transfer": g.transfer, "gain": gain, "tile": tile, "overlap": overlap,
              "precision": model.precision, **(meta or {})}
    if previews is None:
        previews = g.shape[0] * g.shape[1] <= PREVIEW_MAX_PIXELS
    if stream:
        with MapsWriter(out_dir, model.maps, *g.shape, {"propagate": record}, previews, tex) as writer:
            _stream(model, g.rgb, plan, gain, batch, progress, writer)
        summary = _summary(model, plan, gain)
    else:
        maps, summary = propagate_image(model, g.rgb, tile, overlap, gain, batch, progress)
        save_maps(out_dir, MaterialMaps(**{k: torch.from_numpy(v) for k, v in maps.items()}), {"propagate": record},
                  texel_mm=tex, previews=previews)
    return {**summary, "texel_mm": tex, "transfer": g.transfer, "previews": previews, "warnings": warnings}
