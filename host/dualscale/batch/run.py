"""Running a batch: each sample a chain of stage tasks (:func:`stage_task`) on a Dask client or
in this process (:func:`run_batch`; see :mod:`dualscale.batch`)."""

from __future__ import annotations

import os
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from dualscale.errors import Interrupted, one_line
from dualscale.pipeline import STAGES, Check, run_checks

from .samples import Sample


def _failed(stage: str, e: BaseException, seconds: float | None) -> dict[str, Any]:
    return {"stage": stage, "status": "failed", "seconds": seconds, "error_type": type(e).__name__,
            "error": one_line(e), "traceback": "".join(traceback.format_exception(e)[-8:])}


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

    The stage holds the lock of the sample's run folder (:class:`~dualscale.formats.lock.FolderLock`):
    a ``digitize`` writing that folder meanwhile makes the stage fail with "... is in use by PID ...".

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
        from dualscale.formats.lock import FolderLock
        from dualscale.pipeline import Digitizer

        d = Digitizer(sample.options(outdir, threads))
        d.run.mkdir(parents=True, exist_ok=True)
        with FolderLock(d.run, "batch"):  # a `digitize -o` on this sample's folder meanwhile: this stage fails
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
    def checks(self) -> list[Check]:
        """The run's own checks (:func:`dualscale.pipeline.run_checks`, docs/DIGITIZE.md "The
        run's check") on the fit stage's record; empty when the fit did not finish."""
        r = self.stages.get("fit") or {}
        return run_checks({"summary": r.get("summary") or {}}) if r.get("status") in ("done", "up to date") else []

    @property
    def failed_checks(self) -> list[Check]:
        return [c for c in self.checks if c.ok is False]

    @property
    def status(self) -> str:
        """``done`` when every stage finished (or was up to date) and the run's checks passed (or
        were not measured), ``check failed: <check>, ...`` when every stage finished but a check
        failed (a failed sample, as ``digitize`` exits 1), ``interrupted`` when the batch was
        stopped (Ctrl-C) before its stages ended without one failing, else ``failed``."""
        ok = len(self.stages) == len(STAGES) and all(r["status"] in ("done", "up to date")
                                                     for r in self.stages.values())
        if ok:
            bad = self.failed_checks
            return "check failed: " + ", ".join(c.name for c in bad) if bad else "done"
        if self.failure is None and any(r["status"] == "interrupted" for r in self.stages.values()):
            return "interrupted"
        return "failed"

    @property
    def interrupted_stage(self) -> str | None:
        """The stage that was running (or next) when the batch was stopped, or None."""
        return next((s for s, r in self.stages.items() if r["status"] == "interrupted"), None)

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


def _interrupt(result: SampleResult) -> None:
    """Settle a sample the batch stopped before its end (Ctrl-C): its finished stages keep their
    results, the first stage without one is ``interrupted`` (it was running, or next: its work
    folder resumes on the rerun) and the later ones are ``not run``."""
    out, first = {}, True
    for stage in STAGES:
        r = result.stages.get(stage)
        if r is not None and first:
            out[stage] = r
            continue
        if first:
            out[stage] = {"stage": stage, "status": "interrupted", "seconds": None}
            first = False
        else:
            out[stage] = {"stage": stage, "status": "not run", "seconds": None}
    result.stages = out


class BatchInterrupted(Interrupted):
    """The batch was stopped (Ctrl-C) before every sample ended; ``results``: one
    :class:`SampleResult` per sample, in list order, those not ended settled by
    :func:`_interrupt` -- what the summary of what finished is written from.  Exit 130; the same
    command resumes."""

    def __init__(self, results: list[SampleResult]) -> None:
        ended = sum(1 for r in results if r.status != "interrupted")
        stages = sum(1 for r in results for x in r.stages.values() if x["status"] in ("done", "up to date"))
        super().__init__(f"batch interrupted: {ended} of {len(results)} sample(s) ended, {stages} of "
                         f"{len(results) * len(STAGES)} stage(s) finished")
        self.results = results


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
    stop the batch: Ctrl-C raises :class:`BatchInterrupted`, which carries the results so far
    (every finished stage; the cluster's tasks are cancelled)."""
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

    futures: dict[Any, tuple[str, str]] = {}
    try:
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
    except KeyboardInterrupt:
        if futures:
            import contextlib

            with contextlib.suppress(Exception):
                client.cancel(list(futures))
        for r in results.values():
            if len(r.stages) < len(STAGES):
                _interrupt(r)
        raise BatchInterrupted([results[s.name] for s in samples]) from None
    return [results[s.name] for s in samples]


