"""The report of one ``dualscale digitize`` run: ``RUN/report/index.html`` (+ ``RUN/report/assets/``).

:func:`write_run_report` reads only the run folder's contract:

* ``run.json`` and ``stages/<stage>.json`` (stage records: params, versions, seconds, warnings,
  summary); ``stages/capture.json`` too when ``digitize --rig`` captured the input (the capture
  stage runs before the stages ``run.json`` lists).  Every time the page shows comes from the
  records' ``seconds`` (the wall time of the whole stage); a stage's summary breaks it down
  (``of which ...``), never stands beside it as another figure;
* ``fit/maps/`` (maps folder, ``fit.json``), ``fit/residual.exr``, ``fit/heldout/``
  (``heldout.json``: the cross-validated error of every light and the re-rendered lights, and
  their capture/render EXR pairs; the maps are fitted on every light, so those pairs are
  re-renders of training lights and are labelled so);
* ``capture/micro/capture.json`` when ``digitize --rig ... --adaptive`` captured the input: its
  ``"adaptive"`` record gives the "Adaptive capture" section (:mod:`dualscale.report.adaptive`);
* ``flyouts/`` and ``propagate/`` when those stages ran (a skipped stage says why in its summary);
  the propagation section says where the run's training preset sits on the benchmark's
  accuracy-against-training-time curve (:mod:`dualscale.report.trade`, packaged data);
* ``export/`` (the exports of its summary: per scale, the files of each format, each with its own
  size).

The run's own checks (:func:`dualscale.report.checks.run_checks`, from the fit stage's record:
the same ones ``digitize`` records in ``run.json`` and exits 1 on) are shown under the headline,
each with its value, goal and ✓/✗, with a line saying whether the run passed.

The title names the material: ``--name`` (``run.json`` options), else the name the export stage
gave it, else the input folder's.

Required: ``run.json``, the ``calibrate`` and ``fit`` stage records, the fit maps, the fit
residual, ``heldout.json`` and the capture/render pairs it lists. A missing or unreadable required
artefact raises :class:`dualscale.errors.FormatError` naming the file and the stage that writes
it; a missing optional part is one line in the page. Every stage warning is listed at the top and
again in its own section.

The page is self-contained: every image is written into ``report/assets/`` and the page loads
nothing else (no script, no font, no URL), so the folder can be zipped, mailed and opened offline.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import FormatError, InputError
from dualscale.formats.run import CAPTURE_STAGE, STAGES

from . import format as fmt
from . import plots
from .adaptive import section as adaptive_section
from .checks import run_checks
from .html import Assets, write_page
from .trade import trade_rows

REQUIRED_STAGES = ("calibrate", "fit")

MAP_ORDER = ("albedo", "normal", "roughness", "anisotropy", "tangent", "ior", "specular_tint",
             "transmittance", "opacity")
MAX_HELDOUT_FIGURES = 8  # capture/re-render pairs shown (the fit stage writes up to 8)
MAX_OPEN_TABLE_ROWS = 16  # a longer per-light table is folded (<details>)


class _Missing(FormatError):
    """A required artefact of the run folder is missing or unreadable."""


# ---------------------------------------------------------------------------------------------
# reading

def _check_value(c) -> str:
    """A check's value for the page: a percentage (held-out error) or a ratio, or "not measured"."""
    if c.value is None:
        return "not measured"
    return fmt.percent(c.value) if c.name == "fit held-out error" else f"{c.value:.2f}×"


def _json(run: Path, rel: str, *, required: bool, writer: str) -> dict[str, Any] | None:
    path = run / rel
    if not path.is_file():
        if required:
            raise _Missing(f"run report: {path} is missing (written by the {writer}); "
                           f"{run} is not a complete dualscale run folder")
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise _Missing(f"run report: {path} is not readable JSON ({e})") from e
    if not isinstance(doc, dict):
        raise _Missing(f"run report: {path} must hold a JSON object")
    return doc


def _exr_any(run: Path, rel: str, *, writer: str, rgb: bool) -> np.ndarray:
    """An image by channel names (R, G, B or Y), falling back to the first channels."""
    from dualscale.formats.exr import read_exr

    path = run / rel
    if not path.is_file():
        raise _Missing(f"run report: {path} is missing (written by the {writer})")
    try:
        return read_exr(path, ("R", "G", "B") if rgb else ("Y",))
    except ValueError:
        a = read_exr(path)
        if rgb:
            return a[..., :3] if a.shape[2] >= 3 else np.repeat(a[..., :1], 3, -1)
        return a[..., :1]
    except OSError as e:
        raise _Missing(f"run report: cannot read {path}: {e}") from e


def _maps(run: Path, rel: str, writer: str):
    """``(arrays, doc)`` of a maps folder through the one maps reader."""
    from dualscale.formats.maps import load_maps

    root = run / rel
    if not (root / "material.json").is_file():
        raise _Missing(f"run report: {root / 'material.json'} is missing (written by the {writer})")
    try:
        maps, meta = load_maps(root)
    except InputError:
        raise
    except (OSError, ValueError) as e:
        raise _Missing(f"run report: cannot read the maps in {root}: {e}") from e
    arrays = {name: t.detach().cpu().numpy() for name, t in maps.items()}
    return arrays, meta


# ---------------------------------------------------------------------------------------------
# page model

@dataclass
class Fig:
    src: str
    caption: str
    title: str = ""
    alt: str = ""


@dataclass
class Table:
    header: list[str]
    rows: list[list[Any]]
    numeric: set[int] = field(default_factory=set)


@dataclass
class Stage:
    name: str
    record: dict[str, Any] | None
    summary: dict[str, Any]
    warnings: list[dict[str, str]]

    @property
    def skipped(self) -> str | None:
        s = self.summary.get("skipped")
        return str(s) if s else None

    @property
    def seconds(self) -> float | None:
        v = (self.record or {}).get("seconds")
        return float(v) if isinstance(v, (int, float)) else None


#: summary keys that are parts of the stage's wall time (``seconds`` of the record), shown as such
_PART_SECONDS = {"seconds": "of which the per-pixel fit", "cv_seconds": "of which the cross-validation",
                 "train_seconds": "of which the training"}


def _summary_rows(summary: dict[str, Any]) -> list[tuple[str, str]]:
    """A stage summary as rows; its timings are labelled as parts of the stage's time."""
    parts = [(_PART_SECONDS[k], fmt.duration(v)) for k, v in summary.items()
             if k in _PART_SECONDS and isinstance(v, (int, float)) and not isinstance(v, bool)]
    return parts + fmt.rows({k: v for k, v in summary.items() if k not in _PART_SECONDS})


def _stage_rows(st: Stage) -> dict[str, Any]:
    r = st.record or {}
    return {
        "name": st.name,
        "present": st.record is not None,
        "skipped": st.skipped,
        "rows": [("finished", fmt.timestamp(r.get("finished"))), ("time", fmt.duration(r.get("seconds"))),
                 ("warnings", fmt.number(len(st.warnings)))],
        "params": fmt.rows(r.get("params") or {}),
        "versions": [(fmt.label(k), fmt.value(v)) for k, v in (r.get("versions") or {}).items()],
        "inputs": [(k, fmt.short_hash(v, 16) if isinstance(v, str) else fmt.value(v))  # the capture's: cameras
                   for k, v in (r.get("inputs") or {}).items()],
        "outputs": [str(o) for o in (r.get("outputs") or [])],
        "summary": _summary_rows(st.summary),
        "warnings": st.warnings,
    }


def _direction_deg(d) -> tuple[float, float]:
    v = np.asarray(d, float)
    n = float(np.linalg.norm(v)) or 1.0
    theta = math.degrees(math.acos(max(-1.0, min(1.0, v[2] / n))))
    phi = math.degrees(math.atan2(v[1], v[0])) % 360.0
    return theta, phi


def _components_text(c: Any) -> str:
    if isinstance(c, dict):
        on = [fmt.label(k) for k, v in c.items() if v is True]
        other = [f"{fmt.label(k)} {fmt.value(v)}" for k, v in c.items() if not isinstance(v, bool)]
        return ", ".join(on + other) or "none"
    return fmt.value(c)


def _selection(sel: dict[str, Any] | None) -> dict[str, Any] | None:
    """The component decision as tables (robust to missing keys)."""
    if not sel:
        return None
    comps = sel.get("components") if isinstance(sel.get("components"), dict) else {}
    comp_rows = [(fmt.label(k), fmt.value(v)) for k, v in comps.items()]
    decisions = []
    for k, v in sel.items():
        if isinstance(v, dict) and "chosen" in v:
            decisions.append([fmt.label(k), fmt.value(v.get("chosen")), fmt.value(v.get("overridden", False)),
                              fmt.value(v.get("evidence")) if v.get("evidence") is not None else fmt.DASH])
    cands = sel.get("candidates")
    cand_table = None
    if isinstance(cands, list) and cands:
        keys: list[str] = []
        for c in cands:
            for k in (c if isinstance(c, dict) else {}):
                if k not in keys:
                    keys.append(k)
        errs = [c.get("validation_error") for c in cands if isinstance(c, dict)
                and isinstance(c.get("validation_error"), (int, float))]
        best = min(errs) if errs else None
        header = [fmt.label(k) for k in keys] + ["chosen"]
        rows, numeric = [], set()
        for c in cands:
            c = c if isinstance(c, dict) else {"candidate": c}
            row = []
            for i, k in enumerate(keys):
                v = c.get(k)
                if k == "components":
                    row.append(_components_text(v))
                else:
                    if isinstance(v, (int, float)) and not isinstance(v, bool):
                        numeric.add(i)
                    row.append(fmt.value(v))
            chosen = (c.get("components") == comps) if comps and "components" in c else (
                best is not None and c.get("validation_error") == best)
            row.append("✓" if chosen else "")
            rows.append(row)
        cand_table = Table(header, rows, numeric)
    skip = {"components", "candidates"} | {k for k, v in sel.items() if isinstance(v, dict) and "chosen" in v}
    other = fmt.rows({k: v for k, v in sel.items() if k not in skip})
    return {"components": comp_rows, "decisions": decisions, "candidates": cand_table, "other": other}


# ---------------------------------------------------------------------------------------------
# the report

def _not_done(st, not_run: str, what: str) -> str:
    """The one-line note of a stage that did not run (``not_run``) or was skipped (its reason);
    empty when it ran."""
    if st is None or st.record is None:
        return not_run
    if st.skipped:
        return f"{what} was skipped: {st.skipped}."
    return ""


def write_run_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Render ``RUN/report/index.html`` (images in ``RUN/report/assets/``) from the run folder
    ``run_dir``; returns the page's path. ``out`` puts the page and its assets in another folder
    (the pipeline renders into its work folder, then renames it to ``RUN/report``). Raises
    :class:`dualscale.errors.FormatError` when a required artefact is missing."""
    run = Path(run_dir)
    if not run.is_dir():
        raise _Missing(f"run report: {run} is not a folder")
    run_doc = _json(run, "run.json", required=True, writer="digitize command")
    if run_doc.get("format") not in (None, "dualscale-run"):
        raise FormatError(f"run report: {run / 'run.json'} is a {run_doc.get('format')!r} file, "
                          "not dualscale-run")
    order = [str(s) for s in (run_doc.get("stages") or STAGES)]
    if CAPTURE_STAGE not in order and (run / "stages" / f"{CAPTURE_STAGE}.json").is_file():
        order.insert(0, CAPTURE_STAGE)  # digitize --rig: the capture stage ran first

    stages: dict[str, Stage] = {}
    all_warnings: list[dict[str, str]] = []
    for name in order:
        rec = _json(run, f"stages/{name}.json", required=name in REQUIRED_STAGES, writer=f"{name} stage")
        summary = (rec or {}).get("summary") or {}
        ws = [{"stage": name, "text": str(w)} for w in ((rec or {}).get("warnings") or [])]
        stages[name] = Stage(name, rec, summary if isinstance(summary, dict) else {"summary": summary}, ws)
        all_warnings.extend(ws)
    for name in REQUIRED_STAGES:
        if name not in stages:
            raise _Missing(f"run report: {run / 'run.json'} lists no {name!r} stage; the report needs it")
    _check_required(run)
    report_notes: list[dict[str, str]] = []

    def note(text: str) -> None:
        w = {"stage": "report", "text": text}
        report_notes.append(w)
        all_warnings.append(w)

    out_dir = Path(out) if out is not None else run / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    if (out_dir / "assets").is_dir():
        shutil.rmtree(out_dir / "assets")
    assets = Assets(out_dir, "assets")

    def fig(figure_caption, stem: str, title: str = "", alt: str = "") -> Fig:
        f, cap = figure_caption
        return Fig(assets.figure(f, stem), cap, title, alt or title or stem)

    # -- inputs and calibration
    cal = stages["calibrate"].summary
    texel = cal.get("texel_mm")
    calib_rows = [
        ("calibration file", str(cal["calibration"]) if cal.get("calibration") else
         "none: the captures were used as they came, without radiometric or colour calibration"),
        ("radiometric units", f"{cal.get('units_in', fmt.DASH)} → {cal.get('units_out', fmt.DASH)}"),
        ("colour space", f"{cal.get('colour_space_in', fmt.DASH)} → {cal.get('colour_space_out', fmt.DASH)}"),
        ("transfer curve removed", str(cal["transfer"]) if cal.get("transfer") else "none (input already linear)"),
        ("images", fmt.value(cal.get("images"))),
        ("clipped pixels (saturated in every bracket)", fmt.percent(cal.get("clipped_share"))),
        ("texel size", fmt.length_mm(texel)),
        ("micro field", fmt.size_mm(cal.get("field_mm"))),
    ]
    known = {"calibration", "units_in", "units_out", "colour_space_in", "colour_space_out", "transfer", "images",
             "clipped_share", "texel_mm", "field_mm"}
    calib_rows += fmt.rows({k: v for k, v in cal.items() if k not in known})
    inputs = {"rows": [("input", str(run_doc.get("input", fmt.DASH))), ("run folder", str(run.resolve())),
                       ("stages", ", ".join(order))],
              "options": fmt.rows(run_doc.get("options") or {}), "calibration": calib_rows}

    # -- fit: maps, selection, residual, held-out
    fit_sum = stages["fit"].summary
    maps, meta = _maps(run, "fit/maps", "fit stage")
    texel_fit = meta.get("texel_mm")  # None: the maps do not know their size (axes in px)
    field_fit = meta.get("field_mm")
    names = [n for n in MAP_ORDER if n in maps] + [n for n in maps if n not in MAP_ORDER]
    h, w = next(iter(maps.values())).shape[:2]
    map_figs = [fig(plots.map_figure(n, maps[n], texel_fit), f"map_{n}", plots.MAP_TITLES.get(n, n)) for n in names]
    fit_json = _json(run, "fit/maps/fit.json", required=False, writer="fit stage")
    if fit_json is None:
        note("fit/maps/fit.json is missing: the component decision cannot be shown")
    selection = _selection((fit_json or {}).get("selection"))

    residual = _exr_any(run, "fit/residual.exr", writer="fit stage", rgb=False)
    res_fig = fig(plots.residual_figure(residual, texel_fit), "fit_residual", "Fit residual")
    images, fitted = fit_sum.get("images"), fit_sum.get("train_images")
    method = fit_sum.get("heldout_method")
    fit_rows = [
        ("preset", fmt.value(fit_sum.get("preset"))),
        ("maps", f"{', '.join(names)} ({w} × {h} texels"
                 + (f", {fmt.size_mm(field_fit)})" if field_fit else ")")),
        ("images fitted", (f"{fmt.value(fitted)} of {fmt.value(images)} (no light held out)"
                           if images is not None else fmt.value(fitted))),
        ("held-out error measured by", fmt.value(method) if method else "not recorded"),
        ("held-out relative L1 (cross-validated; Σ|prediction − capture| / Σ capture, mean over lights)",
         fmt.percent(fit_sum.get("heldout_relative_l1"))),
        ("the same for the Lambertian baseline (same folds and pixels)",
         fmt.percent(fit_sum.get("heldout_baseline_relative_l1"))),
        ("the same for the per-pixel constant predictor (each pixel's mean over the training lights)",
         fmt.percent(fit_sum.get("heldout_constant_relative_l1"))),
        ("fit stage time", _stage_time(stages["fit"])),
    ]
    rad = (fit_json or {}).get("radiometry")
    if rad:  # photographs: the camera response and light intensities the maps were fitted under
        fit_rows.append(("camera response (photographs)", str(rad.get("response", rad.get("transfer")))))
        fit_rows.append(("lights' relative intensities", str(rad.get("intensities"))))
        for wmsg in rad.get("warnings") or []:
            fit_rows.append(("radiometry warning", str(wmsg)))
    shown = {"preset", "images", "train_images", "heldout_method", "heldout_relative_l1",
             "heldout_baseline_relative_l1", "heldout_constant_relative_l1", "seconds", "cv_seconds", "texel_mm"}
    fit_rows += fmt.rows({k: v for k, v in fit_sum.items() if k not in shown and k != "skipped"}, depth=0)

    heldout = _heldout(run, _json(run, "fit/heldout/heldout.json", required=True, writer="fit stage"), assets,
                       texel_fit)
    uncertainty = _uncertainty(run, fit_json or {}, maps, assets, texel_fit, note)
    adaptive = adaptive_section(run, fig, note)

    # -- fly-outs
    fly: dict[str, Any] = {"note": "", "fig": None, "rows": [], "resolution": None}
    st = stages.get("flyouts")
    fly["note"] = _not_done(st, "Fly-out detection was not run for this material.", "Fly-out detection")
    if not fly["note"]:
        fdoc = _json(run, "flyouts/flyouts.json", required=False, writer="flyouts stage")
        if fdoc is None:
            fly["note"] = "The flyouts stage ran but wrote no flyouts/flyouts.json."
            note(fly["note"])
        else:
            polys = fdoc.get("polylines_px") or []
            mask = None
            if (run / "flyouts/flyout_mask.exr").is_file():
                mask = _exr_any(run, "flyouts/flyout_mask.exr", writer="flyouts stage", rgb=False)
            bg = maps.get("albedo", np.full((h, w, 3), 0.5))
            fly["fig"] = fig(plots.flyout_figure(bg, polys, mask=mask, texel_mm=texel_fit), "flyouts", "Fly-outs")
            fly["rows"] = [("fibres found", fmt.value(fdoc.get("count", len(polys))))]
            if mask is not None:
                fly["rows"].append(("texels on a fibre", fmt.percent(float((mask > 0.5).mean()))))
            res = st.summary.get("resolvability") or fdoc.get("resolvability")
            fly["rows"] += _resolvability_rows(res)
            text = _resolvability_text(res)
            if text and not any(w["text"] == text for w in st.warnings):  # the stage's warning says it already
                fly["resolution"] = text

    # -- propagation
    prop: dict[str, Any] = {"note": "", "guidance": None, "maps": [], "rows": []}
    st = stages.get("propagate")
    prop["note"] = _not_done(st, "No guidance image was given: the maps cover the micro field only.", "Propagation")
    if not prop["note"]:
        ps = st.summary
        gt = ps.get("texel_mm")
        guidance = _exr_any(run, "propagate/guidance.exr", writer="propagate stage", rgb=True)
        prop["guidance"] = fig(plots.guidance_figure(guidance, ps.get("micro_box_px"), texel_mm=gt),
                               "guidance", "Guidance image")
        pmaps, pmeta = _maps(run, "propagate/maps", "propagate stage")
        pt = pmeta.get("texel_mm") or gt
        prop["maps"] = [fig(plots.map_figure(n, pmaps[n], pt, prefix="propagated "), f"propagated_{n}",
                            "propagated " + plots.MAP_TITLES.get(n, n))
                        for n in [n for n in MAP_ORDER if n in pmaps] + [n for n in pmaps if n not in MAP_ORDER]]
        gh, gw = guidance.shape[:2]
        prop["rows"] = [("guidance", str(ps.get("guidance", fmt.DASH))),
                        ("guidance size", f"{gw} × {gh} px" + (f" ({fmt.size_mm([gw * gt, gh * gt])})" if gt else "")),
                        ("guidance texel", fmt.length_mm(gt)),
                        ("micro field in the guidance", _box_text(ps.get("micro_box_px")))]
        try:  # where the run's preset sits on the benchmark's trade curve (issue 29 §4)
            prop["rows"] += trade_rows(ps)
        except FormatError as e:
            prop["rows"].append(("training time", fmt.duration(ps.get("train_seconds"))))
            note(f"the propagation trade curve is not shown: {e}")
        prop["rows"] += [(f"registration › {k}", v) for k, v in fmt.rows(ps.get("registration") or {})]

    # -- export
    exp: dict[str, Any] = {"note": "", "table": None, "files": None, "formats": ""}
    st = stages.get("export")
    exp["note"] = _not_done(st, "The maps were not exported.", "Export")
    if not exp["note"]:
        exports = st.summary.get("exports") or {}
        if not exports:
            exp["note"] = "The export stage wrote no files."
        rows, file_rows = [], []
        for scale, e in exports.items():
            size = e.get("repeat_mm")
            for fmt_name, files in (e.get("files") or {}).items():
                paths = [run / "export" / scale / f for f in files]
                missing = [str(p.relative_to(run)) for p in paths if not p.is_file()]
                for m_ in missing:
                    note(f"export lists {m_}, which is not in the run folder")
                main = next((f for f in files if Path(f).suffix in (".mtlx", ".gltf", ".glb", ".u3ma", ".json")),
                            files[0] if files else "")
                sizes = {f: (run / "export" / scale / f).stat().st_size for f in files
                         if (run / "export" / scale / f).is_file()}
                rows.append([scale, fmt_name, f"export/{scale}/{main}" if main else fmt.DASH,
                             _size(sizes[main]) if main in sizes else "missing",
                             _files_text(len(files), sum(sizes.values())),
                             (fmt.size_mm(size) if size else fmt.DASH) + (" (seamless tile)" if e.get("tiled") else "")])
                file_rows += [[scale, fmt_name, f"export/{scale}/{f}", _size(sizes[f]) if f in sizes else "missing"]
                              for f in files]
        if rows:
            exp["table"] = Table(["scale", "format", "main file", "its size", "files of the format", "repeat"],
                                 rows, {3})
            exp["files"] = Table(["scale", "format", "file", "size"], file_rows, {3})
        if st.summary.get("formats"):
            exp["formats"] = fmt.value(st.summary["formats"])

    # -- time per stage
    timed = [s for s in stages.values() if s.record is not None]
    timing = None
    if timed:
        timing = fig(plots.time_bars([s.name for s in timed], [s.seconds for s in timed]), "time_per_stage",
                     "Time per stage")

    checks = run_checks(stages["fit"].record)
    failed = [c for c in checks if c.ok is False]
    verdict = {"text": ("failed: " + ", ".join(c.name for c in failed)) if failed else
               "passed" if any(c.ok for c in checks) else "not measured",
               "goal": "docs/DIGITIZE.md, “The run's check”", "ok": (not failed) if any(
                   c.ok is not None for c in checks) else None}
    check_table = Table(["check", "value", "goal", "", "what it means"],
                        [[c.name, _check_value(c), c.goal, c.mark or "not measured", c.text] for c in checks], {1})
    headline = [
        ("the run's check", verdict),
        ("held-out relative L1 (cross-validated)", fmt.percent(fit_sum.get("heldout_relative_l1"))),
        ("Lambertian baseline, same folds", fmt.percent(fit_sum.get("heldout_baseline_relative_l1"))),
        ("per-pixel constant predictor, same folds", fmt.percent(fit_sum.get("heldout_constant_relative_l1"))),
        ("maps", f"{len(names)} at {w} × {h}"),
        ("texel", fmt.length_mm(texel_fit)),
        ("total time" + (" (capture included)" if CAPTURE_STAGE in stages and stages[CAPTURE_STAGE].record else ""),
         fmt.duration(sum(s.seconds or 0.0 for s in timed))),
        ("warnings", fmt.number(len(all_warnings))),
    ]
    sections = [("checks", "Checks"), ("warnings", "Warnings"), ("inputs", "Inputs and calibration")] + (
                [("adaptive", "Adaptive capture")] if adaptive else []) + [("selection", "Components"),
                ("maps", "Maps")] + ([("uncertainty", "Uncertainty")] if uncertainty else []) + [
                ("residual", "Fit residual"), ("heldout", "Held-out error"),
                ("flyouts", "Fly-outs"), ("propagation", "Propagation"), ("export", "Export"),
                ("time", "Time"), ("records", "Stage records")]
    stage_warn = {name: s.warnings for name, s in stages.items()}
    stage_warn["report"] = stage_warn.get("report", []) + report_notes
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    from dualscale import __version__

    return write_page(
        out_dir / "index.html", "run.html",
        title=f"dualscale run: {_material_name(run, run_doc, stages)}",
        subtitle=f"{run.resolve()} · {len(order)} stages · report written {now}",
        toc=sections, footer=f"dualscale {__version__} · written {now} · this folder is self-contained and opens offline",
        headline=headline, checks=check_table, checks_failed=bool(failed), warnings=all_warnings, stage_warn=stage_warn, inputs=inputs, selection=selection,
        fit_rows=fit_rows, maps=map_figs, uncertainty=uncertainty, adaptive=adaptive, residual=res_fig, heldout=heldout, flyouts=fly, propagation=prop,
        export=exp, timing=timing, records=[_stage_rows(stages[n]) for n in order],
        timing_table=Table(["stage", "time"], [[s.name, fmt.duration(s.seconds)] for s in timed], {1}),
    )


def _check_required(run: Path) -> None:
    """Fail before drawing anything when a required artefact of the fit is missing."""
    for rel in ("fit/maps/material.json", "fit/residual.exr", "fit/heldout/heldout.json"):
        if not (run / rel).is_file():
            raise _Missing(f"run report: {run / rel} is missing (written by the fit stage)")
    doc = _json(run, "fit/heldout/heldout.json", required=True, writer="fit stage")
    for light in _renders(doc):
        for key in ("capture", "render"):
            name = light.get(key)
            if not name or not (run / "fit" / "heldout" / str(name)).is_file():
                raise _Missing(f"run report: the {key} image {name!r} of LED {light.get('led_id')} is missing "
                               f"from {run / 'fit' / 'heldout'} (written by the fit stage)")


def _renders(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """The capture/render pairs of ``heldout.json``: ``renders`` (re-renders of the final fit),
    or, in a run folder of a dualscale that held lights out of the fit, the ``lights`` with
    images (those were held out)."""
    if "renders" in doc:
        return [r for r in doc.get("renders") or [] if isinstance(r, dict)]
    return [dict(l, held_out=True) for l in doc.get("lights") or [] if isinstance(l, dict) and "capture" in l]


def _heldout(run: Path, doc: dict[str, Any], assets: Assets, texel_mm: float | None) -> dict[str, Any]:
    """The held-out section: the cross-validated error of every light (table, hemisphere) and
    the capture/render pairs, each labelled held out or not (``heldout.json``, module doc)."""
    out: dict[str, Any] = {"figs": [], "table": None, "hemisphere": None, "note": "", "method": "",
                           "fold_table": False, "renders_note": ""}
    lights = [l for l in (doc.get("lights") or []) if isinstance(l, dict)]
    cross = "renders" in doc
    if cross and doc.get("method"):
        out["method"] = (f"Measured by {doc.get('heldout_method')}: in each fold the lights of the fold are left "
                         "out, the rest are fitted on the same pixels, and the left-out lights are predicted. "
                         "Every light is held out once, so every light has an error. The component choice was "
                         "made once, on all lights, and kept in every fold. The final maps are fitted on every "
                         "light; none is held out of them.")
    elif cross:
        out["method"] = (f"No held-out error: {doc.get('heldout_method') or 'no cross-validation pass'}. The final "
                         "maps are fitted on every light.")
    else:
        out["method"] = "Lights held out of the fit by an earlier dualscale (the table lists their errors)."
    if not lights:
        out["note"] = "No per-light held-out error was measured."
    else:
        rows, th, ph, err = [], [], [], []
        for l in lights:
            t, p = _direction_deg(l.get("direction", [0, 0, 1]))
            e = l.get("relative_l1")
            rows.append([fmt.value(l.get("led_id")), fmt.quantity(t, "°"), fmt.quantity(p, "°"),
                         fmt.value(l.get("fold")), fmt.percent(e), fmt.percent(l.get("baseline_relative_l1"))])
            th.append(t)
            ph.append(p)
            err.append(100.0 * float(e) if isinstance(e, (int, float)) else float("nan"))
        header = ["LED", "zenith angle θ", "azimuth φ", "fold", "held-out relative L1", "Lambertian baseline"]
        if all(len(f) == 1 for f in doc.get("folds") or [[0]]):  # leave-one-light-out: the fold is the light
            header.pop(3)
            rows = [r[:3] + r[4:] for r in rows]
        out["table"] = Table(header, rows, set(range(1, len(header))))
        out["fold_table"] = len(rows) > MAX_OPEN_TABLE_ROWS
        if any(np.isfinite(err)):
            f, cap, _ = plots.hemisphere_figure([("held-out error per light", th, ph, err, None)],
                                                label="held-out relative L1 [%]", size=(4.6, 3.6))
            out["hemisphere"] = Fig(assets.figure(f, "heldout_hemisphere"), cap, "Held-out error by light direction")
    renders = _renders(doc)
    if len(renders) > MAX_HELDOUT_FIGURES:
        renders = renders[:MAX_HELDOUT_FIGURES]
    if renders and not all(r.get("held_out") for r in renders):
        out["renders_note"] = ("Captures beside re-renders of the final fit. These lights are training lights: the "
                               "fit saw these captures, so the pairs show what the maps reproduce, not a prediction; "
                               "the errors in the table above are the held-out ones.")
    cv_err = {l.get("led_id"): l.get("relative_l1") for l in lights}
    for r in renders:
        lid = r.get("led_id")
        t, p = _direction_deg(r.get("direction", [0, 0, 1]))
        cap_img = _exr_any(run, f"fit/heldout/{r.get('capture')}", writer="fit stage", rgb=True)
        ren_img = _exr_any(run, f"fit/heldout/{r.get('render')}", writer="fit stage", rgb=True)
        if r.get("held_out"):
            title = (f"LED {fmt.value(lid)} (held out): θ {fmt.quantity(t, '°')}, φ {fmt.quantity(p, '°')}, "
                     f"relative L1 {fmt.percent(r.get('relative_l1'))}")
            f, cap = plots.heldout_figure(cap_img, ren_img, title=title, texel_mm=texel_mm)
        else:
            title = (f"LED {fmt.value(lid)}, a training light (not held out): θ {fmt.quantity(t, '°')}, "
                     f"φ {fmt.quantity(p, '°')}; re-render relative L1 {fmt.percent(r.get('relative_l1'))}, "
                     f"cross-validated {fmt.percent(cv_err.get(lid))}")
            f, cap = plots.heldout_figure(cap_img, ren_img, title=title, texel_mm=texel_mm,
                                          capture_title="capture (training light)",
                                          render_title="re-render of the final fit")
        out["figs"].append(Fig(assets.figure(f, f"rerender_led{lid}"), cap, title, title))
    return out


# ---------------------------------------------------------------------------------------------
# per-pixel uncertainty (issue 26)

def _channel_stats(s: np.ndarray, u: np.ndarray, pct: float) -> list[float | None]:
    out = []
    for c in range(s.shape[2]):
        v = s[..., c][~u[..., c] & np.isfinite(s[..., c])]
        out.append(float(np.percentile(v, pct)) if v.size else None)
    return out


def _channels_text(values, names, unit: str, pct: bool = False) -> str:
    if not values:
        return fmt.DASH
    one = [fmt.percent(v) if pct else fmt.quantity(v, unit) if v is not None else "undetermined" for v in values]
    if len(one) == 1:
        return one[0]
    return ", ".join(f"{n} {v}" for n, v in zip(names, one))


def _uncertainty(run: Path, fit_json: dict[str, Any], maps: dict[str, np.ndarray], assets: Assets,
                 texel_mm: float | None, note) -> dict[str, Any] | None:
    """The uncertainty section (``fit/maps/uncertainty/``, ``fit.json``'s ``"uncertainty"``):
    ``None`` when the fit wrote no uncertainty (a fit of an earlier dualscale).  Per map: the
    sigma image and histogram, beside the absolute error against the ground truth when the fit
    was scored against one (``fit.json``'s ``"ground_truth"``, its ``dir`` still readable), with
    the share of texels whose |error| <= 1.96 sigma (the normal's angle <= 1.73 sigma, a 2-D
    error: :func:`dualscale.fit.uncertainty.calibration`'s rule)."""
    from dualscale.fit.uncertainty import Z95, Z95_NORMAL, map_error
    from dualscale.formats.maps import SIGMA_UNITS, UNCERTAINTY_DIR, load_maps, load_uncertainty

    root = run / "fit" / "maps"
    if not (root / UNCERTAINTY_DIR / "uncertainty.json").is_file():
        return None
    try:
        sigma, und, doc = load_uncertainty(root)
    except (OSError, ValueError) as e:  # FormatError is a ValueError
        note(f"fit/maps/{UNCERTAINTY_DIR} is not readable ({e}); the uncertainty is not shown")
        return None
    rec = fit_json.get("uncertainty") if isinstance(fit_json.get("uncertainty"), dict) else {}
    gt_maps, gt_note = None, ""
    gt = fit_json.get("ground_truth")
    if isinstance(gt, dict) and gt.get("dir"):
        try:
            loaded, _ = load_maps(gt["dir"])
            gt_maps = {n: t.detach().cpu().numpy() for n, t in loaded.items()}
        except (OSError, ValueError, InputError) as e:
            gt_note = f"The ground truth the fit was scored against ({gt['dir']}) is not readable here ({e}): no error maps."
    units = doc.get("units") or {}
    names = [n for n in MAP_ORDER if n in sigma] + [n for n in sigma if n not in MAP_ORDER]
    figs, rows = [], []
    for n in names:
        s, u = sigma[n], und[n]
        unit = plots.sigma_unit(n)
        qunit = "" if unit == "map value" else unit
        chans = ("R", "G", "B") if s.shape[2] == 3 else ("",)
        err = None
        if gt_maps is not None and n in gt_maps and n in maps and gt_maps[n].shape[:2] == s.shape[:2]:
            err = np.abs(map_error(n, maps[n], gt_maps[n]))
        f, cap = plots.sigma_figure(n, s, u, units=str(units.get(n, SIGMA_UNITS.get(n, ""))), error=err,
                                    texel_mm=texel_mm)
        coverage = None
        if err is not None:
            ok = ~u & np.isfinite(s) & np.isfinite(err)
            if ok.any():
                z95 = Z95_NORMAL if n == "normal" else Z95
                coverage = float((err[ok] <= z95 * s[ok]).mean())
                cap += (f" Coverage: {fmt.percent(coverage)} of the determined texel channels have |error| ≤ "
                        f"{z95:.2f}σ (95 % if σ is right and the error Gaussian"
                        + (", 2-D for the normal, whose σ is the RMS angle)." if n == "normal" else ")."))
        title = f"σ of {plots.MAP_TITLES.get(n, n)}"
        figs.append(Fig(assets.figure(f, f"sigma_{n}"), cap, title, title))
        undet = [float(u[..., c].mean()) for c in range(u.shape[2])]
        row = [plots.MAP_TITLES.get(n, n), str(units.get(n, SIGMA_UNITS.get(n, ""))),
               _channels_text(_channel_stats(s, u, 50), chans, qunit),
               _channels_text(_channel_stats(s, u, 90), chans, qunit),
               _channels_text(undet, chans, "", pct=True)]
        if gt_maps is not None:
            row.append(fmt.percent(coverage) if coverage is not None else "not measured")
        rows.append(row)
    header = ["map", "unit of σ", "median σ", "90th percentile", "undetermined"]
    if gt_maps is not None:
        header.append(f"|error| ≤ {Z95:.2f}σ, the normal's ≤ {Z95_NORMAL:.2f}σ (ground truth; 95 % expected)")
    noise = rec.get("noise")
    info = [("noise scale", fmt.value(noise) if noise else "not recorded"),
            ("time", fmt.duration(rec.get("seconds")) if isinstance(rec.get("seconds"), (int, float)) else "not recorded"),
            ("undetermined texels shown in", f"{plots.UNDETERMINED_NAME} (a flat colour outside the colour map)")]
    if gt_maps is not None:
        info.append(("ground truth", str(gt.get("dir"))))
    return {"info": info, "table": Table(header, rows, set(range(2, len(header)))), "figs": figs,
            "gt": gt_maps is not None, "gt_note": gt_note}


def _material_name(run: Path, run_doc: dict[str, Any], stages: dict[str, Stage]) -> str:
    """The material's name for the title: ``--name`` (``run.json`` options), else the name the
    export stage used (its params), else the input folder's (its parent's for ``micro/``)."""
    name = (run_doc.get("options") or {}).get("name")
    if not name and stages.get("export") is not None and stages["export"].record:
        name = (stages["export"].record.get("params") or {}).get("name")
    if not name:
        src = Path(str(run_doc.get("input") or run.name))
        name = (src.parent.name if src.name == "micro" else src.name) or run.name
    return str(name)


def _stage_time(st: Stage) -> str:
    """The stage's wall time from its record, with the parts its summary records."""
    parts = [f"{_PART_SECONDS[k][len('of which '):]} {fmt.duration(v)}" for k, v in st.summary.items()
             if k in _PART_SECONDS and isinstance(v, (int, float)) and not isinstance(v, bool)]
    total = fmt.duration(st.seconds) if st.seconds is not None else "not recorded"
    return total + (f" (of which {', '.join(parts)})" if parts and st.seconds is not None else "")


def _resolvability_rows(res: Any) -> list[tuple[str, str]]:
    """The fly-out stage's resolvability record (:func:`dualscale.fit.flyouts.resolvability`) as rows."""
    if not isinstance(res, dict):
        return [("fibres resolved by the texel", "not recorded (a run of an earlier dualscale)")]
    sim = res.get("simulated_precision") or {}
    rows = [("fibre diameter", f"{fmt.length_mm(res.get('fibre_diameter_mm'))} ({res.get('fibre_diameter_source', '')})"),
            ("texels across a fibre", f"{fmt.number(res.get('texels_across'))} (texel {fmt.length_mm(res.get('texel_mm'))}); "
                                      f"{res.get('criterion', '')}"),
            ("fibres resolved by the texel", "yes" if res.get("resolved") else "no: under-resolved")]
    if sim:
        rows.append(("precision expected (simulated rig)",
                     f"{fmt.percent(sim.get('median'), 2)} of the detected length within {sim.get('tolerance_px', 2)} px "
                     f"of a true fibre (range {fmt.percent((sim.get('range') or [None])[0], 2)}–"
                     f"{fmt.percent((sim.get('range') or [None, None])[-1], 2)}, at "
                     f"{fmt.number(sim.get('texels_across'))} texels across; {sim.get('source', '')})"))
    demo = sim.get("demo_pipeline")
    if isinstance(demo, dict):
        rows.append(("the whole pipeline on the simulated rig",
                     f"{fmt.value(demo.get('fibres_detected'))} of {fmt.value(demo.get('fibres_true'))} fibres found, "
                     f"precision {fmt.percent(demo.get('precision'), 2)}, at {fmt.number(demo.get('texels_across'))} "
                     f"texels across ({demo.get('source', '')})"))
    return rows


def _resolvability_text(res: Any) -> str | None:
    """The warning of an under-resolved fibre (None when resolved or not recorded)."""
    if not isinstance(res, dict) or res.get("resolved", True):
        return None
    return str(res.get("warning") or "the texel under-resolves the fibres")


def _files_text(n: int, total: int) -> str:
    return f"{n} file{'s' if n != 1 else ''}, {_size(total)} in all"


def _box_text(box) -> str:
    if not box or len(box) != 4:
        return fmt.DASH
    x, y, bw, bh = box
    return f"{fmt.number(bw)} × {fmt.number(bh)} px at column {fmt.number(x)}, row {fmt.number(y)}"


def _size(n: int) -> str:
    for unit, k in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= k:
            return fmt.quantity(n / k, unit)
    return f"{n} B"


__all__ = ["write_run_report"]
