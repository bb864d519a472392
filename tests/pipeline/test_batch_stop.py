"""`dualscale batch` on a stop request (issue 24, fresh-user trial): SIGTERM wrote no summary and
died with 143 (Ctrl-C wrote one).  Now, as on Ctrl-C: exit 130, one line naming the signal and
the summary, and summary.json saying the batch was interrupted.  With ``--workers 2`` the signal
goes to the whole process group, Dask's worker processes too, as Slurm sends it to a job step."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.pipeline.test_run_folders import _env, _project, _wait, tiny  # noqa: F401 - tiny: a fixture


@pytest.mark.parametrize("workers,sig", [("1", signal.SIGTERM), ("2", signal.SIGTERM),
                                         ("2", signal.SIGHUP)])  # SIGHUP to the group once killed the resource tracker
def test_sigterm_during_a_batch_writes_the_summary_of_what_finished(tiny, tmp_path, workers, sig):  # noqa: F811
    if workers != "1":
        pytest.importorskip("distributed", reason="the dask extra is not installed")
    proj = _project(tiny, tmp_path / "project", "a,b")
    out = proj / "out"
    cmd = [sys.executable, "-m", "dualscale.cli", "batch", str(proj / "samples.csv"), "-o", str(out),
           "--workers", workers, "--no-progress"]
    env = _env()
    env.pop("DUALSCALE_DEBUG", None)
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        started = lambda: any((out / n / "stages").is_dir() for n in "ab")  # noqa: E731
        _wait(lambda: started() or p.poll() is not None, what="a sample's first stage")
        time.sleep(0.5)
        assert p.poll() is None, p.communicate()
        if workers == "1":
            p.send_signal(sig)
        else:
            os.killpg(p.pid, sig)
        stdout, stderr = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(30)
    assert p.returncode == 130, (p.returncode, stderr)
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert "resource_tracker" not in stderr, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith(f"dualscale batch: stopped by {sig.name}: batch interrupted: "), stderr
    assert str(out / "summary.html") in last and last.endswith("run the same command again to resume"), stderr
    doc = json.loads((out / "summary.json").read_text())
    assert doc["interrupted"] is True
    assert (out / "summary.csv").is_file() and "The batch was interrupted" in (out / "summary.html").read_text()
