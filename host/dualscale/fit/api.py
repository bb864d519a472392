"""``fit_dataset``: the whole micro fit of a dataset directory, as run by ``dualscale fit``."""

from __future__ import annotations

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
from .core import FitResult, fit_observations, stride_leds
from .holdout import CV_PIXELS, HoldoutReport, cross_validate, parse_folds
from .io import save_fit
from .metrics import map_errors
from .observations import load_observations
from .presets import Preset, get_preset
from .select import preset_for, select_components
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
                tile_px: int = TILE) -> tuple[FitResult, dict]:
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

    ``engine``: fit in ``tile_px`` pixel tiles on that Dask cluster (:mod:`.tiled`; the same
    maps as in-process); finished tiles are kept in ``out/tiles/`` until the
    fit completes, so an interrupted tiled fit resumes.  ``fit.json`` then records the engine,
    the tiling and the workers.  Raises ``ValueError`` for a bad ``cv_folds`` or ``cv_pixels``
    before any work.
    """
    p = get_preset(preset) if isinstance(preset, str) else preset
    if engine is not None:
        check_tileable(p)
        check_tile(tile_px)  # before any work
    folds = parse_folds(cv_folds)
    if cv_pixels < 0:
        raise ValueError(f"cross-validation pixels {cv_pixels}: give a count >= 0 (0 = no cross-validation)")
    obs = load_observations(dataset) if obs is None else obs
    out = Path(out)
    ck = out / "checkpoint.pt"
    state = out / "tiles"
    cv_path = out / "crossval.json"
    if restart:
        remove_file(ck)
        remove_file(cv_path)
        clear_state(state)
    sel_path = out / "selection.json"
    if comps is None:
        if (ck.is_file() or any(state.glob("*.pt"))) and sel_path.is_file():  # resuming: keep the decision already made
            sel = read_json(sel_path)
            try:
                comps = Components(**sel["components"])
            except (KeyError, TypeError) as e:
                raise FormatError(f"{sel_path}: malformed component decision ({e}); delete it or pass "
                                  "--restart") from None
        else:
            comps, sel = select_components(obs, overrides, seed=seed)
            write_json(sel_path, sel)
    else:
        sel = {"method": "given by caller", "components": comps.__dict__}
    p = preset_for(p, sel)  # the loss the selection chose (unpolarised captures), for the fit and every fold
    cv = _cross_validation(obs, p, comps, cv_pixels, folds, seed, progress, cv_path) if cv_pixels else None
    tiled: dict[str, Any] = {}
    if engine is None:
        res = fit_observations(obs, p, comps, checkpoint=ck, checkpoint_every=checkpoint_every,
                               progress=progress, stop_after=stop_after, seed=seed)
    else:
        with connect(engine) as client:
            res, tiled = fit_tiled(obs, p, comps, client, tile=tile_px,
                                   threads=engine.threads_per_worker, seed=seed, state=state, progress=progress)
        tiled["engine"] = engine.describe
    fitted = stride_leds(obs, p.led_stride)
    extra: dict[str, Any] = {"dataset": str(dataset),
                             "lights": {"images": obs.n, "leds": len(set(obs.led_ids.tolist())),
                                        "fitted_images": fitted.n, "fitted_leds": len(set(fitted.led_ids.tolist()))},
                             "cross_validation": cv, "threads": effective_threads()}
    if tiled:
        extra["tiled"] = tiled
    rad = _radiometry(dataset)
    if rad is not None:
        extra["radiometry"] = rad
        import warnings

        for w in rad.get("warnings") or []:  # the import's radiometric warning stays a warning of the fit
            warnings.warn(f"the dataset's radiometry: {w}", RuntimeWarning, stacklevel=2)
    if gt is not None:
        from dualscale.formats.maps import load_maps

        gt_maps, _ = load_maps(gt)
        if gt_maps.shape != res.maps.shape:
            raise ValueError(f"--gt {gt}: maps are {gt_maps.shape}, the fit is {res.maps.shape}")
        extra["ground_truth"] = {"dir": str(gt), "errors": map_errors(res.maps, gt_maps, comps.ior)}
    save_fit(out, res, sel, extra, previews, texel_mm=obs.pixel_mm)
    remove_file(ck)
    clear_state(state)
    remove_file(sel_path)
    remove_file(cv_path)
    return res, extra


def _cross_validation(obs, preset: Preset, comps: Components, pixels: int, folds: int | str, seed: int,
                      progress: bool, cache: Path) -> dict[str, Any]:
    """The cross-validation record of :func:`fit_dataset` (its docstring), reused from ``cache``
    when that holds the record of the same data, preset, components, seed, pixels and folds
    (a resumed fit), else computed and written there.  With fewer than two distinct lights there
    is nothing to hold out: ``{"skipped": reason}``."""
    leds = len(set(obs.led_ids.tolist()))
    if leds < 2:
        return {"skipped": f"cross-validation over the lights needs at least two distinct lights; the dataset has "
                           f"{leds}"}
    key = fingerprint(preset=asdict(preset), comps=asdict(comps), seed=seed, pixels=pixels, folds=str(folds),
                      ids=obs.led_ids, sums=obs.images.sum(dim=(1, 2, 3)),
                      valid=obs.valid.sum(dim=(1, 2)) if obs.valid is not None else 0)
    if cache.is_file():
        try:
            doc = read_json(cache)
        except (OSError, ValueError, FormatError):
            doc = None
        if isinstance(doc, dict) and doc.get("key") == key and isinstance(doc.get("report"), dict):
            return doc["report"]
    rep: HoldoutReport = cross_validate(obs, preset, comps, pixels, folds, seed=seed, progress=progress)
    doc = rep.as_json()
    doc.update({"relative_l1": doc["ours_mean"], "baseline_relative_l1": doc["baseline_mean"],
                "constant_relative_l1": doc["constant_mean"],
                "images": obs.n, "requested_pixels": pixels, "requested_folds": folds,
                "components_chosen": "once, on all lights (the same components in every fold)"})
    write_json(cache, {"key": key, "report": doc})
    return doc
