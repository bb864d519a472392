"""The coarse level of a preset (``coarse_factor`` f > 1, :mod:`.pyramid`) in the fit out of
core (:mod:`.stream`): the whole map's coarse-to-fine maps, bit for bit, without the map.

In memory, the coarse level fits the box-downsampled observations (``f x f`` blocks,
:func:`.pyramid.downsample`) of the whole map, and the full-resolution fit starts from its maps,
upsampled (:func:`.pyramid.start_from_coarse`).  Both steps are per pixel but for the
upsampling's reach, so out of core they run on bands of full rows whose height is a multiple of
``f`` (:func:`.stream.band_boxes` with ``multiple=f``: every block lies whole in one band; the
bands' 64- or 16-row rounding, the EXR chunks' heights, is already a multiple of ``f = 2``):

1. **coarse pass** (:func:`coarse_pass`, one more pass over the dataset): each band is read,
   strided to the preset's LEDs, downsampled and fitted with the coarse preset
   (:func:`.pyramid.coarse_preset`); its coarse maps (``1/f^2`` of the band's pixels) are saved
   to ``out/tiles/coarse_<row>.pt``, where a rerun of the same fit (same data, preset,
   components, seed and budget) finds and reuses them.  A coarse pixel's fit is that of the
   whole downsampled map (the fused kernel fits a pixel to the same bits in any region), and a
   block's mean is the same in a band as in the map (the same ``f x f`` pixels, the bottom
   edge's short blocks included, ``ceil_mode``);
2. **fine start** (:func:`CoarseMaps.crop`): each band's start reads the coarse rows of its own
   blocks and one coarse row above and below (:func:`.pyramid.coarse_rows`: the bilinear corners
   and nearest cells of its pixels), loaded from the saved files; its photometric-stereo part
   and albedo counts are the band's own (:func:`.init.start_params`).

The maps equal the in-memory ``coarse-to-fine`` fit's bit for bit (``tests/fit/test_stream.py``).
The one difference: the coarse level's own bright-albedo warning (on the downsampled map, in
memory) is not given; the full-resolution one, on the whole map's counts, is.  Memory: a band's
fit within the budget as for ``standard``, plus the coarse maps of three bands.

**On a Dask cluster** over the budget the same two passes run as tasks on bands (not
``--tile-px`` tiles: a band spans the full width, so only rows need a halo), each worker reading
its band from the dataset (:func:`coarse_task`, :func:`fine_task`); the driver saves the coarse
maps and sends each fine band its coarse rows (``1/f^2`` of the band's pixels, a few maps), no
observation.  (Within the budget, a cluster keeps the whole-map coarse start of
:func:`.tiled.fit_tiled`: the driver holds the map.)
"""

from __future__ import annotations

import warnings
from pathlib import Path
from dataclasses import replace
from typing import Any, Callable

import torch
from torch import Tensor

from dualscale.bsdf import Components, MaterialMaps
from dualscale.errors import FormatError
from dualscale.formats.torchfile import load_torch, save_torch
from dualscale.progress import Progress, tracker

from .checkpoint import fingerprint
from .core import fit_observations
from .observations import DatasetOrigin, Observations, read_tile, stride_leds
from .presets import Preset
from .pyramid import coarse_preset, coarse_rows, downsample


def coarse_path(state: Path, box: tuple[int, int, int, int]) -> Path:
    """The file of the coarse maps of the band ``box`` in the fit's ``state`` folder."""
    return state / f"coarse_{box[0]:05d}.pt"


def coarse_part(o: Observations, box: tuple[int, int, int, int], preset: Preset, comps: Components,
                seed: int) -> dict[str, Tensor]:
    """The coarse maps ``{name: (ceil(rows / f), ceil(W / f), C) float32}`` of the band ``o`` (the
    map's rows ``box[0] .. box[1] - 1``, all columns; ``box[0]`` a multiple of ``f``): its LEDs
    strided, downsampled, fitted with :func:`.pyramid.coarse_preset` (the albedo warning left to
    the whole map's check)."""
    f = preset.coarse_factor
    if box[0] % f or box[2] != 0:
        raise ValueError(f"band {box}: a coarse band starts at a multiple of {f} rows and spans all columns")
    small = downsample(stride_leds(o, preset.led_stride), f)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*Lambertian albedo", category=RuntimeWarning)
        res = fit_observations(small, coarse_preset(preset), comps, seed=seed, uncertainty=False)
    return dict(res.maps.items())


class CoarseMaps:
    """The saved coarse maps of a fit out of core, one file per band (:func:`coarse_pass`),
    read back as a band asks for them (at most the files of its rows and halo stay loaded)."""

    def __init__(self, state: Path, boxes: list[tuple[int, int, int, int]], factor: int, key: str,
                 shape: tuple[int, int]) -> None:
        self.state, self.boxes, self.f, self.key = state, boxes, factor, key
        self.coarse_h = -(-shape[0] // factor)
        self._held: dict[tuple, dict[str, Tensor]] = {}

    def rows_of(self, box: tuple[int, int, int, int]) -> tuple[int, int]:
        """The coarse rows ``(c0, c1)`` of the band ``box``'s own blocks."""
        return box[0] // self.f, -(-box[1] // self.f)

    def load(self, box: tuple[int, int, int, int]) -> dict[str, Tensor] | None:
        """The saved coarse maps of ``box``, ``None`` when there are none; a file of another fit
        is refused (:class:`~dualscale.errors.FormatError`)."""
        p = coarse_path(self.state, box)
        if not p.is_file():
            return None
        rec = load_torch(p, "coarse maps", "delete the tiles folder or pass --restart", weights_only=False)
        if not isinstance(rec, dict) or rec.get("fingerprint") != self.key or tuple(rec.get("box", ())) != box:
            raise FormatError(f"{p}: the coarse maps of a different fit (data, preset, components or memory budget "
                              "changed); delete the folder or pass --restart")
        return rec["maps"]

    def crop(self, box: tuple[int, int, int, int]) -> tuple[dict[str, Tensor], int]:
        """``(maps, c0)``: the coarse rows ``c0 ..`` that the fine band ``box`` reads
        (:func:`.pyramid.coarse_rows`), joined from the saved bands."""
        c0, c1 = coarse_rows(box[0], box[1], self.f, self.coarse_h)
        pieces = []
        for b in self.boxes:
            b0, b1 = self.rows_of(b)
            if b1 <= c0 or b0 >= c1:
                self._held.pop(b, None)
                continue
            if b not in self._held:
                maps = self.load(b)
                if maps is None:
                    raise FormatError(f"{coarse_path(self.state, b)}: the coarse maps are missing; pass --restart")
                self._held[b] = maps
            lo, hi = max(c0, b0) - b0, min(c1, b1) - b0
            pieces.append({k: v[lo:hi] for k, v in self._held[b].items()})
        return {k: torch.cat([p[k] for p in pieces], 0) for k in pieces[0]}, c0


def coarse_task(origin: DatasetOrigin, box: tuple[int, int, int, int], preset: Preset, comps: Components,
                seed: int, threads: int) -> dict[str, Tensor]:
    """:func:`coarse_part` of the band ``box`` a worker reads itself from ``origin`` (a Dask task)."""
    from dualscale.engine import in_worker

    in_worker(threads)
    return coarse_part(read_tile(origin, box), box, preset, comps, seed)


def coarse_pass(read: Callable[[tuple], Observations], boxes: list[tuple[int, int, int, int]], todo: list[tuple],
                preset: Preset, comps: Components, seed: int, state: Path, key: str, shape: tuple[int, int],
                progress: Progress = None, release: Callable[[], None] = lambda: None, client=None,
                origin: DatasetOrigin | None = None, threads: int = 1) -> CoarseMaps:
    """The coarse level of the bands ``boxes`` (module doc): the bands that the fine bands
    ``todo`` read (their own and their neighbours), each fitted and saved unless an earlier run
    of the same fit (``key``) saved it, here (each band read by ``read``) or on the Dask
    ``client`` (each band read by its worker from ``origin``, :func:`coarse_task`); returns the
    :class:`CoarseMaps` to start from."""
    maps = CoarseMaps(state, boxes, preset.coarse_factor, fingerprint(part="coarse", fit=key), shape)
    need = set()
    for k, b in enumerate(boxes):
        if b in todo:
            need.update(boxes[max(0, k - 1):k + 2])
    wanted = [b for b in boxes if b in need and maps.load(b) is None]
    if client is None:
        results = ((b, coarse_part(read(b), b, preset, comps, seed)) for b in wanted)
    else:
        from dualscale.engine import bounded

        from .tiled import INFLIGHT_PER_WORKER

        results = bounded(client, wanted, lambda b: client.submit(coarse_task, origin, b, preset, comps, seed, threads,
                                                                 pure=False), INFLIGHT_PER_WORKER)
    with tracker(progress, len(wanted), f"fit[{preset.name}] coarse bands", unit="band") as bar:
        for b, got in results:
            save_torch(coarse_path(state, b), {"maps": got, "box": b, "fingerprint": maps.key})
            del got
            release()
            bar.update(1, f"rows {b[0]}..{b[1] - 1}")
    return maps


def fine_task(origin: DatasetOrigin, box: tuple[int, int, int, int], preset: Preset, comps: Components,
              crop: dict[str, Tensor], c0: int, seed: int, threads: int, uncertainty: bool) -> dict[str, Any]:
    """A fine band on a Dask worker: the ``box`` it reads itself from ``origin``, strided to the
    preset's LEDs, started from its coarse rows ``crop`` (from row ``c0``, :meth:`CoarseMaps.crop`)
    and fitted (:func:`.tiled.fit_tile`, with its loss sums and its start's albedo counts)."""
    from dualscale.engine import in_worker

    from .init import start_params
    from .pyramid import start_from_coarse
    from .tiled import fit_tile

    in_worker(threads)
    band = stride_leds(read_tile(origin, box), preset.led_stride)
    base, counts = start_params(band, comps)
    init = start_from_coarse(MaterialMaps(**crop), band, preset, comps, rows=(box[0], c0), base=base)
    rec = fit_tile(band, replace(preset, led_stride=1), comps, init, seed, threads, sums=True, uncertainty=uncertainty)
    rec["albedo"] = counts
    return rec


def bands_on_cluster(client, todo: list[tuple], origin: DatasetOrigin, coarse: CoarseMaps, preset: Preset,
                     comps: Components, seed: int, threads: int, finish, bar, uncertainty: bool) -> int:
    """The fine bands ``todo`` as Dask tasks (:func:`fine_task`), each carrying its coarse rows
    (``1/f^2`` of its pixels, a few maps) and reading its pixels itself; ``finish(box, record)``
    as each one ends; returns the number of workers."""
    from dualscale.engine import bounded

    from .tiled import INFLIGHT_PER_WORKER

    def submit(box):
        crop, c0 = coarse.crop(box)
        return client.submit(fine_task, origin, box, preset, comps, crop, c0, seed, threads, uncertainty,
                             key=f"dualscale-fit-band-{coarse.key[:16]}-{box[0]}{'-u' if uncertainty else ''}",
                             pure=False)

    for box, rec in bounded(client, todo, submit, INFLIGHT_PER_WORKER):
        finish(box, rec)
        del rec
        bar.update(1, f"rows {box[0]}..{box[1] - 1}")
    return max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))


def start_of(band: Observations, box: tuple[int, int, int, int], coarse: CoarseMaps | None, preset: Preset,
             comps: Components, base: dict[str, Tensor]) -> dict[str, Tensor]:
    """The fine start of the (strided) ``band`` at ``box``: ``base`` (its photometric stereo),
    with the coarse level's specular maps where the preset has one."""
    from .pyramid import start_from_coarse

    if coarse is None:
        return base
    crop, c0 = coarse.crop(box)
    return start_from_coarse(MaterialMaps(**crop), band, preset, comps, rows=(box[0], c0), base=base)


__all__ = ["coarse_part", "coarse_task", "coarse_pass", "CoarseMaps", "coarse_path", "fine_task", "bands_on_cluster",
           "start_of"]
