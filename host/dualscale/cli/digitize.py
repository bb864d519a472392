"""``dualscale digitize INPUT -o RUN``: the whole job, resumable (see :mod:`dualscale.pipeline`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .choices import QUALITIES, STAGES
from .common import add_engine_options, add_output, add_work_options, apply_threads, engine_spec, output_folder, want_progress


def _line(st) -> str:
    rec, s = st.record, st.record.get("summary", {})
    state = "up to date" if st.skipped else f"{rec['seconds']:.1f} s"
    if "skipped" in s:
        state += f" (skipped: {s['skipped']})"
    warn = f", {len(rec['warnings'])} warning(s)" if rec.get("warnings") else ""
    lines = [f"  {st.name:<10s} {state}{warn}"]
    lines += [f"             warning: {w}" for w in (rec.get("warnings") or [])[:5]]
    if len(rec.get("warnings") or []) > 5:
        lines.append(f"             ... and {len(rec['warnings']) - 5} more in RUN/stages/{st.name}.json")
    return "\n".join(lines)


def _dataset_root(path: Path) -> Path:
    """The one name of a dataset given as its folder or as the folder holding its ``micro/``
    (``syn`` and ``syn/micro`` are the same input): the folder holding ``micro/``, resolved."""
    p = path.resolve()
    if (p / "micro" / "manifest.json").is_file() and not (p / "manifest.json").is_file():
        return p
    if p.name == "micro" and (p / "manifest.json").is_file():
        return p.parent
    return p


def _own_run(inp: str | None):
    """For ``output_folder(own=...)``: a run folder without a record (from before records) is this
    run's when its ``run.json`` names the same input; another input's when it names another."""
    def own(out: Path):
        import json

        doc_path = out / "run.json"
        if not doc_path.is_file():
            return False
        try:
            doc = json.loads(doc_path.read_text())
            before = doc.get("input") if isinstance(doc, dict) else None
        except (OSError, ValueError):
            return "its run.json is unreadable"
        if inp is not None and before is not None and _dataset_root(Path(before)) == _dataset_root(Path(inp)):
            return None
        return f"it holds the digitize run of another input ({before})"
    return own


def _empty(run: Path) -> None:
    """Remove what a refused run wrote into the run folder it made, but the folder's lock and
    record (:func:`.common.output_folder` removes those, and the folder, as it lets go) -- only
    when no stage finished (a stage record in ``RUN/stages/``: finished work is kept, and the
    run resumes), and only what a run writes (``run.json``, ``work/``, ``stages/``, the stage
    folders): a file someone else put there keeps the folder."""
    import shutil

    from dualscale.formats.run import CAPTURE_STAGE, STAGES

    from .common import LOCK_FILE, RECORD

    if any((run / "stages").glob("*.json")):
        return
    ours = {"run.json", "work", "stages", "selection.json", CAPTURE_STAGE, *STAGES}
    for p in run.iterdir() if run.is_dir() else []:
        if p.name in (LOCK_FILE, RECORD) or p.name not in ours:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _check_lines(res) -> list[str]:
    return [f"check: {c.text}" + ("" if c.ok is None else " ✓" if c.ok else " ✗") for c in res.checks]


def cmd_digitize(a: argparse.Namespace) -> int:
    from .export import parse_formats

    from dualscale.pipeline import CAPTURE_STAGE, DigitizeOptions, Digitizer, RigCapture, digitize

    from dualscale.errors import EXIT_CODES, InputError
    from dualscale.fit.stream import parse_memory

    if (a.input is None) == (a.rig is None):
        raise InputError("digitize: give a dataset folder INPUT, or --rig PORT with --camera SPEC (not both)")
    if a.rig is not None and not a.camera:
        raise InputError("digitize --rig: add the cameras, e.g. --camera sim:micro --camera sim:mid")
    if a.rig is not None and a.calibration is None:  # before the rig (or its simulator) is started
        from dualscale.errors import UnitsError

        raise UnitsError("digitize --rig: the rig captures camera counts: give its calibration file with "
                         "--calibration CAL (dualscale calibrate)")
    if a.adaptive and a.rig is None:
        raise InputError("digitize --adaptive: the adaptive capture runs on the rig (--rig PORT); a dataset is "
                         "already captured")
    if a.rig is not None:  # before the run folder or the rig: the adaptive options and the calibration's LEDs
        from dualscale.capture.plan import make_plan

        from .capture import adaptive_options

        a.adaptive_options = adaptive_options(a, make_plan("micro", a.lights))
    inp = a.input if a.input is not None else Path(a.output) / CAPTURE_STAGE / "micro"
    opts = DigitizeOptions(input=inp, run=a.output, calibration=a.calibration, guidance=a.guidance,
                           guidance_transfer=a.transfer, guidance_texel_mm=a.guidance_texel_mm, quality=a.quality,
                           until=a.until, threads=apply_threads(a), progress=want_progress(a), seed=a.seed,
                           engine=engine_spec(a), tile_px=a.tile_px, memory=parse_memory(a.memory),
                           export=tuple(parse_formats(a.export, '--export')), tile=a.tile, name=a.name, gt=a.gt)
    def start() -> None:
        print(f"digitize {opts.input} -> {opts.run} (quality {opts.quality})", flush=True)

    # every input is checked (Digitizer's preflight) before the run folder is made or touched
    prepared = Digitizer(opts) if a.rig is None else None
    ident = [_dataset_root(Path(a.input))] if a.rig is None else [f"rig:{a.rig}", *a.camera]
    run = Path(a.output)
    fresh = not run.exists()
    # the run folder is locked from before it is looked at until the end: a second digitize on the
    # same RUN is refused at once ("RUN is in use by PID ...", exit 2) instead of writing RUN/work/ too
    with output_folder(a, "digitize", ident, own=_own_run(a.input), lock=True):
        try:
            res = _run(a, opts, start, prepared, digitize, RigCapture)
        except InputError:
            if fresh:  # refused on its input: what this command wrote goes again (the folder too, on the way out)
                _empty(run)
            raise
    fit = res.record("fit")

    if fit is not None:
        s = fit["summary"]
        rel = s.get("heldout_relative_l1")
        print(f"fit: preset {s['preset']}, maps fitted on {s.get('train_images')} of {s.get('images')} images; "
              f"held-out relative L1 {'n/a' if rel is None else f'{rel:.3f}'}, {s.get('heldout_method', 'n/a')}")
        from .fit import _uncertainty_line

        line = _uncertainty_line(run / "fit" / "maps")  # the maps' sigma, as `dualscale fit` says it
        if line:
            print(f"fit: {line}")
    exp = res.record("export")
    if exp is not None:
        for scale, e in exp["summary"].get("exports", {}).items():
            size = e.get("repeat_mm")
            where = f"{size[0]:.3g} x {size[1]:.3g} mm" if size else "size unknown"
            print(f"export: {run / 'export' / scale} ({e['name']}, {'tile ' if e.get('tiled') else ''}{where}: "
                  f"{', '.join(f for f in e['files'] if f != 'maps')})")
    if res.record("report") is not None:
        print(f"report: {run / 'report' / 'index.html'}")
    if res.record("export") is not None:
        print(f"view it: {_cli_name()} view {run}")
    for line in _check_lines(res):
        print(line)
    failed = res.failed
    if failed:
        import sys

        print(f"dualscale digitize: check failed: {failed[0].text} (the outputs are in {run}; "
              "docs/DIGITIZE.md, \"The run's check\")", file=sys.stderr, flush=True)
        return EXIT_CODES["check_failed"]
    return 0


def _cli_name() -> str:
    """How this shell can run the command line again: ``dualscale`` when that name on PATH is
    the script now running, else that script's path (``.venv/bin/dualscale`` after ``make
    demo``, relative when it is below the working folder), else ``python -m dualscale.cli``."""
    import os
    import shutil
    import sys

    here = os.path.abspath(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    if not (here and os.path.basename(here) == "dualscale" and os.path.isfile(here)):
        return f"{sys.executable} -m dualscale.cli"
    on_path = shutil.which("dualscale")
    if on_path and os.path.samefile(on_path, here):
        return "dualscale"
    rel = os.path.relpath(here)
    return rel if not rel.startswith("..") else here


def _run(a, opts, start, prepared, digitize, RigCapture):
    """The stages, from the dataset or (``--rig``) after capturing on the rig."""
    if a.rig is None:
        return digitize(opts, on_stage=lambda st: print(_line(st), flush=True), on_start=start, prepared=prepared)
    from .capture import capture_options, rig_and_cameras

    roles = ("micro", "mid")
    with rig_and_cameras(a.rig, a.camera, roles, a.parity, a.stopbits, a.sim_speed) as (rig, cams):
        print(f"digitize from the rig {a.rig} ({', '.join(f'{r}: {c.spec}' for r, c in cams.items())})",
              flush=True)
        return digitize(opts, on_stage=lambda st: print(_line(st), flush=True), on_start=start,
                        rig=RigCapture(rig, cams, a.lights, capture_options(a, a.rig), a.adaptive_options))



EXIT_EPILOG = """exit codes:
  0    done, and the run's own check passed (or was not measured)
  1    the run finished but failed its own check: the fit's cross-validated held-out relative L1
       is above 50 % (the last line names it; docs/DIGITIZE.md, "The run's check")
  2    bad input: a file, a value, an output folder holding another run, or RUN in use by another
       command (its PID is named); nothing is written
  3    the rig or a camera (--rig)
  4    a missing tool or environment (a full disk, the dask extra for --workers)
  5    an internal error (please report it)
  130  interrupted (Ctrl-C, a stop request): run the same command again to resume"""


class _Formatter(argparse.HelpFormatter):
    """Wraps the description as usual, keeps the epilog's table as written."""

    def _fill_text(self, text, width, indent):
        if text.startswith("exit codes:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def register(sub) -> None:
    """Add ``digitize`` to an argparse subparsers object."""
    from .export import FORMATS_HELP

    d = sub.add_parser("digitize", help="the whole job: calibrate, fit, fly-outs, propagate, export, report "
                                        "(resumable: rerun the same command to continue)",
                       description="Turn a photometric capture into SVBSDF maps and materials: RUN/export/{micro,mesoscale}/ "
                                   "hold the maps and the MaterialX, glTF/GLB, U3M and EXR exports (docs/EXPORT.md), "
                                   "RUN/report/index.html the report. Rerunning the same command skips finished "
                                   "stages and resumes an interrupted one. RUN must be new, or this run's own "
                                   "folder (the same INPUT): a folder holding another command's outputs or "
                                   "another input's run is refused unless --overwrite (which empties it first). "
                                   "Every input (the dataset and its images, --calibration, --guidance) is checked "
                                   "before RUN is made.",
                       epilog=EXIT_EPILOG, formatter_class=_Formatter)
    d.add_argument("input", nargs="?", default=None,
                   help="photometric dataset folder (manifest.json), or a folder holding micro/; or use --rig")
    d.add_argument("--rig", default=None, metavar="PORT",
                   help="capture on the rig first (its serial port, or 'sim' for the simulated rig): the micro plan "
                        "with the micro camera, and the guidance with a mid camera if given (RUN/capture/)")
    add_output(d, "run folder RUN (created; reused to resume)")
    d.add_argument("--calibration", default=None, metavar="CAL",
                   help="calibration file (`dualscale calibrate`); required for datasets in sensor units")
    d.add_argument("--guidance", default=None, metavar="IMAGE",
                   help="mid-range image of the whole sample (image file or dataset folder) to propagate to")
    d.add_argument("--transfer", default=None, metavar="srgb|linear|gamma:G",
                   help="transfer function of a display-encoded --guidance image (PNG/JPEG/TIFF); only with "
                        "--guidance (default: none)")
    d.add_argument("--guidance-texel-mm", type=float, default=None, metavar="MM",
                   help="texel size of the guidance image (default: from its dataset, else the mid camera)")
    d.add_argument("--quality", choices=sorted(QUALITIES), default="standard",
                   help="coherent presets across stages (default: standard; docs/DIGITIZE.md measures them)")
    d.add_argument("--until", choices=STAGES, default=None, help="stop after this stage")
    d.add_argument("--seed", type=int, default=0, help="random seed of the fit and the training (default: 0)")
    d.add_argument("--export", default="all", metavar="FORMATS",
                   help=f"export formats, comma-separated: {FORMATS_HELP}; or 'all' (default)")
    d.add_argument("--tile", action="store_true",
                   help="export a seamless tile of whole repeats of the propagated maps (docs/TILE.md)")
    d.add_argument("--name", default=None, help="material name in the exports (default: the input folder's name)")
    d.add_argument("--gt", default=None, metavar="MAPS",
                   help="ground-truth maps (e.g. a synth sample's maps/) to score the fit stage against: the report "
                        "then shows the maps' errors beside their sigma and how often |error| <= 1.96 sigma "
                        "(evaluation only; docs/FITTING.md)")
    from .capture import add_adaptive_options, add_capture_options

    add_capture_options(d)
    add_adaptive_options(d)
    add_work_options(d)
    g = add_engine_options(d, "run the fit stage in pixel tiles on N local Dask worker processes (the same maps; "
                              "default: one process; docs/SCALE.md)")
    g.add_argument("--tile-px", type=int, default=None, metavar="PX",
                   help="side of the fit's tiles with --workers/--scheduler/--cluster (default 64; the same maps at "
                        "any side; docs/SCALE.md)")
    d.add_argument("--memory", default="2G", metavar="SIZE",
                   help="memory budget of the fit stage, e.g. 2G, 800M, or 'unlimited': a micro capture whose fit "
                        "needs more is fitted out of core, band by band from disk, with the same maps (default: 2G; "
                        "docs/SCALE.md)")
    d.set_defaults(fn=cmd_digitize)
