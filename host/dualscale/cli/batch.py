"""``dualscale batch LIST -o OUTDIR``: many samples through digitize, on a Dask cluster by
default (see :mod:`dualscale.batch`; docs/BATCH.md)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from .choices import QUALITIES
from .common import add_engine_options, add_output, add_work_options, apply_threads, engine_spec, output_folder, want_progress


def requested_engine(a: argparse.Namespace):
    """The :class:`dualscale.engine.EngineSpec` the options ask for, before the list is read
    (``--scheduler`` is reached here, within :data:`dualscale.engine.SCHEDULER_TIMEOUT_S`), or
    None for this process.  ``--workers`` defaults to the usable cores
    (:func:`dualscale.threads.usable_cores`) when the ``dask`` extra is installed, else 1."""
    from dualscale import engine
    from dualscale.threads import usable_cores

    if a.workers is None and a.scheduler is None and a.cluster == "local":
        a.workers = usable_cores() if engine.available() else 1
    return engine_spec(a)


def choose_engine(a: argparse.Namespace, samples: int, spec=False):
    """The :class:`dualscale.engine.EngineSpec` of the batch, or None to run in this process:
    :func:`requested_engine` (``spec``: its result when already made), then a local cluster
    gets no more workers than there are samples (a sample's stages are a chain: one worker
    each), and one worker is run in-process.  ``--threads N`` is each worker's thread count
    (default 1; ``auto`` is 1 too: the workers fill the cores)."""
    if spec is False:
        spec = requested_engine(a)
    if spec is None:
        return None
    if spec.scheduler is None and spec.cluster == "local":
        n = min(spec.workers, samples)
        if n <= 1:
            return None
        spec = replace(spec, workers=n)
    threads = a.threads if isinstance(a.threads, int) else 1
    return replace(spec, threads_per_worker=threads)


def cmd_batch(a: argparse.Namespace) -> int:
    import time
    from contextlib import nullcontext

    from dualscale.batch import BatchInterrupted, read_list, run_batch, table, write_summary
    from dualscale.errors import Interrupted

    from .export import parse_formats

    export = None if a.export.strip() == "all" else tuple(parse_formats(a.export, "--export"))
    requested = requested_engine(a)  # an unreachable --scheduler is told before the list and its datasets are read
    samples = read_list(a.list, quality=a.quality, export=export)  # every row checked before anything is written
    spec = choose_engine(a, len(samples), requested)
    threads = apply_threads(a) if spec is None else spec.threads_per_worker
    where = "in this process" if spec is None else f"on {spec.describe}"

    def ended(r) -> None:
        if r.status == "done":
            secs = sum(x["seconds"] or 0.0 for x in r.stages.values())
            up = sum(1 for x in r.stages.values() if x["status"] == "up to date")
            print(f"  {r.name}: done in {secs:.1f} s" + (f" ({up} stage(s) up to date)" if up else ""), flush=True)
        elif r.failure is None and r.failed_checks:  # every stage ran; the fit failed the run's check
            print(f"  {r.name}: FAILED {r.status}: {'; '.join(c.text for c in r.failed_checks)}", flush=True)
        else:
            f = r.failure or {}
            print(f"  {r.name}: FAILED at {f.get('stage')}: {f.get('error_type')}: {f.get('error')}", flush=True)

    with output_folder(a, "batch", [Path(a.list)], lock=True) as out:
        print(f"batch {a.list}: {len(samples)} sample(s) -> {out} {where}", flush=True)
        t0 = time.perf_counter()
        if spec is None:
            ctx = nullcontext(None)
        else:
            from dualscale.engine import connect

            ctx = connect(spec)
        engine = "in-process" if spec is None else spec.describe
        try:
            with ctx as client:
                results = run_batch(samples, out, client=client, threads=threads, progress=want_progress(a),
                                    on_sample=ended, quiet_exit=spec is not None and spec.scheduler is None
                                    and spec.cluster == "local")
        except BatchInterrupted as e:  # Ctrl-C: the summary of what finished, then exit 130
            doc = write_summary(e.results, out, list_path=a.list, engine=engine, seconds=time.perf_counter() - t0,
                                interrupted=True)
            print(table(doc), flush=True)
            raise Interrupted(f"{e}; the summary of what finished: {out / 'summary.html'}") from None
        doc = write_summary(results, out, list_path=a.list, engine=engine, seconds=time.perf_counter() - t0)
    print(table(doc))
    print(f"summary: {out / 'summary.html'} (and summary.csv, summary.json)")
    failed = [r.name for r in results if r.status != "done"]
    if failed:
        print(f"dualscale batch: {len(failed)} of {len(results)} sample(s) failed: {', '.join(failed)} "
              f"(errors in {out / 'summary.html'})", file=sys.stderr)
        return 1
    return 0


def register(sub) -> None:
    """Add ``batch`` to an argparse subparsers object."""
    from .export import FORMATS_HELP

    b = sub.add_parser("batch", help="digitize many samples (a CSV or YAML list), on a Dask cluster by default; "
                                     "summary.csv/.html (resumable)",
                       description="Run `dualscale digitize` for every sample of LIST into OUTDIR/<name>/, each sample "
                                   "a chain of stage tasks (on a local Dask cluster by default), and write "
                                   "OUTDIR/summary.csv, summary.html and summary.json: status, time per stage, the "
                                   "component decision, held-out quality, exports. A failing sample does not stop the "
                                   "others. Rerunning the same command skips every finished stage. LIST columns: name, "
                                   "input (required), calibration, guidance, transfer, guidance_texel_mm, quality, "
                                   "export, tile, seed (docs/BATCH.md). Exit codes: 0 every sample done, 1 some "
                                   "failed (see the summary), 2 bad LIST or options, or OUTDIR in use by another "
                                   "batch, 4 no dask extra or a --scheduler that does not answer, 130 interrupted "
                                   "(the summary of what finished is written; rerun to resume).")
    b.add_argument("list", metavar="LIST", help="the samples: a .csv with a header row, or a .yaml list "
                                                "(relative paths are relative to LIST's folder)")
    add_output(b, "output folder OUTDIR: one run folder per sample, and the summary (reused to resume)")
    b.add_argument("--quality", choices=sorted(QUALITIES), default="standard",
                   help="quality of samples whose row gives none (default: standard)")
    b.add_argument("--export", default="all", metavar="FORMATS",
                   help=f"export formats of samples whose row gives none, comma-separated: {FORMATS_HELP}; "
                        "or 'all' (default)")
    add_work_options(b, "threads of each Dask worker, or of the stages when the batch runs in this process "
                        "(--workers 1)", defaults="1 per worker (auto too: the workers fill the cores); in this "
                        "process OMP_NUM_THREADS if set, else auto")
    add_engine_options(b, "worker processes, each running one sample's stages at a time (default: the usable "
                          "cores when Dask is installed, at most one per sample; 1 = in this process, no Dask)")
    b.set_defaults(fn=cmd_batch)
