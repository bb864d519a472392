"""``fit_dataset``: the whole micro fit of a dataset directory, as run by ``dualscale fit``,
maps and (by default) their per-pixel uncertainty, on every path: in memory, tiled, out of core."""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any


from dualscale.bsdf import Components
from dualscale.errors import FormatError
from dualscale.formats.atomic import remove_file, write_json
from dualscale.formats.versioned import read_json
from dualscale.engine import EngineSpec, connect
from dualscale.threads import effective_threads

from .checkpoint import fingerprint
from .core import FitResult, fit_observations
from .holdout import CV_PIXELS, HoldoutReport, cross_validate, cross_validate_pixels, parse_folds, sample_pixels_of
from .io import save_fit, save_fit_rows
from .metrics import map_errors
from .observations import DatasetOrigin, Observations, fit_layout, load_observations, stride_leds
from .presets import Preset, get_preset
from .select import PIXELS as SELECT_PIXELS
from .select import choose_components, preset_for, select_components, selection_pixels
from .stream import (DEFAULT_MEMORY, band_boxes, estimate_bytes, fit_parts, gather, memory_record,
                     reader, result, survey, uncertainty_rows, warn_albedo, write_rows)
from .tiled import TILE, check_tile, check_tileable, clear_state, fit_tiled


def _radiometry(dataset: str | Path) -> dict | None:
    """The dataset's radiometry summary (:func:`dualscale.formats.response.radiometry_summary`),
    None when it has none or cannot be read here (the observations were given)."""
    from dualscale.formats.dataset import read_dataset
    from dualscale.formats.response import radiometry_summary

    try:
        return radiometry_summary(read_dataset(dataset).manifest)
    except (OSError, ValueError):
        return None


def fit_dataset(dataset: str | Path, out: str | Path, preset: str | Preset = "standard",
                overrides: dict[str, bool | None] | None = None, cv_pixels: int = CV_PIXELS,
                cv_folds: int | str = "auto", progress: bool = False,
                checkpoint_every: int = 50, restart: bool = False, stop_after: int | None = None,
                seed: int = 0, previews: bool = True, comps: Components | None = None,
                gt: str | Path | None = None, obs=None, engine: EngineSpec | None = None,
                tile_px: int = TILE, memory: int | None = DEFAULT_MEMORY,
                uncertainty: bool = True) -> tuple[FitResult, dict]:
    """Fit a photometric dataset on **every** light and write the maps to ``out``.

    The held-out figure comes from a separate cross-validation pass over the lights
    (:func:`.holdout.cross_validate`) on ``cv_pixels`` random sample pixels (0: no pass):
    ``cv_folds`` ``"auto"`` is leave-one-light-out for at most 16 distinct lights, else 8 folds
    with the lights dealt round-robin in id order; ``"loo"`` or an int ``k >= 2`` choose.  The
    pass uses the components chosen once on all lights and the preset (without a coarse level),
    and runs in this process also when the fit is tiled.  Its report is ``extra
    ["cross_validation"]`` (:meth:`.holdout.HoldoutReport.as_json` plus ``relative_l1``, the mean
    over the lights, ``baseline_relative_l1`` and ``constant_relative_l1``, the same for the
    Lambertian baseline and the per-pixel constant predictor, and ``images``), also written into ``fit.json``; while the fit is in progress
    it is kept in ``out/crossval.json`` so a resumed fit does not redo it.  ``FitResult.losses``
    are the final fit's re-render errors on the images it was fitted on (``train_*``).

    Components are chosen from the data (all lights) unless ``comps`` is given or ``overrides``
    fixes them; the loss the choice makes for unpolarised captures (:func:`.select.preset_for`)
    replaces the preset's, in the final fit and in every fold.  The checkpoint lives at ``out/checkpoint.pt`` and is removed after a successful
    fit; ``restart`` discards an existing one.  ``gt``: a ground-truth maps folder to score
    against (only when given: nothing beside the dataset is taken as ground truth).  ``obs``:
    observations already loaded and calibrated (then ``dataset`` is only recorded).  The maps
    carry the dataset's texel size.  ``extra["lights"]``: ``images`` and ``leds`` given,
    ``fitted_images`` and ``fitted_leds`` after the preset's ``led_stride`` (equal unless a
    strided preset such as ``draft`` thins more than 32 LEDs).

    ``memory``: the budget in bytes (:data:`.stream.DEFAULT_MEMORY`; ``None``: unlimited).  A
    dataset (``obs`` not given) whose fit would not fit in it is fitted **out of core**
    (:mod:`.stream`): read band by band from disk, the maps written by rows, the same maps;
    ``FitResult.maps`` is then ``None`` (the maps are on disk) and ``extra["out_of_core"]``
    records the parts and the peak memory.  Finished parts are kept in ``out/tiles/`` until the
    fit completes, so an interrupted fit resumes; ``checkpoint_every`` and ``stop_after`` then do
    not apply (a part is the unit of resuming).

    ``engine``: fit in ``tile_px`` pixel tiles on that Dask cluster (:mod:`.tiled`; the same
    maps as in-process); finished tiles are kept in ``out/tiles/`` until the
    fit completes, so an interrupted tiled fit resumes.  ``fit.json`` then records the engine,
    the tiling and the workers.  With a dataset (``obs`` not given) the driver holds no map
    either: the workers read their tiles and the driver its survey bands (:mod:`.stream`).

    ``uncertainty`` (default on): the maps' per-pixel uncertainty (:mod:`.uncertainty`, issue
    26) is computed on every path (in memory, tiled, out of core) and written to
    ``out/uncertainty/`` with its summary in ``fit.json``'s ``"uncertainty"``; off, an earlier
    fit's is removed.

    Raises ``ValueError`` for a bad ``cv_folds`` or ``cv_pixels``, and
    :class:`~dualscale.errors.InputError` for a budget too small or a preset the fit out of
    core cannot run, before any work.
    """
    p = get_preset(preset) if isinstance(preset, str) else preset
    if engine is not None:
        check_tileable(p)
        check_tile(tile_px)  # before any work
    folds = parse_folds(cv_folds)
    if cv_pixels < 0:
        raise ValueError(f"cross-validation pixels {cv_pixels}: give a count >= 0 (0 = no cross-validation)")
    out = Path(out)
    ck, state, cv_path, sel_path = out / "checkpoint.pt", out / "tiles", out / "crossval.json", out / "selection.json"
    ooc = None
    if obs is None:
        root, camera, shape, images = fit_layout(dataset)
        banded = len(band_boxes(shape, images, memory, p.coarse_factor)) > 1  # (refuses a budget under f rows)
        if banded or (engine is not None and p.coarse_factor <= 1):  # (a coarse level over it: .stream_coarse)
            ooc = _OutOfCore(root, camera, shape, images, memory)
        else:  # (a coarse level within the budget on a cluster: the driver's whole-map coarse start, fit.tiled)
            obs = load_observations(dataset)
        memory_note = {"memory_bytes": memory, "estimate_bytes": estimate_bytes(shape, images),
                       "path": "out of core" if ooc is not None else "in memory"}
    else:
        memory_note = {"memory_bytes": memory, "path": "in memory (observations given)"}
    if gt is not None:  # before any work: a ground truth of another size is refused now, not after the fit
        _check_ground_truth(gt, tuple(obs.shape) if obs is not None else tuple(shape))
    if restart:
        remove_file(ck)
        remove_file(cv_path)
        clear_state(state)
    if ooc is None:
        return _fit(dataset, out, p, obs, None, overrides, cv_pixels, folds, progress, checkpoint_every, stop_after,
                    seed, previews, comps, gt, engine, tile_px, memory_note, uncertainty)
    try:
        ooc.open(p, progress, engine)
        return _fit(dataset, out, p, obs, ooc, overrides, cv_pixels, folds, progress, checkpoint_every, stop_after,
                    seed, previews, comps, gt, engine, tile_px, memory_note, uncertainty)
    finally:
        ooc.close()


def _fit(dataset, out: Path, p: Preset, obs, ooc, overrides, cv_pixels: int, folds, progress, checkpoint_every: int,
         stop_after, seed: int, previews: bool, comps, gt, engine, tile_px: int,
         memory_note: dict[str, Any], uncertainty: bool = True) -> tuple[FitResult, dict]:
    """The body of :func:`fit_dataset` after its checks, on ``obs`` in memory or out of core
    (``ooc``, opened)."""
    ck, state, cv_path, sel_path = out / "checkpoint.pt", out / "tiles", out / "crossval.json", out / "selection.json"
    resuming = (ck.is_file() or any(state.glob("*.pt"))) and sel_path.is_file()
    if comps is None:
        if resuming:  # resuming: keep the decision already made
            sel = read_json(sel_path)
            try:
                comps = Components(**sel["components"])
            except (KeyError, TypeError) as e:
                raise FormatError(f"{sel_path}: malformed component decision ({e}); delete it or pass "
                                  "--restart") from None
        else:
            comps, sel = (select_components(obs, overrides, seed=seed) if ooc is None else
                          ooc.select(overrides, seed, cv_pixels))
            write_json(sel_path, sel)
    else:
        sel = {"method": "given by caller", "components": comps.__dict__}
    p = preset_for(p, sel)  # the loss the selection chose (unpolarised captures), for the fit and every fold
    head = obs if ooc is None else ooc.survey.head
    cv = None
    if cv_pixels:
        key = (dict(ids=obs.led_ids, sums=obs.images.sum(dim=(1, 2, 3)),
                    valid=obs.valid.sum(dim=(1, 2)) if obs.valid is not None else 0) if ooc is None else
               dict(ids=head.led_ids, data=ooc.survey.key))
        run = ((lambda: cross_validate(obs, p, comps, cv_pixels, folds, seed=seed, progress=progress)) if ooc is None
               else (lambda: cross_validate_pixels(ooc.cv_sample(seed, cv_pixels), p, comps, folds, seed, progress)))
        cv = _cross_validation(head, key, run, p, comps, cv_pixels, folds, seed, cv_path)
    tiled: dict[str, Any] = {}
    if ooc is not None:
        res, tiled = ooc.fit(p, comps, seed, state, tile_px, progress, uncertainty)
    elif engine is None:
        res = fit_observations(obs, p, comps, checkpoint=ck, checkpoint_every=checkpoint_every,
                               progress=progress, stop_after=stop_after, seed=seed, uncertainty=uncertainty)
    else:
        with connect(engine) as client:
            res, tiled = fit_tiled(obs, p, comps, client, tile=tile_px, threads=engine.threads_per_worker, seed=seed,
                                   state=state, progress=progress, uncertainty=uncertainty)
        tiled["engine"] = engine.describe
    fitted = stride_leds(head, p.led_stride)
    extra: dict[str, Any] = {"dataset": str(dataset),
                             "lights": {"images": head.n, "leds": len(set(head.led_ids.tolist())),
                                        "fitted_images": fitted.n, "fitted_leds": len(set(fitted.led_ids.tolist()))},
                             "cross_validation": cv, "threads": effective_threads(), "memory": memory_note}
    if tiled:
        extra["tiled"] = tiled
    rad = _radiometry(dataset)
    if rad is not None:
        extra["radiometry"] = rad
        import warnings

        for w in rad.get("warnings") or []:  # the import's radiometric warning stays a warning of the fit
            warnings.warn(f"the dataset's radiometry: {w}", RuntimeWarning, stacklevel=2)
    if ooc is None:
        if gt is not None:
            extra["ground_truth"] = _ground_truth(gt, res.maps, comps)
        save_fit(out, res, sel, extra, previews, texel_mm=obs.pixel_mm)
    else:
        extra["out_of_core"] = ooc.record()
        names, rows = write_rows(ooc.parts)
        save_fit_rows(out, res, ooc.shape, names, rows, sel, extra, previews, texel_mm=head.pixel_mm,
                      uncertainty=uncertainty_rows(ooc.parts) if uncertainty else None)
        if gt is not None:  # scored on the maps read back by rows (.score)
            from .score import score_by_rows

            extra["ground_truth"] = {"dir": str(gt), "errors": score_by_rows(out, gt, comps.ior, out)}
            write_json(out / "fit.json", {**read_json(out / "fit.json"), "ground_truth": extra["ground_truth"]})
    remove_file(ck)
    clear_state(state)
    remove_file(sel_path)
    remove_file(cv_path)
    return res, extra


def _check_ground_truth(gt: str | Path, shape: tuple[int, int]) -> None:
    """``gt`` is a maps folder (its ``material.json``) of the dataset's size ``shape`` (H, W):
    ``FileNotFoundError``/:class:`~dualscale.errors.FormatError` otherwise, naming ``--gt``."""
    from dualscale.formats.maps import read_material_json

    doc = read_material_json(gt)
    if (doc["height"], doc["width"]) != tuple(shape):
        raise FormatError(f"--gt {gt}: the ground-truth maps are {doc['height']} x {doc['width']}, the dataset "
                          f"{shape[0]} x {shape[1]}")


def _ground_truth(gt: str | Path, maps, comps: Components) -> dict[str, Any]:
    from dualscale.formats.maps import load_maps

    gt_maps, _ = load_maps(gt)
    if gt_maps.shape != maps.shape:
        raise ValueError(f"--gt {gt}: maps are {gt_maps.shape}, the fit is {maps.shape}")
    return {"dir": str(gt), "errors": map_errors(maps, gt_maps, comps.ior)}


class _OutOfCore:
    """The passes of a fit out of core over a dataset (:mod:`.stream`): the survey when opened,
    the gather on the first sample asked for, then the fit part by part."""

    def __init__(self, root: str, camera: str, shape: tuple[int, int], images: int, memory: int | None) -> None:
        self.shape, self.images, self.memory = shape, images, memory
        self.origin = DatasetOrigin(root, camera, None, "float32", "")
        self.read = reader(self.origin)
        self.passes: dict[str, float] = {}
        self._samples: dict[str, Any] | None = None
        self._stack = contextlib.ExitStack()
        self.client, self.engine = None, None

    def open(self, preset: Preset, progress, engine: EngineSpec | None) -> None:
        """Connect to ``engine``'s cluster (if any), then survey the dataset: in bands within the
        budget (a worker's, on a cluster: :data:`.stream.DEFAULT_MEMORY` when unlimited), read
        here or by the workers."""
        if engine is not None:
            self.engine, self.client = engine, self._stack.enter_context(connect(engine))
        self.threads = 1 if engine is None else engine.threads_per_worker
        self.boxes = band_boxes(self.shape, self.images, self.memory if self.memory is not None else DEFAULT_MEMORY)
        self.survey = survey(self.read, self.boxes, self.shape, progress=progress, client=self.client,
                             origin=self.origin, threads=self.threads)
        self.passes["survey"] = round(self.survey.seconds, 2)
        self.origin = DatasetOrigin(self.origin.root, self.origin.camera, None, "float32", self.survey.key)

    def _gather(self, seed: int, cv_pixels: int | None) -> dict[str, Any]:
        if self._samples is None:
            t0 = time.perf_counter()
            sv = self.survey
            flats = {"selection": selection_pixels(sv.fitted, sv.shape, SELECT_PIXELS, seed)}
            if cv_pixels:
                flats["cv"] = sample_pixels_of(sv.fitted, sv.shape, cv_pixels, seed)
            got = gather(self.read, self.boxes, self.shape, list(flats.values()), client=self.client,
                         origin=self.origin, threads=self.threads)
            self._samples = {"seed": seed, "cv_pixels": cv_pixels, **dict(zip(flats, got))}
            self.passes["gather"] = round(time.perf_counter() - t0, 2)
        return self._samples

    def select(self, overrides, seed: int, cv_pixels: int | None):
        return choose_components(self._gather(seed, cv_pixels)["selection"], self.survey.transmission, overrides)

    def cv_sample(self, seed: int, cv_pixels: int) -> Observations:
        s = self._gather(seed, cv_pixels)
        if s.get("cv") is None or s["cv_pixels"] != cv_pixels or s["seed"] != seed:
            self._samples = None
            s = self._gather(seed, cv_pixels)
        return s["cv"]

    def close(self) -> None:
        self._stack.close()

    def fit(self, preset: Preset, comps: Components, seed: int, state: Path, tile_px: int,
            progress, uncertainty: bool = True) -> tuple[FitResult, dict[str, Any]]:
        tiled: dict[str, Any] = {}
        self.parts = fit_parts(self.read, self.origin, self.survey, preset, comps, memory=self.memory, state=state,
                               seed=seed, client=self.client, tile=tile_px, threads=self.threads, progress=progress,
                               uncertainty=uncertainty)
        if self.engine is not None:
            tiled = {"tile_px": tile_px if self.parts.unit == "tile" else None, "part_kind": self.parts.unit + "s",
                     "tiles": len(self.parts.boxes), "resumed_tiles": self.parts.resumed,
                     "workers": self.parts.workers, "engine": self.engine.describe,
                     "tile_data": "read by the workers from " + self.origin.root}
        self.passes["fit"] = round(self.parts.seconds, 2)
        warn_albedo(self.parts, self.survey.head.imported)
        return result(self.parts, preset, comps), tiled

    def record(self) -> dict[str, Any]:
        return memory_record(self.memory, self.parts, self.passes, self.shape, self.images)


def _cross_validation(head: Observations, key_parts: dict[str, Any], run, preset: Preset, comps: Components,
                      pixels: int, folds: int | str, seed: int, cache: Path) -> dict[str, Any]:
    """The cross-validation record of :func:`fit_dataset` (its docstring): ``run()`` computes the
    :class:`.holdout.HoldoutReport`, unless ``cache`` holds the record of the same data
    (``key_parts``), preset, components, seed, pixels and folds (a resumed fit); the record is
    written there.  With fewer than two distinct lights (``head``'s) there is nothing to hold
    out: ``{"skipped": reason}``."""
    leds = len(set(head.led_ids.tolist()))
    if leds < 2:
        return {"skipped": f"cross-validation over the lights needs at least two distinct lights; the dataset has "
                           f"{leds}"}
    key = fingerprint(preset=asdict(preset), comps=asdict(comps), seed=seed, pixels=pixels, folds=str(folds),
                      **key_parts)
    if cache.is_file():
        try:
            doc = read_json(cache)
        except (OSError, ValueError, FormatError):
            doc = None
        if isinstance(doc, dict) and doc.get("key") == key and isinstance(doc.get("report"), dict):
            return doc["report"]
    rep: HoldoutReport = run()
    doc = rep.as_json()
    doc.update({"relative_l1": doc["ours_mean"], "baseline_relative_l1": doc["baseline_mean"],
                "constant_relative_l1": doc["constant_mean"],
                "images": head.n, "requested_pixels": pixels, "requested_folds": folds,
                "components_chosen": "once, on all lights (the same components in every fold)"})
    write_json(cache, {"key": key, "report": doc})
    return doc
