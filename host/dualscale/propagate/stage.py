"""Propagation as a pipeline stage (seed Section 7): from a micro capture, its fitted maps and
a guidance image to maps over the whole guidance, at the guidance's texel size.

:func:`run_propagation` does, in order:

1. read the guidance (:mod:`.guidance`: linear, non-finite pixels refused, the transfer of
   display-encoded images stated) and write it as ``out/guidance.exr``;
2. read the micro capture and its maps (:mod:`.data`) and their texel size (a capture over the
   in-memory threshold as a :class:`~.data.DiskSource`, its images left on disk);
3. locate the micro field in the guidance (:mod:`.bridge`: the rig geometry's prior, refined by
   OpenCV registration; a poor match falls back to the prior with a warning);
4. resample the micro images and maps to the guidance's texel size (:mod:`.resample`, a
   DiskSource a few lights at a time), so the network learns the structure at the scale it will
   see it;
5. train (:mod:`.train`; resumable from ``out/model.dsp.ckpt``; a finished model is reused) with
   the preset's crops, or smaller ones that still move around the resampled micro field
   (:func:`training_crop`; at least :data:`MIN_TRAIN_PX`);
6. export to ONNX and run tiled over the guidance (:mod:`.export`, :mod:`.infer`), matching the
   exposure inside the registered micro field; the maps go to ``out/maps`` through
   :func:`dualscale.formats.maps.save_maps` with ``texel_mm`` = the guidance's;
7. compare the propagated maps inside the micro field with the resampled fitted maps (the
   in-field L1, a self-check) and write the summary ``out/propagate.json`` last.

Every file is written atomically; an interrupted run resumes from the training checkpoint.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import InputError

from .bridge import SEARCH_MM, prior_box, register_micro
from .guidance import LUMA, read_guidance

MIN_TRAIN_PX = 32  # the U-Net pools 4 times: 32 px leaves a 2 x 2 bottleneck
RIG_GUIDANCE_FIELD_MM = 100.0  # the mid-range camera's field (seed Sec. 7.2: 10 x 10 cm)
SUMMARY = "propagate.json"


def require_coverage(micro_hw: tuple[int, int], micro_texel_mm: float, guidance_texel_mm: float, where: str,
                     hint: str) -> tuple[int, int]:
    """The micro field's size in guidance pixels, ``(h, w)`` (:func:`.resample.new_size` of the
    micro ``(h, w)`` texels at ``micro_texel_mm / guidance_texel_mm``), which the network trains
    on.  Raises :class:`~dualscale.errors.InputError` naming ``where`` (and ending with ``hint``,
    the way out) when its shorter side is under :data:`MIN_TRAIN_PX`.  The one coverage rule of
    the propagate stage and of ``digitize``'s check before any stage."""
    from .resample import new_size

    h, w = new_size(int(micro_hw[0]), int(micro_hw[1]), micro_texel_mm / guidance_texel_mm)
    if min(h, w) < MIN_TRAIN_PX:
        raise InputError(f"{where}: the micro field ({micro_hw[1] * micro_texel_mm:.3g} x "
                         f"{micro_hw[0] * micro_texel_mm:.3g} mm) covers only {w}x{h} guidance pixels at "
                         f"{guidance_texel_mm:.4g} mm/px; propagation needs at least {MIN_TRAIN_PX} px: {hint}")
    return h, w


def training_crop(side: int, preset_crop: int) -> int:
    """The crop for a training image of ``side`` px: the preset's, else the largest multiple of 16
    that leaves at least 16 px of room to move (a crop the size of the whole image always shows
    the network the same picture, which it then memorises), never under :data:`MIN_TRAIN_PX`."""
    return max(MIN_TRAIN_PX, min(preset_crop, (side - 16) // 16 * 16))


def _guidance_texel(g, warnings: list[str]) -> float:
    if g.texel_mm is not None:
        return float(g.texel_mm)
    h, w = g.shape
    tex = RIG_GUIDANCE_FIELD_MM / w
    warnings.append(f"the texel size of the guidance {g.file.name} is unknown: assumed the rig's mid-range camera "
                    f"({RIG_GUIDANCE_FIELD_MM:g} mm over {w} px = {tex:.4g} mm/px); pass the guidance texel size "
                    "if that is wrong")
    return tex


def _trained(model_path: Path, name: str, preset) -> dict | None:
    """The training record of a finished model file for this very run (same source and scale,
    same preset settings), else ``None``."""
    from dataclasses import asdict

    from dualscale.formats.model import read_model_file

    if not model_path.is_file():
        return None
    try:
        info = read_model_file(model_path).get("train") or {}
    except (InputError, OSError):
        return None
    if info.get("datasets") == [name] and info.get("preset") == asdict(preset):
        return info
    return None


def _in_field(pred: dict[str, np.ndarray], src, box) -> dict[str, float]:
    """Mean absolute difference (axial for the tangent) between the propagated maps inside the
    micro field and the resampled fitted maps."""
    h, w = src.size
    x0, y0 = int(round(box[0])), int(round(box[1]))
    H, W = next(iter(pred.values())).shape[:2]
    if x0 < 0 or y0 < 0 or x0 + w > W or y0 + h > H:
        return {}
    out = {}
    for k, v in src.maps.items():
        d = np.abs(pred[k][y0:y0 + h, x0:x0 + w] - v.permute(1, 2, 0).numpy())
        if k == "tangent":
            d = np.minimum(d, 1 - d)
        out[k] = float(d.mean())
    return out


def run_propagation(dataset: Path, maps: Path, guidance: Path, out: Path, *, preset: str = "fast",
                    texel_mm_guidance: float | None = None, transfer: str | None = None,
                    threads: int | None = None, progress: bool = False, init: str | Path | None = None,
                    search_mm: float = SEARCH_MM, micro_centre_mm: tuple[float, float] = (0.0, 0.0),
                    tile: int = 512, overlap: int = 64, seed: int = 0, iterations: int | None = None,
                    batch: int | None = None, in_memory_bytes: float | None = None) -> dict[str, Any]:
    """Train on ``dataset`` (micro photometric dataset) + ``maps`` (its fitted maps) and propagate
    over ``guidance`` (image file or dataset folder); writes into ``out`` (module docstring).

    ``preset``: a training preset of :data:`dualscale.propagate.train.PRESETS`;
    ``texel_mm_guidance``: the guidance's pixel pitch in mm (default: its dataset camera's, else
    the rig's mid-range camera, 100 mm over the width, with a warning); ``transfer``: of a
    display-encoded guidance (``srgb``, ``linear``, ``gamma:G``); ``threads``: torch and
    onnxruntime threads; ``init``: a warm-start model; ``search_mm``: registration search radius;
    ``micro_centre_mm``: the micro field's centre on the sample (a calibration's; default the
    origin); ``iterations``, ``batch``: override the preset's; ``in_memory_bytes``: the micro
    capture's in-memory threshold (default :func:`dualscale.propagate.data.in_memory_limit`): a
    larger capture is read from disk a few lights at a time while it is resampled to the guidance
    texel (the same resampled source, so the same model and maps), so the stage's peak memory is
    the resampled source's plus a few full-size images, not the whole capture's.

    Returns ``{"guidance", "texel_mm", "micro_box_px": [x, y, w, h], "registration": {...},
    "train_seconds", "run_seconds", "preset", "warnings": [...], ...}``.  Raises
    :class:`~dualscale.errors.InputError` (and subclasses) on input it cannot interpret, before
    writing anything.
    """
    from dualscale.bsdf import MAP_NAMES
    from dualscale.formats.atomic import clean_stale, write_json
    from dualscale.formats.exr import write_exr
    from dualscale.formats.maps import load_maps

    from .data import load_source
    from .export import ensure_exported, onnx_paths
    from .infer import OnnxModel, run_tiled
    from .resample import resample_source
    from .train import TrainOptions, preset_with, train

    out = Path(out)
    warnings: list[str] = []
    g = read_guidance(guidance, transfer, texel_mm_guidance)
    warnings += g.warnings
    tex = _guidance_texel(g, warnings)
    # over the in-memory threshold (data.IN_MEMORY_BYTES, $DUALSCALE_PROPAGATE_IN_MEMORY_MB) a DiskSource,
    # which resample_source reads a few lights at a time: the same resampled source, bit for bit
    src = load_source(dataset, maps, in_memory_bytes=in_memory_bytes)
    if src.texel_mm is None:
        raise InputError(f"{dataset}: the micro texel size is unknown (no texel_mm in {maps}/material.json and no "
                         "camera field_mm in the dataset manifest): it is needed to bridge the two scales")
    # 3. where the micro field is in the guidance
    scale = src.texel_mm / tex
    h_m, w_m = src.size
    prior = prior_box(g.shape, tex, (w_m * src.texel_mm, h_m * src.texel_mm), g.camera, micro_centre_mm)
    micro_lum = np.einsum("chw,c->hw", src.diffuse_image().numpy(), LUMA)
    reg = register_micro(g.luminance(), micro_lum, scale, prior, tex, search_mm)
    warnings += reg.warnings

    # 4. the micro data at the guidance's texel size
    require_coverage((h_m, w_m), src.texel_mm, tex, str(dataset),
                     "capture a larger micro field or a finer guidance (or state the guidance's true texel size: "
                     "--guidance-texel-mm / --texel-mm)")
    small = resample_source(src, scale)
    side = min(small.size)
    if scale > 1:
        warnings.append(f"the guidance ({tex:.4g} mm/px) is finer than the micro capture ({src.texel_mm:.4g} mm/px): "
                        "the micro data were enlarged, and the maps hold no detail finer than the micro texel")

    out.mkdir(parents=True, exist_ok=True)
    clean_stale(out)
    write_exr(out / "guidance.exr", g.rgb, attributes={"dualscale:texel_mm": f"{tex:.9g}",
                                                       "dualscale:source": str(g.file),
                                                       "dualscale:transfer": g.transfer})
    if threads:
        import torch

        torch.set_num_threads(threads)

    # 5. train (or resume, or reuse a finished model)
    p = preset_with(preset, iterations=iterations, batch=batch)
    p = preset_with(preset, iterations=iterations, batch=batch, crop=training_crop(side, p.crop))
    model_path = out / "model.dsp"
    t0 = time.perf_counter()
    done = _trained(model_path, small.name, p)
    if done is None:
        res = train([small], p, model_path, TrainOptions(resume=True, progress=progress, seed=seed,
                                                        init=None if init is None else str(init)))
        resumed_from = res.resumed_from
        done = _trained(model_path, small.name, p) or {}
    else:
        resumed_from = p.iterations
    train_seconds = time.perf_counter() - t0
    warm_start = done.get("init")  # the warm-start model the training started from (None: random weights)

    # 6. export and run over the guidance
    t1 = time.perf_counter()
    p32, p16 = onnx_paths(model_path)
    parity = None
    ex = ensure_exported(model_path, check=True)  # by content (the hash recorded in the ONNX), not by time
    if ex is not None:
        parity = max(ex["parity_fp32"].values())
        if parity >= 1e-4:
            warnings.append(f"ONNX fp32 parity {parity:.2g} is worse than 1e-4")
    om = OnnxModel.open(p32, threads)
    info = run_tiled(om, g, out / "maps", tile, overlap, "auto", 1, progress, texel_mm=tex, box=reg.box_px,
                     meta={"micro_box_px": list(reg.box_px), "model": model_path.name, "preset": p.name})
    warnings += [w for w in info["warnings"] if w not in warnings]
    run_seconds = time.perf_counter() - t1

    # 7. self-check inside the micro field, then the summary (the stage's completion marker)
    pred, _ = load_maps(out / "maps")
    in_field = _in_field({k: v.numpy() for k, v in pred.items()}, small, reg.box_px)
    summary = {"guidance": str(g.file), "guidance_exr": "guidance.exr", "transfer": g.transfer,
               "texel_mm": tex, "guidance_size_px": [g.shape[1], g.shape[0]], "micro_texel_mm": src.texel_mm,
               "micro_size_px": [w_m, h_m], "training_size_px": [small.size[1], small.size[0]],
               "micro_box_px": [round(v, 3) for v in reg.box_px], "registration": reg.to_json(),
               "preset": p.name, "iterations": p.iterations, "crop": p.crop, "resumed_from": resumed_from,
               "warm_start": Path(warm_start).name if warm_start else None,
               "train_seconds": train_seconds, "run_seconds": run_seconds, "gain": info["gain"],
               "maps": [m for m in MAP_NAMES if m in info["maps"]], "onnx_parity_fp32": parity,
               "in_field_l1": in_field, "warnings": warnings}
    write_json(out / SUMMARY, summary)
    return summary
