"""dualscale.engine and the cluster options (issue 16): what is refused, the job script
dask-jobqueue makes for SLURM (nothing is submitted: no batch system here), a scheduler that
does not answer."""

from __future__ import annotations

import argparse

import pytest

from dualscale.engine import EngineSpec, read_config
from dualscale.errors import InputError, ToolError


def _args(*argv: str) -> argparse.Namespace:
    from dualscale.cli.common import add_engine_options

    p = argparse.ArgumentParser()
    add_engine_options(p, "workers")
    return p.parse_args(list(argv))


def test_spec_refuses_what_it_cannot_use(tmp_path):
    for bad in (0, -1, 1.5, True):
        with pytest.raises(InputError, match="--workers"):
            EngineSpec(workers=bad)
    with pytest.raises(InputError, match="--cluster 'k8s'"):
        EngineSpec(cluster="k8s")
    with pytest.raises(InputError, match="no such file"):
        EngineSpec(cluster="slurm", config=tmp_path / "missing.yaml")
    with pytest.raises(InputError, match="job-queue"):
        EngineSpec(workers=2, config=__file__)
    assert EngineSpec(workers=2).describe == "local (2 workers x 1 thread)"
    assert EngineSpec(scheduler="tcp://h:8786").describe == "scheduler tcp://h:8786"


def test_engine_options_map_to_a_spec_or_to_in_process():
    from dualscale.cli.common import engine_spec

    assert engine_spec(_args()) is None and engine_spec(_args("--workers", "1")) is None
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    assert engine_spec(_args("--workers", "3")) == EngineSpec(workers=3)
    assert engine_spec(_args("--scheduler", "tcp://x:1"), reach=False).scheduler == "tcp://x:1"
    with pytest.raises(InputError, match="at least 1"):
        engine_spec(_args("--workers", "0"))
    with pytest.raises(InputError, match="job-queue"):
        engine_spec(_args("--cluster-config", __file__))
    for other in (("--workers", "2"), ("--cluster", "slurm")):
        with pytest.raises(InputError, match="choose one"):
            engine_spec(_args("--scheduler", "tcp://x:1", *other))


def test_a_batch_system_without_its_submit_command_is_refused_before_any_work(tmp_path, monkeypatch):
    """dask-jobqueue would log tracebacks and wait for ever for workers that never come."""
    pytest.importorskip("dask_jobqueue", reason="the dask extra is not installed")
    from dualscale.cli.common import engine_spec

    cfg = tmp_path / "slurm.yaml"
    cfg.write_text("memory: 2GiB\n")
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch, no qsub
    with pytest.raises(ToolError, match="`sbatch` is not on PATH"):
        engine_spec(_args("--cluster", "slurm", "--cluster-config", str(cfg)))
    with pytest.raises(ToolError, match="`qsub` is not on PATH"):
        engine_spec(_args("--cluster", "pbs", "--cluster-config", str(cfg)))
    (tmp_path / "sbatch").write_text("#!/bin/sh\nexit 0\n")
    (tmp_path / "sbatch").chmod(0o755)
    assert engine_spec(_args("--cluster", "slurm", "--cluster-config", str(cfg))).cluster == "slurm"


def test_local_workers_leave_ctrl_c_to_the_command():
    """Ctrl-C reaches the whole process group: the workers ignore it (no traceback from each),
    and the command stops them; this process's own handler is restored."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import signal

    from dualscale.engine import connect

    before = signal.getsignal(signal.SIGINT)
    with connect(EngineSpec(workers=1)) as c:
        assert list(c.run(lambda: signal.getsignal(signal.SIGINT) == signal.SIG_IGN).values()) == [True]
        assert signal.getsignal(signal.SIGINT) is before


def test_without_the_extra_a_cluster_is_a_missing_tool(monkeypatch):
    import dualscale.engine as engine
    from dualscale.cli.common import engine_spec

    monkeypatch.setattr(engine, "available", lambda: False)
    assert engine_spec(_args()) is None  # in-process, as without the extra
    with pytest.raises(ToolError, match=r"pip install 'dualscale\[dask\]'"):
        engine_spec(_args("--workers", "2"))


def test_cluster_config_is_a_mapping(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("slurm:\n  memory: 8GiB\n  queue: short\n")
    assert read_config(p) == {"memory": "8GiB", "queue": "short"}
    p.write_text("- a\n- b\n")
    with pytest.raises(InputError, match="mapping"):
        read_config(p)
    p.write_text("memory: [unclosed\n")
    with pytest.raises(InputError, match="not readable YAML"):
        read_config(p)


def test_slurm_job_script_from_a_small_config(tmp_path):
    """dask-jobqueue's own SLURMCluster writes the script (not submitted)."""
    pytest.importorskip("dask_jobqueue", reason="the dask extra is not installed")
    from dualscale.engine import job_script

    cfg = tmp_path / "slurm.yaml"
    cfg.write_text("memory: 6GiB\nqueue: fabrics\nwalltime: '02:00:00'\naccount: lab42\n"
                   "job_extra_directives: ['--exclusive']\n")
    script = job_script(EngineSpec(workers=4, cluster="slurm", config=cfg))
    for line in ("#SBATCH -p fabrics", "#SBATCH -A lab42", "#SBATCH -t 02:00:00", "#SBATCH --exclusive",
                 "#SBATCH -n 1", "--nthreads 1"):
        assert line in script, script
    assert "--memory-limit 6.00GiB" in script or "6.00GiB" in script
    cfg.write_text("queue: fabrics\n")
    with pytest.raises(InputError, match="memory per job"):
        job_script(EngineSpec(cluster="slurm", config=cfg))
    cfg.write_text("memory: 1GiB\nno_such_setting: 3\n")
    with pytest.raises(InputError, match="refuses the settings"):
        job_script(EngineSpec(cluster="slurm", config=cfg))


def test_a_scheduler_that_does_not_answer_is_a_clear_error(monkeypatch):
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import socket

    import dualscale.engine as engine

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 2)
    with pytest.raises(ToolError, match=f"--scheduler tcp://127.0.0.1:{port}: no Dask scheduler"):
        with engine.connect(EngineSpec(scheduler=f"tcp://127.0.0.1:{port}")):
            pass


def test_local_workers_do_not_trim_malloc_early(monkeypatch):
    """Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in workers (and in the process that starts
    them): measured 1.4-1.5x slower tile fits (docs/SCALE.md). Our local cluster leaves it unset,
    also for a second cluster in the same process."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import os

    import dualscale.engine as engine

    monkeypatch.setattr(engine, "_USER_MALLOC_TRIM", None)
    for _ in range(2):
        with engine.connect(EngineSpec(workers=1)) as c:
            assert c.submit(os.environ.get, "MALLOC_TRIM_THRESHOLD_", pure=False).result() is None
    assert "MALLOC_TRIM_THRESHOLD_" not in os.environ


@pytest.mark.parametrize("kind", ["silent", "closed"])
def test_an_unreachable_scheduler_is_told_within_5_s_before_the_list_is_read(kind, tmp_path, monkeypatch, capsys):
    """Issue 24 §8: ``batch --scheduler`` at an address where no Dask scheduler answers -- a port
    that accepts the connection and then says nothing (as a firewall or another service), or
    one nobody listens on -- is one line and exit 4 within 5 s (it took the 30 s connect
    timeout), and it is told before the sample list is read (the list here does not exist)."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import socket
    import time

    import dualscale.batch
    from dualscale.cli import main

    read = []
    monkeypatch.setattr(dualscale.batch, "read_list", lambda *a, **k: read.append(a))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        if kind == "silent":
            s.listen(4)  # the kernel completes the TCP connection; nobody ever answers Dask's handshake
        else:
            s.close()
        t0 = time.perf_counter()
        rc = main(["batch", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "out"),
                   "--scheduler", f"tcp://127.0.0.1:{port}", "--no-progress"])
        seconds = time.perf_counter() - t0
    err = capsys.readouterr().err.strip()
    assert rc == 4 and seconds < 5.0, (rc, seconds, err)
    assert len(err.splitlines()) == 1 and f"--scheduler tcp://127.0.0.1:{port}: no Dask scheduler answers" in err
    assert read == [] and not (tmp_path / "out").exists()


def test_a_malformed_scheduler_address_is_bad_input():
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    from dualscale.cli.common import engine_spec

    with pytest.raises(InputError, match="--scheduler 'foo://x:1'"):
        engine_spec(_args("--scheduler", "foo://x:1"))
