"""How many CPU threads a command uses (``--threads N|auto``, issue 15): the one choice, applied
to every threaded library the process has loaded, and readable by any module through
:func:`effective_threads`.

**Why a choice at all.**  torch (OpenMP), OpenCV, onnxruntime and numba each start one thread
per core by default.  On a machine whose cores are already busy, the extra threads fight the
other jobs for the same cores and wait on each other at every parallel region: on the project's
shared 2-core machine a second torch thread made the fit 5.6x *slower* (issue 15).  On an idle
machine the same second thread nearly halves the time.  So the count follows the load.

**The ``auto`` rule** (:func:`auto_threads`), evaluated once when a command starts::

    usable = min(len(os.sched_getaffinity(0)), cgroup CPU quota)     # the cores we may run on
    free   = os.cpu_count() - os.getloadavg()[0]                     # the machine's idle cores
    auto   = clamp(floor(min(usable, free) + 0.5), 1, floor(usable))

The cgroup quota is ``quota / period`` of cgroup v2's ``cpu.max`` or cgroup v1's
``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (the smallest over the process's cgroup and its
ancestors; none = no limit), floored to whole cores (at least 1), because threads beyond the
quota are throttled mid-region.  When the process may use every core of the machine (the usual
case) this is *usable cores minus the 1-minute load average*; the ``min`` keeps a process pinned
to a few cores of a large machine from counting the other cores' load against itself (the load
average is the whole machine's, also inside a container).  The 1-minute average lags: for about
a minute after a heavy job ends it still counts part of it.  ``--threads N`` overrides the rule.

**numba.**  Its OpenMP threading layer resets OpenMP's thread count, which torch uses, when
its pool starts (the first ``numba.get_num_threads``, ``set_num_threads`` or parallel call):
with ``--threads 1`` torch would silently run two threads again.  :func:`set_threads` starts
numba's pool first, and a numba kernel that may be the first to start it calls
:func:`sync_numba` before it runs.

**The default** (no ``--threads``): ``OMP_NUM_THREADS`` when the environment sets it to a whole
number >= 1 (the libraries' own convention, so one variable sets every library), else ``auto``;
like ``--threads N``, a value above the machine's cores is lowered to them, with a notice.

Bottom layer: imports nothing of dualscale but :mod:`dualscale.errors` and no heavy library
(torch, cv2 and numba are only *set* here, and only when the process has already imported them).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Iterable, Union

from dualscale.errors import InputError

#: ``--threads`` as given: a count, ``"auto"``, or ``None`` (the default rule)
Spec = Union[int, str, None]

CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")

_chosen: int | None = None


def parse(text: str) -> int | str:
    """``--threads`` text -> a count >= 1 or ``"auto"``.  Raises :class:`InputError` (one line)
    for anything else (``0``, ``-1``, ``abc``, ``1.5``)."""
    t = str(text).strip().lower()
    if t == "auto":
        return "auto"
    try:
        n = int(t)
    except ValueError:
        raise InputError(f"--threads takes a whole number >= 1 or 'auto', got {text!r}") from None
    if n < 1:
        raise InputError(f"--threads must be at least 1 (or 'auto'), got {n}")
    return n


def parse_cpu_max(text: str) -> float | None:
    """Cores allowed by a cgroup v2 ``cpu.max`` line (``"QUOTA PERIOD"`` in microseconds, or
    ``"max PERIOD"`` for none): ``QUOTA / PERIOD``, or ``None`` for no limit or a line that
    does not parse."""
    parts = text.split()
    if not parts or parts[0] == "max":
        return None
    try:
        quota = int(parts[0])
        period = int(parts[1]) if len(parts) > 1 else 100_000
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def _read(p: Path) -> str | None:
    try:
        return p.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def _limit_in(d: Path) -> float | None:
    """The CPU limit set in one cgroup folder (v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``)."""
    text = _read(d / "cpu.max")
    if text is not None:
        return parse_cpu_max(text)
    quota, period = _read(d / "cpu.cfs_quota_us"), _read(d / "cpu.cfs_period_us")
    if quota is None:
        return None
    return parse_cpu_max(f"{quota.strip()} {(period or '100000').strip()}")  # v1: -1 = none


def _up(mount: Path, rel: str) -> Iterable[Path]:
    """``mount/rel`` and its ancestors up to ``mount``."""
    d = mount / rel.strip("/")
    while True:
        yield d
        if d == mount or mount not in d.parents:
            return
        d = d.parent


def cgroup_cpu_limit(root: str | Path | None = None, proc_cgroup: str | Path | None = None) -> float | None:
    """The CPU quota of this process's cgroups in cores (e.g. ``1.5``), the smallest over its
    cgroup and their ancestors, v2 (``root/PATH/cpu.max``) and v1 (``root/cpu/PATH/
    cpu.cfs_quota_us``); ``None`` where none is set or nothing can be read.  ``root`` and
    ``proc_cgroup`` (the ``/proc/self/cgroup`` lines ``ID:CONTROLLERS:PATH``) are arguments for
    the tests (default :data:`CGROUP_ROOT`, :data:`PROC_CGROUP`)."""
    root = Path(root if root is not None else CGROUP_ROOT)
    proc_cgroup = proc_cgroup if proc_cgroup is not None else PROC_CGROUP
    dirs: list[Path] = [root, root / "cpu", root / "cpu,cpuacct"]
    for line in (_read(Path(proc_cgroup)) or "").splitlines():
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        hid, ctrls, rel = fields
        if hid == "0" and ctrls == "":
            dirs += _up(root, rel)
        elif "cpu" in ctrls.split(","):
            for mount in (root / ctrls, root / "cpu"):
                dirs += _up(mount, rel)
    limits = [x for x in (_limit_in(d) for d in dict.fromkeys(dirs)) if x is not None]
    return min(limits) if limits else None


def _affinity() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def usable_cores(root: str | Path | None = None, proc_cgroup: str | Path | None = None) -> int:
    """The cores this process may run on: its CPU affinity, capped by the cgroup CPU quota
    (floored to whole cores, at least 1)."""
    n = _affinity()
    q = cgroup_cpu_limit(root, proc_cgroup)
    if q is not None:
        n = min(n, max(1, math.floor(q)))
    return n


def auto_threads(root: str | Path | None = None, proc_cgroup: str | Path | None = None) -> int:
    """The ``auto`` count (module docstring): the machine's idle cores by the 1-minute load
    average, at most :func:`usable_cores`, rounded, at least 1."""
    usable = usable_cores(root, proc_cgroup)
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # no load average: assume an idle machine
        load = 0.0
    online = max(os.cpu_count() or usable, usable)
    free = min(float(usable), online - load)
    return max(1, min(usable, math.floor(free + 0.5)))


def default_threads() -> int:
    """The count when ``--threads`` is not given: ``OMP_NUM_THREADS`` if it is a whole number
    >= 1, else :func:`auto_threads`.  A value above :func:`machine_cores` is lowered to them as
    ``--threads`` is (:func:`clamp`), with the same kind of notice (a :class:`UserWarning`, which
    the command line prints as ``dualscale CMD: warning: ...``), and lowered in ``os.environ``
    too, so that the processes started later (simulator, Dask workers) inherit the lowered count
    and the notice is given once."""
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        n = int(env)
        cores = machine_cores()
        if n > cores:
            import warnings

            warnings.warn(f"OMP_NUM_THREADS={n} is more than this machine's {cores} core{'s' if cores > 1 else ''}: "
                          f"using {cores}", stacklevel=2)
            os.environ["OMP_NUM_THREADS"] = str(cores)
            return cores
        return n
    return auto_threads()


def resolve(spec: Spec) -> int:
    """``--threads`` -> a count: ``N`` itself, ``"auto"`` -> :func:`auto_threads`, ``None`` ->
    :func:`default_threads`.  Raises :class:`InputError` for a count below 1 or other text."""
    if spec is None:
        return default_threads()
    if isinstance(spec, str):
        spec = parse(spec)
        if spec == "auto":
            return auto_threads()
    if isinstance(spec, bool) or not isinstance(spec, int):
        raise InputError(f"--threads takes a whole number >= 1 or 'auto', got {spec!r}")
    if spec < 1:
        raise InputError(f"--threads must be at least 1 (or 'auto'), got {spec}")
    return spec


def machine_cores() -> int:
    """The machine's logical cores (``os.cpu_count()``), the most threads a count may ask for."""
    return max(1, os.cpu_count() or 1)


def clamp(spec: Spec) -> tuple[Spec, str | None]:
    """``--threads``: a count above :func:`machine_cores` lowered to it, with the notice to show
    (``None`` when unchanged; ``"auto"`` and ``None`` pass as they are).  Thousands of threads
    per library would only wait on each other (and may exhaust the process's thread limit)."""
    cores = machine_cores()
    if isinstance(spec, int) and not isinstance(spec, bool) and spec > cores:
        return cores, (f"--threads {spec} is more than this machine's {cores} core{'s' if cores > 1 else ''}: "
                       f"using {cores}")
    return spec, None


def _set_numba(numba, n: int) -> int:
    """Set numba's pool to ``n`` capped at ``numba.config.NUMBA_NUM_THREADS`` and keep torch's
    count: numba's OpenMP threading layer resets OpenMP's thread count (which torch reports and
    uses) when its pool starts, on the first ``get/set_num_threads`` or parallel call."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None and hasattr(torch, "get_num_threads") else None
    m = max(1, min(n, int(numba.config.NUMBA_NUM_THREADS)))
    if numba.get_num_threads() != m:
        numba.set_num_threads(m)
    if before is not None and torch.get_num_threads() != before:
        torch.set_num_threads(before)
    return m


def set_threads(n: int) -> int:
    """Make ``n`` the process's thread count: remembered for :func:`effective_threads`, and set
    in each threaded library *already imported*: numba's pool (capped at
    ``numba.config.NUMBA_NUM_THREADS``, the size of its pool; set first, because starting it
    resets OpenMP's count), torch's intra-op threads and OpenCV's.  onnxruntime has no global
    setting: a session takes the count (``intra_op_num_threads``) when it is made.  Raises
    :class:`InputError` for a count below 1.  Returns ``n``."""
    global _chosen
    n = resolve(n)
    _chosen = n
    numba = sys.modules.get("numba")
    if numba is not None and hasattr(numba, "set_num_threads"):
        _set_numba(numba, n)
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "set_num_threads"):
        torch.set_num_threads(n)
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and hasattr(cv2, "setNumThreads"):
        cv2.setNumThreads(n)
    return n


def effective_threads() -> int:
    """The thread count chosen for this process: the last :func:`set_threads` (a command's
    ``--threads``); else, for a library caller that chose nothing here, torch's intra-op count
    when torch is loaded (what the caller set with ``torch.set_num_threads``), else
    :func:`default_threads`.  Use it for a pool the process makes later (an onnxruntime session)."""
    if _chosen is not None:
        return _chosen
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "get_num_threads"):
        return int(torch.get_num_threads())
    return default_threads()


def sync_numba() -> int | None:
    """For a numba kernel, before it runs: set numba's pool to :func:`effective_threads` (capped
    at ``NUMBA_NUM_THREADS``) without changing torch's count (starting numba's OpenMP pool
    would reset it, e.g. back to 2 after ``--threads 1``).  Cheap when nothing changes.
    Returns numba's count, or ``None`` when numba is not imported (it is never imported here)."""
    numba = sys.modules.get("numba")
    if numba is None or not hasattr(numba, "set_num_threads"):
        return None
    return _set_numba(numba, effective_threads())
