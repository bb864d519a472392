"""``dualscale digitize``: one pipeline from a photometric dataset to a material.

Stages, in order (:data:`STAGES`; each imports only the stages before it):

1. ``calibrate`` -- the units boundary: the input dataset (any documented units, colour space
   and exposure) becomes calibrated linear radiance through the calibration file
   (:func:`dualscale.calib.apply.to_radiance`; supplementary Sec. 2-3);
2. ``fit`` -- the per-pixel SVBSDF fit of the micro capture on every light, with component
   selection, the residual map, a cross-validation pass over the lights on a pixel sample for the
   held-out error, and re-renders of a few lights beside their captures (Sec. 4-6);
3. ``flyouts`` -- fly-out fibres from the grazing lights and the fitted tangent (Sec. 4.1);
   skipped, with the reason, on data without the polarised grazing captures it needs;
4. ``propagate`` -- train the U-Net on the micro capture and its fitted maps, locate the micro
   field in the mid-range guidance image and run over the whole guidance (Sec. 7); skipped
   without ``--guidance``;
5. ``export`` -- the maps users load (EXR maps and previews, with their texel size);
6. ``report`` -- ``RUN/report/index.html``, self-contained.

Every stage writes into ``RUN/work/<stage>/``, which is renamed to ``RUN/<stage>/`` when the
stage is complete, and then its record ``RUN/stages/<stage>.json`` (:mod:`dualscale.formats.run`:
inputs' fingerprints, parameters, versions, time, warnings, summary).  A rerun skips every stage
whose record matches its inputs and parameters and whose outputs are intact; an interrupted
stage resumes from its work folder (the fit and the training checkpoint there).  ``Ctrl-C`` or
``kill -9`` at any moment leaves no half-written artefact under a final name.

Quality presets (:data:`QUALITIES`) choose coherent presets across stages; docs/DIGITIZE.md
measures them.

**Before any stage** (:class:`Digitizer`), every input is checked, so that a refused run writes
nothing: the dataset's manifest and the header of each of its images, the calibration file, and
the guidance (``--guidance``: an image is read whole -- readable, RGB, finite, its transfer
function stated; a dataset folder's manifest and diffuse image header -- and the micro field must
cover at least :data:`dualscale.propagate.stage.MIN_TRAIN_PX` guidance pixels).  Errors about
the guidance name ``--guidance``.

**The run's own checks** (:func:`run_checks`, :mod:`dualscale.report.checks`, docs/DIGITIZE.md
"The run's check"): a run that finished its fit passes when the fitted maps predict the lights
they were not fitted on -- the fit's cross-validated held-out relative L1,
``Σ|prediction − capture| / Σ capture``, is at most :data:`HELDOUT_L1_GOAL` (predicting black
scores 1) and below :data:`CONSTANT_MARGIN` times that of the per-pixel constant predictor (a
prediction that ignores the light).  The checks are recorded in
``run.json`` (``checks``); ``dualscale digitize`` exits 1 when one fails, its last line naming
it.  A fit without a cross-validation pass (too few lights) is not checked.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from dualscale.capture.stage import RigCapture, capture_spec, check_rig_calibration
from dualscale.errors import InputError, UnitsError
from dualscale.formats.atomic import clean_stale, write_text
from dualscale.formats.run import (CAPTURE_STAGE, STAGES, file_sha256, json_sha256, read_stage, stage_path, tree_sha256,
                                   write_run, write_stage)
from dualscale.report.checks import CONSTANT_MARGIN, HELDOUT_L1_GOAL, Check, run_checks  # noqa: F401 (re-exported)

CHECKPOINT_EVERY = 2  # fit iterations between checkpoints (the LM presets run 11-21 iterations in all)
# rough share of a run's time per stage, for the overall ETA (measured in docs/DIGITIZE.md)
_WEIGHTS = {"calibrate": 1.0, "fit": 10.0, "flyouts": 1.0, "propagate": 8.0, "export": 0.5, "report": 1.0}


@dataclass(frozen=True)
class Quality:
    """Presets of every stage that belong together: the fit preset (``dualscale.fit.PRESETS``),
    the propagation training preset (``dualscale.propagate.train.PRESETS``), the cross-validation
    pass that measures the fit (``cv_pixels`` sample pixels, 0 = none; ``cv_folds`` as
    ``dualscale fit --cv-folds``: the final maps are fitted on every light either way), and
    whether fly-outs are detected."""

    name: str
    fit_preset: str
    propagate_preset: str
    cv_pixels: int = 2000
    cv_folds: str = "auto"
    flyouts: bool = True


QUALITIES: dict[str, Quality] = {
    "draft": Quality("draft", "draft", "quick"),
    "standard": Quality("standard", "standard", "fast"),
    "paper": Quality("paper", "paper", "paper"),
}


@dataclass
class DigitizeOptions:
    """What ``dualscale digitize`` was asked.  ``input``: a photometric dataset folder (or a
    folder holding ``micro/``); ``calibration``: a calibration file (required for datasets in
    sensor units); ``guidance``: the mid-range image (an image file or a dataset folder whose
    diffuse capture is used); ``guidance_transfer``: its transfer function when display-encoded
    (``srgb``, ``linear``, ``gamma:G``; only with a ``guidance`` image, else refused);
    ``until``: the last stage to run; ``source``: where the options came from, for the hints of
    errors (None: the ``digitize`` command line, whose options they name; ``"LIST row N"``: a
    ``dualscale batch`` list, whose columns they name)."""

    input: Path
    run: Path
    calibration: Path | None = None
    guidance: Path | None = None
    guidance_transfer: str | None = None
    guidance_texel_mm: float | None = None
    quality: str = "standard"
    until: str | None = None
    threads: int | None = None
    progress: bool = False
    seed: int = 0
    export: tuple[str, ...] = ("exr", "mtlx", "gltf", "glb", "u3m")
    tile: bool = False
    name: str | None = None
    engine: Any = None  # a dualscale.engine.EngineSpec: the fit stage runs in tiles on that cluster
    tile_px: int | None = None  # the side of those tiles (None: fit.tiled.TILE); the same maps at any side
    memory: int | None = 2 * 1024 ** 3  # the fit stage's budget in bytes (fit.stream.DEFAULT_MEMORY; None: unlimited)
    #: ground-truth maps (a synthetic sample's ``maps/``) the fit stage is scored against
    #: (evaluation only: ``fit.json``'s ``ground_truth``; the report then shows the maps' errors
    #: beside their sigma and sigma's coverage)
    gt: Path | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        self.input, self.run = Path(self.input), Path(self.run)
        self.calibration = None if self.calibration is None else Path(self.calibration)
        self.guidance = None if self.guidance is None else Path(self.guidance)
        self.gt = None if self.gt is None else Path(self.gt).resolve()  # the report reads it from anywhere
        if self.gt is not None and not (self.gt / "material.json").is_file():
            raise InputError(f"{self.option('gt')} {self.gt}: not a maps folder (no material.json): give the "
                             "ground-truth maps, e.g. a synthetic sample's maps/")
        if self.guidance_transfer is not None and self.guidance is None:
            raise InputError(f"{self.option('transfer')} {self.guidance_transfer}: the transfer function is that of a "
                             f"display-encoded guidance image, and no guidance is given ({self.option('guidance')}); "
                             f"leave out {self.option('transfer')}, or add the guidance image")
        if self.quality not in QUALITIES:
            raise InputError(f"--quality {self.quality!r}: choose one of {', '.join(QUALITIES)}")
        self.export = tuple(self.export)
        from dualscale.export.material import ALL_FORMATS, OPTIONAL_FORMATS

        bad = [f for f in self.export if f not in ALL_FORMATS + OPTIONAL_FORMATS]
        if bad:
            raise InputError(f"--export {','.join(bad)}: choose from {', '.join(ALL_FORMATS + OPTIONAL_FORMATS)}")
        if self.name is not None:
            from dualscale.export.material import check_name

            check_name(self.name)
        if self.until is not None and self.until not in STAGES:
            raise InputError(f"--until {self.until!r}: choose one of {', '.join(STAGES)}")
        if self.engine is not None:
            from dualscale.fit.presets import get_preset
            from dualscale.fit.tiled import check_tileable

            check_tileable(get_preset(QUALITIES[self.quality].fit_preset))
        if self.tile_px is not None:
            from dualscale.fit.tiled import check_tile

            check_tile(self.tile_px)


    def option(self, name: str) -> str:
        """How the user gives the option ``name`` (``calibration``, ``guidance``, ``transfer``):
        ``--calibration CAL`` on the command line, ``the list's 'calibration' column (LIST row N)``
        in a batch (``source``)."""
        if self.source is None:
            return {"calibration": "--calibration CAL", "guidance": "--guidance", "transfer": "--transfer"}.get(
                name, f"--{name.replace('_', '-')}")
        return f"the list's {name!r} column ({self.source})"

    def give(self, name: str) -> str:
        """The words that tell the user how to give ``name``: ``with --calibration CAL``, or
        ``in the list's 'calibration' column (LIST row N)`` (:meth:`option`)."""
        return f"{'with' if self.source is None else 'in'} {self.option(name)}"


@dataclass
class StageResult:
    """What one stage did: its record and whether it was skipped (up to date)."""

    name: str
    record: dict[str, Any]
    skipped: bool


@dataclass
class RunResult:
    """The stages run or skipped, in order, and the run folder."""

    run: Path
    stages: list[StageResult] = field(default_factory=list)

    def record(self, name: str) -> dict[str, Any] | None:
        return next((s.record for s in self.stages if s.name == name), None)

    @property
    def checks(self) -> list[Check]:
        """The run's own checks (:func:`run_checks`) on the stages it ran."""
        return run_checks(self.record("fit"))

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if c.ok is False]


def versions() -> dict[str, str]:
    """Versions of dualscale and the libraries whose results the stages depend on."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("dualscale", "torch", "numpy", "OpenImageIO", "colour-science", "onnxruntime", "opencv-python"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


def _named(option: str, e: BaseException, hint: str = "") -> InputError:
    """``e`` as an :class:`InputError` (its own class when one) whose one line names ``option``."""
    from dualscale.errors import one_line

    msg = one_line(e)
    if not msg.startswith(option.split()[0]):
        msg = f"{option}: {msg}"
    if hint:
        msg += f"; {hint}"
    try:
        return type(e)(msg) if isinstance(e, InputError) else InputError(msg)
    except TypeError:
        return InputError(msg)


def _check_images(ds: Any, option: str) -> None:
    """Every image of the dataset ``ds`` opens as an image (its header): a corrupt or missing one
    is refused before any stage, naming the file."""
    from dualscale.formats.exr import open_image

    for rec in ds.records:
        try:
            open_image(ds.root / rec.file).close()
        except (InputError, OSError) as e:
            raise _named(option or f"dataset {ds.root}", e) from None


def _micro_texel(ds: Any) -> float | None:
    """The micro images' pixel pitch in mm from the dataset's first camera (``field_mm / width``)."""
    cam = (ds.manifest.get("cameras") or {}).get(ds.records[0].camera) if ds.records else None
    try:
        return float(cam["field_mm"][0]) / float(cam["width"]) if cam and cam.get("field_mm") else None
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None


def input_dataset(path: Path) -> Path:
    """The dataset folder of ``path``: itself (``manifest.json``) or its ``micro/``."""
    if not path.exists():
        raise FileNotFoundError(f"input not found: {path}")
    if (path / "manifest.json").is_file():
        return path
    if (path / "micro" / "manifest.json").is_file():
        return path / "micro"
    raise InputError(f"{path}: not a photometric dataset (no manifest.json, nor micro/manifest.json); "
                     "make one with `dualscale import` (photographs) or `dualscale synth --dataset`")


class _Progress:
    """One progress view over the stages (weighted by their usual share of the time, so the ETA
    means something); each stage's own bars appear beneath it."""

    def __init__(self, stages: list[str], enabled: bool) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=sum(_WEIGHTS[s] for s in stages), disable=not enabled, position=0, leave=True,
                        file=sys.stderr, unit="", bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")

    def start(self, stage: str, index: int, count: int) -> None:
        self.bar.set_description_str(f"digitize {index}/{count} {stage}")
        self.bar.refresh()

    def done(self, stage: str) -> None:
        self.bar.update(_WEIGHTS[stage])

    def close(self) -> None:
        self.bar.close()


def run_stage(run: Path, name: str, inputs: dict[str, Any], params: dict[str, Any], versions_: dict[str, str],
              fn: Callable[[Path], dict[str, Any]]) -> StageResult:
    """Run (or skip, when its record matches and its outputs are intact) the stage ``name`` of the
    run folder ``run``: ``fn(work)`` fills ``RUN/work/<name>/`` and returns the summary; the work
    folder is then renamed to ``RUN/<name>/`` and the record written (module docstring)."""
    key = json_sha256({"stage": name, "inputs": inputs, "params": params, "versions": versions_})
    final = run / name
    rec = read_stage(run, name)
    if rec is not None and rec.get("key") == key and final.is_dir() \
            and tree_sha256(final) == rec.get("outputs_sha256"):
        return StageResult(name, rec, True)
    work = run / "work" / name
    key_file = work / ".stage-key"
    if work.is_dir() and (not key_file.is_file() or key_file.read_text().strip() != key):
        shutil.rmtree(work)  # left by a run with other inputs or parameters: not resumable
    work.mkdir(parents=True, exist_ok=True)
    clean_stale(work)
    write_text(key_file, key)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = fn(work)
    stage_warnings = list(summary.pop("warnings", []))
    stage_warnings += sorted({f"{w.category.__name__}: {w.message}" for w in caught
                              if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning))})
    key_file.unlink()
    stage_path(run, name).unlink(missing_ok=True)
    if final.exists():
        shutil.rmtree(final)
    os.replace(work, final)
    outputs = sorted(str(p.relative_to(run)) for p in final.rglob("*") if p.is_file())
    record = {"key": key, "inputs": inputs, "params": params, "versions": versions_,
              "seconds": round(time.perf_counter() - t0, 3),
              "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "warnings": stage_warnings, "outputs": outputs, "outputs_sha256": tree_sha256(final),
              "summary": summary}
    write_stage(run, name, record)
    return StageResult(name, record, False)


def _calibration_key(path: Path) -> str:
    """What the calibrate stage keys on in a calibration file: its content without the time it
    was written (``created``), so that recomputing an unchanged calibration does not redo the run
    (issue 24 §8); the file's bytes when it is not JSON (the stage then refuses it)."""
    import json

    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return file_sha256(path)
    if isinstance(doc, dict):
        doc = {k: v for k, v in doc.items() if k != "created"}
    return json_sha256(doc)


def guidance_extent(g: Path, opts: DigitizeOptions) -> tuple[int, int, float]:
    """``(width, height, texel_mm)`` of the guidance ``g`` as the propagate stage will read it
    (module docstring), every error naming ``--guidance``: a dataset folder's manifest, units and
    diffuse image (its header; it goes through the calibrate stage first), an image file read
    whole.  The texel: ``opts.guidance_texel_mm``, else the guidance's own, else the rig's
    mid-range field over its width (:data:`~dualscale.propagate.stage.RIG_GUIDANCE_FIELD_MM`)."""
    from dualscale.formats.dataset import read_dataset
    from dualscale.formats.exr import open_image
    from dualscale.propagate.guidance import _dataset_image, read_guidance
    from dualscale.propagate.stage import RIG_GUIDANCE_FIELD_MM

    opt = f"--guidance {g}"
    try:
        if g.is_dir():
            gds = read_dataset(g)
            raw = {r.units for r in gds.records} - {"relative_radiance"}
            if raw and opts.calibration is None:
                raise UnitsError(f"the guidance is in {', '.join(sorted(raw))} (camera counts): give the rig's "
                                 f"calibration file {opts.give('calibration')}")
            file, cam, _ = _dataset_image(g)
            inp = open_image(file)
            try:
                width, height = inp.spec().width, inp.spec().height
            finally:
                inp.close()
            tex = cam.pixel_mm[0] if cam is not None else None
        else:
            guide = read_guidance(g, opts.guidance_transfer, opts.guidance_texel_mm)
            height, width = guide.shape
            tex = guide.texel_mm
    except (InputError, OSError) as e:
        hint = ("the guidance is an image (EXR, or PNG/JPEG/TIFF with --transfer) or a dataset folder with a "
                "manifest.json (`dualscale synth --mid`, `dualscale import`)") if g.is_dir() else ""
        raise _named(opt, e, hint) from None
    if opts.guidance_texel_mm is not None:
        tex = float(opts.guidance_texel_mm)
    if tex is None:
        tex = RIG_GUIDANCE_FIELD_MM / width
    return width, height, tex


def check_rig_guidance(rc: RigCapture, opts: DigitizeOptions) -> None:
    """``digitize --rig``, before the first shot: the coverage rule of the propagate stage
    (:func:`~dualscale.propagate.stage.require_coverage`) on what the capture will give, so that
    a guidance too coarse for the micro field is refused before the rig starts, not after the
    capture.  The micro field: the micro camera's geometry
    (:func:`dualscale.capture.session.geometry_for`: its size and field, as the dataset records
    them); the guidance: ``--guidance`` (:func:`guidance_extent`), else the mid camera's geometry
    (its size, pixel pitch = field / width, or ``--guidance-texel-mm``); no mid camera and no
    ``--guidance``: nothing to check.  ``InputError`` naming the option or the camera."""
    from dualscale.capture.session import geometry_for, stable_spec
    from dualscale.propagate.stage import require_coverage

    if "micro" not in rc.cameras:
        return  # the capture stage refuses it (the micro plan needs the micro camera)
    micro = geometry_for("micro", rc.cameras["micro"])
    hint = "a finer guidance, or its true texel size (--guidance-texel-mm)"
    if opts.guidance is not None:
        width, height, tex = guidance_extent(opts.guidance, opts)
        where = f"--guidance {opts.guidance} (a {width}x{height} guidance)"
    elif "mid" in rc.cameras:
        mid = geometry_for("mid", rc.cameras["mid"])
        width, height = mid.width, mid.height
        tex = float(opts.guidance_texel_mm) if opts.guidance_texel_mm is not None else mid.pixel_mm[0]
        where = f"--camera {stable_spec(rc.cameras['mid'].spec)} (the guidance: {width}x{height} px of {tex:.4g} mm)"
        hint = "a mid camera with more pixels over its field, or a finer --guidance"
    else:
        return
    require_coverage((micro.height, micro.width), micro.field_mm[0] / micro.width, tex, where, hint)


class Digitizer:
    """Runs the stages of one run folder (see the module docstring)."""

    def __init__(self, opts: DigitizeOptions) -> None:
        self.opts = opts
        self.run = opts.run
        self.quality = QUALITIES[opts.quality]
        self.dataset_in = input_dataset(opts.input)
        if opts.calibration is not None and not opts.calibration.is_file():
            raise FileNotFoundError(f"calibration file not found: {opts.calibration}")
        if opts.guidance is not None and not opts.guidance.exists():
            raise FileNotFoundError(f"--guidance {opts.guidance}: no such image or folder")
        self.versions = versions()
        self._preflight()

    def _preflight(self) -> None:
        """Refuse, before anything is written, what a later stage would refuse: captures in
        camera counts without a calibration, a memory budget below the fit's least, a calibration
        file that is not one, a display-encoded guidance image without its transfer function."""
        from dualscale.formats.calibration import read_calibration
        from dualscale.formats.dataset import read_dataset
        from dualscale.formats.photo import parse_transfer

        ds = read_dataset(self.dataset_in)
        raw = {r.units for r in ds.records} - {"relative_radiance"}
        if raw and self.opts.calibration is None:
            raise UnitsError(f"{self.dataset_in}: the captures are in {', '.join(sorted(raw))} (camera counts): "
                             f"give the rig's calibration file {self.opts.give('calibration')} "
                             "(dualscale calibrate)")
        _check_images(ds, "")
        from dualscale.fit.observations import fit_camera
        from dualscale.fit.stream import check_memory

        cam = fit_camera(ds)
        check_memory(self.opts.memory, sum(1 for r in ds.records if r.camera == cam and r.light_kind == "led"))
        if self.opts.calibration is not None:
            read_calibration(self.opts.calibration)
        g = self.opts.guidance
        if g is not None and g.is_file() and g.suffix.lower() != ".exr":
            if self.opts.guidance_transfer is None:
                raise UnitsError(f"--guidance {g}: a display-encoded image needs its transfer function: "
                                 "--transfer srgb|linear|gamma:G (dualscale never guesses it)")
            try:
                parse_transfer(self.opts.guidance_transfer)
            except InputError as e:
                raise _named(f"--guidance {g} --transfer {self.opts.guidance_transfer}", e) from None
        if g is not None:
            self._check_guidance(g, ds)

    def _check_guidance(self, g: Path, ds: Any) -> None:
        """The guidance as the propagate stage will read it (:func:`guidance_extent`), then whether
        the micro field covers enough guidance pixels to train on."""
        from dualscale.propagate.stage import require_coverage

        width, height, tex = guidance_extent(g, self.opts)
        micro = _micro_texel(ds)
        if micro is None:
            return  # the propagate stage refuses it, naming the missing texel size
        rec = ds.records[0]
        cam = (ds.manifest.get("cameras") or {}).get(rec.camera) or {}
        if cam.get("width") and cam.get("height"):
            require_coverage((int(cam["height"]), int(cam["width"])), micro, tex,
                             f"--guidance {g} (a {width}x{height} guidance)",
                             "a finer guidance, or its true texel size (--guidance-texel-mm)")

    # -- paths of the finished stages
    def out(self, stage: str) -> Path:
        return self.run / stage

    @property
    def dataset(self) -> Path:
        return self.out("calibrate") / "dataset"

    # -- the stage runner
    def _stage(self, name: str, inputs: dict[str, str | None], params: dict[str, Any],
               fn: Callable[[Path], dict[str, Any]]) -> StageResult:
        return run_stage(self.run, name, inputs, params, self.versions, fn)

    def _prev(self, name: str) -> str:
        rec = read_stage(self.run, name)
        if rec is None:
            raise RuntimeError(f"stage {name} has no record")  # the runner guarantees the order
        return rec["outputs_sha256"]

    # -- the stages
    def calibrate(self) -> StageResult:
        from dualscale.calib.apply import to_radiance

        g = self.opts.guidance
        inputs = {"dataset": tree_sha256(self.dataset_in),
                  "calibration": None if self.opts.calibration is None else _calibration_key(self.opts.calibration),
                  "guidance_dataset": tree_sha256(g) if g is not None and g.is_dir() else None}

        def run(work: Path) -> dict[str, Any]:
            summary = to_radiance(self.dataset_in, work / "dataset", self.opts.calibration,
                                  progress=self.opts.progress)
            if g is not None and g.is_dir():  # a guidance dataset goes through the same calibration
                gs = to_radiance(g, work / "guidance", self.opts.calibration, progress=self.opts.progress)
                summary["guidance"] = {k: gs[k] for k in ("units_in", "colour_space_in", "applied", "images")
                                       if k in gs}
            return summary

        return self._stage("calibrate", inputs, {}, run)

    @property
    def guidance(self) -> Path | None:
        """The guidance the propagation reads: the calibrated guidance dataset when the guidance
        was a dataset, else the image file as given."""
        cal = self.out("calibrate") / "guidance"
        return cal if (cal / "manifest.json").is_file() else self.opts.guidance

    def _micro(self) -> tuple[Any, Any, tuple[int, int], list[tuple[int, int, int, int]]]:
        """``(obs, origin, (H, W), bands)`` of the micro dataset under the memory budget: its
        :class:`~dualscale.fit.observations.DatasetOrigin`, the bands of
        :func:`dualscale.fit.stream.band_boxes`, and the observations loaded whole when one band
        holds the map, else one pixel of them (the lights, the texel size) for a stage that then
        reads the dataset band by band."""
        from dualscale.fit.observations import DatasetOrigin, fit_layout, load_observations, read_tile
        from dualscale.fit.stream import band_boxes

        root, camera, shape, images = fit_layout(self.dataset)
        bands = band_boxes(shape, images, self.opts.memory)
        origin = DatasetOrigin(root, camera, None, "float32", "")
        obs = load_observations(self.dataset) if len(bands) == 1 else read_tile(origin, (0, 1, 0, 1))
        return obs, origin, shape, bands

    def fit(self) -> StageResult:
        params = {"preset": self.quality.fit_preset, "cv_pixels": self.quality.cv_pixels,
                  "cv_folds": self.quality.cv_folds, "seed": self.opts.seed}
        self._prev("calibrate")
        inputs = {"dataset": tree_sha256(self.dataset), **({"gt": tree_sha256(self.opts.gt)} if self.opts.gt else {})}
        return self._stage("fit", inputs, params, self._fit)

    def _fit(self, work: Path) -> dict[str, Any]:
        """The fit on every light (:func:`dualscale.fit.api.fit_dataset`, with its
        cross-validation pass), the residual map over every image, and ``fit/heldout/``:
        ``heldout.json`` (the cross-validated error of every light, and the re-renders) and the
        capture/re-render EXR pairs of up to :data:`RENDERED_LIGHTS` lights, spread from the
        largest to the smallest cross-validated error.  Those re-renders are of the final fit,
        which was fitted on these captures too: they show what the maps reproduce, not a
        prediction (the table's errors are the held-out ones)."""
        from dualscale.fit.api import fit_dataset
        from dualscale.fit.residuals import light_views, residual_by_bands, residual_map, views_by_bands
        from dualscale.formats.atomic import write_json
        from dualscale.formats.exr import write_exr

        # over the budget: the fit reads the dataset band by band (fit.stream) and so does the evidence below
        obs, origin, shape, bands = self._micro()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res, extra = fit_dataset(self.dataset, work / "maps", self.quality.fit_preset,
                                     cv_pixels=self.quality.cv_pixels, cv_folds=self.quality.cv_folds,
                                     progress=self.opts.progress, seed=self.opts.seed,
                                     obs=obs if len(bands) == 1 else None, memory=self.opts.memory,
                                     checkpoint_every=CHECKPOINT_EVERY, engine=self.opts.engine, gt=self.opts.gt,
                                     **({} if self.opts.tile_px is None else {"tile_px": self.opts.tile_px}))
        for w in caught:  # to the stage's record
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        # fitted out of core: res.maps is None and obs one pixel (the lights and the texel size)
        residual = (residual_map(res.maps, res.comps, obs) if res.maps is not None else
                    residual_by_bands(work / "maps", res.comps, origin, bands, shape))
        write_exr(work / "residual.exr", residual.numpy()[..., None], ("Y",))
        lights = extra["lights"]
        cv = extra["cross_validation"]
        done = cv is not None and "skipped" not in cv
        summary: dict[str, Any] = {
            "preset": res.preset.name, "seconds": res.seconds, "components": asdict(res.comps),
            "images": lights["images"], "train_images": lights["fitted_images"], "leds": lights["leds"],
            "fitted_leds": lights["fitted_leds"],
            "heldout_relative_l1": cv["relative_l1"] if done else None,
            "heldout_baseline_relative_l1": cv["baseline_relative_l1"] if done else None,
            "heldout_constant_relative_l1": cv.get("constant_relative_l1") if done else None,
            "heldout_method": (f"{cv['scheme']} cross-validation over {cv['lights']} lights on {cv['pixels']} "
                               "sample pixels" if done else
                               "none (no cross-validation pass)" if cv is None else f"none ({cv['skipped']})"),
            "cv_seconds": cv["seconds_ours"] + cv["seconds_baseline"] if done else None,
            "texel_mm": obs.pixel_mm, "size_px": list(shape)}
        per_light = []
        if done:
            for i, lid in enumerate(cv["light_ids"]):
                per_light.append({"led_id": lid, "direction": cv["directions"][i], "fold": cv["fold"][i],
                                  "relative_l1": cv["ours"][i], "baseline_relative_l1": cv["baseline"][i]})
        renders = []
        shown = _rendered_lights(obs, per_light)
        views = (light_views(res.maps, res.comps, obs.select_leds(shown)) if res.maps is not None else
                 views_by_bands(work / "maps", res.comps, origin, bands, shape, shown))
        for v in views:
            cap, ren = f"capture_{v.led_id:03d}.exr", f"render_{v.led_id:03d}.exr"
            write_exr(work / "heldout" / cap, v.capture.numpy())
            write_exr(work / "heldout" / ren, v.render.numpy())
            renders.append({"led_id": v.led_id, "direction": v.direction, "capture": cap, "render": ren,
                            "relative_l1": v.relative_l1, "held_out": False})
        doc = {"method": "cross-validation" if done else None, "heldout_method": summary["heldout_method"],
               "relative_l1": summary["heldout_relative_l1"],
               "baseline_relative_l1": summary["heldout_baseline_relative_l1"],
               "scheme": cv["scheme"] if done else None, "folds": cv["fold_lights"] if done else [],
               "pixels": cv["pixels"] if done else 0, "components_chosen": cv.get("components_chosen") if done else None,
               "lights": per_light, "renders": renders}
        write_json(work / "heldout" / "heldout.json", doc)
        return summary

    def flyouts(self) -> StageResult:
        params = {"enabled": self.quality.flyouts, "seed": self.opts.seed}
        return self._stage("flyouts", {"dataset": tree_sha256(self.dataset), "fit": self._prev("fit")}, params,
                           self._flyouts)

    def _flyouts(self, work: Path) -> dict[str, Any]:
        from dualscale.fit.flyouts import confidence_by_bands, detect_dataset

        if not self.quality.flyouts:
            return {"skipped": f"quality {self.quality.name} does not detect fly-outs"}
        obs, origin, shape, bands = self._micro()  # over the budget: the confidence map band by band
        if not obs.has_polarisation:
            return {"skipped": "fly-out detection needs captures with the specular passed and blocked "
                               "(polarised LEDs with the P0/P90 analyser); this dataset has none"}
        if float(obs.dirs[:, 2].min()) > 0.5:
            return {"skipped": "fly-out detection needs grazing LEDs (elevation under 30 deg); the lowest "
                               f"light here is at {90 - float(obs.dirs[:, 2].min().acos().rad2deg()):.0f} deg"}
        maps = self.out("fit") / "maps"
        tangent = maps if (maps / "tangent.exr").is_file() else None
        conf = None if len(bands) == 1 else confidence_by_bands(origin, bands, shape)
        rep = detect_dataset(self.dataset, work, tangent_maps=tangent, obs=obs, seed=self.opts.seed, conf=conf)
        out = {"count": rep["count"], "tangent_filter": rep["tangent_filter"], "pixel_mm": rep["pixel_mm"],
               "resolvability": rep["resolvability"]}
        out["warnings"] = [rep["resolvability"]["warning"]] if rep["resolvability"]["warning"] else []
        if tangent is None:
            out["warnings"].append("the fit found the sample isotropic (no tangent map): fly-outs are detected without "
                                   "the yarn-direction filter, which lets more yarn highlights through")
        return out

    def propagate(self) -> StageResult:
        gp = self.guidance
        inputs = {"dataset": tree_sha256(self.dataset), "fit": self._prev("fit"),
                  "guidance": None if gp is None else tree_sha256(gp)}
        params = {"preset": self.quality.propagate_preset, "transfer": self.opts.guidance_transfer,
                  "texel_mm": self.opts.guidance_texel_mm, "seed": self.opts.seed}
        return self._stage("propagate", inputs, params, self._propagate)

    def _propagate(self, work: Path) -> dict[str, Any]:
        if self.opts.guidance is None:
            return {"skipped": "no guidance image (--guidance): the maps cover the micro field only"}
        from dualscale.propagate.stage import run_propagation

        return run_propagation(self.dataset, self.out("fit") / "maps", self.guidance, work,
                               preset=self.quality.propagate_preset, texel_mm_guidance=self.opts.guidance_texel_mm,
                               transfer=self.opts.guidance_transfer, threads=self.opts.threads,
                               progress=self.opts.progress, in_memory_bytes=_propagate_in_memory(self.opts.memory))

    def export(self) -> StageResult:
        inputs = {"fit": self._prev("fit"), "propagate": self._prev("propagate")}
        params = {"formats": list(self.opts.export), "tile": self.opts.tile, "name": self.material_name()}
        return self._stage("export", inputs, params, self._export)

    def material_name(self) -> str:
        """The exported material's name: ``--name``, else the input folder's (its parent's for
        a ``micro/`` folder), sanitised to a file stem."""
        import re

        if self.opts.name:
            return self.opts.name
        src = self.opts.input.resolve()
        stem = src.parent.name if src.name == "micro" else src.name
        return re.sub(r"[^A-Za-z0-9_.-]", "_", stem).strip("._-") or "material"

    def _export(self, work: Path) -> dict[str, Any]:
        """Both scales in every requested format (:func:`dualscale.export.material.export_material`):
        ``RUN/export/micro`` from the fit, ``RUN/export/mesoscale`` from propagation.  The seamless
        tile (``--tile``) is cut from the mesoscale maps, the only ones spanning several repeats;
        where no repeat is found the untiled maps are exported and the stage records why.  U3M
        needs the physical size: without a texel size it is left out, with a warning."""
        from dualscale.errors import InputError as _InputError
        from dualscale.export.material import export_material

        summary: dict[str, Any] = {"formats": list(self.opts.export), "exports": {}}
        notes: list[str] = []
        sources = {"micro": self.out("fit") / "maps", "mesoscale": self.out("propagate") / "maps"}
        for scale, src in sources.items():
            if not (src / "material.json").is_file():
                continue
            formats = list(self.opts.export)
            name = self.material_name() + ("" if scale == "mesoscale" else "_micro")
            tile = self.opts.tile and scale == "mesoscale"
            try:
                doc = export_material(src, work / scale, formats, name=name, tile=tile, skip_unsized=True)
            except _InputError as e:
                if not tile:
                    raise
                notes.append(f"{scale}: no seamless tile ({e}); exported the untiled maps")
                doc = export_material(src, work / scale, formats, name=name, tile=False, skip_unsized=True)
            notes += [f"{scale}: {fmt} left out: {why}" for fmt, why in doc.get("skipped", {}).items()]
            summary["exports"][scale] = {"name": doc["name"], "repeat_mm": doc["repeat_mm"], "tiled": doc["tiled"],
                                         "tile": doc["tile"], "files": doc["formats"]}
        summary["warnings"] = notes
        return summary

    def report(self) -> StageResult:
        inputs = {s: self._prev(s) for s in STAGES[:-1]}
        return self._stage("report", inputs, {}, self._report)

    def _report(self, work: Path) -> dict[str, Any]:
        from dualscale.report.run import write_run_report

        index = write_run_report(self.run, out=work)
        return {"index": str(Path("report") / index.relative_to(work))}

    def begin(self) -> list[str]:
        """Create the run folder and write its ``run.json``; returns the names of the stages to
        run (up to ``until``), in order.  Then call :meth:`stage` for each, then :meth:`end`
        (what :meth:`digitize` does; ``dualscale batch`` calls them one stage per task)."""
        self.run.mkdir(parents=True, exist_ok=True)
        names = list(STAGES if self.opts.until is None else STAGES[:STAGES.index(self.opts.until) + 1])
        write_run(self.run, {"input": str(self.opts.input), "options": _options_json(self.opts),
                             "stages": names})
        return names

    def stage(self, name: str) -> StageResult:
        """Run (or skip, when up to date) the stage ``name`` of :data:`STAGES`; the stages before
        it must have finished (their records are its inputs)."""
        if name not in STAGES:
            raise InputError(f"stage {name!r}: choose one of {', '.join(STAGES)}")
        return getattr(self, name)()

    def end(self) -> list[Check]:
        """Remove the run's ``work/`` folder once every stage has moved its work out of it, and
        record the run's own checks (:func:`run_checks`) in ``run.json``; returns them."""
        work = self.run / "work"
        if work.is_dir() and not any(work.iterdir()):
            work.rmdir()
        names = list(STAGES if self.opts.until is None else STAGES[:STAGES.index(self.opts.until) + 1])
        checks = run_checks(read_stage(self.run, "fit") if "fit" in names else None)
        write_run(self.run, {"input": str(self.opts.input), "options": _options_json(self.opts), "stages": names,
                             "checks": [c.to_json() for c in checks]})
        return checks

    def _snapshot(self) -> tuple[bytes | None, set[Path], dict[Path, bytes]]:
        """What a refused rerun puts back (:meth:`_put_back`): ``run.json``'s bytes (``None``: none),
        the paths under ``RUN/work/`` and the bytes of its stage keys."""
        doc = self.run / "run.json"
        work = self.run / "work"
        before = set(work.rglob("*")) if work.is_dir() else set()
        keys = {p: p.read_bytes() for p in before if p.name == ".stage-key" and p.is_file()}
        return (doc.read_bytes() if doc.is_file() else None), before, keys

    def _put_back(self, snap: tuple[bytes | None, set[Path], dict[Path, bytes]], run_json: bool) -> None:
        """Undo what this process wrote before a stage refused its input (issue 24 trial: a refused
        run leaves the run folder as it was): the work files and folders it made go, the stage
        keys it rewrote come back, and (``run_json``: no stage finished in this process) so does
        ``run.json``."""
        import contextlib

        from dualscale.formats.atomic import write_bytes

        doc_bytes, before, keys = snap
        work = self.run / "work"
        made = sorted((p for p in (work.rglob("*") if work.is_dir() else []) if p not in before),
                      key=lambda p: len(p.parts), reverse=True)
        for p in made:
            with contextlib.suppress(OSError):
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                else:
                    p.unlink()
        for p, b in keys.items():
            with contextlib.suppress(OSError):
                if p.parent.is_dir() and (not p.is_file() or p.read_bytes() != b):
                    write_bytes(p, b)
        if not before and work.is_dir():
            with contextlib.suppress(OSError):
                work.rmdir()
        if run_json:
            doc = self.run / "run.json"
            with contextlib.suppress(OSError):
                if doc_bytes is None:
                    doc.unlink(missing_ok=True)
                elif not doc.is_file() or doc.read_bytes() != doc_bytes:
                    write_bytes(doc, doc_bytes)

    def digitize(self, on_stage: Callable[[StageResult], None] | None = None) -> RunResult:
        """Run (or skip) every stage up to ``until``; returns what each did.  A stage that refuses
        its input (:class:`InputError`) leaves the run folder as it was: :meth:`_put_back`."""
        snap = self._snapshot()
        names = self.begin()
        result = RunResult(self.run)
        bar = _Progress(names, self.opts.progress)
        try:
            for i, name in enumerate(names, 1):
                bar.start(name, i, len(names))
                st = self.stage(name)
                result.stages.append(st)
                bar.done(name)
                if on_stage is not None:
                    on_stage(st)
        except InputError:
            self._put_back(snap, run_json=all(st.skipped for st in result.stages))
            raise
        finally:
            bar.close()
        self.end()
        return result


#: lights whose capture and re-render the fit stage writes for the report (fit/heldout/)
RENDERED_LIGHTS = 8


def _rendered_lights(obs: Any, per_light: list[dict[str, Any]]) -> list[int]:
    """Up to :data:`RENDERED_LIGHTS` LED ids of ``obs``: spread evenly from the largest to the
    smallest cross-validated error of ``per_light`` (lights without one last), or evenly over
    the ids when there is no cross-validation."""
    ids = sorted(set(obs.led_ids.tolist()))
    if per_light:
        err = {p["led_id"]: p["relative_l1"] for p in per_light}
        ids = sorted(ids, key=lambda i: -err[i] if isinstance(err.get(i), (int, float)) else float("inf"))
    if len(ids) <= RENDERED_LIGHTS:
        return sorted(ids)
    step = (len(ids) - 1) / (RENDERED_LIGHTS - 1)
    return sorted({ids[round(k * step)] for k in range(RENDERED_LIGHTS)})


#: the propagate stage's peak over the micro capture's own bytes held in memory (float16 images and
#: float32 maps: the resampling copies them; docs/PROPAGATION.md, "Memory", measured 5.4x at 512^2)
PROPAGATE_PEAK_FACTOR = 5.5


def _propagate_in_memory(memory: int | None) -> float | None:
    """The propagate stage's in-memory threshold (``propagate.stage.run_propagation``
    ``in_memory_bytes``) under digitize's memory budget: the lesser of its own
    (``propagate.data.in_memory_limit``, which ``$DUALSCALE_PROPAGATE_IN_MEMORY_MB`` sets) and the
    budget's share; above it the stage reads the micro capture from disk, with the same results
    (``None``, an unlimited budget: the stage's own threshold)."""
    from dualscale.propagate.data import in_memory_limit

    return None if memory is None else min(in_memory_limit(), memory / PROPAGATE_PEAK_FACTOR)


def _options_json(o: DigitizeOptions) -> dict[str, Any]:
    out = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(o).items()
           if k not in ("run", "engine", "tile_px", "memory", "source")}
    out["engine"] = None if o.engine is None else o.engine.describe
    return out


def capture_stage(run: Path, rc: RigCapture, progress: Callable[[int, int, str], None] | None = None,
                  calibration: Path | None = None, log: Callable[[str], None] | None = None) -> StageResult:
    """The stage before ``calibrate`` when digitizing from the rig (:mod:`dualscale.capture.stage`):
    the plans captured into ``RUN/capture/{micro,mid}/``; an interrupted capture resumes from its
    journal in ``RUN/work/capture/``.  With ``rc.adaptive`` the micro plan is captured adaptively
    (:class:`dualscale.adaptive.loop.AdaptiveCapture`, each round calibrated with ``calibration``;
    ``log`` gets its lines)."""
    runners = None
    if rc.adaptive is not None:
        from dualscale.adaptive.loop import AdaptiveCapture

        runners = {"micro": lambda session: AdaptiveCapture(session, calibration, rc.adaptive, log=log).run()}
    inputs, params, fn = capture_spec(rc, progress, runners)
    return run_stage(run, CAPTURE_STAGE, inputs, params, versions(), fn)


def digitize(opts: DigitizeOptions, on_stage: Callable[[StageResult], None] | None = None,
             on_start: Callable[[], None] | None = None, rig: RigCapture | None = None,
             prepared: Digitizer | None = None) -> RunResult:
    """Run ``dualscale digitize`` (see the module docstring); ``on_start`` is called once the
    inputs passed their checks, ``on_stage`` after each stage.  Raises :class:`~dualscale.errors.InputError` (and subclasses) for input a stage
    cannot interpret, before anything of that stage is written.

    ``rig``: digitize from the rig: :func:`capture_stage` runs first, and its micro dataset (and
    mid guidance, unless ``opts.guidance`` is given) are the input of the other stages.
    ``prepared``: the :class:`Digitizer` of ``opts`` already made (its inputs checked), e.g. by a
    caller that checks them before making the run folder."""
    if opts.threads:
        import torch

        torch.set_num_threads(opts.threads)
    captured = None
    if rig is not None:
        if opts.calibration is None:
            raise UnitsError("digitize --rig: the rig captures camera counts: give its calibration file with "
                             "--calibration CAL (dualscale calibrate)")
        if opts.calibration is not None and not opts.calibration.is_file():
            raise FileNotFoundError(f"calibration file not found: {opts.calibration}")
        check_rig_calibration(rig, opts.calibration)
        check_rig_guidance(rig, opts)
        opts.run.mkdir(parents=True, exist_ok=True)
        captured = capture_stage(opts.run, rig, calibration=opts.calibration,
                                 log=lambda line: print(f"  adaptive capture: {line}", flush=True))
        if on_stage is not None:
            on_stage(captured)
        opts.input = opts.run / CAPTURE_STAGE / "micro"
        mid = opts.run / CAPTURE_STAGE / "mid"
        if opts.guidance is None and (mid / "manifest.json").is_file():
            opts.guidance = mid
    d = prepared if prepared is not None and rig is None else Digitizer(opts)
    if on_start is not None:
        on_start()
    result = d.digitize(on_stage)
    if captured is not None:
        result.stages.insert(0, captured)
    return result
