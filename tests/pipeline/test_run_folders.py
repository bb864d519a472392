"""Run folders and batches under the failures other projects' trackers report (issue 24 §7, §8):
a project folder moved or renamed resumes (digitize and batch); two processes on one run folder
(the second is refused with the holder's PID, a killed holder's lock file does not block);
Ctrl-C during a batch still writes the summary of what finished; the batch's help and hints."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dualscale.cli import main
from dualscale.pipeline import STAGES

DRAFT = ("--quality", "draft", "--no-progress")


def _main(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A 16 x 16 synthetic twill dataset (every 4th LED, P0/P90), to copy into project folders."""
    root = tmp_path_factory.mktemp("tiny") / "syn"
    assert main(["synth", "twill", "-o", str(root), "--size", "16", "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--no-previews", "--no-progress"]) == 0
    return root


def _project(tiny: Path, where: Path, samples: str = "a") -> Path:
    """A project folder: the dataset and a sample list naming it relative to the list."""
    where.mkdir(parents=True)
    shutil.copytree(tiny, where / "syn")
    rows = "".join(f"{n},syn/micro,draft,exr,{i}\n" for i, n in enumerate(samples.split(",")))
    (where / "samples.csv").write_text("name,input,quality,export,seed\n" + rows)
    return where


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}


def _wait(cond, seconds: float = 180.0, what: str = "") -> None:
    t0 = time.time()
    while not cond():
        assert time.time() - t0 < seconds, f"timed out waiting for {what}"
        time.sleep(0.05)


# ------------------------------------------------------------------ a project folder moved or renamed

def test_a_moved_digitize_run_resumes(tiny, tmp_path):
    """The run folder and its input move together (the project folder renamed): the same command
    from the new place is this run's, and its finished stage is up to date (it was refused as
    'another run of digitize' because the record kept the old absolute path)."""
    old = tmp_path / "project"
    old.mkdir()
    shutil.copytree(tiny, old / "syn")
    assert _main("digitize", str(old / "syn"), "-o", str(old / "run"), "--until", "calibrate", *DRAFT)[0] == 0
    new = tmp_path / "renamed"
    old.rename(new)
    rc, out, err = _main("digitize", str(new / "syn"), "-o", str(new / "run"), "--until", "calibrate", *DRAFT)
    assert rc == 0, err
    assert "calibrate  up to date" in out
    rec = json.loads((new / "run" / ".dualscale-output.json").read_text())
    assert rec["inputs"] == [str((new / "syn").resolve())] and rec["relative"] == ["../syn"]
    # another input at the old relative place is still another run
    shutil.copytree(tiny, new / "other")
    rc, _, err = _main("digitize", str(new / "other"), "-o", str(new / "run"), "--until", "calibrate", *DRAFT)
    assert rc == 2 and "another run of digitize" in err


def test_a_moved_batch_resumes_and_reuses_its_finished_stages(tiny, tmp_path, figures_not_drawn):
    """Issue 24 §7: a batch, its list and its inputs in one project folder; the folder is moved;
    the same batch from the new place is not refused (nor would --overwrite be needed, which
    deletes every finished stage): every stage of the sample is up to date.  (The report's
    figures not drawn, figures_not_drawn: most of the time; tests/report draws them.)"""
    old = _project(tiny, tmp_path / "lab" / "project")
    rc, _, err = _main("batch", str(old / "samples.csv"), "-o", str(old / "out"), "--workers", "1", "--no-progress")
    assert rc == 0, err
    fit_before = (old / "out" / "a" / "stages" / "fit.json").read_text()
    new = tmp_path / "moved" / "project-2"
    new.parent.mkdir()
    old.rename(new)
    rc, out, err = _main("batch", str(new / "samples.csv"), "-o", str(new / "out"), "--workers", "1", "--no-progress")
    assert rc == 0, err
    doc = json.loads((new / "out" / "summary.json").read_text())
    (row,) = doc["samples"]
    assert row["status"] == "done" and all(row["stages"][s]["status"] == "up to date" for s in STAGES), row["stages"]
    assert (new / "out" / "a" / "stages" / "fit.json").read_text() == fit_before
    assert "a: done" in out and "(6 stage(s) up to date)" in out


# --------------------------------------------------------------------- two processes on one run folder

def test_a_second_digitize_on_a_run_folder_in_use_is_refused_and_a_killed_ones_lock_does_not_block(tiny, tmp_path):
    """Issue 24 §7: a real `digitize` process holds RUN (stopped with SIGSTOP while it works, so
    that it surely still does); a second one on the same -o -- this process -- is refused at once,
    exit 2, "RUN is in use by PID <the first's> (started ...)", with or without --overwrite, and
    touches nothing.  The first is then killed with SIGKILL: its lock file stays behind, and the
    same command now runs (the kernel released the lock), resuming the run."""
    data = tmp_path / "syn"
    shutil.copytree(tiny, data)
    run = tmp_path / "run"
    argv = ["digitize", str(data / "micro"), "-o", str(run), "--until", "fit", *DRAFT]
    p = subprocess.Popen([sys.executable, "-m", "dualscale.cli", *argv], env=_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    lock = run / ".dualscale-lock"
    try:
        _wait(lambda: lock.is_file() and f'"pid": {p.pid}' in lock.read_text(), what="the first digitize's lock")
        _wait(lambda: (run / "run.json").is_file(), what="the first digitize's stages")
        p.send_signal(signal.SIGSTOP)
        before = sorted(str(x.relative_to(run)) for x in run.rglob("*"))
        for extra in ((), ("--overwrite",)):
            t0 = time.perf_counter()
            rc, out, err = _main(*argv, *extra)
            assert rc == 2, (extra, err)
            line = err.strip()
            assert len(line.splitlines()) == 1 and f"{run} is in use by PID {p.pid} (started " in line, line
            assert "`dualscale digitize`" in line and out == ""
            assert time.perf_counter() - t0 < 30  # refused at once, not after waiting for the first
            assert sorted(str(x.relative_to(run)) for x in run.rglob("*")) == before
        p.send_signal(signal.SIGKILL)
        p.wait(30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(30)
    assert lock.is_file()  # left behind by the killed process ...
    rc, out, err = _main(*argv)  # ... and it does not block
    assert rc == 0, err
    assert (run / "stages" / "fit.json").is_file() and not lock.exists()


def test_a_folder_in_use_by_a_batch_is_refused_to_digitize_and_to_another_batch(tiny, tmp_path):
    """The lock is the OS's (fcntl.flock), held by a live process; the message names it."""
    from dualscale.formats.lock import FolderLock

    run = tmp_path / "run"
    run.mkdir()
    (run / ".dualscale-lock").write_text("not json: left by a process that died\n")  # a stale file: no holder
    with FolderLock(run, "batch"):
        info = json.loads((run / ".dualscale-lock").read_text())
        assert info["pid"] == os.getpid() and info["command"] == "batch"
        code = ("import sys; from dualscale.formats.lock import FolderLock\n"
                "try:\n    FolderLock(sys.argv[1], 'digitize').acquire()\n"
                "except Exception as e:\n    print(type(e).__name__, e); sys.exit(2)\n")
        r = subprocess.run([sys.executable, "-c", code, str(run)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and r.stdout.startswith("InputError ") and f"in use by PID {os.getpid()}" in r.stdout
    assert not (run / ".dualscale-lock").exists()
    r = subprocess.run([sys.executable, "-c", code, str(run)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout


# ------------------------------------------------------------------------------------ Ctrl-C in a batch

@pytest.mark.parametrize("workers", ["1", "2"])
def test_ctrl_c_during_a_batch_still_writes_the_summary_of_what_finished(tiny, tmp_path, workers):
    """Issue 24 §8: SIGINT to a real `dualscale batch` process (in this process with --workers 1,
    on a local cluster with 2) while its first sample is in the report stage: exit 130, one line
    naming the summary, and summary.json/.csv/.html say what finished -- the sample's five done
    stages, its report interrupted -- and that the batch was interrupted."""
    proj = _project(tiny, tmp_path / "project", "a,b")
    out = proj / "out"
    cmd = [sys.executable, "-m", "dualscale.cli", "batch", str(proj / "samples.csv"), "-o", str(out),
           "--workers", workers, "--no-progress"]
    # the child starts with Ctrl-C's default action whatever this test process inherited (a clean
    # clone's `make test` started in the background has SIGINT ignored, and exec keeps that): the
    # test is of the command's own handling
    p = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        first = lambda: next((n for n in "ab" if (out / n / "stages" / "export.json").is_file()), None)  # noqa: E731
        _wait(lambda: first() is not None or p.poll() is not None, what="a sample's report stage")
        assert p.poll() is None, p.communicate()
        name = first()
        time.sleep(0.3)
        p.send_signal(signal.SIGINT)
        stdout, stderr = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(30)
    assert p.returncode == 130, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("dualscale batch: batch interrupted: ") and str(out / "summary.html") in last, stderr
    doc = json.loads((out / "summary.json").read_text())
    assert doc["interrupted"] is True
    rows = {r["name"]: r for r in doc["samples"]}
    r = rows[name]
    if r["status"] != "done":  # the report may have ended as the signal came
        assert r["status"] == "interrupted" and r["interrupted_stage"] == "report", r
        assert [r["stages"][s]["status"] for s in STAGES] == ["done"] * 5 + ["interrupted"]
        assert r["failed_stage"] is None and r["error"] is None
    other = rows["b" if name == "a" else "a"]
    assert other["status"] in ("interrupted", "done")
    csv_text = (out / "summary.csv").read_text()
    assert f"\n{name},{r['status']}," in csv_text
    html = (out / "summary.html").read_text()
    assert "The batch was interrupted" in html
    assert "STOPPED" in stdout or r["status"] == "done"
    assert not (out / name / "stages" / "report.json").exists() or r["status"] == "done"


# ------------------------------------------------------------------------------------ help and hints

def test_batch_help_says_one_thing_about_threads(capsys):
    """Issue 24 §8: it said "default 1 with a cluster" and "default: OMP_NUM_THREADS if set, else
    auto" in one breath; now one default clause, for both cases."""
    import re

    assert main(["batch", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    m = re.search(r"--threads N\|auto (.*?) --progress", text)
    assert m, text
    help_ = m.group(1)
    assert help_.count("default") == 1, help_
    assert "1 per worker" in help_ and "in this process OMP_NUM_THREADS if set, else auto" in help_


def test_a_sample_in_camera_counts_is_told_to_fill_the_lists_calibration_column(tmp_path):
    """Issue 24 §8: inside a batch the hint names the list's `calibration` column (and the row),
    not the `--calibration` option, which batch does not have."""
    from dualscale.batch import read_list, run_batch

    raw = tmp_path / "raw"
    assert main(["synth", "leather", "-o", str(raw), "--size", "8", "--texel-um", "9", "--dataset", "--lights",
                 "mod32", "--realistic", "--no-previews", "--no-progress"]) == 0
    (tmp_path / "samples.csv").write_text("name,input\nraw,raw/micro\n")
    (res,) = run_batch(read_list(tmp_path / "samples.csv"), tmp_path / "out")
    f = res.failure
    assert res.status == "failed" and f["stage"] == "calibrate" and f["error_type"] == "UnitsError"
    assert "in the list's 'calibration' column (samples.csv row 1)" in f["error"], f["error"]
    assert "--calibration" not in f["error"]


def test_digitize_transfer_without_guidance_is_refused_before_anything(tiny, tmp_path):
    """--transfer is the transfer function of a display-encoded --guidance image: without a
    guidance it would be accepted and ignored; it is refused, exit 2, one line, no run folder."""
    run = tmp_path / "run"
    rc, out, err = _main("digitize", str(tiny / "micro"), "-o", str(run), "--transfer", "srgb", *DRAFT)
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert "--transfer srgb" in err and "no guidance" in err and "--guidance" in err
    assert not run.exists()


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_rerun_refused_on_a_damaged_image_leaves_the_run_folder_as_it_was(tiny, tmp_path):
    """issue 24 trial: a rerun whose calibrate stage refuses a truncated image (exit 2) rewrote
    run.json and left work/calibrate/.stage-key; now the run folder is byte for byte as before."""
    ds, run = tmp_path / "syn", tmp_path / "R"
    assert main(["synth", "twill", "-o", str(ds), "--size", "32", "--texel-um", "9", "--dataset", "--lights", "mod4",
                 "--no-previews", "--no-progress"]) == 0  # images large enough to cut after their header
    assert _main("digitize", str(ds), "-o", str(run), "--until", "calibrate", "--no-progress", "--threads", "1")[0] == 0
    before = _tree(run)
    exr = sorted((ds / "micro" / "images").glob("*led*.exr"))[0]
    exr.write_bytes(exr.read_bytes()[:exr.stat().st_size // 2])  # the header whole: the check before any stage passes
    rc, _, err = _main("digitize", str(ds), "-o", str(run), *DRAFT, "--until", "calibrate", "--threads", "1")
    assert rc == 2 and exr.name in err, err
    assert _tree(run) == before
