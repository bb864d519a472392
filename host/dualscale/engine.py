"""Where work runs beyond one process (issue 16): a Dask distributed cluster, or none.

dualscale does not schedule work across processes itself; `Dask distributed
<https://distributed.dask.org>`_ does.  This module only *chooses and opens* the cluster; the
stages that can use one (the tiled fit, :mod:`dualscale.fit.tiled`; the batch,
:mod:`dualscale.batch`) submit their tasks to the :class:`distributed.Client` it yields.

**Clusters** (:data:`CLUSTERS`, a ``method=``-style registry; :class:`EngineSpec`):

- ``local`` (the default): a ``distributed.LocalCluster`` of ``workers`` *processes* on this
  machine, each with ``threads_per_worker`` threads (1 by default).  Every worker runs
  :func:`dualscale.threads.set_threads` at the start of each task (:func:`in_worker`), so
  torch, numba and OpenCV each use that many threads: N workers x 1 thread fill N cores without
  oversubscription.  The workers do not get Dask's ``MALLOC_TRIM_THRESHOLD_`` (it made the
  fit 1.4-1.5x slower in a worker; :data:`MALLOC_TRIM`).  Killed worker processes are
  restarted by their nanny, and the scheduler reruns the tasks they held on another worker
  (up to ``distributed.scheduler.allowed-failures`` times, 3 by default).
- ``--scheduler ADDRESS`` (``tcp://host:8786``): an existing scheduler and its workers, started
  by whoever runs the cluster (``dask scheduler`` / ``dask worker``, a Kubernetes operator ...).
  The workers need dualscale and its dependencies installed, the same version.
- ``slurm``, ``pbs``, ``sge``, ``lsf``, ``htcondor``: ``dask-jobqueue`` submits batch jobs that
  start workers (``workers`` of them, ``cluster.scale(workers)``).  Its settings (``cores``,
  ``memory``, ``queue``, ``walltime``, ``account``, ``job_extra_directives`` ...: the keyword
  arguments of ``dask_jobqueue.SLURMCluster`` and its siblings) come from a small YAML file
  (``--cluster-config``), else from Dask's own configuration (``~/.config/dask/jobqueue.yaml``).
  ``job_script(spec)`` returns the batch script without submitting anything.

**Without the extra** (``pip install dualscale[dask]``), :func:`available` is False and the
commands run in-process as before; asking for a cluster then raises
:class:`~dualscale.errors.ToolError` naming the extra.

Bottom layer: imports nothing of dualscale but :mod:`dualscale.errors` and
:mod:`dualscale.threads`; ``distributed`` only when a cluster is opened.
"""

from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from dualscale.errors import InputError, ToolError

#: cluster kinds: ``local`` (distributed.LocalCluster) and the dask-jobqueue classes
CLUSTERS: dict[str, str] = {"local": "LocalCluster", "slurm": "SLURMCluster", "pbs": "PBSCluster",
                            "sge": "SGECluster", "lsf": "LSFCluster", "htcondor": "HTCondorCluster"}
EXTRA = "pip install 'dualscale[dask]'"
#: seconds to wait for a scheduler given by address, and for a cluster's first worker
CONNECT_TIMEOUT_S = 30
#: seconds :func:`check_scheduler` waits for a ``--scheduler`` to answer Dask's handshake, before
#: any work (an unreachable address is told within 5 s of the command's start, issue 24 §8)
SCHEDULER_TIMEOUT_S = 3.0
#: Dask's nannies start workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (return freed memory to the
#: system early): every tile fit then page-faults its scratch arrays back in, 1.4-1.5x slower than
#: in-process (docs/SCALE.md).  The local cluster does not set it; a value the user set is kept.
MALLOC_TRIM = "MALLOC_TRIM_THRESHOLD_"
_USER_MALLOC_TRIM = os.environ.get(MALLOC_TRIM)


@dataclass(frozen=True)
class EngineSpec:
    """Which cluster to open.  ``workers``: worker processes (``local``) or jobs' workers
    (jobqueue kinds; ignored for ``scheduler``), at least 1; ``threads_per_worker``: threads of
    each worker *and* of the libraries in it; ``scheduler``: address of an existing scheduler
    (takes precedence over ``cluster``); ``cluster``: a key of :data:`CLUSTERS`; ``config``: a
    YAML file of keyword arguments for a jobqueue cluster.  Raises
    :class:`~dualscale.errors.InputError` for values that cannot be used."""

    workers: int = 1
    threads_per_worker: int = 1
    scheduler: str | None = None
    cluster: str = "local"
    config: Path | None = None

    def __post_init__(self) -> None:
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise InputError(f"--workers must be a whole number >= 1, got {self.workers!r}")
        if isinstance(self.threads_per_worker, bool) or not isinstance(self.threads_per_worker, int) \
                or self.threads_per_worker < 1:
            raise InputError(f"threads per worker must be a whole number >= 1, got {self.threads_per_worker!r}")
        if self.cluster not in CLUSTERS:
            raise InputError(f"--cluster {self.cluster!r}: choose one of {', '.join(CLUSTERS)}")
        if self.config is not None:
            object.__setattr__(self, "config", Path(self.config))
            if self.cluster == "local" and self.scheduler is None:
                raise InputError("--cluster-config is for a job-queue cluster (--cluster slurm, pbs, ...); "
                                 "the local cluster takes --workers only")
            if not self.config.is_file():
                raise InputError(f"--cluster-config {self.config}: no such file")

    @property
    def describe(self) -> str:
        """One line for logs and records: ``local (2 workers x 1 thread)``, ``scheduler tcp://...``."""
        if self.scheduler is not None:
            return f"scheduler {self.scheduler}"
        return f"{self.cluster} ({self.workers} worker{'s' if self.workers != 1 else ''} x " \
               f"{self.threads_per_worker} thread{'s' if self.threads_per_worker != 1 else ''})"


def available() -> bool:
    """Whether Dask distributed is installed (the ``dask`` extra)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


def require(what: str) -> None:
    """Raise :class:`~dualscale.errors.ToolError` naming the extra unless :func:`available`
    (``what``: the option or command that needs it, for the message)."""
    if not available():
        raise ToolError(f"{what} needs Dask distributed, which is not installed: {EXTRA}")


def read_config(path: Path) -> dict[str, Any]:
    """The keyword arguments in a ``--cluster-config`` YAML file (a mapping; an optional top-level
    ``jobqueue:`` or cluster-kind key is unwrapped).  Raises :class:`~dualscale.errors.InputError`
    for a file that is not such a mapping."""
    import yaml

    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as e:
        raise InputError(f"--cluster-config {path}: not readable YAML ({e})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise InputError(f"--cluster-config {path}: expected a mapping of cluster settings, got {type(doc).__name__}")
    for key in ("jobqueue", *CLUSTERS):
        if set(doc) == {key} and isinstance(doc[key], dict):
            doc = doc[key]
    bad = [k for k in doc if not isinstance(k, str)]
    if bad:
        raise InputError(f"--cluster-config {path}: setting names must be text, got {bad}")
    return doc


def _jobqueue_class(kind: str):
    try:
        import dask_jobqueue
    except ImportError:
        raise ToolError(f"--cluster {kind} needs dask-jobqueue, which is not installed: {EXTRA}") from None
    return getattr(dask_jobqueue, CLUSTERS[kind])


def _jobqueue_kwargs(spec: EngineSpec) -> dict[str, Any]:
    kw = read_config(spec.config) if spec.config is not None else {}
    kw.setdefault("processes", 1)  # one worker process per job ...
    kw.setdefault("cores", spec.threads_per_worker)  # ... with this many threads
    if "memory" not in kw:
        import dask

        if dask.config.get(f"jobqueue.{spec.cluster}.memory", None) is None:
            raise InputError(f"--cluster {spec.cluster}: give the memory per job (e.g. 'memory: 8GiB') in "
                             "--cluster-config or in Dask's jobqueue configuration")
    return kw


def check_jobqueue(spec: EngineSpec, submit: bool = True) -> None:
    """Before any work: the jobqueue class exists, its settings are complete and (``submit``)
    its submit command (``sbatch``, ``qsub``, ...) is on ``PATH`` -- without it dask-jobqueue
    logs tracebacks and waits for workers for ever.  Raises :class:`~dualscale.errors.ToolError`
    or :class:`~dualscale.errors.InputError`."""
    import shutil

    cls = _jobqueue_class(spec.cluster)
    _jobqueue_kwargs(spec)
    cmd = cls.job_cls.submit_command
    if submit and shutil.which(cmd) is None:
        raise ToolError(f"--cluster {spec.cluster}: `{cmd}` is not on PATH; run dualscale where the batch system's "
                        "commands are (a login node), or use --scheduler ADDRESS")


def check_scheduler(address: str, timeout: float | None = None) -> None:
    """Before any work: a Dask scheduler answers at ``address`` (``tcp://host:8786``; a bare
    ``host:port`` is TCP, as Dask takes it) -- a connection and Dask's handshake within
    ``timeout`` seconds (default :data:`SCHEDULER_TIMEOUT_S`), then closed.  Raises
    :class:`~dualscale.errors.InputError` for an address Dask cannot parse and
    :class:`~dualscale.errors.ToolError` (exit 4, the environment) when nothing answers: no
    host, no listener, a firewall, or a port that is not a Dask scheduler's."""
    require("--scheduler")
    import asyncio

    from distributed.comm import connect as comm_connect
    from distributed.comm.addressing import parse_address

    wait = SCHEDULER_TIMEOUT_S if timeout is None else float(timeout)
    try:
        parse_address(address)
    except (TypeError, ValueError) as e:
        raise InputError(f"--scheduler {address!r}: not a Dask address such as tcp://host:8786 ({e})") from None

    async def probe() -> None:
        comm = await comm_connect(address, timeout=wait)
        await comm.close()

    try:
        asyncio.run(asyncio.wait_for(probe(), wait))
    except (OSError, TimeoutError, asyncio.TimeoutError) as e:
        why = str(e) or f"no answer within {wait:g} s"
        raise ToolError(f"--scheduler {address}: no Dask scheduler answers there ({why}); start one "
                        "(`dask scheduler`) or check the address") from None
    except ValueError as e:  # e.g. an unknown protocol in the address
        raise InputError(f"--scheduler {address!r}: {e}") from None


def jobqueue_cluster(spec: EngineSpec):
    """A dask-jobqueue cluster object for ``spec`` (not yet scaled: no job is submitted).  Raises
    :class:`~dualscale.errors.ToolError` without dask-jobqueue, :class:`~dualscale.errors.InputError`
    for settings it refuses."""
    cls = _jobqueue_class(spec.cluster)
    try:
        return cls(**_jobqueue_kwargs(spec))
    except (TypeError, ValueError) as e:
        raise InputError(f"--cluster {spec.cluster}: dask-jobqueue refuses the settings ({e})") from None


def job_script(spec: EngineSpec) -> str:
    """The batch script a jobqueue cluster would submit for one job of ``spec`` (nothing is
    submitted; the cluster's local scheduler is closed again)."""
    require(f"--cluster {spec.cluster}")
    if spec.cluster == "local" or spec.scheduler is not None:
        raise InputError("a job script exists for job-queue clusters only (--cluster slurm, pbs, ...)")
    cluster = jobqueue_cluster(spec)
    try:
        return cluster.job_script()
    finally:
        cluster.close()


def bounded(client, items: list, submit, per_worker: int = 2) -> Iterator[tuple[Any, Any]]:
    """Yield ``(item, result)`` of ``submit(item)`` (a function returning a Dask future) for every
    item, in the order they finish, with at most ``per_worker`` tasks per worker of ``client``
    in flight (which bounds the memory of the driver and of the workers); each future is released
    once its result is taken.  A task's error is raised here as the worker raised it."""
    from distributed import as_completed

    limit = per_worker * max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
    queue = list(items)
    futures = {submit(it): it for it in queue[:limit]}
    queue = queue[limit:]
    pending = as_completed(list(futures))
    for fut in pending:
        item = futures.pop(fut)
        res = fut.result()
        fut.release()
        if queue:
            nxt = queue.pop(0)
            f = submit(nxt)
            futures[f] = nxt
            pending.add(f)
        yield item, res


def in_worker(threads: int) -> None:
    """Call first in a task: :func:`dualscale.threads.set_threads` with the worker's thread count
    (a worker restarted after a crash starts with the libraries' defaults again, so every task
    sets it; the call costs microseconds)."""
    import torch  # noqa: F401 - loaded so that set_threads reaches it

    from dualscale.threads import set_threads

    set_threads(threads)


@contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """Spawn the local workers with SIGINT ignored (an ignored signal stays ignored across
    ``exec``, and Python then installs no handler): Ctrl-C in a terminal reaches the whole
    process group, and the workers would each print a ``KeyboardInterrupt`` traceback; this
    process handles it and closes them (exit 130, one line)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


#: the multiprocessing resource tracker's shutdown notice: a worker process the nanny had to kill
#: while it ran a task (the command was interrupted) leaves a semaphore registered, which the
#: tracker then removes -- and says so in two lines after the command's one-line message
_TRACKER_NOTICE = "ignore:resource_tracker:UserWarning"


def _quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (shared by this process and the workers it
    spawns) with :data:`_TRACKER_NOTICE` among its warning filters: it still cleans up, without
    printing under the command's last line, and with SIGHUP ignored (an ignored signal stays
    ignored across exec): the tracker ignores SIGINT and SIGTERM itself, but a SIGHUP to the
    command's process group (a closed terminal) killed it, and the workers then printed its
    restart and a traceback per semaphore.  Nothing when a tracker already runs."""
    import signal
    import sys
    from multiprocessing import resource_tracker

    if getattr(resource_tracker._resource_tracker, "_fd", None) is not None:
        return
    if _TRACKER_NOTICE not in sys.warnoptions:
        sys.warnoptions.append(_TRACKER_NOTICE)  # passed on the tracker's command line (-W)
    hup = signal.signal(signal.SIGHUP, signal.SIG_IGN) if hasattr(signal, "SIGHUP") else None
    try:
        resource_tracker.ensure_running()
    finally:
        sys.warnoptions.remove(_TRACKER_NOTICE)
        if hup is not None:
            signal.signal(signal.SIGHUP, hup)


#: the environment variable through which Dask's processes read the level of the ``distributed``
#: logger when they import it (dask's config: ``distributed.logging.distributed``)
LOG_LEVEL_ENV = "DASK_DISTRIBUTED__LOGGING__DISTRIBUTED"


def _quiet_distributed_logs() -> None:
    """Errors only from Dask's ``distributed`` logger, here and in the worker processes started
    from here (they read :data:`LOG_LEVEL_ENV` on import), unless the user set that variable.
    A stop request (SIGTERM to the process group) closes the comms of a cluster being torn down,
    and ``distributed.batched`` then logged a traceback at INFO ("Batched Comm Closed") from
    whichever process lost its comm first: ``silence_logs`` only lowers the handlers it finds,
    for the lifetime of the cluster, and a worker's logger is configured before it applies."""
    if os.environ.get(LOG_LEVEL_ENV) is None:
        os.environ[LOG_LEVEL_ENV] = "error"
    logging.getLogger("distributed").setLevel(getattr(logging, os.environ[LOG_LEVEL_ENV].upper(), logging.ERROR))


@contextmanager
def connect(spec: EngineSpec) -> Iterator[Any]:
    """Open the cluster of ``spec`` and yield a :class:`distributed.Client` on it; closes the
    cluster (not a scheduler given by address) on exit.  Raises
    :class:`~dualscale.errors.ToolError` without the ``dask`` extra or when the scheduler cannot
    be reached."""
    require("--workers/--scheduler/--cluster" if spec.cluster == "local" else f"--cluster {spec.cluster}")
    import dask
    from distributed import Client, LocalCluster

    _quiet_distributed_logs()
    cluster = None
    local_env = {} if _USER_MALLOC_TRIM is not None else {f"distributed.nanny.pre-spawn-environ.{MALLOC_TRIM}": None}
    with dask.config.set({"distributed.worker.daemon": False,  # a stage may start its own processes
                          **local_env,
                          "distributed.logging.distributed": "error"}):
        if spec.scheduler is not None:
            try:
                client = Client(spec.scheduler, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError) as e:
                raise ToolError(f"--scheduler {spec.scheduler}: no Dask scheduler answers there ({e})") from None
        elif spec.cluster == "local":
            if _USER_MALLOC_TRIM is None:  # the nanny copies it into this process's environment
                os.environ.pop(MALLOC_TRIM, None)
            _quiet_resource_tracker()
            with _workers_ignore_sigint():
                cluster = LocalCluster(n_workers=spec.workers, threads_per_worker=spec.threads_per_worker,
                                       processes=True, dashboard_address=":0",  # a free port: never 8787 taken
                                       silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            check_jobqueue(spec)
            cluster = jobqueue_cluster(spec)
            cluster.scale(spec.workers)
            client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
