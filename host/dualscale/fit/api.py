"""``fit_dataset``: the whole micro fit of a dataset directory, as run by ``dualscale fit``."""

from __future__ import annotations

from pathlib import Path
from typing import Any


from dualscale.bsdf import Components
from dualscale.errors import FormatError
from dualscale.formats.atomic import remove_file, write_json
from dualscale.formats.versioned import read_json
from dualscale.engine import EngineSpec, connect
from dualscale.threads import effective_threads

from .core import FitResult, fit_observations, split_holdout
from .io import save_fit
from .metrics import map_errors
from .observations import load_observations
from .presets import Preset, get_preset
from .select import select_components
from .tiled import TILE, check_tile, check_tileable, clear_state, fit_tiled


def fit_dataset(dataset: str | Path, out: str | Path, preset: str | Preset = "standard",
                overrides: dict[str, bool | None] | None = None, holdout_every: int = 8, progress: bool = False,
                checkpoint_every: int = 50, restart: bool = False, stop_after: int | None = None,
                seed: int = 0, previews: bool = True, comps: Components | None = None,
                gt: str | Path | None = None, obs=None, engine: EngineSpec | None = None,
                tile_px: int = TILE) -> tuple[FitResult, dict]:
    """Fit a photometric dataset and write the maps to ``out``.

    Held-out LEDs (every ``holdout_every``-th, 0 = none) are kept out of the fit and used to
    report re-render SSIM.  Components are chosen from the data unless ``comps`` is given or
    ``overrides`` fixes them.  The checkpoint lives at ``out/checkpoint.pt`` and is removed
    after a successful fit; ``restart`` discards an existing one.  ``gt``: a ground-truth maps
    folder to score against (only when given: nothing beside the dataset is taken as ground
    truth).  ``obs``: observations already loaded and calibrated (then ``dataset`` is only
    recorded).  The maps carry the dataset's texel size.

    ``engine``: fit in ``tile_px`` pixel tiles on that Dask cluster (:mod:`.tiled`; the same
    maps as in-process); finished tiles are kept in ``out/tiles/`` until the
    fit completes, so an interrupted tiled fit resumes.  ``fit.json`` then records the engine,
    the tiling and the workers.
    """
    p = get_preset(preset) if isinstance(preset, str) else preset
    if engine is not None:
        check_tileable(p)
        check_tile(tile_px)  # before any work
    obs = load_observations(dataset) if obs is None else obs
    train, held = split_holdout(obs, holdout_every)
    out = Path(out)
    ck = out / "checkpoint.pt"
    state = out / "tiles"
    if restart:
        remove_file(ck)
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
            comps, sel = select_components(train, overrides, seed=seed)
            write_json(sel_path, sel)
    else:
        sel = {"method": "given by caller", "components": comps.__dict__}
    tiled: dict[str, Any] = {}
    if engine is None:
        res = fit_observations(train, p, comps, held_out=held, checkpoint=ck, checkpoint_every=checkpoint_every,
                               progress=progress, stop_after=stop_after, seed=seed)
    else:
        with connect(engine) as client:
            res, tiled = fit_tiled(train, p, comps, client, held_out=held, tile=tile_px,
                                   threads=engine.threads_per_worker, seed=seed, state=state, progress=progress)
        tiled["engine"] = engine.describe
    extra: dict[str, Any] = {"dataset": str(dataset), "lights": {"train_images": train.n,
                                                                  "heldout_images": 0 if held is None else held.n},
                             "threads": effective_threads()}
    if tiled:
        extra["tiled"] = tiled
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
    return res, extra
