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
more often than Dask's ``allowed-failures``) counts as a failure of that stage.  Ctrl-C stops
the batch (:class:`BatchInterrupted`): the summary of what finished is still written, each
sample not ended marked ``interrupted`` at the stage that was running or next, and the same
command resumes.

**The summary** (:func:`write_summary`): ``OUTDIR/summary.csv``, ``summary.json`` and a
self-contained ``summary.html`` (escaped; links to each sample's report and exports), written
atomically: per sample the status, the failed stage and error, the seconds of each stage (and
which were up to date), the fitted component decision (opaque / isotropic / tinted, Sec. 5),
the fit's held-out SSIM and relative L1 (Sec. 6), the propagation's in-field L1 and
registration NCC when it ran (Sec. 7), and the export files.
"""

from .run import BatchInterrupted, SampleResult, run_batch, stage_task
from .samples import FIELDS, RESERVED, Sample, read_list
from .summary import components_text, sample_row, table, write_summary

__all__ = ["BatchInterrupted", "FIELDS", "RESERVED", "Sample", "SampleResult", "components_text", "read_list", "run_batch",
           "sample_row", "stage_task", "table", "write_summary"]
