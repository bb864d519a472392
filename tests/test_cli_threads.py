"""``--threads N|auto`` (issue 15, "Threads"): the ``auto`` rule on a mocked load average,
affinity and cgroup quota (the OS boundary), the quota files' parsing, the bounds, the one-line
refusals, and that a command runs with the chosen count in torch, OpenCV and numba."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

import pytest

from dualscale import threads
from dualscale.cli import main
from dualscale.cli.common import apply_threads
from dualscale.errors import InputError


@pytest.fixture
def machine(monkeypatch, tmp_path):
    """A machine of ``cores`` CPUs, this process on ``affinity`` of them, a 1-minute load
    average ``load`` and no cgroup quota (an empty cgroup tree under tmp_path); restores the
    libraries' thread counts afterwards."""
    import cv2
    import torch

    saved = (torch.get_num_threads(), cv2.getNumThreads(), threads._chosen)
    monkeypatch.setattr(threads, "CGROUP_ROOT", tmp_path / "cgroup")
    monkeypatch.setattr(threads, "PROC_CGROUP", tmp_path / "no-proc-cgroup")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)

    def set_(cores: int, load: float, affinity: int | None = None) -> None:
        monkeypatch.setattr(os, "cpu_count", lambda: cores)
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(affinity or cores)))
        monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))

    yield set_
    torch.set_num_threads(saved[0])
    cv2.setNumThreads(saved[1])
    threads._chosen = saved[2]


@pytest.mark.parametrize("cores,load,affinity,want", [
    (2, 0.0, None, 2),     # idle: every core
    (2, 0.4, None, 2),     # 1.6 rounds to 2
    (2, 0.6, None, 1),     # 1.4 rounds to 1
    (2, 1.4, None, 1),     # busy (the 5.6x case): one thread
    (2, 9.0, None, 1),     # overloaded: never below 1
    (8, 2.6, None, 5),     # 8 - 2.6 = 5.4
    (64, 0.0, 4, 4),       # pinned to 4 of 64 cores: never above the usable cores
    (64, 30.0, 4, 4),      # the load of the other 60 cores leaves our 4 free
    (64, 62.5, 4, 2),      # 1.5 idle cores on the whole machine: 2
])
def test_auto_is_the_usable_cores_less_the_load(machine, cores, load, affinity, want):
    machine(cores, load, affinity)
    assert threads.auto_threads() == want
    assert threads.resolve("auto") == want


def test_auto_is_capped_by_the_cgroup_quota(machine, tmp_path):
    machine(8, 0.0)
    root = tmp_path / "cgroup"
    root.mkdir()
    (root / "cpu.max").write_text("150000 100000\n")  # 1.5 cores: floored to 1
    assert threads.usable_cores() == 1 and threads.auto_threads() == 1
    (root / "cpu.max").write_text("300000 100000\n")
    assert threads.usable_cores() == 3 and threads.auto_threads() == 3
    (root / "cpu.max").write_text("max 100000\n")
    assert threads.usable_cores() == 8


@pytest.mark.parametrize("text,cores", [("max 100000", None), ("150000 100000", 1.5), ("50000 100000\n", 0.5),
                                        ("400000 200000", 2.0), ("-1 100000", None), ("", None), ("x y", None)])
def test_cpu_max_lines(text, cores):
    assert threads.parse_cpu_max(text) == cores


def test_cgroup_limit_is_the_smallest_over_the_process_cgroups(tmp_path):
    root, proc = tmp_path / "cg", tmp_path / "self-cgroup"
    (root / "a" / "b").mkdir(parents=True)
    (root / "cpu.max").write_text("max 100000")
    (root / "a" / "cpu.max").write_text("250000 100000")
    (root / "a" / "b" / "cpu.max").write_text("max 100000")
    proc.write_text("0::/a/b\n")
    assert threads.cgroup_cpu_limit(root, proc) == 2.5  # the parent's quota binds the child
    (root / "a" / "b" / "cpu.max").write_text("120000 100000")
    assert threads.cgroup_cpu_limit(root, proc) == 1.2
    # cgroup v1: cpu controller with cfs quota / period (-1 = none)
    v1, proc1 = tmp_path / "v1", tmp_path / "self-cgroup-v1"
    (v1 / "cpu,cpuacct" / "docker" / "x").mkdir(parents=True)
    proc1.write_text("4:memory:/docker/x\n2:cpu,cpuacct:/docker/x\n0::/\n")
    (v1 / "cpu,cpuacct" / "docker" / "x" / "cpu.cfs_quota_us").write_text("-1\n")
    (v1 / "cpu,cpuacct" / "docker" / "x" / "cpu.cfs_period_us").write_text("100000\n")
    assert threads.cgroup_cpu_limit(v1, proc1) is None
    (v1 / "cpu,cpuacct" / "docker" / "x" / "cpu.cfs_quota_us").write_text("200000\n")
    assert threads.cgroup_cpu_limit(v1, proc1) == 2.0
    # nothing readable: no limit
    assert threads.cgroup_cpu_limit(tmp_path / "none", tmp_path / "none.txt") is None


def test_default_is_omp_num_threads_when_set_else_auto(machine, monkeypatch):
    machine(2, 1.5)
    assert threads.resolve(None) == threads.default_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads.resolve(None) == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "3")  # above the 2 cores: lowered, with a notice (issue 24)
    with pytest.warns(UserWarning, match="OMP_NUM_THREADS=3 is more than this machine's 2 cores: using 2"):
        assert threads.resolve(None) == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "lots")  # not a count: ignored
    assert threads.resolve(None) == 1


@pytest.mark.parametrize("value", ["0", "-1", "abc", "1.5", ""])
def test_bad_counts_are_refused_in_one_line(value, tmp_path, capsys):
    assert main(["synth", "twill", "-o", str(tmp_path / "s"), "--threads", value]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "--threads" in err and "'auto'" in err, err
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("value", [0, -1, "abc"])
def test_library_callers_get_an_input_error(value):
    with pytest.raises(InputError, match="--threads"):
        threads.resolve(value)
    with pytest.raises(InputError, match="--threads"):
        apply_threads(argparse.Namespace(threads=value))


def test_apply_threads_sets_torch_opencv_and_numba(machine):
    import cv2
    import numba
    import torch

    machine(2, 0.0)
    assert apply_threads(argparse.Namespace(threads=1)) == 1
    assert (torch.get_num_threads(), cv2.getNumThreads(), numba.get_num_threads()) == (1, 1, 1)
    assert threads.effective_threads() == 1
    # auto on an idle machine: both cores; numba never beyond its pool
    assert apply_threads(argparse.Namespace(threads="auto")) == 2
    assert torch.get_num_threads() == 2 and threads.effective_threads() == 2
    assert numba.get_num_threads() == min(2, numba.config.NUMBA_NUM_THREADS)
    big = numba.config.NUMBA_NUM_THREADS + 1
    assert apply_threads(argparse.Namespace(threads=big)) == big
    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    apply_threads(argparse.Namespace(threads=1))
    # omitted: the default rule (auto here, the machine is busy)
    machine(2, 1.8)
    assert apply_threads(argparse.Namespace(threads=None)) == 1 and torch.get_num_threads() == 1


def test_a_command_runs_with_the_chosen_count(machine, monkeypatch, tmp_path):
    """``synth`` (a long command) on a busy 2-core machine without --threads: the default
    ``auto`` gives one thread, set in torch before the work."""
    import torch

    from dualscale.cli import sim as sim_cli

    seen = []

    def spy(a, real=sim_cli.apply_threads):
        n = real(a)
        seen.append((n, torch.get_num_threads()))
        return n

    machine(2, 1.7)
    torch.set_num_threads(2)
    monkeypatch.setattr(sim_cli, "apply_threads", spy)
    assert main(["synth", "twill", "-o", str(tmp_path / "s"), "--size", "16", "--no-previews"]) == 0
    assert seen == [(1, 1)] and torch.get_num_threads() == 1 and threads.effective_threads() == 1
    machine(2, 0.0)
    assert main(["synth", "twill", "-o", str(tmp_path / "s"), "--size", "16", "--no-previews", "--threads",
                 "auto"]) == 0
    assert seen[-1] == (2, 2)


def test_numba_is_not_imported_to_set_it():
    """Setting the count touches only the libraries already loaded: numba (and torch) stay out
    of a process that has not imported them."""
    code = ("import sys; from dualscale.threads import set_threads, effective_threads, sync_numba; set_threads(1); "
            "print(effective_threads(), sync_numba(), 'numba' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "None", "False", "False"]


def test_starting_numba_keeps_torch_at_the_chosen_count():
    """numba's OpenMP pool resets OpenMP's count when it starts after torch has used OpenMP (on
    a machine of 2+ cores torch then runs 2+ threads after --threads 1; fresh processes, so that
    the pool has not started yet): set_threads starts it before setting torch, and sync_numba
    (for a kernel that starts it later) puts torch back."""
    work = "torch.ones(1 << 20).sum(); "  # torch's OpenMP in use: what numba's start then resets
    code = ("import torch, numba; from dualscale.threads import set_threads, sync_numba; " + work +
            "set_threads(1); print(torch.get_num_threads(), numba.get_num_threads())")
    later = ("import torch; from dualscale.threads import set_threads, sync_numba; set_threads(1); " + work +
             "import numba; print(sync_numba(), torch.get_num_threads(), numba.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    for c, want in ((code, ["1", "1"]), (later, ["1", "1", "1"])):
        out = subprocess.run([sys.executable, "-c", c], capture_output=True, text=True, timeout=120, env=env)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split() == want, c


def test_help_states_auto_and_the_default(capsys):
    assert main(["fit", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "--threads N|auto" in out and "default: OMP_NUM_THREADS if set, else auto" in out
