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
