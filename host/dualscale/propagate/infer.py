"""Tiled onnxruntime inference over a large guidance image, streamed strip by strip.

* The guidance is read in horizontal strips (OpenImageIO scanlines) and processed in
  ``tile`` x ``tile`` tiles overlapping by ``overlap`` pixels.
* Blending: each tile's output is weighted by a separable window that is 0 on a ``margin`` of
  ``overlap / 4`` px at inner tile edges (where zero padding hurts the network), then rises as a
  raised cosine over the rest of the overlap, and is 1 inside; sides on the image border keep
  weight 1.  Outputs are divided by the summed weights.  Normals are renormalised; the axial
  tangent map is blended as the doubled angle ``(cos 2 pi v, sin 2 pi v)`` so that 0.02 and 0.98
  average to 0 and not to 0.5.
* Memory is bounded by one strip of ``tile + stride`` rows: finished rows are written to the EXR
  files (scanlines) and dropped.  Peak ~ ``(C + 4) * (tile + stride) * width * 4`` bytes plus
  onnxruntime's working set for one tile.
* Exposure: ``exposure="auto"`` scales the guidance so its mean luminance equals the model's
  ``input_reference`` (mean of the training diffuse images); a float is used as-is.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualscale.bsdf import MAP_CHANNELS

from .unet import MULTIPLE

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
_EXR_CHANNELS = {"normal": ("X", "Y", "Z"), 1: ("Y",), 3: ("R", "G", "B")}


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
        from .io import COMPATIBLE

        sess = session(path, threads)
        meta = sess.get_modelmeta().custom_metadata_map
        if "dualscale:maps" not in meta:
            raise ValueError(f"{path}: not a dualscale propagation ONNX model (no dualscale:maps metadata)")
        ver = int(meta.get("dualscale:version", -1))
        if ver not in COMPATIBLE:
            raise ValueError(f"{path}: model version {ver} is incompatible (this dualscale reads {COMPATIBLE}); "
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
    margin = overlap // 4
    ramp = overlap - margin
    if ramp > 0:
        t = (np.arange(ramp, dtype=np.float32) + 0.5) / ramp
        r = np.concatenate([np.zeros(margin, np.float32), 0.5 - 0.5 * np.cos(np.pi * t)])
        if not lo_border:
            w[:overlap] = np.minimum(w[:overlap], r)
        if not hi_border:
            w[tile - overlap:] = np.minimum(w[tile - overlap:], r[::-1])
    return w


class GuidanceReader:
    """RGB float strips of an image file (EXR or anything OpenImageIO reads)."""

    def __init__(self, path: str | Path) -> None:
        import OpenImageIO as oiio

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"guidance image not found: {self.path}")
        self.inp = oiio.ImageInput.open(str(self.path))
        if self.inp is None:
            raise OSError(f"cannot read {self.path}: {oiio.geterror()}")
        spec = self.inp.spec()
        names = list(spec.channelnames)
        self.idx = [spec.channelindex(c) for c in "RGB"]
        if spec.nchannels not in (3, 4) or min(self.idx) < 0:
            self.inp.close()
            raise ValueError(f"guidance must be an RGB image (channels R, G, B[, A]); {self.path} has "
                             f"{spec.nchannels} channel(s) {names}")
        self.height, self.width, self.nch = spec.height, spec.width, spec.nchannels

    def rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows ``[y0, y1)`` as float32 ``(y1 - y0, W, 3)``."""
        data = self.inp.read_scanlines(0, 0, y0, y1, 0, 0, self.nch, "float")
        if data is None:
            raise OSError(f"cannot read rows {y0}..{y1} of {self.path}: {self.inp.geterror()}")
        return np.asarray(data, np.float32).reshape(y1 - y0, self.width, self.nch)[..., self.idx]

    def mean_luminance(self, strip: int = 256) -> float:
        acc = 0.0
        for y in range(0, self.height, strip):
            acc += float((self.rows(y, min(self.height, y + strip)) @ LUMA).sum(dtype=np.float64))
        return acc / (self.height * self.width)

    def close(self) -> None:
        self.inp.close()


class MapWriters:
    """One scanline EXR writer per map, plus ``material.json`` (dualscale-maps format)."""

    def __init__(self, root: Path, maps: list[str], height: int, width: int, meta: dict) -> None:
        import OpenImageIO as oiio

        from dualscale.materials.io import CONVENTIONS

        root.mkdir(parents=True, exist_ok=True)
        self.outs = {}
        for m in maps:
            names = _EXR_CHANNELS["normal"] if m == "normal" else _EXR_CHANNELS[MAP_CHANNELS[m]]
            spec = oiio.ImageSpec(width, height, len(names), "float")
            spec.channelnames = names
            spec.attribute("compression", "zip")
            spec.attribute("dualscale:map", m)
            out = oiio.ImageOutput.create(str(root / f"{m}.exr"))
            if out is None or not out.open(str(root / f"{m}.exr"), spec):
                raise OSError(f"cannot write {root / f'{m}.exr'}: {oiio.geterror()}")
            self.outs[m] = out
        (root / "material.json").write_text(json.dumps(
            {"format": "dualscale-maps", "version": 1, "maps": maps, "height": height, "width": width,
             "conventions": CONVENTIONS, "meta": meta}, indent=1))

    def write(self, y0: int, y1: int, maps: dict[str, np.ndarray]) -> None:
        for m, out in self.outs.items():
            if not out.write_scanlines(y0, y1, 0, np.ascontiguousarray(maps[m], np.float32)):
                raise OSError(f"cannot write {m}.exr: {out.geterror()}")

    def close(self) -> None:
        for out in self.outs.values():
            out.close()


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


def run_tiled(model: OnnxModel, guidance: str | Path, out_dir: str | Path, tile: int = 512, overlap: int = 64,
              exposure: str | float = "auto", batch: int = 1, progress: bool = True) -> dict:
    """Propagate maps over ``guidance`` and write ``out_dir/<map>.exr``; returns a summary."""
    from tqdm import tqdm

    if tile % MULTIPLE or overlap < 0 or overlap >= tile // 2:
        raise ValueError(f"tile must be a multiple of {MULTIPLE} and 0 <= overlap < tile/2 (got {tile}, {overlap})")
    reader = GuidanceReader(guidance)
    try:
        H, W = reader.height, reader.width
        th = min(tile, math.ceil(H / MULTIPLE) * MULTIPLE)
        tw = min(tile, math.ceil(W / MULTIPLE) * MULTIPLE)
        stride_y, stride_x = th - overlap, tw - overlap
        ys, xs = tile_positions(H, th, stride_y), tile_positions(W, tw, stride_x)
        if exposure == "auto":
            if model.input_reference is None:
                raise ValueError("the model has no input reference; pass an explicit exposure")
            gain = float(np.dot(model.input_reference, LUMA)) / max(reader.mean_luminance(), 1e-12)
        else:
            gain = float(exposure)
        maps = model.maps
        layout = _acc_layout(maps)
        nacc = max(s.stop for s in layout.values())
        writers = MapWriters(Path(out_dir), maps, H, W, {"propagate": {"guidance": str(guidance), "gain": gain,
                                                                       "tile": tile, "overlap": overlap}})
        base = 0  # first row held in the accumulator
        acc = np.zeros((nacc, 0, W), np.float32)
        wsum = np.zeros((0, W), np.float32)
        bar = tqdm(total=len(ys) * len(xs), disable=not progress, desc="propagate run", unit="tile")
        try:
            for k, y0 in enumerate(ys):
                y1 = min(H, y0 + th)
                strip = _pad_to(reader.rows(y0, y1) * gain, th, max(W, tw))
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
                writers.write(base, done, _decode(maps, acc[:, :n] / np.maximum(wsum[:n], 1e-12)))
                acc, wsum, base = acc[:, n:].copy(), wsum[n:].copy(), done
        finally:
            bar.close()
            writers.close()
    finally:
        reader.close()
    return {"height": H, "width": W, "tiles": len(ys) * len(xs), "tile": (th, tw), "overlap": overlap,
            "gain": gain, "maps": maps, "precision": "fp16" if model.half else "fp32"}
