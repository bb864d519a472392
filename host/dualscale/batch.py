"""``dualscale batch LIST -o OUTDIR``: many samples through the digitize pipeline, each sample a
chain of stage tasks on a Dask cluster (or in this process), and one summary table (issue 16 §3).

**The list** (:func:`read_list`).  ``LIST`` is a CSV file (``.csv``, a header row, one sample a
row; blank rows and rows whose first cell starts with ``#`` are ignored) or a YAML file
(``.yaml``/``.yml``: a list of mappings, or ``{samples: [...]}``).  Fields (:data:`FIELDS`):

- ``name`` (required): the sample's folder ``OUTDIR/<name>/`` and its material name; a safe
  file stem (:func:`dualscale.export.material.check_name`), unique (ignoring case), not one of
  the batch's own files (:data:`RESERVED`);
- ``input`` (required): what ``dualscale digitize INPUT`` takes: a photometric dataset folder
  (``manifest.json``), or a folder holding ``micro/`` -- e.g. ``RUN/capture`` of a
  ``digitize --rig`` run (:func:`dualscale.pipeline.input_dataset`);
- ``calibration``, ``guidance``, ``transfer``, ``guidance_texel_mm`` (mm per guidance pixel),
  ``quality`` (``draft|standard|paper``, default ``--quality``), ``export`` (comma-separated
  formats or ``all``, default ``--export``; a YAML list too), ``tile`` (true/false, yes/no, 1/0),
  ``seed`` (a whole number >= 0, default 0): as the ``digitize`` options of the same names.

Relative paths are relative to the LIST file's folder.  Every row is checked before anything
runs or is written: an unknown column, a missing or duplicate name, a path that does not exist,
an input that is not a dataset, a value out of its range all raise one
:class:`~dualscale.errors.InputError` naming the file, the row and the column.  What only a
stage can tell (captures in camera counts without a calibration, a guidance too coarse to
propagate to) fails that sample when its stage runs, and is reported in the summary.

**The run** (:func:`run_batch`).  Each sample is ``dualscale digitize`` into ``OUTDIR/<name>/``
(a run folder of :mod:`dualscale.pipeline`: calibrate, fit, fly-outs, propagate, export, report;
paper Sections 2-7) as a chain of :data:`~dualscale.pipeline.STAGES` tasks, each depending on
the one before (:func:`stage_task`).  A stage goes through :func:`dualscale.pipeline.run_stage`,
so it writes its record ``OUTDIR/<name>/stages/<stage>.json``, and a rerun of the batch skips
every stage whose record still matches (``up to date``) and resumes an interrupted one from its
work folder.  With a Dask client (:mod:`dualscale.engine`) the stage tasks run on its workers,
samples in parallel, one worker thread each by default; without one they run here, one after
another.  Each sample's fit runs whole in its worker (samples, not pixel tiles, are the unit of
parallel work here; ``digitize --workers`` tiles one sample's fit).  The workers need the same
files at the same paths as this process (one machine, or shared storage).

**Failures.**  A stage that raises marks its sample ``failed`` with the stage, the error's class
and its message (the traceback goes into ``summary.json``); the sample's later stages are
``not run``, and every other sample goes on.  A task the cluster itself loses (a worker killed
more often than Dask's ``allowed-failures``) counts as a failure of that stage.

**The summary** (:func:`write_summary`): ``OUTDIR/summary.csv``, ``summary.json`` and a
self-contained ``summary.html`` (escaped; links to each sample's report and exports), written
atomically: per sample the status, the failed stage and error, the seconds of each stage (and
which were up to date), the fitted component decision (opaque / isotropic / tinted, Sec. 5),
the fit's held-out SSIM and relative L1 (Sec. 6), the propagation's in-field L1 and
registration NCC when it ran (Sec. 7), and the export files.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
import traceback
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from dualscale.errors import InputError
from dualscale.pipeline import QUALITIES, STAGES, DigitizeOptions

#: the columns (CSV) or keys (YAML) of a sample
FIELDS = ("name", "input", "calibration", "guidance", "transfer", "guidance_texel_mm", "quality", "export",
          "tile", "seed")
#: names a sample cannot take: the batch's own files in OUTDIR
RESERVED = ("summary.csv", "summary.html", "summary.json")
SUMMARY_FORMAT, SUMMARY_VERSION = "dualscale-batch-summary", 1
_TRUE, _FALSE = {"true", "yes", "1", "on"}, {"false", "no", "0", "off", ""}


@dataclass(frozen=True)
class Sample:
    """One row of the list, checked: absolute paths, a known quality, known export formats.
    ``where``: ``"LIST row N"`` for messages."""

    name: str
    input: Path
    calibration: Path | None = None
    guidance: Path | None = None
    transfer: str | None = None
    guidance_texel_mm: float | None = None
    quality: str = "standard"
    export: tuple[str, ...] = ()
    tile: bool = False
    seed: int = 0
    where: str = ""

    def options(self, outdir: str | Path, threads: int | None = None) -> DigitizeOptions:
        """The :class:`~dualscale.pipeline.DigitizeOptions` of this sample's run folder
        ``OUTDIR/<name>`` (no progress bars: the batch draws its own; no engine: the sample's
        fit runs whole in its task)."""
        return DigitizeOptions(input=self.input, run=Path(outdir) / self.name, calibration=self.calibration,
                               guidance=self.guidance, guidance_transfer=self.transfer,
                               guidance_texel_mm=self.guidance_texel_mm, quality=self.quality, threads=threads,
                               progress=False, seed=self.seed, export=self.export, tile=self.tile, name=self.name)


# ---------------------------------------------------------------------------------------- the list

class _Row:
    """Where a value came from, for the one-line errors."""

    def __init__(self, path: Path, index: int, line: int | None = None) -> None:
        self.path, self.index, self.line = path, index, line

    def error(self, column: str | None, message: str) -> InputError:
        at = f"row {self.index}" + (f" (line {self.line})" if self.line is not None else "")
        col = f", column {column!r}" if column is not None else ""
        return InputError(f"{self.path}: {at}{col}: {message}")


def _text(row: _Row, col: str, v: Any) -> str | None:
    if v is None:
        return None
    if not isinstance(v, str):
        raise row.error(col, f"expected text, got {v!r} (quote it in YAML)")
    v = v.strip()
    return v or None


def _path(row: _Row, col: str, v: Any, base: Path) -> Path | None:
    t = _text(row, col, v)
    if t is None:
        return None
    p = Path(t).expanduser()
    return Path(os.path.abspath(p if p.is_absolute() else base / p))  # '..' folded, links kept


def _bool(row: _Row, col: str, v: Any) -> bool:
    if v is None or isinstance(v, bool):
        return bool(v)
    if isinstance(v, str) and v.strip().lower() in _TRUE | _FALSE:
        return v.strip().lower() in _TRUE
    raise row.error(col, f"{v!r} is not true or false (true/false, yes/no, 1/0)")


def _seed(row: _Row, col: str, v: Any) -> int:
    if v is None or (isinstance(v, str) and not v.strip()):
        return 0
    if isinstance(v, bool):
        raise row.error(col, f"{v!r} is not a whole number")
    try:
        n = int(v.strip()) if isinstance(v, str) else v
    except ValueError:
        n = None
    if not isinstance(n, int) or n < 0:
        raise row.error(col, f"{v!r} is not a whole number >= 0")
    return n


def _positive(row: _Row, col: str, v: Any) -> float | None:
    if v is None or (isinstance(v, str) and not v.strip()):
        return None
    try:
        x = float(v) if not isinstance(v, bool) else math.nan
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise row.error(col, f"{v!r} is not a size in mm > 0")
    return x


def _formats(row: _Row, col: str, v: Any, default: tuple[str, ...]) -> tuple[str, ...]:
    from dualscale.export.material import ALL_FORMATS

    if v is None:
        return default
    if isinstance(v, str):
        names = [t for t in v.replace(";", ",").replace(" ", ",").split(",") if t]
    elif isinstance(v, list) and all(isinstance(t, str) for t in v):
        names = [t.strip() for t in v if t.strip()]
    else:
        raise row.error(col, f"expected formats separated by commas, got {v!r}")
    if not names:
        return default
    if names == ["all"]:
        return tuple(ALL_FORMATS)
    bad = [n for n in names if n not in ALL_FORMATS]
    if bad:
        raise row.error(col, f"{', '.join(bad)}: choose from {', '.join(ALL_FORMATS)} or 'all'")
    return tuple(dict.fromkeys(names))


def _sample(row: _Row, values: dict[str, Any], base: Path, quality: str, export: tuple[str, ...]) -> Sample:
    """Check one row's values (``{column: value}``, only known columns) into a :class:`Sample`."""
    from dualscale.export.material import check_name
    from dualscale.formats.photo import parse_transfer
    from dualscale.pipeline import input_dataset

    name = _text(row, "name", values.get("name"))
    if name is None:
        raise row.error("name", "every sample needs a name (its folder in OUTDIR)")
    try:
        check_name(name)
    except InputError as e:
        raise row.error("name", str(e)) from None
    if name.lower() in RESERVED:
        raise row.error("name", f"{name!r} is one of the batch's own files ({', '.join(RESERVED)})")
    inp = _path(row, "input", values.get("input"), base)
    if inp is None:
        raise row.error("input", "every sample needs an input (a dataset folder, or a folder holding micro/)")
    try:
        input_dataset(inp)
    except (FileNotFoundError, InputError) as e:
        raise row.error("input", str(e)) from None
    cal = _path(row, "calibration", values.get("calibration"), base)
    if cal is not None and not cal.is_file():
        raise row.error("calibration", f"calibration file not found: {cal}")
    guidance = _path(row, "guidance", values.get("guidance"), base)
    if guidance is not None and not guidance.exists():
        raise row.error("guidance", f"guidance image or dataset not found: {guidance}")
    transfer = _text(row, "transfer", values.get("transfer"))
    if transfer is not None:
        try:
            parse_transfer(transfer)
        except ValueError as e:
            raise row.error("transfer", str(e)) from None
    elif guidance is not None and guidance.is_file() and guidance.suffix.lower() != ".exr":
        raise row.error("transfer", f"the guidance {guidance.name} is display-encoded: give its transfer function "
                                    "(srgb, linear or gamma:G; dualscale never guesses it)")
    q = _text(row, "quality", values.get("quality")) or quality
    if q not in QUALITIES:
        raise row.error("quality", f"{q!r}: choose one of {', '.join(QUALITIES)}")
    return Sample(name=name, input=inp, calibration=cal, guidance=guidance, transfer=transfer,
                  guidance_texel_mm=_positive(row, "guidance_texel_mm", values.get("guidance_texel_mm")),
                  quality=q, export=_formats(row, "export", values.get("export"), export),
                  tile=_bool(row, "tile", values.get("tile")), seed=_seed(row, "seed", values.get("seed")),
                  where=f"{row.path.name} row {row.index}")


def _csv_rows(path: Path) -> list[tuple[_Row, dict[str, Any]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = None
        for cells in reader:
            if any(c.strip() for c in cells) and not cells[0].lstrip().startswith("#"):
                header = [c.strip() for c in cells]
                break
        if header is None:
            raise InputError(f"{path}: empty: expected a header row ({', '.join(FIELDS)}) and one row per sample")
        head = _Row(path, 0, reader.line_num)
        for col in header:
            if col not in FIELDS:
                raise head.error(col, f"unknown column: the columns are {', '.join(FIELDS)}")
        dup = sorted({c for c in header if header.count(c) > 1})
        if dup:
            raise head.error(dup[0], "the column appears twice")
        for col in ("name", "input"):
            if col not in header:
                raise head.error(col, "missing column (every sample needs a name and an input)")
        rows = []
        for cells in reader:
            if not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
                continue
            row = _Row(path, len(rows) + 1, reader.line_num)
            if len(cells) > len(header):
                raise row.error(None, f"{len(cells)} cells for {len(header)} columns (quote a value holding a comma)")
            rows.append((row, {c: v for c, v in zip(header, cells)}))
    except csv.Error as e:
        raise InputError(f"{path}: line {reader.line_num}: not valid CSV ({e})") from None
    return rows


def _yaml_rows(path: Path) -> list[tuple[_Row, dict[str, Any]]]:
    import yaml

    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8-sig"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not readable YAML ({' '.join(str(e).split())})") from None
    if isinstance(doc, dict) and set(doc) == {"samples"}:
        doc = doc["samples"]
    if not isinstance(doc, list):
        raise InputError(f"{path}: expected a list of samples (or 'samples:' holding one), got "
                         f"{type(doc).__name__ if doc is not None else 'nothing'}")
    rows = []
    for i, entry in enumerate(doc, 1):
        row = _Row(path, i)
        if not isinstance(entry, dict):
            raise row.error(None, f"expected a mapping of {', '.join(FIELDS)}, got {type(entry).__name__}")
        for key in entry:
            if key not in FIELDS:
                raise row.error(str(key), f"unknown column: the columns are {', '.join(FIELDS)}")
        rows.append((row, entry))
    return rows


def read_list(path: str | Path, quality: str = "standard", export: tuple[str, ...] | None = None) -> list[Sample]:
    """The samples of the list file ``path`` (module docstring), checked; ``quality`` and
    ``export`` are the defaults of rows without them (``export`` None: every format).  Raises
    :class:`~dualscale.errors.InputError` (one line: the file, row and column) for anything
    that cannot be run, before anything is written."""
    from dualscale.export.material import ALL_FORMATS

    path = Path(path)
    if not path.is_file():
        raise InputError(f"sample list not found: {path}")
    if quality not in QUALITIES:
        raise InputError(f"--quality {quality!r}: choose one of {', '.join(QUALITIES)}")
    export = tuple(ALL_FORMATS) if export is None else tuple(export)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        rows = _csv_rows(path)
    elif suffix in (".yaml", ".yml"):
        rows = _yaml_rows(path)
    else:
        raise InputError(f"{path}: a sample list is a .csv or a .yaml/.yml file")
    base = path.absolute().parent
    samples: list[Sample] = []
    seen: dict[str, int] = {}
    for row, values in rows:
        s = _sample(row, values, base, quality, export)
        if s.name.lower() in seen:
            raise row.error("name", f"{s.name!r} is the name of row {seen[s.name.lower()]} too: names must be "
                                    "unique (ignoring case: they are folders)")
        seen[s.name.lower()] = row.index
        samples.append(s)
    if not samples:
        raise InputError(f"{path}: no samples")
    return samples


# ----------------------------------------------------------------------------------------- the run

def _one_line(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror:
        msg = f"{e.strerror}: {e.filename}" if e.filename is not None else e.strerror
    else:
        msg = str(e) or type(e).__name__
    return "; ".join(ln.strip() for ln in msg.splitlines() if ln.strip())


def _failed(stage: str, e: BaseException, seconds: float | None) -> dict[str, Any]:
    return {"stage": stage, "status": "failed", "seconds": seconds, "error_type": type(e).__name__,
            "error": _one_line(e), "traceback": "".join(traceback.format_exception(e)[-8:])}


_QUIET_EXIT = False


def _quiet_exit() -> None:
    """In a Dask worker process: end it with ``os._exit`` once the interpreter starts to shut
    down (an ``atexit`` handler, registered once), as the ``dualscale`` console script ends
    (:func:`dualscale.cli.run`): OpenImageIO's nanobind bindings otherwise print a page of
    benign "leaked instance" warnings from every worker when the cluster closes.  Every
    artefact is closed by then (atomic writes, no exit handlers of ours)."""
    global _QUIET_EXIT
    if _QUIET_EXIT:
        return
    import atexit
    import sys

    def bye() -> None:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(0)

    atexit.register(bye)
    _QUIET_EXIT = True


def stage_task(sample: Sample, outdir: str, stage: str, threads: int | None,
               previous: dict[str, Any] | None = None, quiet_exit: bool = False) -> dict[str, Any]:
    """The task of one stage of one sample: :func:`dualscale.engine.in_worker` (``threads``
    threads; ``None``: leave them), then :class:`~dualscale.pipeline.Digitizer` of the sample
    and its stage ``stage`` (:meth:`~dualscale.pipeline.Digitizer.begin` before the first,
    :meth:`~dualscale.pipeline.Digitizer.end` after the last).  ``previous``: what the task of
    the stage before returned; when it did not finish, this stage is ``not run``;
    ``quiet_exit``: the task runs in a worker process of our own local cluster (:func:`_quiet_exit`).

    Returns ``{"stage", "status": "done" | "up to date" | "failed" | "not run", "seconds"
    (this task's wall time), "record_seconds" (the stage's time in its record), "warnings",
    "summary" (the record's)}``, and for a failure ``"error_type", "error"`` (one line) and
    ``"traceback"``.  Never raises for the stage's own errors (they are the result)."""
    if previous is not None and previous.get("status") not in ("done", "up to date"):
        return {"stage": stage, "status": "not run", "seconds": None}
    if quiet_exit:
        _quiet_exit()
    t0 = time.perf_counter()
    try:
        if threads is not None:
            from dualscale.engine import in_worker

            in_worker(threads)
        from dualscale.pipeline import Digitizer

        d = Digitizer(sample.options(outdir, threads))
        if stage == STAGES[0]:
            d.begin()
        st = d.stage(stage)
        if stage == STAGES[-1]:
            d.end()
    except Exception as e:  # noqa: BLE001 - a sample's failure is its result, not the batch's
        return _failed(stage, e, round(time.perf_counter() - t0, 3))
    rec = st.record
    return {"stage": stage, "status": "up to date" if st.skipped else "done",
            "seconds": round(time.perf_counter() - t0, 3), "record_seconds": rec.get("seconds"),
            "warnings": list(rec.get("warnings") or []), "summary": rec.get("summary") or {}}


@dataclass
class SampleResult:
    """What the batch did with one sample: ``stages`` maps each stage to :func:`stage_task`'s
    result, in :data:`~dualscale.pipeline.STAGES` order."""

    sample: Sample
    stages: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.sample.name

    @property
    def failure(self) -> dict[str, Any] | None:
        """The failed stage's result, or None."""
        return next((r for r in self.stages.values() if r["status"] == "failed"), None)

    @property
    def status(self) -> str:
        """``done`` when every stage finished (or was up to date), else ``failed``."""
        ok = len(self.stages) == len(STAGES) and all(r["status"] in ("done", "up to date")
                                                     for r in self.stages.values())
        return "done" if ok else "failed"

    def summary(self, stage: str) -> dict[str, Any]:
        r = self.stages.get(stage) or {}
        return (r.get("summary") or {}) if r.get("status") in ("done", "up to date") else {}


def _settle(result: SampleResult) -> None:
    """Order the stages and, after the first failure, mark the later stages ``not run`` (a task
    the cluster failed makes its dependants fail with the same error)."""
    out, broken = {}, False
    for stage in STAGES:
        r = result.stages.get(stage) or {"stage": stage, "status": "not run", "seconds": None}
        if broken:
            r = {"stage": stage, "status": "not run", "seconds": None}
        elif r["status"] != "done" and r["status"] != "up to date":
            broken = True
            if r["status"] != "failed":
                r = {**r, "status": "failed", "error_type": "RuntimeError", "error": "the stage did not run"}
        out[stage] = r
    result.stages = out


def run_batch(samples: list[Sample], outdir: str | Path, *, client: Any = None, threads: int | None = None,
              progress: Any = None, on_sample: Callable[[SampleResult], None] | None = None,
              quiet_exit: bool = False) -> list[SampleResult]:
    """Digitize every sample into ``OUTDIR/<name>/`` (module docstring): on ``client`` (a
    :class:`distributed.Client`), one task per stage chained per sample, or in this process
    when ``client`` is None.  ``threads``: each task's thread count (None: leave them);
    ``progress`` (:mod:`dualscale.progress`) counts stages over all samples; ``on_sample`` is
    called as each sample ends; ``quiet_exit``: the client's workers are processes of a local
    cluster opened for this batch, which may end without the interpreter's teardown
    (:func:`_quiet_exit`; never for workers someone else runs).  Returns one :class:`SampleResult` per sample, in list order.
    A stage's error is its sample's result; only Ctrl-C (and errors of the cluster connection)
    stop the batch."""
    from dualscale.progress import tracker

    outdir = str(Path(outdir).absolute())
    results = {s.name: SampleResult(s) for s in samples}

    def record(name: str, stage: str, res: dict[str, Any], bar) -> None:
        r = results[name]
        r.stages[stage] = res
        bar.update(1, f"{name} {stage}" + ("" if res["status"] in ("done", "up to date") else f" {res['status']}"))
        if len(r.stages) == len(STAGES):
            _settle(r)
            if on_sample is not None:
                on_sample(r)

    with tracker(progress, len(samples) * len(STAGES), "batch", unit="stage") as bar:
        if client is None:
            for s in samples:
                prev = None
                for stage in STAGES:
                    prev = stage_task(s, outdir, stage, threads, prev)
                    record(s.name, stage, prev, bar)
        else:
            from distributed import as_completed

            token = uuid.uuid4().hex[:12]
            futures = {}
            for s in samples:
                prev = None
                for stage in STAGES:
                    prev = client.submit(stage_task, s, outdir, stage, threads, prev, quiet_exit, pure=False,
                                         key=f"dualscale-batch-{token}-{s.name}-{stage}")
                    futures[prev] = (s.name, stage)
            for fut in as_completed(list(futures)):
                name, stage = futures[fut]
                try:
                    res = fut.result()
                except Exception as e:  # noqa: BLE001 - the cluster lost the task (e.g. KilledWorker)
                    res = _failed(stage, e, None)
                record(name, stage, res, bar)
    return [results[s.name] for s in samples]


# ------------------------------------------------------------------------------------- the summary

def components_text(components: dict[str, Any] | None) -> str | None:
    """The fit's component decision in words: ``opaque, anisotropic, tinted`` (from the fit
    record's ``components``: :class:`dualscale.bsdf.maps.Components`)."""
    if not components:
        return None
    return ", ".join(["opaque" if components.get("opaque", True) else "transmissive",
                      "isotropic" if components.get("isotropic", True) else "anisotropic",
                      "tinted" if components.get("tinted") else "untinted"])


def _main_file(files: list[str]) -> str | None:
    """The file a user opens of one export format (``.gltf``, ``.glb``, ``.mtlx``, ``.u3ma``),
    else the format's folder (EXR and map sets)."""
    for f in files:
        if Path(f).suffix.lower() in (".gltf", ".glb", ".mtlx", ".u3ma", ".u3m"):
            return f
    return str(Path(files[0]).parent) + "/" if files else None


def sample_row(r: SampleResult) -> dict[str, Any]:
    """One sample's entry of ``summary.json`` (paths relative to OUTDIR)."""
    fail = r.failure
    fit, prop, exp = r.summary("fit"), r.summary("propagate"), r.summary("export")
    in_field = prop.get("in_field_l1") or {}
    reg = prop.get("registration") or {}
    exports = {}
    for scale, e in (exp.get("exports") or {}).items():
        folder = f"{r.name}/export/{scale}"
        exports[scale] = {"name": e.get("name"), "folder": folder, "tiled": e.get("tiled"),
                          "files": {fmt: f"{folder}/{_main_file(files)}"
                                    for fmt, files in (e.get("files") or {}).items() if fmt != "maps" and files}}
    report = r.summary("report").get("index")
    return {
        "name": r.name, "input": str(r.sample.input), "quality": r.sample.quality, "status": r.status,
        "failed_stage": None if fail is None else fail["stage"],
        "error": None if fail is None else f"{fail.get('error_type')}: {fail.get('error')}",
        "traceback": None if fail is None else fail.get("traceback"),
        "seconds": round(sum(x["seconds"] or 0.0 for x in r.stages.values()), 3),
        "stages": {s: {"status": x.get("status"), "seconds": x.get("seconds"),
                       "record_seconds": x.get("record_seconds"), "warnings": len(x.get("warnings") or [])}
                   for s, x in r.stages.items()},
        "components": fit.get("components"), "components_text": components_text(fit.get("components")),
        "heldout_ssim": fit.get("heldout_ssim"), "heldout_relative_l1": fit.get("heldout_relative_l1"),
        "propagate": None if not prop or "skipped" in prop else {
            "in_field_l1_mean": (sum(in_field.values()) / len(in_field)) if in_field else None,
            "registration_ncc": reg.get("score"), "registration_method": reg.get("method")},
        "propagate_skipped": prop.get("skipped"),
        "exports": exports, "report": None if report is None else f"{r.name}/{report}",
    }


CSV_COLUMNS = ("name", "status", "failed_stage", "error", "seconds", *(f"seconds_{s}" for s in STAGES), "up_to_date",
               "components", "heldout_ssim", "heldout_relative_l1", "propagate_in_field_l1", "registration_ncc",
               "exports", "report")


def _csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)

    def num(x):
        return "" if x is None else (f"{x:.6g}" if isinstance(x, float) else x)

    for r in rows:
        p = r["propagate"] or {}
        w.writerow([r["name"], r["status"], r["failed_stage"] or "", r["error"] or "", num(r["seconds"]),
                    *(num(r["stages"][s]["seconds"]) for s in STAGES),
                    ";".join(s for s in STAGES if r["stages"][s]["status"] == "up to date"),
                    r["components_text"] or "", num(r["heldout_ssim"]), num(r["heldout_relative_l1"]),
                    num(p.get("in_field_l1_mean")), num(p.get("registration_ncc")),
                    ";".join(f for e in r["exports"].values() for f in e["files"].values()), r["report"] or ""])
    return buf.getvalue()


_HTML = """{% extends "base.html" %}
{% block content %}
<style>
table.batch { font-size: 0.82rem; }
table.batch td.num { white-space: nowrap; }
table.batch .error { min-width: 22em; max-width: 40em; overflow-wrap: anywhere; font-size: 0.85em; }
pre.mono { white-space: pre-wrap; overflow-wrap: anywhere; background: var(--panel); padding: 8px; }
</style>
<section id="samples">
<h2>Samples</h2>
<p>{{ done }} done, {{ failed }} failed{% if up_to_date %}; {{ up_to_date }} stage(s) were up to date{% endif %}.
Times are each stage's wall time in this batch; an up-to-date stage was skipped (its record matched: hover for
the time it took when it ran).</p>
<table class="batch">
<thead><tr><th>sample</th><th>status</th><th>quality</th>{% for s in stages %}<th class="num">{{ s }}</th>{% endfor %}
<th class="num">total</th><th>components</th><th class="num">held-out SSIM</th><th class="num">held-out rel. L1</th>
<th class="num">propagation in-field L1</th><th>exports</th></tr></thead>
<tbody>
{% for r in rows %}
<tr class="sample {{ r.status }}" data-name="{{ r.name }}">
<td>{% if r.report %}<a href="{{ r.report }}">{{ r.name }}</a>{% else %}{{ r.name }}{% endif %}</td>
<td>{% if r.status == "done" %}<span class="ok">done</span>{% else %}<span class="bad">failed</span>
<div class="error">{{ r.failed_stage }}: {{ r.error }}</div>{% endif %}</td>
<td>{{ r.quality }}</td>
{% for s in stages %}{% set st = r.stages[s] %}<td class="num {{ st.status | replace(' ', '-') }}">
{% if st.status == "not run" %}
<span class="muted">not run</span>
{% elif st.status == "failed" %}
<span class="bad">failed</span> {{ st.seconds | dur }}
{% elif st.status == "up to date" %}
<span class="muted" title="checked in {{ st.seconds | dur }}; ran in {{ st.record_seconds | dur }} when it was done">up to date</span>
{% else %}
{{ st.seconds | dur }}
{% endif %}
</td>
{% endfor %}
<td class="num">{{ r.seconds | dur }}</td>
<td>{{ r.components_text or "—" }}</td>
<td class="num">{{ r.heldout_ssim | num }}</td>
<td class="num">{{ r.heldout_relative_l1 | num }}</td>
<td class="num">{% if r.propagate %}{{ r.propagate.in_field_l1_mean | num }}{% else %}
<span class="muted">{{ "skipped" if r.propagate_skipped else "—" }}</span>{% endif %}</td>
<td>{% for scale, e in r.exports.items() %}
<div><b>{{ scale }}</b>:
{% for fmt, f in e.files.items() %}<a href="{{ f }}">{{ fmt }}</a>{% if not loop.last %}, {% endif %}{% endfor %}
</div>
{% endfor %}</td>
</tr>
{% endfor %}
</tbody>
</table>
</section>
{% if failures %}
<section id="failures">
<h2>Failures</h2>
{% for r in failures %}<h3>{{ r.name }}: {{ r.failed_stage }}</h3><pre class="mono">{{ r.traceback or r.error }}</pre>
{% endfor %}
</section>
{% endif %}
{% endblock %}
"""


def _html(doc: dict[str, Any]) -> str:
    from dualscale.report.html import environment

    rows = doc["samples"]
    failures = [r for r in rows if r["status"] != "done"]
    up = sum(1 for r in rows for s in r["stages"].values() if s["status"] == "up to date")
    sub = (f"{doc['list']} → {doc['outdir']} · {doc['engine']} · finished {doc['finished']} · "
           f"{len(rows) - len(failures)}/{len(rows)} done")
    return environment().from_string(_HTML).render(
        title="dualscale batch", subtitle=sub,
        toc=[("samples", "samples")] + ([("failures", "failures")] if failures else []),
        footer=f"dualscale batch summary (format {SUMMARY_FORMAT} v{SUMMARY_VERSION}); per-sample reports: "
               "OUTDIR/<name>/report/index.html",
        stages=STAGES, rows=rows, failures=failures, done=len(rows) - len(failures), failed=len(failures),
        up_to_date=up)


def write_summary(results: list[SampleResult], outdir: str | Path, *, list_path: str | Path, engine: str,
                  seconds: float) -> dict[str, Any]:
    """Write ``OUTDIR/summary.json``, ``summary.csv`` and ``summary.html`` atomically
    (module docstring); returns the JSON document (``{"format", "version", "list", "outdir",
    "engine", "finished", "seconds", "samples": [sample_row ...]}``)."""
    from dualscale.formats.atomic import write_json, write_text

    outdir = Path(outdir)
    doc = {"format": SUMMARY_FORMAT, "version": SUMMARY_VERSION, "list": str(Path(list_path).absolute()),
           "outdir": str(outdir.absolute()), "engine": engine,
           "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"), "seconds": round(seconds, 3),
           "samples": [sample_row(r) for r in results]}
    write_json(outdir / "summary.json", doc)
    write_text(outdir / "summary.csv", _csv(doc["samples"]))
    write_text(outdir / "summary.html", _html(doc))
    return doc


def table(doc: dict[str, Any]) -> str:
    """The short text table of a summary document, for the terminal."""
    rows = doc["samples"]
    w = max([6] + [len(r["name"]) for r in rows])
    out = [f"{'sample':<{w}s}  {'status':<6s}  {'time':>10s}  {'components':<30s}  {'SSIM':>6s}  {'rel.L1':>7s}  "
           "exports"]
    for r in rows:
        t = f"{r['seconds']:.1f} s"
        if r["status"] != "done":
            out.append(f"{r['name']:<{w}s}  {'FAILED':<6s}  {t:>10s}  {r['failed_stage']}: {r['error']}")
            continue
        up = sum(1 for s in r["stages"].values() if s["status"] == "up to date")
        if up == len(STAGES):
            t = "up to date"
        ssim, rel = r["heldout_ssim"], r["heldout_relative_l1"]
        exports = "; ".join(f"{e['folder']} ({', '.join(e['files'])})" for e in r["exports"].values())
        out.append(f"{r['name']:<{w}s}  {'done':<6s}  {t:>10s}  {(r['components_text'] or '-'):<30s}  "
                   f"{'-' if ssim is None else f'{ssim:.3f}':>6s}  {'-' if rel is None else f'{rel:.4f}':>7s}  "
                   f"{exports}")
    return "\n".join(out)

