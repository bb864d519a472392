"""The per-pixel fit in tiles, as Dask tasks (issue 16; ``dualscale fit --workers N``).

The model has no spatial coupling (supplementary Sec. 4: every texel's SVBSDF is fitted to its
own pixel's observations), so the LM presets fit each pixel as its own problem
(:mod:`.lm`).  The map is cut into ``tile x tile`` pixel tiles; each tile's observations go to
a worker as one task, which runs :func:`.core.fit_observations` on them and returns the tile's
maps; the driver stitches them into the full maps and computes the report figures
(:func:`.core.fit_losses`) on the whole map, as the single-process fit does.

**Same result.**  Everything a tile's fit computes is per pixel: the start (photometric stereo,
the grid start), the LM step, the L1 reweighting, the median likelihood scale, the shadow test,
the accept test.  What is not is done once, by the driver, on the whole map, before the tiles:

- the component decision (:func:`.select.select_components`, on a sample of pixels), so every
  tile fits the same model;
- a preset's coarse level (``coarse-to-fine``): the coarse fit and its upsampling look across
  tile borders, so the driver runs them and each tile starts from its crop of the result;
- the bright-albedo check of :func:`.init.check_albedo_range` (a share of all pixels).

The stitched maps equal the single-process fit's bit for bit (``tests/fit/test_tiled.py`` checks
every preset); the loss history, a report only, is assembled from the tiles' (:func:`_history`).

**Adam presets** (``paper``, ``adam-fast``) fit every pixel with one optimiser whose loss is
the *mean* over the whole map's valid samples; Adam's step depends on the gradient's scale
(through its ``eps``), so a tile must use the whole map's mean, not its own.  Each tile's
observations carry the whole map's sample counts (:class:`.observations.WholeMap`), by which
the loss divides its sum: every pixel then gets the same gradient as in the whole-map fit, and
the light batches, drawn from the same seeded generator, are the same in every tile.  The
counts are exact integers, so the maps are bit for bit the same while the whole map's float32
sum of its valid samples is exact (fewer than 2^24 = 16.7 million samples: a 512^2 map with 64
images); above that the single-process mean rounds its denominator and the tiles' (exact) one
can differ from it in the last bit (docs/SCALE.md).

**Kernels.**  Tiles run the fused kernel only (every built-in preset's default but
``standard-compiled``).  The eager and compiled reference kernels go through torch's CPU
kernels, which may round a pixel's float32 result differently with the size of the tensor it
sits in (vectorised body or tail, matrix-product blocking); the LM presets' forward differences
then amplify one unit in the last place into the step (measured: maps 5e-6 to 1e-5 apart after
a short fit), so they are refused rather than merely close (:func:`check_tileable`).

**Data movement** (issue 25 Sec. 2).  When the observations are still exactly what
:func:`.observations.load_observations` read from a dataset (their
:class:`~.observations.DatasetOrigin` and :meth:`~.observations.Observations.unchanged`), a
task carries the dataset's path and its tile's coordinates, and the worker reads the tile itself
(:func:`fit_tile_read`: OpenImageIO reads the tile's scanlines of each image), so the driver
ships no pixels: a task is a few kB (plus its crop of a coarse start), whatever the map's size
(``tests/fit/test_tiled.py`` measures the bytes).  The dataset must then be on storage the
workers share at the same path (a local cluster always is).  Observations changed after loading
(a replaced mask, a subset of lights, a calibration applied in memory) are sent with each task
instead (``fit.json``'s ``tiled.tile_data`` says which).  The driver still reads the whole map
for the steps done once (below: components, coarse level, albedo check, the report's losses).

**Faults.**  A tile's task holds its data or its coordinates (no scattered futures), so when the
worker running it dies the scheduler reruns it on another worker
(``distributed.scheduler.allowed-failures``).
**Uncertainty** (issue 26).  With ``uncertainty`` each tile also computes its pixels'
uncertainty (:func:`.uncertainty.pixel_uncertainty`, per pixel like the fit), which its record
and its saved state carry and the driver stitches like the maps (:func:`stitch_uncertainty`).
**Resuming.**  Each finished tile is saved at once to ``state/<y0>_<x0>.pt`` with the fit's
fingerprint; a rerun submits only the tiles not yet saved (and those saved without the
uncertainty a fit with it needs).  **Memory.**  At most ``2 x workers``
tiles are in flight; a task carries its tile's coordinates, or its images (``K x tile^2 x 3``
float32, above), and returns its maps (``tile^2 x ~20`` float32).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps
from dualscale.errors import FormatError, InputError
from dualscale.formats.atomic import remove_file
from dualscale.formats.torchfile import load_torch, save_torch
from dualscale.progress import Progress, tracker

from .checkpoint import fingerprint
from .core import FitResult, coarse_start, fit_losses, fit_observations
from .init import check_albedo_range, photometric_stereo, start_params
from .observations import DatasetOrigin, Observations, WholeMap, read_tile, stride_leds
from .presets import Preset
from .uncertainty import Uncertainty

#: default tile side in pixels: Dask's round trip and the fit's fixed cost are ~5 % of a 64 px tile
#: (34 % at 16 px), and a 128^2 map still makes 4 tiles (docs/SCALE.md)
TILE = 64
#: tiles in flight per worker (bounds the driver's and the workers' memory)
INFLIGHT_PER_WORKER = 2


def check_tile(tile: int) -> None:
    """Raise :class:`~dualscale.errors.InputError` unless ``tile`` is a whole number >= 1."""
    if isinstance(tile, bool) or not isinstance(tile, int) or tile < 1:
        raise InputError(f"--tile-px must be a whole number >= 1, got {tile!r}")


def tiles(shape: tuple[int, int], tile: int) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` of the ``tile x tile`` tiles covering a ``(H, W)`` map, row by row;
    the last row and column are cut short.  Raises :class:`~dualscale.errors.InputError` for a
    tile side below 1 (:func:`check_tile`)."""
    check_tile(tile)
    h, w = shape
    return [(y, min(y + tile, h), x, min(x + tile, w)) for y in range(0, h, tile) for x in range(0, w, tile)]


def check_tileable(preset: Preset) -> None:
    """Raise :class:`~dualscale.errors.InputError` unless ``preset`` runs the fused kernel (module
    doc: only it gives the single-process maps bit for bit)."""
    if preset.kernel != "fused":
        raise InputError(f"--workers: the {preset.kernel} kernel (preset {preset.name}) rounds a pixel differently "
                         "with the tile's size, so its tiles would not reproduce the one-process maps; the tiled "
                         "fit runs --kernel fused (the presets' default) (docs/SCALE.md)")


def fit_tile(obs: Observations, preset: Preset, comps: Components, init: dict[str, Tensor] | None, seed: int,
             threads: int, sums: bool = False, uncertainty: bool = False) -> dict[str, Any]:
    """The task: fit one tile's observations (``fit_observations`` with no held-out lights, no
    checkpoint) on ``threads`` threads; returns ``{"maps": {name: (h, w, C) float32},
    "history": [(iteration, step, mean cost)], "pixels": h * w, "uncertainty": None}``, with
    ``uncertainty`` the tile's per-pixel uncertainty (:func:`uncertainty_record`), and with ``sums`` its loss
    sums (:func:`.metrics.image_loss_sums`) and its start's albedo counts
    (:func:`.init.start_params`): the fit out of core adds them up (:mod:`.stream`)."""
    from dualscale.engine import in_worker

    in_worker(threads)
    counts = None
    if sums and init is None and preset.coarse_factor <= 1:  # the start, and its albedo counts (.stream)
        init, counts = start_params(stride_leds(obs, preset.led_stride), comps)
    with warnings.catch_warnings():  # the driver checks the albedo range on the whole map
        warnings.filterwarnings("ignore", message=r".*Lambertian albedo", category=RuntimeWarning)
        res = fit_observations(obs, preset, comps, seed=seed, init=init, uncertainty=uncertainty)
    rec = {"maps": dict(res.maps.items()), "history": list(res.history), "pixels": obs.shape[0] * obs.shape[1],
           "uncertainty": uncertainty_record(res.uncertainty)}
    if sums:
        from .metrics import image_loss_sums

        rec["sums"] = image_loss_sums(res.maps, comps, stride_leds(obs, preset.led_stride))
        rec["albedo"] = counts
    return rec


def fit_tile_read(origin: DatasetOrigin, box: tuple[int, int, int, int], stride: int, whole: WholeMap | None,
                  preset: Preset, comps: Components, init: dict[str, Tensor] | None, seed: int,
                  threads: int, sums: bool = False, uncertainty: bool = False) -> dict[str, Any]:
    """The task when the worker reads its tile itself (module doc, "Data movement"): the
    ``box`` of the observations ``origin`` names (:func:`.observations.read_tile`), the same
    ``stride`` of LEDs the driver took (:func:`.core.stride_leds`) and, for the Adam presets, the
    whole map's sample counts ``whole``; then :func:`fit_tile`.  Raises ``FileNotFoundError``
    saying that the dataset must be on storage the workers share, when a worker cannot find it."""
    try:
        obs = stride_leds(read_tile(origin, box), stride)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{e} (a worker of a tiled fit reads its tile from the dataset {origin.root} itself: "
                                "it must be on storage the workers share, at the same path; docs/SCALE.md)") from None
    if whole is not None:
        obs = replace(obs, whole=whole)
    return fit_tile(obs, preset, comps, init, seed, threads, sums, uncertainty)


def _fingerprint(obs: Observations, preset: Preset, comps: Components, seed: int, tile: int) -> str:
    sample = obs.images.flatten()[:: max(1, obs.images.numel() // 4096)]
    valid = torch.zeros(1) if obs.valid is None else obs.valid.sum(dim=(1, 2))
    return fingerprint(kind="tiled fit", preset=asdict(preset), comps=asdict(comps), seed=seed, tile=tile,
                       ids=obs.led_ids, sample=sample, sums=obs.images.sum(dim=(1, 2, 3)), valid=valid,
                       shape=list(obs.shape), back=obs.backlight if obs.backlight is not None else torch.zeros(1))


def _tile_path(state: Path, box: tuple[int, int, int, int]) -> Path:
    return state / f"{box[0]:05d}_{box[2]:05d}.pt"


def _load_done(state: Path | None, key: str, boxes: list[tuple[int, int, int, int]],
               fields: tuple[str, ...] | None = None, need: str | None = None) -> dict[tuple, dict]:
    """The tiles (or bands) saved by an earlier run of the same fit, whole or only their
    ``fields``; a part of another fit is refused (:class:`~dualscale.errors.FormatError`).  A
    part without a ``need`` field (``"uncertainty"``: saved by a run without it) counts as not
    done: it is fitted again."""
    done: dict[tuple, dict] = {}
    if state is None or not state.is_dir():
        return done
    for box in boxes:
        p = _tile_path(state, box)
        if not p.is_file():
            continue
        rec = load_torch(p, "fit part", "delete the tiles folder or pass --restart", weights_only=False)
        if not isinstance(rec, dict) or rec.get("fingerprint") != key or tuple(rec.get("box", ())) != box:
            raise FormatError(f"{p}: a part of a different fit (data, preset, components, tile size or memory "
                              "budget changed); delete the folder or pass --restart")
        if need is not None and rec.get(need) is None:
            continue
        done[box] = rec if fields is None else {k: rec[k] for k in fields}
    return done


def _own(obs: Observations) -> Observations:
    """``obs`` with every per-pixel tensor copied into storage of its own: a crop is a view, and
    pickling a view ships its whole base storage (the whole map's images) with every task."""
    def own(t):
        return None if t is None else t.clone()

    return replace(obs, images=own(obs.images), backlight=own(obs.backlight), valid=own(obs.valid),
                   back_valid=own(obs.back_valid), view=own(obs.view))


def _crop_init(init: dict[str, Tensor] | None, box: tuple[int, int, int, int]) -> dict[str, Tensor] | None:
    if init is None:
        return None
    y0, y1, x0, x1 = box
    return {k: v[y0:y1, x0:x1].clone() for k, v in init.items()}


def _stitch_arrays(shape: tuple[int, int], parts: dict[tuple, dict[str, Tensor]]) -> dict[str, Tensor]:
    """``{name: (H, W, C)}`` from the parts' ``{name: (h, w, C)}`` at their boxes."""
    first = next(iter(parts.values()))
    full = {k: torch.empty((*shape, v.shape[-1]), dtype=v.dtype) for k, v in first.items()}
    for (y0, y1, x0, x1), arrays in parts.items():
        for k, v in arrays.items():
            full[k][y0:y1, x0:x1] = v
    return full


def _stitch(shape: tuple[int, int], parts: dict[tuple, dict]) -> MaterialMaps:
    return MaterialMaps(**_stitch_arrays(shape, {b: rec["maps"] for b, rec in parts.items()}))


def uncertainty_record(u: Uncertainty | None) -> dict[str, Any] | None:
    """A part's uncertainty as its record (and its saved state, ``state/*.pt``) carries it:
    ``{"sigma", "undetermined", "noise", "seconds"}`` (the :class:`.uncertainty.Uncertainty`'s
    fields, the part's own pixels: the parts do not overlap), ``None`` without one."""
    if u is None:
        return None
    return {"sigma": dict(u.sigma), "undetermined": dict(u.undetermined), "noise": u.noise, "seconds": u.seconds}


def stitch_uncertainty(shape: tuple[int, int], parts: dict[tuple, dict]) -> Uncertainty | None:
    """The whole map's :class:`.uncertainty.Uncertainty` from the parts' records
    (:func:`uncertainty_record`; pixels are independent, so it is the one-process fit's);
    ``seconds``: the parts' sum.  ``None`` when a part has none."""
    recs = [rec.get("uncertainty") for rec in parts.values()]
    if not recs or any(r is None for r in recs):
        return None
    return Uncertainty(_stitch_arrays(shape, {b: rec["uncertainty"]["sigma"] for b, rec in parts.items()}),
                       _stitch_arrays(shape, {b: rec["uncertainty"]["undetermined"] for b, rec in parts.items()}),
                       recs[0]["noise"], float(sum(r["seconds"] for r in recs)))


def _history(parts: dict[tuple, dict], mean_over_whole: bool) -> list[tuple[int, str, float]]:
    """Per iteration, the whole map's loss: the sum of the tiles' losses when each is already
    divided by the whole map's counts (Adam), else the pixel-weighted mean of their mean costs."""
    recs = list(parts.values())
    total = 1.0 if mean_over_whole else sum(r["pixels"] for r in recs)
    out = []
    for i, (done, step, _) in enumerate(recs[0]["history"]):
        out.append((done, step, sum(r["history"][i][2] * (1.0 if mean_over_whole else r["pixels"])
                                    for r in recs) / total))
    return out


def fit_tiled(obs: Observations, preset: Preset, comps: Components, client, *,
              held_out: Observations | None = None, tile: int = TILE, threads: int = 1, seed: int = 0,
              state: str | Path | None = None, progress: Progress = None,
              uncertainty: bool = False) -> tuple[FitResult, dict[str, Any]]:
    """:func:`.core.fit_observations` of ``obs`` with ``preset`` and ``comps``, as one Dask task
    per ``tile x tile`` pixel tile on ``client`` (a :class:`distributed.Client`), each worker
    using ``threads`` threads; ``state``: folder of the finished tiles (resuming: module doc);
    ``progress`` counts tiles; ``uncertainty``: each tile computes its pixels' uncertainty too,
    stitched into ``FitResult.uncertainty`` (a saved tile without one is fitted again).  Returns the :class:`.core.FitResult` of the whole map (its
    ``seconds`` is the wall time here) and a record for ``fit.json``: ``{"tile_px", "tiles",
    "resumed_tiles", "workers"}``.

    Raises :class:`~dualscale.errors.InputError` for a kernel other than the fused one
    (:func:`check_tileable`) or a bad tile side,
    :class:`~dualscale.errors.FormatError` for a saved tile of another fit; a
    task's own error is raised here as it was raised in the worker."""
    from dualscale.engine import bounded

    check_tileable(preset)
    t0 = time.perf_counter()
    boxes = tiles(obs.shape, tile)
    strided = stride_leds(obs, preset.led_stride)
    adam = preset.optimizer == "adam"
    if adam:  # each tile divides by the whole map's sample counts (module doc)
        strided = replace(strided, whole=WholeMap.of(strided))
    key = _fingerprint(strided, preset, comps, seed, tile)
    state = None if state is None else Path(state)
    parts = _load_done(state, key, boxes, need="uncertainty" if uncertainty else None)
    resumed = len(parts)
    init = coarse_start(strided, preset, comps, seed) if preset.coarse_factor > 1 and len(parts) < len(boxes) else None
    if preset.coarse_factor <= 1:  # else start_from_coarse ran the check already, on the whole map
        check_albedo_range(strided, photometric_stereo(strided)[1])
    todo = [b for b in boxes if b not in parts]
    n_workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
    # the tiles hold the strided LEDs already: fit_observations must not stride them again (with
    # 127 LEDs and draft's stride 2 it fitted 32 of the 64 in the tiles, 64 in one process)
    tile_preset = replace(preset, led_stride=1)

    # the workers read their tiles from the dataset themselves when the observations are still
    # what was read from it (module doc, "Data movement"); else each task carries its tile
    origin = obs.origin if obs.unchanged() else None

    def submit(box):
        y0, y1, x0, x1 = box
        task_key = f"dualscale-fit-tile-{key}-{y0}-{x0}{'-u' if uncertainty else ''}"
        if origin is not None:
            return client.submit(fit_tile_read, origin, box, preset.led_stride, strided.whole, tile_preset, comps,
                                 _crop_init(init, box), seed, threads, uncertainty=uncertainty, key=task_key,
                                 pure=False)
        return client.submit(fit_tile, _own(strided.crop(y0, y1, x0, x1)), tile_preset, comps, _crop_init(init, box),
                             seed, threads, uncertainty=uncertainty, key=task_key, pure=False)

    with tracker(progress, len(boxes), f"fit[{preset.name}] tiles", unit="tile") as bar, warnings.catch_warnings():
        # a task carries its tile's images on purpose (module doc: a lost worker's task can rerun)
        warnings.filterwarnings("ignore", message=r"Sending large graph", category=UserWarning)
        if resumed:  # the tiles saved by an earlier run count as done (all of them: the bar is full)
            bar.update(resumed, f"{resumed} tile(s) done before")
        for box, rec in bounded(client, todo, submit, INFLIGHT_PER_WORKER):
            rec["box"] = box
            if state is not None:
                save_torch(_tile_path(state, box), {**rec, "fingerprint": key})
            parts[box] = rec
            bar.update(1, f"tile {box[0]},{box[2]}")
    ordered = {b: parts[b] for b in boxes}
    maps = _stitch(obs.shape, ordered)
    res = FitResult(maps, comps, preset, preset.total, time.perf_counter() - t0,
                    fit_losses(maps, comps, strided, held_out), _history(ordered, adam),
                    uncertainty=stitch_uncertainty(obs.shape, ordered) if uncertainty else None)
    return res, {"tile_px": tile, "tiles": len(boxes), "resumed_tiles": resumed, "workers": n_workers,
                 "tile_data": ("read by the workers from " + origin.root) if origin is not None
                 else "sent with each task (the observations are not the dataset's as read)"}


def clear_state(state: str | Path) -> None:
    """Remove the finished tiles of a completed fit (and the folder when it is empty)."""
    state = Path(state)
    if not state.is_dir():
        return
    for p in state.glob("*.pt"):
        remove_file(p)
    try:
        state.rmdir()
    except OSError:
        pass
