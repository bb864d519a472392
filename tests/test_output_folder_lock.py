"""Every command's output folder honours the lock of a live process (issue 24 trial: while
`digitize syn -o RL2` ran, `synth ... -o RL2 --overwrite` emptied the folder)."""

from __future__ import annotations

import subprocess
import sys
import time

from dualscale.cli import main

HOLD = ("import sys, time\nfrom dualscale.formats.lock import FolderLock\n"
        "FolderLock(sys.argv[1], 'digitize').acquire()\nprint('held', flush=True)\ntime.sleep(120)\n")


def test_synth_overwrite_refuses_a_folder_another_live_process_holds(tmp_path, capsys):
    out = tmp_path / "RL2"
    out.mkdir()
    (out / "run.json").write_text("{}")
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        rc = main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress", "--overwrite"])
        assert rc == 2
        assert f"{out} is in use by PID {p.pid}" in capsys.readouterr().err
        assert (out / "run.json").read_text() == "{}" and not (out / "maps").exists()
    finally:
        p.kill()
        p.wait(30)
    time.sleep(0.05)
    assert main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress",
                 "--overwrite"]) == 0  # a dead holder's lock file does not block
    assert not (out / "run.json").exists() and not (out / ".dualscale-lock").exists()


def test_no_command_writes_inside_a_folder_a_live_process_holds(tmp_path, capsys):
    """Second trial: `render ... -o RUN/fit --overwrite` and `lights sphere ... -o RUN/L` wrote into a
    running digitize's folder (the lock was tried on the exact folder only)."""
    run = tmp_path / "X7"
    (run / "fit").mkdir(parents=True)
    (run / "fit" / "kept.txt").write_text("the fit stage's")
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        for argv in (["synth", "twill", "-o", str(run / "fit"), "--size", "8", "--no-previews", "--no-progress",
                      "--overwrite"],
                     ["synth", "twill", "-o", str(run / "export" / "x"), "--size", "8", "--no-previews",
                      "--no-progress"]):
            assert main(argv) == 2, argv
            assert f"{run} is in use by PID {p.pid}" in capsys.readouterr().err
        assert (run / "fit" / "kept.txt").read_text() == "the fit stage's" and not (run / "export").exists()
    finally:
        p.kill()
        p.wait(30)
    time.sleep(0.05)
    assert main(["synth", "twill", "-o", str(run / "export" / "x"), "--size", "8", "--no-previews",
                 "--no-progress"]) == 0  # a dead holder's lock file does not block


def test_a_refused_fresh_run_keeps_finished_stages_and_others_files(tmp_path):
    """Second trial: a digitize that a late stage refused deleted the whole run folder it had made,
    its finished stages and a file the user had put there."""
    from dualscale.cli.digitize import _empty

    run = tmp_path / "R"
    (run / "stages").mkdir(parents=True)
    (run / "work" / "fit").mkdir(parents=True)
    (run / "run.json").write_text("{}")
    (run / "notes.txt").write_text("mine")
    _empty(run)  # no stage finished: what a run writes goes, the user's file stays
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]
    (run / "stages").mkdir()
    (run / "stages" / "calibrate.json").write_text("{}")
    (run / "calibrate").mkdir()
    _empty(run)  # a finished stage: nothing goes, the run resumes
    assert (run / "calibrate").is_dir() and (run / "stages" / "calibrate.json").is_file()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait(30)
    return p.pid


def test_a_killed_overwrites_set_aside_contents_are_kept_where_the_notice_says(tmp_path, capsys):
    """kill -9 during `--overwrite` left `.RUN.overwritten-PID` (the old run) forever: the next run
    of the folder keeps it beside it, visibly, and says where (the interrupted run wrote outputs)."""
    out = tmp_path / "S"
    (out / "maps").mkdir(parents=True)
    (out / "maps" / "half.exr").write_bytes(b"x")  # what the killed run wrote
    aside = tmp_path / f".S.overwritten-{_dead_pid()}"
    aside.mkdir()
    (aside / "run.json").write_text("old")
    assert main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress",
                 "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert not aside.exists() and (tmp_path / "S.before-overwrite" / "run.json").read_text() == "old"
    assert str(tmp_path / "S.before-overwrite") in err and len([ln for ln in err.splitlines() if "note" in ln]) == 1


def test_a_killed_overwrite_that_wrote_nothing_gets_its_contents_back(tmp_path, capsys):
    out = tmp_path / "S"
    out.mkdir()
    aside = tmp_path / f".S.overwritten-{_dead_pid()}"
    aside.mkdir()
    (aside / "notes.txt").write_text("mine")
    assert main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress"]) == 0
    assert (out / "notes.txt").read_text() == "mine" and not aside.exists()
    assert "back in it" in capsys.readouterr().err


def test_digitize_of_a_dataset_and_of_its_micro_folder_is_one_input(tmp_path, capsys):
    syn = tmp_path / "syn"
    assert main(["synth", "twill", "-o", str(syn), "--size", "16", "--texel-um", "9", "--dataset", "--lights", "mod8",
                 "--no-previews", "--no-progress"]) == 0
    run = str(tmp_path / "R1")
    common = ["-o", run, "--until", "calibrate", "--no-progress", "--threads", "1"]
    assert main(["digitize", str(syn), *common]) == 0
    assert main(["digitize", str(syn / "micro"), *common]) == 0, capsys.readouterr().err


def test_digitize_rig_without_calibration_is_refused_before_the_rig_starts(tmp_path, capsys, monkeypatch):
    import dualscale.cli.capture as capture

    def never(*a, **k):
        raise AssertionError("the rig was started")

    monkeypatch.setattr(capture, "rig_and_cameras", never)
    assert main(["digitize", "--rig", "sim", "--camera", "sim:micro", "-o", str(tmp_path / "R")]) == 2
    assert "--calibration" in capsys.readouterr().err and not (tmp_path / "R").exists()
