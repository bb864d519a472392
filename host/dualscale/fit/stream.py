"""The fit out of core (issue 25 Sec. 1): a dataset larger than the memory budget is read from
disk a part at a time, and the maps are written by rows; the driver never holds the map.

The model has no spatial coupling (supplementary Sec. 4: each texel's SVBSDF is fitted to its
own pixel's observations), and the fused kernel fits a pixel to the same bits whatever the
region it sits in (:mod:`.tiled`), so a map can be fitted in any parts.  :func:`fit_parts`
cuts it into **bands** of full rows, as many rows as the budget allows
(:func:`band_boxes`; a scanline EXR reads a band's rows once), fitted one after the other in
this process, or into ``tile x tile`` **tiles** on a Dask cluster, each read by its worker
(:func:`.tiled.fit_tile_read`).  What is not per pixel is gathered in passes over the dataset,
band by band, before the fit (:func:`survey`, :func:`gather`; on a cluster each band is a task
that its worker reads, so the driver reads no pixel):

- the **survey** (one pass): the sample's pixels (``Observations.fitted_pixels``), each image's
  sum and valid-sample count (the Adam presets' whole-map counts, :class:`.observations.WholeMap`,
  and the resume fingerprint) and the back-lit statistics of the transmittance decision
  (:func:`.select.transmission_from`);
- the **gather** (one pass, only when a decision is still to make): the sample pixels of the
  component selection (:func:`.select.selection_pixels`) and of the cross-validation
  (:func:`.holdout.sample_pixels_of`), the very pixels the whole-map steps draw;
- the **fit** (one pass): each part's maps go to ``out/tiles/`` as they finish (a rerun
  resumes from them), its loss sums (:func:`.metrics.image_loss_sums`) add up to the report's
  losses and its start's bright-albedo counts (:func:`.init.start_params`, the photometric
  stereo the fit starts from) to the whole map's albedo check, warned about once after the
  fit; then the maps are written by rows (:func:`write_rows`), and so is their per-pixel
  uncertainty when the fit computes it (issue 26: each part's, saved with it,
  :func:`uncertainty_rows`).

**Same result.**  The maps equal the whole-map fit's bit for bit, and so do the component
decision, the cross-validation and the albedo check (the same pixels, the same counts).  The
report's ``train_l1`` and ``train_rmse`` are summed in float64 over the parts, where the
whole-map fit takes a float32 mean: they may differ in the last digits (measured in
``tests/fit/test_stream.py``: relative 1e-6 at most).  A preset with a coarse level
(``coarse-to-fine``) runs it band by band first (:mod:`.stream_coarse`, the same maps; refused
on a cluster over the budget), and ``--gt`` scores the maps by rows (:mod:`.score`).  Not out
of core: the in-band checkpoint (a part is the unit of resuming).

**Memory.**  A band holds ``rows x W`` pixels of every LED image, plus the fit's work:
:data:`BYTES_PER_SAMPLE` per pixel and image, measured on this machine (docs/SCALE.md), on top
of :data:`RESERVE` for the process itself.  :func:`band_boxes` sizes the bands so that the
estimate stays within the budget (``dualscale fit --memory``, :data:`DEFAULT_MEMORY`).
"""

from __future__ import annotations

import re
import resource
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from dualscale.bsdf import Components
from dualscale.errors import FormatError, InputError
from dualscale.formats.torchfile import load_torch, save_torch
from dualscale.progress import Progress, tracker

from .checkpoint import fingerprint
from .core import FitResult, fit_observations
from .init import start_params, warn_bright
from .metrics import image_loss_sums, losses_from_sums
from .observations import DatasetOrigin, Observations, WholeMap, read_tile, stride_leds
from .presets import Preset
from .select import TRANS_LEVEL, transmission_from
from .tiled import INFLIGHT_PER_WORKER, _tile_path, uncertainty_record

#: the default memory budget of a fit (``dualscale fit --memory``): a 512^2 map of 254 images
#: fits in four bands under it (docs/SCALE.md)
DEFAULT_MEMORY = 2 * 1024 ** 3
#: the fit's resident bytes per pixel and LED image: 85 measured (load + standard fit of
#: 64^2 .. 256^2 crops of a 254-image twill, docs/SCALE.md), with a margin
BYTES_PER_SAMPLE = 100
#: the process's resident memory before its first band (imports: 281 MB; fixed costs of a fit:
#: 124 MB; measured, docs/SCALE.md; the CLI with one-row bands held 500 MiB), with a margin
RESERVE = 512 * 1024 ** 2
#: the fewest pixels a part may hold (a 64^2 tile): below, the passes' per-part cost (opening every
#: image of the dataset) dominates (a 192^2 map in one-row bands took 16x as long)
MIN_PART_PIXELS = 4096
#: what a fitted part's record keeps in memory (its maps stay on disk)
RECORD = ("history", "pixels", "sums", "albedo")
#: back-lit pixels kept for the transmittance statistics' 99th percentile (all of them up to a
#: 2048^2 map; every k-th above)
P99_PIXELS = 1 << 22

_UNITS = {"": 1, "k": 1024, "m": 1024 ** 2, "g": 1024 ** 3, "t": 1024 ** 4}


def parse_memory(text: str | int | None) -> int | None:
    """Bytes of a memory budget: ``"2G"``, ``"1.5GiB"``, ``"800M"``, ``"64k"`` (binary units:
    K = 1024; ``GB`` and ``GiB`` alike), a plain number of bytes, or ``"unlimited"`` (``None``: the whole map in memory, as before issue 25).  Raises
    :class:`~dualscale.errors.InputError` for anything else, or a budget of zero."""
    if text is None or (isinstance(text, str) and text.strip().lower() in ("unlimited", "none")):
        return None
    if isinstance(text, int) and not isinstance(text, bool):
        value = text
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kmgt]?)(i?b)?\s*", str(text).lower())
        if m is None:
            raise InputError(f"--memory {text!r}: give a size such as 2G, 1.5GiB, 800M, or 'unlimited'")
        value = int(float(m.group(1)) * _UNITS[m.group(2)])
    if value <= 0:
        raise InputError(f"--memory {text!r}: the budget must be at least one byte (a plain number is bytes; "
                         "give a size such as 2G, 800M)")
    return value


def minimum_memory(images: int) -> int:
    """The smallest budget for a fit of ``images`` LED images: :data:`RESERVE` plus one part of
    :data:`MIN_PART_PIXELS` pixels."""
    return RESERVE + MIN_PART_PIXELS * max(1, images) * BYTES_PER_SAMPLE


def check_memory(memory: int | None, images: int) -> None:
    """Raise :class:`~dualscale.errors.InputError` when ``memory`` (bytes; ``None``: unlimited)
    is below :func:`minimum_memory` for ``images`` LED images (checked before any work)."""
    if memory is not None and memory < minimum_memory(images):
        raise InputError(f"--memory {memory_text(memory)} is below what a fit of {images} images needs: "
                         f"{memory_text(minimum_memory(images))} at least (the process's {memory_text(RESERVE)} and a part of "
                         f"{MIN_PART_PIXELS} pixels at {BYTES_PER_SAMPLE * max(1, images) / 2 ** 10:.0f} KiB each); "
                         "give more, e.g. --memory 2G")


def memory_text(n: float) -> str:
    """``n`` bytes as the messages give a memory size: GiB (3 digits), MiB, KiB or bytes."""
    if n >= 2 ** 30:
        return f"{n / 2 ** 30:.3g} GiB"
    return f"{n / 2 ** 20:.0f} MiB" if n >= 2 ** 20 else f"{n / 2 ** 10:.1f} KiB" if n >= 1024 else f"{n:.0f} bytes"


def band_boxes(shape: tuple[int, int], images: int, memory: int | None,
               multiple: int = 1) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` parts of a ``(H, W)`` map of ``images`` LED images whose estimated
    fit stays within ``memory`` bytes (module doc): bands of full rows, their height rounded
    down to a multiple of 64 (or 16) rows, the EXR chunks' heights, when there are that many,
    and to a multiple of ``multiple`` (a coarse level's factor: :mod:`.stream_coarse`); a
    single row split into runs of columns when even one row is over the budget (not with a
    ``multiple``: refused).  ``memory`` ``None``: one part, the whole map.  Raises
    :class:`~dualscale.errors.InputError` when the budget is below :func:`minimum_memory`, or
    holds fewer than ``multiple`` rows."""
    h, w = shape
    if memory is None:
        return [(0, h, 0, w)]
    check_memory(memory, images)
    pixels = (memory - RESERVE) // (max(1, images) * BYTES_PER_SAMPLE)
    if pixels >= h * w:
        return [(0, h, 0, w)]
    rows = pixels // w
    if multiple > 1 and rows < multiple:
        need = RESERVE + multiple * w * max(1, images) * BYTES_PER_SAMPLE
        raise InputError(f"--memory {memory_text(memory)} holds {rows} row(s) of this {h} x {w} map; a coarse level "
                         f"of {multiple} x {multiple} blocks fits bands of {multiple} rows at least: give "
                         f"--memory {memory_text(need)} or more")
    if rows >= 1:
        for align in (64, 16):
            if rows >= align:
                rows -= rows % align
                break
        rows -= rows % multiple
        return [(y, min(y + rows, h), 0, w) for y in range(0, h, rows)]
    cols = int(pixels)
    return [(y, y + 1, x, min(x + cols, w)) for y in range(h) for x in range(0, w, cols)]


@dataclass
class Survey:
    """What the whole-map steps need of a map, gathered band by band (:func:`survey`).

    ``head``: the observations' lights, weights and flags with no pixel (``N x 1 x 0``);
    ``shape``: ``(H, W)``; ``fitted``: ``(H, W)`` bool, the sample's pixels (``None``: every
    pixel, no valid-sample mask); ``sums`` ``(N,)`` float64 per image; ``counts`` ``(N,)``
    float64 valid samples per image (``None``: all); ``back``: valid back-lit pixels (``None``:
    all, or no back-lit image); ``transmission``: :func:`.select.transmission_evidence`;
    ``key``: a SHA-256 of it all
    (the resume fingerprint's data part); ``seconds``: the pass's wall time."""

    head: Observations
    shape: tuple[int, int]
    fitted: Tensor | None
    sums: Tensor
    counts: Tensor | None
    back: float | None
    transmission: dict[str, Any]
    key: str
    seconds: float

    @property
    def whole(self) -> WholeMap:
        """The whole map's sample counts (the Adam presets' loss divides by them)."""
        return WholeMap(self.shape[0] * self.shape[1], self.counts, self.back)


Reader = Callable[[tuple[int, int, int, int]], Observations]


def survey_part(o: Observations, box: tuple[int, int, int, int], shape: tuple[int, int]) -> dict[str, Any]:
    """The statistics :func:`survey` takes of one part ``o``, the ``box`` of the ``(H, W)`` map
    (a plain dict of small tensors and numbers: what a survey task returns)."""
    y0, y1, x0, x1 = box
    w = shape[1]
    step = max(1, (shape[0] * w) // P99_PIXELS)
    rec: dict[str, Any] = {"box": box, "head": o.pixels(torch.zeros(0, dtype=torch.long)),
                           "sums": o.images.to(torch.float64).sum(dim=(1, 2, 3)),
                           "counts": None if o.valid is None else o.valid.sum(dim=(1, 2)).to(torch.float64),
                           "fitted": o.fitted_pixels,
                           "back": None if o.back_valid is None else float(o.back_valid.sum()),
                           "y": None}
    if o.backlight is not None:
        y = (o.backlight / o.back_wd).mean(-1)
        flat = (torch.arange(y0, y1).reshape(-1, 1) * w + torch.arange(x0, x1).reshape(1, -1)).reshape(-1)
        rec["y"] = (int((y > TRANS_LEVEL).sum()), float(y.to(torch.float64).sum()), y.numel(),
                    y.reshape(-1)[flat % step == 0].to(torch.float64))
    return rec


def survey_task(origin: DatasetOrigin, box: tuple[int, int, int, int], shape: tuple[int, int],
                threads: int) -> dict[str, Any]:
    """:func:`survey_part` of the ``box`` a worker reads itself from ``origin`` (a Dask task)."""
    from dualscale.engine import in_worker

    in_worker(threads)
    return survey_part(read_tile(origin, box), box, shape)


def _parts(read: Reader, boxes, client, task, args: tuple, threads: int, bar, origin) -> Any:
    """Yield ``(box, result)`` of ``task`` (:func:`survey_part`) over ``boxes``: in this process
    on ``read(box)``, or as Dask tasks on ``client`` (:func:`survey_task`, each worker reading
    its part from ``origin``), at most two per worker in flight, in the order they finish."""
    if client is None:
        for box in boxes:
            yield box, task(read(box), box, *args)
            release_memory()
            bar.update(1)
        return
    from dualscale.engine import bounded

    def submit(box):
        return client.submit(survey_task, origin, box, *args, threads, pure=False)

    for box, res in bounded(client, boxes, submit, INFLIGHT_PER_WORKER):
        yield box, res
        bar.update(1)


def survey(read: Reader, boxes: list[tuple[int, int, int, int]], shape: tuple[int, int],
           progress: Progress = None, client=None, origin: DatasetOrigin | None = None,
           threads: int = 1) -> Survey:
    """One pass over the parts ``boxes`` of the map, each read by ``read`` in this process, or
    by a worker of the Dask ``client`` from ``origin`` (module doc): the :class:`Survey`.  The
    parts' statistics are added in box order, so the result does not depend on where they ran."""
    t0 = time.perf_counter()
    recs: dict[tuple, dict[str, Any]] = {}
    with tracker(progress, len(boxes), "survey", unit="band" if client is None else "tile") as bar:
        for box, rec in _parts(read, boxes, client, survey_part, (shape,), threads, bar, origin):
            recs[box] = rec
    first = recs[boxes[0]]
    head = first["head"]
    sums = torch.zeros_like(first["sums"])
    counts = None if first["counts"] is None else torch.zeros_like(first["counts"])
    fitted = None if first["fitted"] is None else torch.zeros(shape, dtype=torch.bool)
    back = None
    y_above, y_sum, y_n, y_keep = 0, 0.0, 0, []
    for box in boxes:
        rec = recs.pop(box)
        y0, y1, x0, x1 = box
        sums += rec["sums"]
        if counts is not None:
            counts += rec["counts"]
            fitted[y0:y1, x0:x1] = rec["fitted"]
        if rec["back"] is not None:
            back = (back or 0.0) + rec["back"]
        if rec["y"] is not None:
            y_above, y_sum, y_n = y_above + rec["y"][0], y_sum + rec["y"][1], y_n + rec["y"][2]
            y_keep.append(rec["y"][3])
    trans = {"backlit_capture": False, "transmits": False}
    if y_n:
        trans = transmission_from(y_above / y_n, y_sum / y_n, float(torch.quantile(torch.cat(y_keep), 0.99)))
    key = fingerprint(kind="survey", shape=list(shape), ids=head.led_ids, dirs=head.dirs, ws=head.w_s, wp=head.w_p,
                      wd=head.w_d, sums=sums, counts=torch.zeros(0) if counts is None else counts,
                      fitted=torch.zeros(0) if fitted is None else fitted.sum(dim=0), back=back or 0.0,
                      trans=trans, px=head.pixel_mm, imported=head.imported)
    return Survey(head, shape, fitted, sums, counts, back, trans, key, time.perf_counter() - t0)


def gather_part(o: Observations, box: tuple[int, int, int, int], locals_: list[Tensor]) -> list[Observations]:
    """The pixels ``locals_`` (flat indices within the part, one tensor per sample) of the part
    ``o``, each as a ``1 x M`` image."""
    return [o.pixels(local) for local in locals_]


def gather_task(origin: DatasetOrigin, box: tuple[int, int, int, int], locals_: list[Tensor],
                threads: int) -> list[Observations]:
    """:func:`gather_part` of the ``box`` a worker reads itself from ``origin`` (a Dask task)."""
    from dualscale.engine import in_worker

    in_worker(threads)
    return gather_part(read_tile(origin, box), box, locals_)


def gather(read: Reader, boxes: list[tuple[int, int, int, int]], shape: tuple[int, int],
           flats: list[Tensor], client=None, origin: DatasetOrigin | None = None,
           threads: int = 1) -> list[Observations]:
    """One pass: for each sorted flat-index set of ``flats``, the observations of those pixels
    laid out as a ``1 x M`` image, in index order: what ``whole.pixels(flat)`` gives, read part
    by part (in this process, or by the workers of ``client`` as in :func:`survey`); parts
    holding none of the pixels are not read."""
    w = shape[1]
    pieces: list[list[tuple[Tensor, Observations]]] = [[] for _ in flats]
    wanted: dict[tuple, list[tuple[Tensor, Tensor]]] = {}
    for box in boxes:
        y0, y1, x0, x1 = box
        sel = []
        for flat in flats:
            y, x = flat // w, flat % w
            inside = (y >= y0) & (y < y1) & (x >= x0) & (x < x1)
            sel.append((torch.nonzero(inside).flatten(), (y[inside] - y0) * (x1 - x0) + (x[inside] - x0)))
        if any(pos.numel() for pos, _ in sel):
            wanted[box] = sel
    todo = list(wanted)

    def per_box(o, box, *_):  # in this process: the box's own local indices
        return gather_part(o, box, [local for _, local in wanted[box]])

    def here(b):
        got = per_box(read(b), b)
        release_memory()
        return b, got

    if client is None:
        results = (here(b) for b in todo)
    else:
        results = _gathered_remote(client, todo, wanted, origin, threads)
    for box, got in results:
        for k, ((pos, _), obs) in enumerate(zip(wanted[box], got)):
            if pos.numel():
                pieces[k].append((pos, obs))
    return [_join(p) for p in pieces]


def _gathered_remote(client, todo, wanted, origin, threads):
    from dualscale.engine import bounded

    def submit(box):
        return client.submit(gather_task, origin, box, [local for _, local in wanted[box]], threads, pure=False)

    yield from bounded(client, todo, submit, INFLIGHT_PER_WORKER)


def _join(pieces: list[tuple[Tensor, Observations]]) -> Observations:
    """``1 x M`` pixel rows ``(positions, rows)`` joined into one, ordered by position."""
    pos = torch.cat([p for p, _ in pieces])
    order = torch.argsort(pos)
    first = pieces[0][1]

    def cat(name: str, dim: int) -> Tensor | None:
        parts = [getattr(o, name) for _, o in pieces]
        return None if parts[0] is None else torch.cat(parts, dim).index_select(dim, order)

    view = cat("view", 1) if first.view.ndim == 3 else first.view
    return replace(first, images=cat("images", 2), valid=cat("valid", 2), backlight=cat("backlight", 1),
                   back_valid=cat("back_valid", 1), view=view)


def _done(state: Path, key: str, boxes: list[tuple[int, int, int, int]], uncertainty: bool) -> dict[tuple, dict]:
    """The parts an earlier run of the same fit saved, without their maps (those stay on disk);
    with ``uncertainty``, only those that carry it."""
    from .tiled import _load_done

    return _load_done(state, key, boxes, RECORD, need="uncertainty" if uncertainty else None)


@dataclass
class Parts:
    """The fitted parts of a map (:func:`fit_parts`): their boxes, their records without maps
    (:data:`RECORD`: loss history, pixels, loss sums, albedo counts), the folder their maps are
    in, how many an earlier run
    had finished, and the fit's wall time."""

    boxes: list[tuple[int, int, int, int]]
    records: dict[tuple, dict]
    state: Path
    resumed: int
    seconds: float
    workers: int | None = None
    unit: str = "band"

    @property
    def albedo_share(self) -> float:
        """The share of the sample's pixels with a start albedo >= 1 (:func:`.init.albedo_counts`
        summed over the parts)."""
        bright = sum(r["albedo"][0] for r in self.records.values())
        counted = sum(r["albedo"][1] for r in self.records.values())
        return bright / counted if counted else 0.0

    def losses(self) -> dict[str, float]:
        """The whole map's ``train_l1`` and ``train_rmse`` from the parts' sums."""
        a = sum(r["sums"][0] for r in self.records.values())
        q = sum(r["sums"][1] for r in self.records.values())
        n = sum(r["sums"][2] for r in self.records.values())
        return {f"train_{k}": v for k, v in losses_from_sums(a, q, n).items()}


def fit_parts(read: Reader, origin: DatasetOrigin, sv: Survey, preset: Preset, comps: Components, *,
              memory: int | None, state: Path, seed: int = 0, client=None, tile: int = 64, threads: int = 1,
              progress: Progress = None, uncertainty: bool = False) -> Parts:
    """Fit the map part by part (module doc): in this process, the bands of
    :func:`band_boxes` within ``memory`` (each read by ``read``), or on the Dask ``client``,
    ``tile x tile`` tiles each read by its worker from ``origin``
    (:func:`.tiled.fit_tile_read`).  Each finished part is saved in ``state`` (the maps, its
    loss history, pixels and loss sums, with the fit's fingerprint); parts already there from
    an earlier run of the same fit are not fitted again.  ``uncertainty``: each part computes
    its pixels' uncertainty too, saved with it (:func:`.tiled.uncertainty_record`; written by
    rows, :func:`uncertainty_rows`); a part saved without one is then fitted again.  A preset
    with a coarse level runs it band by band first (:mod:`.stream_coarse`; the bands' height a
    multiple of its factor; on a cluster too, in bands of the budget, :data:`DEFAULT_MEMORY`
    when unlimited).  Raises :class:`~dualscale.errors.InputError` for a budget under the
    factor's rows and :class:`~dualscale.errors.FormatError` for a saved part of another fit."""
    from .tiled import check_tileable, tiles

    from .stream_coarse import bands_on_cluster, coarse_pass, start_of

    t0 = time.perf_counter()
    adam = preset.optimizer == "adam"
    whole = sv.whole
    if client is not None:
        check_tileable(preset)
    coarse_level = preset.coarse_factor > 1
    if client is None or coarse_level:  # a coarse level runs in bands on a cluster too (.stream_coarse)
        budget = memory if client is None or memory is not None else DEFAULT_MEMORY
        boxes = band_boxes(sv.shape, sv.head.n, budget, preset.coarse_factor)
        kind = {"kind": "bands", "memory": budget}
    else:
        boxes = tiles(sv.shape, tile)
        kind = {"kind": "tiles", "tile": tile}
    key = fingerprint(part="fit part", preset=repr(preset), comps=repr(comps), seed=seed, data=sv.key, **kind)
    state.mkdir(parents=True, exist_ok=True)
    records = _done(state, key, boxes, uncertainty)
    resumed = len(records)
    todo = [b for b in boxes if b not in records]

    def finish(box, rec) -> None:
        save_torch(_tile_path(state, box), {**rec, "box": box, "fingerprint": key})
        records[box] = {k: rec[k] for k in RECORD}

    unit = "tile" if client is not None and not coarse_level else "band"
    workers = None
    coarse = None
    if coarse_level and todo:  # the coarse level, band by band (.stream_coarse)
        coarse = coarse_pass(read, boxes, todo, preset, comps, seed, state, key, sv.shape, progress, release_memory,
                             client, origin, threads)
    with tracker(progress, len(boxes), f"fit[{preset.name}] {unit}s", unit=unit) as bar:
        if resumed:
            bar.update(resumed, f"{resumed} {unit}(s) done before")
        if client is None:
            for box in todo:
                band = read(box)
                if adam:
                    band = replace(band, whole=whole)
                # the start of the whole-map fit, and its albedo counts (the map's share is warned about once)
                fitted = stride_leds(band, preset.led_stride)
                init, counts = start_params(fitted, comps)
                init = start_of(fitted, box, coarse, preset, comps, init)
                res = fit_observations(band, preset, comps, seed=seed, init=init, uncertainty=uncertainty)
                finish(box, {"maps": dict(res.maps.items()), "history": list(res.history),
                             "uncertainty": uncertainty_record(res.uncertainty),
                             "pixels": band.shape[0] * band.shape[1], "albedo": counts,
                             "sums": image_loss_sums(res.maps, comps, fitted)})
                del band, res, fitted, init
                release_memory()
                bar.update(1, f"rows {box[0]}..{box[1] - 1}")
        elif coarse is not None:
            workers = bands_on_cluster(client, todo, origin, coarse, preset, comps, seed, threads, finish, bar,
                                       uncertainty)
        else:
            workers = _on_cluster(client, todo, origin, sv, preset, comps, seed, threads, finish, bar, uncertainty)
    if client is not None and workers is None:  # every part done before
        workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
    return Parts(boxes, records, state, resumed, time.perf_counter() - t0, workers, unit)


def _on_cluster(client, todo, origin, sv: Survey, preset: Preset, comps: Components, seed: int, threads: int,
                finish, bar, uncertainty: bool = False) -> int:
    """The tiles ``todo`` as Dask tasks, at most :data:`.tiled.INFLIGHT_PER_WORKER` per worker
    in flight, each read by its worker; returns the number of workers."""
    from dualscale.engine import bounded

    from .tiled import fit_tile_read

    n_workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
    whole = None
    if preset.optimizer == "adam":  # the whole map's counts of the fitted (strided) images
        whole = stride_leds(replace(sv.head, whole=sv.whole), preset.led_stride).whole
    tile_preset = replace(preset, led_stride=1)  # the task strides the LEDs as it reads them

    def submit(box):
        return client.submit(fit_tile_read, origin, box, preset.led_stride, whole, tile_preset, comps, None, seed,
                             threads, True, uncertainty,
                             key=f"dualscale-fit-part-{sv.key[:16]}-{box[0]}-{box[2]}{'-u' if uncertainty else ''}",
                             pure=False)

    for box, rec in bounded(client, todo, submit, INFLIGHT_PER_WORKER):
        finish(box, rec)
        del rec
        bar.update(1, f"tile {box[0]},{box[2]}")
    return n_workers


def _part_rows(parts: Parts, pick: Callable[[dict], Any]):
    """Yield ``(y0, [pick(record) of each part of that row of parts, left to right])``, each row
    of parts read back from its files in turn (one row of parts in memory at a time)."""
    rows: dict[tuple[int, int], list[tuple[int, int, int, int]]] = {}
    for box in parts.boxes:
        rows.setdefault((box[0], box[1]), []).append(box)
    for (y0, _), boxes in sorted(rows.items()):
        yield y0, [pick(load_torch(_tile_path(parts.state, b), "fit part", "pass --restart", weights_only=False))
                   for b in sorted(boxes, key=lambda b: b[2])]


def _first(parts: Parts) -> dict[str, Any]:
    return load_torch(_tile_path(parts.state, parts.boxes[0]), "fit part", "pass --restart", weights_only=False)


def write_rows(parts: Parts) -> tuple[list[str], Any]:
    """``(names, rows)``: the maps' names and an iterator of ``(y0, {name: (n, W, C) float32})``
    row strips, read back from the parts' files one row of parts at a time (what
    :class:`~dualscale.formats.maps.MapsWriter` writes)."""
    names = list(_first(parts)["maps"])

    def strips():
        for y0, maps in _part_rows(parts, lambda rec: rec["maps"]):
            yield y0, {n: torch.cat([m[n] for m in maps], dim=1).numpy() for n in names}

    return names, strips()


@dataclass
class UncertaintyRows:
    """The uncertainty of a fit out of core, by rows (:func:`uncertainty_rows`): the maps'
    ``names``, the ``noise`` scale, the parts' summed ``seconds`` (once ``strips`` are read) and
    ``strips``, an iterator of
    ``(y0, sigma {name: (n, W, C) float32}, undetermined {name: (n, W, C) bool})`` (what
    :class:`~dualscale.formats.maps.UncertaintyWriter` writes)."""

    names: list[str]
    noise: str
    seconds: float
    strips: Any


def uncertainty_rows(parts: Parts) -> UncertaintyRows | None:
    """The parts' saved uncertainty as :class:`UncertaintyRows`, read back one row of parts at a
    time like :func:`write_rows`; ``None`` when the parts carry none (fitted without it)."""
    first = _first(parts).get("uncertainty")
    if first is None:
        return None
    out = UncertaintyRows(list(first["sigma"]), first["noise"], 0.0, None)

    def strips():
        for y0, recs in _part_rows(parts, lambda rec: rec["uncertainty"]):
            out.seconds += sum(r["seconds"] for r in recs)  # complete once every strip was read
            yield y0, *({n: torch.cat([r[kind][n] for r in recs], dim=1).numpy() for n in out.names}
                        for kind in ("sigma", "undetermined"))

    out.strips = strips()
    return out


def release_memory() -> None:
    """Hand the heap a part freed back to the system (glibc ``malloc_trim``): without it the
    freed temporaries of one band stay in the process, fragmented, and the peak crept up with the
    number of bands (2.11 GB over 4 bands at 512^2, 2.33 GB over 16 at 1024^2, the same band
    size).  A no-op where there is no glibc."""
    import ctypes
    import ctypes.util

    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MiB (``getrusage``: Linux reports kiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def warn_albedo(parts: "Parts", imported: bool) -> None:
    """The bright-albedo warning of :func:`.init.check_albedo_range`, for the whole map (its
    parts' counts summed)."""
    warn_bright(parts.albedo_share, imported)


def result(parts: Parts, preset: Preset, comps: Components) -> FitResult:
    """The :class:`.core.FitResult` of a fit out of core: no maps (``maps`` is ``None``: they are
    on disk), the losses and history assembled from the parts'."""
    from .tiled import _history

    ordered = {b: parts.records[b] for b in parts.boxes}
    return FitResult(None, comps, preset, preset.total, parts.seconds, parts.losses(),  # type: ignore[arg-type]
                     _history(ordered, preset.optimizer == "adam"))


def reader(origin: DatasetOrigin) -> Reader:
    """The part reader of a dataset (:func:`.observations.read_tile`)."""
    return lambda box: read_tile(origin, box)


def estimate_bytes(shape: tuple[int, int], images: int) -> int:
    """The estimated peak of a whole-map fit of a ``(H, W)`` map of ``images`` LED images (the
    module doc's model)."""
    return RESERVE + shape[0] * shape[1] * max(1, images) * BYTES_PER_SAMPLE


def memory_record(memory: int | None, parts: Parts, passes: dict[str, float], shape: tuple[int, int],
                  images: int) -> dict[str, Any]:
    """``fit.json``'s ``out_of_core`` record: the budget, the whole map's estimated need, the
    parts (``bands`` of ``part_rows`` rows fitted here, or ``tiles`` on a cluster), the passes'
    times, and this process's peak resident memory in MiB (the driver's, on a cluster); a coarse
    level on a cluster runs in ``bands`` too (:mod:`.stream_coarse`)."""
    b = parts.boxes[0]
    return {"memory_bytes": memory, "estimate_bytes": estimate_bytes(shape, images),
            "part_kind": parts.unit + "s", "parts": len(parts.boxes),
            "part_rows": b[1] - b[0], "part_columns": b[3] - b[2], "resumed_parts": parts.resumed,
            "workers": parts.workers, "pass_seconds": passes, "peak_rss_mib": round(peak_rss_mb(), 1)}


__all__ = ["DEFAULT_MEMORY", "BYTES_PER_SAMPLE", "RESERVE", "parse_memory", "band_boxes", "Survey", "survey",
           "gather", "survey_part", "survey_task", "gather_part", "gather_task", "Parts", "fit_parts", "write_rows", "uncertainty_rows", "UncertaintyRows", "result", "reader", "peak_rss_mb", "release_memory", "warn_albedo",
           "memory_record", "memory_text", "estimate_bytes", "minimum_memory", "check_memory", "MIN_PART_PIXELS"]
