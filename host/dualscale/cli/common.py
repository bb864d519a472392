"""Options every long command shares: ``-o/--output`` (with ``--overwrite``), ``--threads N``
and ``--progress/--no-progress``; and the one way a command takes its output folder
(:func:`output_folder`).

**Output folders.**  Before any work, :func:`output_folder` creates the folder and writes,
renames and removes a probe file in it (:func:`dualscale.formats.atomic.probe_writable`): a
folder that cannot be written fails at once, not after the work.  It then writes the folder's
record, ``.dualscale-output.json`` (``{"format": "dualscale-output", "version": 1, "command":
..., "inputs": [...], "relative": [...]}``: the command and its resolved inputs, e.g. the
dataset, or the material and seed of ``synth``; ``relative``: each input path relative to the
folder, ``null`` for other values, so that a project folder moved or renamed with its inputs is
still the same run).  A folder is **foreign** when it holds a record of another command or
other inputs, or, without a record, the outputs of an earlier dualscale run (a
``material.json``, ``manifest.json``, ``fit.json``, ... in it or one level down; a command may
recognise its own earlier, unrecorded outputs: ``own``).  A foreign folder is refused (exit 2)
unless ``--overwrite`` is given.  ``--overwrite`` removes the folder's whole contents first,
whatever they are (another run's outputs, unrelated files, or the same run's, which then starts
over; ``capture --resume`` keeps its own capture); it never empties a folder that is, or holds,
one of the command's inputs, the working folder or the home folder.  Without ``--overwrite``,
rerunning the same command on the same inputs into its own folder is not foreign: it resumes or
replaces its own outputs, and files that mark no dualscale run are left alone beside them.  A
command that fails on its input before writing anything leaves no folder behind.

``--threads N|auto`` (:mod:`dualscale.threads`) sets torch's intra-op threads, OpenCV's and,
when the process has loaded it, numba's; onnxruntime takes the count from the command
(``propagate run``, the pipeline's propagate stage); numpy's BLAS follows ``OMP_NUM_THREADS``
set before the start.  ``auto`` is the usable cores (affinity, cgroup CPU quota) less the
1-minute load average, at least 1: on busy shared cores a second torch thread made the fit
5.6x slower (issue 15).  Without ``--threads`` the count is ``OMP_NUM_THREADS`` when set, else
``auto``.
``--progress`` draws a bar on stderr for each long step; the default is on when stderr is a
terminal.  Library functions never print: they get the choice as their ``progress`` argument
(:mod:`dualscale.progress`).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Iterator, Sequence

from dualscale.errors import InputError, ToolError
from dualscale.formats.lock import LOCK_FILE  # the lock of a folder being written (output_folder(lock=True))

RECORD = ".dualscale-output.json"
RECORD_FORMAT = "dualscale-output"
#: files that mark a folder (or a subfolder one level down) as holding a dualscale run's outputs
MARKERS = ("material.json", "manifest.json", "fit.json", "captures.json", "calibration.json", "flyouts.json",
           "study.json", "propagate.json", "evaluation.json", "run.json", "tile.json", "geometry.exr", "lights.json")


def add_output(parser: argparse.ArgumentParser, help: str, required: bool = True) -> None:
    """The one output option: ``-o/--output`` (dest ``output``), with ``--overwrite``."""
    parser.add_argument("-o", "--output", required=required, help=help)
    parser.add_argument("--overwrite", action="store_true",
                        help="empty the output folder first: all its contents are removed (another run's outputs, "
                             "unrelated files, or this same run's, which then starts over); needed for a folder that "
                             "holds another command's or another input's outputs; a rerun of the same command on "
                             "the same inputs into its own folder needs none (it resumes)")


def _is_path(x: object) -> bool:
    return isinstance(x, Path) or (isinstance(x, str) and os.path.exists(x))


def _identity(command: str, inputs: Sequence[object], out: Path | None = None) -> dict:
    """The record's identity of a run: the command and its inputs (paths resolved).  With
    ``out``, also ``relative``: each path input relative to the output folder (``None`` for
    values that are not paths), so that a project folder moved or renamed with its inputs and
    outputs inside is still the same run (:func:`_same_inputs`)."""
    inputs = [x for x in inputs if x is not None]
    doc: dict = {"command": command, "inputs": [str(Path(x).resolve()) if _is_path(x) else x for x in inputs]}
    if out is not None:
        base = out.resolve()
        doc["relative"] = [os.path.relpath(Path(x).resolve(), base) if _is_path(x) else None for x in inputs]
    return doc


def _same_inputs(doc: dict, ident: dict, out: Path) -> bool:
    """Whether a folder's record ``doc`` names the inputs of ``ident``: the same resolved paths,
    or (the folder moved or renamed with its inputs, issue 24 §7) the record's paths relative to
    the folder lead from where the folder is now to the same inputs."""
    before = doc.get("inputs")
    if before == ident["inputs"]:
        return True
    rel = doc.get("relative")
    if not isinstance(before, list) or not isinstance(rel, list) or len(rel) != len(before):
        return False
    base = out.resolve()
    moved = [str((base / r).resolve()) if isinstance(r, str) else b for r, b in zip(rel, before)]
    return moved == ident["inputs"]


def _foreign(out: Path, ident: dict, own=None) -> str | None:
    """Why ``out`` holds another run's outputs, or ``None``.  ``own(out)``: for a folder without a
    record, the reason it holds another run (text), or ``None`` when it holds this command's own
    earlier outputs; without it any marker file is another run's."""
    rec = out / RECORD
    if rec.is_file():
        try:
            doc = json.loads(rec.read_text())
        except (OSError, ValueError):
            return f"its record {rec.name} is unreadable"
        if not isinstance(doc, dict):
            return f"its record {rec.name} is unreadable"
        if doc.get("command") != ident["command"]:
            return f"it holds the outputs of 'dualscale {doc.get('command')}'"
        if not _same_inputs(doc, ident, out):
            return f"it holds the outputs of another run of {ident['command']} (inputs {doc.get('inputs')})"
        return None
    if own is not None:
        why = own(out)
        if why is not False:
            return why
    for m in MARKERS:
        for p in (out / m, *out.glob(f"*/{m}")):
            if p.is_file():
                return f"it holds the outputs of an earlier run ({p.relative_to(out)})"
    return None


def _read_record(out: Path) -> dict | None:
    """The folder's record as written, or ``None`` (none, or unreadable)."""
    try:
        doc = json.loads((out / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _is_within(a: Path, b: Path) -> bool:
    """Whether ``a`` is ``b`` or inside it."""
    try:
        a.relative_to(b)
        return True
    except ValueError:
        return False


def _clear(out: Path, inputs: Sequence[object]) -> Path | None:
    """Empty ``out`` (``--overwrite``), refusing folders it must never empty.  The contents are
    moved aside into a hidden sibling folder, which is returned: :func:`output_folder` deletes it
    when the command succeeds and puts the contents back when it refuses its input or fails, so
    that bad input loses nothing.  None when nothing could be set aside (then they are deleted)."""
    res = out.resolve()
    guarded = [Path.home().resolve(), Path.cwd().resolve(), Path(res.anchor)]
    for x in inputs:
        if isinstance(x, (str, Path)) and os.path.exists(x):
            p = Path(x).resolve()
            if _is_within(p, res):
                raise InputError(f"-o {out} holds the input {x}: --overwrite would delete it; choose another folder")
    for g in guarded:
        if _is_within(g, res):
            raise InputError(f"-o {out} contains {g}: --overwrite empties only a folder of its own; "
                             "choose another folder")
    aside = res.parent / f".{res.name}.overwritten-{os.getpid()}"
    try:
        aside.mkdir()
        for p in res.iterdir():
            if p.name != LOCK_FILE:  # this command's own lock stays where it is held
                os.rename(p, aside / p.name)
        return aside
    except OSError:  # another filesystem or an unwritable parent: delete, as before
        if aside.is_dir():
            for p in aside.iterdir():
                os.rename(p, res / p.name)
            aside.rmdir()
    for p in res.iterdir():
        if p.name == LOCK_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return None


def _restore(out: Path, aside: Path) -> None:
    """Put back what :func:`_clear` set aside, removing what the failed command wrote."""
    for p in out.iterdir():
        if p.name == LOCK_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                p.unlink()
    for p in aside.iterdir():
        os.rename(p, out / p.name)
    aside.rmdir()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # someone else's process: alive
    return True


def _recover_aside(out: Path, command: str) -> None:
    """What a killed ``--overwrite`` left beside ``out``: ``.OUT.overwritten-PID`` (the folder's
    earlier contents, set aside by :func:`_clear`) whose PID is dead.  Nothing is lost: when the
    interrupted run wrote nothing into ``out`` the contents go back; otherwise they are kept under
    a visible name beside it, ``OUT.before-overwrite`` (the user's previous run), and a one-line
    notice says where."""
    res = out.resolve()
    if not res.parent.is_dir():
        return
    for aside in sorted(res.parent.glob(f".{res.name}.overwritten-*")):
        pid = aside.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid() or _pid_alive(int(pid)) or not aside.is_dir():
            continue
        try:
            left = [p for p in res.iterdir() if p.name not in (LOCK_FILE, RECORD)] if res.is_dir() else []
            if not left:
                res.mkdir(exist_ok=True)
                for p in aside.iterdir():
                    if p.name != LOCK_FILE:
                        os.replace(p, res / p.name)  # (the killed run's own record, if any, gives way)
                shutil.rmtree(aside, ignore_errors=True)
                print(f"dualscale {command}: note: an --overwrite of {out} was interrupted (PID {pid}) before it "
                      "wrote anything: the folder's earlier contents are back in it", file=sys.stderr)
                continue
            keep = res.parent / f"{res.name}.before-overwrite"
            n = 1
            while keep.exists():
                n += 1
                keep = res.parent / f"{res.name}.before-overwrite-{n}"
            os.rename(aside, keep)
            print(f"dualscale {command}: note: an --overwrite of {out} was interrupted (PID {pid}): the folder's "
                  f"earlier contents are in {keep} (delete it when you no longer need them)", file=sys.stderr)
        except OSError:
            continue


def _writable_error(out: Path, e: OSError) -> Exception:
    what = e.strerror or str(e)
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EEXIST, errno.EISDIR, errno.ENOENT):
        return InputError(f"cannot write the output folder {out}: {what}")
    return ToolError(f"cannot write the output folder {out}: {what}")


def refuse_inside_held(out: str | Path, command: str) -> None:
    """Refuse an output inside a folder that another live process holds (a running digitize's
    ``RUN/fit``, ``RUN/export``, a light file in ``RUN/``): the folders above ``out`` whose lock
    file ``.dualscale-lock`` exists are tried (:class:`~dualscale.formats.lock.FolderLock`),
    and a held one raises :class:`~dualscale.errors.InputError` "... is in use by PID ..."
    (exit 2).  A lock file left by a killed process does not block (and is removed)."""
    from dualscale.formats.lock import FolderLock

    for parent in Path(out).absolute().parents:
        if (parent / LOCK_FILE).is_file():
            try:
                FolderLock(parent, command).acquire().release()
            except OSError:
                pass  # a folder this user cannot write: not one a command of theirs holds


@contextlib.contextmanager
def output_folder(args: argparse.Namespace, command: str, inputs: Sequence[object] = (), *,
                  record: bool = True, folder: str | Path | None = None, own=None,
                  lock: bool = False) -> Iterator[Path]:
    """Take the command's output folder (``folder``, default ``args.output``) before any work:
    refuse a foreign one unless ``args.overwrite`` (module docstring), check that it can be
    written (a probe file through :mod:`dualscale.formats.atomic`; ``InputError`` for a folder
    the user cannot write, ``ToolError`` for a full disk), and write its record (``record``).
    Yields the folder.  When the body fails and the folder was created here and holds nothing
    but its record, it is removed again.

    ``inputs``: what identifies the run (paths are resolved; other values kept as they are).
    ``own(folder)``: for a folder without a record, ``None`` when it holds this command's own
    earlier outputs of the same inputs (written before records existed), a reason (text) when
    another run's, ``False`` to apply the usual marker files.

    The record names the inputs by their resolved paths and by their paths relative to the
    folder: a folder moved or renamed together with its inputs (a project folder) is still this
    run's, and resumes (issue 24 §7).

    ``lock``: hold :class:`dualscale.formats.lock.FolderLock` on the folder from before anything in
    it is looked at (``--overwrite`` included) until the command ends, so that a second command
    on the same folder is refused at once (``InputError``: "... is in use by PID ...") instead of
    writing into the first one's work; the lock file ``.dualscale-lock`` is removed at the end,
    and one left by a killed process does not block.  Without ``lock`` the folder's lock is still
    tried before anything in it is cleared or written: a folder that another live process holds
    (a running digitize) is refused the same way, ``--overwrite`` or not."""
    out = Path(folder if folder is not None else args.output)
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out} is a file, not a folder")
    refuse_inside_held(out, command)
    created = []  # the folders made here, deepest last
    p = out.absolute()
    while not p.exists():
        created.append(p)
        p = p.parent
    from dualscale.formats.lock import FolderLock

    if not lock:
        if out.is_dir():  # a folder another command holds (a digitize running in it) is refused, --overwrite or not
            try:
                FolderLock(out, command).acquire().release()
            except OSError:
                pass  # a folder that cannot be written: the probe below says so
        _recover_aside(out, command)
        yield from _output_folder(args, command, inputs, out, created, record, own)
        return

    held = FolderLock(out, command)
    try:
        out.mkdir(parents=True, exist_ok=True)
        held.acquire()
    except (InputError, OSError) as e:
        for d in created:
            with contextlib.suppress(OSError):
                d.rmdir()  # only when empty: made here for the lock
        if isinstance(e, InputError):
            raise
        raise _writable_error(out, e) from None
    try:
        _recover_aside(out, command)
        yield from _output_folder(args, command, inputs, out, created, record, own)
    finally:
        held.release()
        for d in created:  # a refused run's folder made here went with its record; its lock file too
            if d.is_dir() and not any(d.iterdir()):
                with contextlib.suppress(OSError):
                    d.rmdir()


def _output_folder(args: argparse.Namespace, command: str, inputs: Sequence[object], out: Path,
                   created: list[Path], record: bool, own) -> Iterator[Path]:
    """The body of :func:`output_folder` (``created``: the folders it made, deepest first)."""
    from dualscale.formats.atomic import probe_writable, write_json

    ident = _identity(command, inputs, out)
    aside: Path | None = None
    if out.is_dir() and record:
        why = _foreign(out, ident, own)
        overwrite = getattr(args, "overwrite", False)
        if why is not None:
            if not overwrite:
                raise InputError(f"-o {out}: {why}; pass --overwrite to replace them, or choose another folder")
            aside = _clear(out, inputs)
        elif overwrite and not getattr(args, "resume", False) and any(out.iterdir()):
            aside = _clear(out, inputs)  # --overwrite empties the folder, as its help says (capture --resume keeps it)
    had_record = (out / RECORD).is_file()
    try:
        probe_writable(out)
        if record and _read_record(out) != {"format": RECORD_FORMAT, "version": 1, **ident}:
            write_json(out / RECORD, {"format": RECORD_FORMAT, "version": 1, **ident})  # (the same one is left be)
    except OSError as e:
        if aside is not None:
            _restore(out, aside)
        raise _writable_error(out, e) from None
    try:
        yield out
        if record and not (out / RECORD).is_file():  # a writer that replaced the whole folder (atomic_dir)
            write_json(out / RECORD, {"format": RECORD_FORMAT, "version": 1, **ident})
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)
    except BaseException as e:
        if aside is not None:
            from dualscale.errors import DualscaleError, Interrupted

            if isinstance(e, DualscaleError) and not isinstance(e, Interrupted) or isinstance(e, (ValueError, OSError)):
                _restore(out, aside)  # refused or failed: the folder's earlier contents come back
                raise
            shutil.rmtree(aside, ignore_errors=True)  # interrupted: the new run's outputs stay, to resume
        if record and not had_record and isinstance(e, InputError) and (out / RECORD).is_file():
            # refused on its input: leave a folder that was already there as it was (an interrupted
            # run keeps its record, so that the rerun resumes)
            with contextlib.suppress(OSError):
                (out / RECORD).unlink()
        for d in created:
            left = [x for x in d.iterdir() if x.name != LOCK_FILE] if d.is_dir() else []
            if d == out.absolute() and all(x.name == RECORD for x in left):
                shutil.rmtree(d, ignore_errors=True)
            elif d.is_dir() and not left:
                with contextlib.suppress(OSError):
                    d.rmdir()
        raise


AUTO_HELP = ("'auto' = the usable cores less the 1-minute load average, at least 1 (on busy cores extra "
             "threads slow everything down)")
THREADS_HELP = f"{AUTO_HELP}; default: OMP_NUM_THREADS if set, else auto"


def _threads_arg(text: str) -> int | str:
    """argparse type of ``--threads``: a count >= 1 or ``"auto"``; anything else is a one-line
    usage error (exit 2)."""
    from dualscale.threads import parse

    try:
        return parse(text)
    except InputError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--threads ")) from None


class _ThreadsAction(argparse.Action):
    """Stores ``--threads``; a count above the machine's cores (:func:`dualscale.threads.clamp`)
    is lowered to them with a one-line notice on stderr (``dualscale CMD: warning: ...``): more
    threads than cores only make the libraries' threads wait on each other."""

    def __call__(self, parser, namespace, values, option_string=None):
        from dualscale.threads import clamp

        n, note = clamp(values)
        if note:
            print(f"{parser.prog}: warning: {note}", file=sys.stderr)
        setattr(namespace, self.dest, n)


def add_work_options(parser: argparse.ArgumentParser, threads_help: str | None = None,
                     defaults: str | None = None) -> None:
    """Add ``--threads N|auto`` and ``--progress/--no-progress`` to a long command
    (``threads_help``: what the count drives, before the common words on ``auto``; ``defaults``:
    the command's own default, in place of the usual one, so that the help states one)."""
    default = f"default: {defaults}" if defaults else "default: OMP_NUM_THREADS if set, else auto"
    parser.add_argument("--threads", type=_threads_arg, action=_ThreadsAction, default=None, metavar="N|auto",
                        help=f"{threads_help or 'CPU threads for torch, OpenCV and numba'}; {AUTO_HELP}; {default}")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: on when stderr is a terminal)")


def apply_threads(args: argparse.Namespace) -> int:
    """Choose the command's thread count from ``args.threads`` (``N``, ``"auto"`` or ``None``:
    :func:`dualscale.threads.resolve`), set it in torch, OpenCV and (when loaded) numba
    (:func:`dualscale.threads.set_threads`), and return it for the pools a command makes itself
    (onnxruntime sessions).  Raises :class:`~dualscale.errors.InputError` for a count below 1."""
    from dualscale.threads import resolve, set_threads

    n = resolve(getattr(args, "threads", None))  # --threads above the cores was lowered when parsed
    import cv2
    import torch  # noqa: F401 - loaded here so that set_threads reaches it

    return set_threads(n)


def want_progress(args: argparse.Namespace) -> bool:
    """``--progress`` / ``--no-progress`` if given, else whether stderr is a terminal."""
    p = getattr(args, "progress", None)
    return sys.stderr.isatty() if p is None else bool(p)


def add_engine_options(parser: argparse.ArgumentParser, workers_help: str, default_workers: int | None = None):
    """Add ``--workers N``, ``--scheduler ADDRESS``, ``--cluster KIND`` and ``--cluster-config
    FILE`` (:mod:`dualscale.engine`; they need the ``dask`` extra); returns their argument group
    (for a command's own cluster options)."""
    from dualscale.engine import CLUSTERS

    g = parser.add_argument_group("cluster (Dask; pip install 'dualscale[dask]')")
    g.add_argument("--workers", type=int, default=default_workers, metavar="N", help=workers_help)
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="an existing Dask scheduler (tcp://host:8786) and its workers, instead of a local cluster")
    g.add_argument("--cluster", choices=list(CLUSTERS), default="local",
                   help="'local' (worker processes on this machine, the default) or a batch system through "
                        "dask-jobqueue (--workers jobs; settings in --cluster-config)")
    g.add_argument("--cluster-config", default=None, metavar="YAML",
                   help="dask-jobqueue settings for --cluster slurm/pbs/...: memory, cores, queue, walltime, "
                        "account, job_extra_directives (docs/SCALE.md)")
    return g


def engine_spec(args: argparse.Namespace, reach: bool = True):
    """The :class:`dualscale.engine.EngineSpec` the engine options ask for, or ``None`` to run
    in-process (no ``--workers`` above 1, no ``--scheduler``, no job-queue ``--cluster``).
    Raises :class:`~dualscale.errors.InputError` for unusable values and
    :class:`~dualscale.errors.ToolError` when a cluster is asked for without the ``dask`` extra,
    when a job-queue cluster's submit command is missing, or (``reach``) when a ``--scheduler``
    does not answer within :data:`dualscale.engine.SCHEDULER_TIMEOUT_S`
    (:func:`dualscale.engine.check_scheduler`): the commands call this before they read their
    datasets."""
    from dualscale.engine import EngineSpec, require

    workers, scheduler = getattr(args, "workers", None), getattr(args, "scheduler", None)
    cluster, config = getattr(args, "cluster", "local"), getattr(args, "cluster_config", None)
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if scheduler is not None and (cluster != "local" or (workers or 1) > 1 or config is not None):
        raise InputError("--scheduler ADDRESS uses that scheduler's workers: leave out --workers, --cluster and "
                         "--cluster-config (choose one)")
    if scheduler is None and cluster == "local" and (workers is None or workers <= 1):
        if config is not None:
            raise InputError("--cluster-config is for a job-queue cluster (--cluster slurm, pbs, ...)")
        return None
    spec = EngineSpec(workers=workers or 1, scheduler=scheduler, cluster=cluster,
                      config=None if config is None else Path(config))
    require("--scheduler" if scheduler else (f"--cluster {cluster}" if cluster != "local" else "--workers"))
    if cluster != "local":  # a typo in the settings, or no sbatch here: say so before any work
        from dualscale.engine import check_jobqueue

        check_jobqueue(spec)
    if scheduler is not None and reach:  # an address nobody answers at: say so now, not 30 s after the data loaded
        from dualscale.engine import check_scheduler

        check_scheduler(scheduler)
    return spec
