"""Ctrl-C in a long command: exit code 130 and one line with the hint to resume, never a
traceback (issue 13 §3).  A terminal's Ctrl-C signals the whole process group, so the tests do
the same, once the command is at work (its output record or run folder is on disk)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.units.conftest import small_dataset

HINT = "run the same command again to resume"


def _interrupt(argv: list[str], started: Path, after_s: float = 1.0, timeout: float = 120,
               sig: signal.Signals = signal.SIGINT, group: bool = True) -> subprocess.CompletedProcess:
    """Run ``dualscale ARGV`` in its own session, wait until ``started`` exists and ``after_s``
    more, then send ``sig`` to its process group (Ctrl-C in a terminal) or, ``group=False``, to
    the process alone (``kill PID``); the finished process."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("DUALSCALE_DEBUG", None)
    p = subprocess.Popen([sys.executable, "-m", "dualscale.cli", *argv], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    t0 = time.monotonic()
    try:
        while not started.exists():
            assert p.poll() is None, p.communicate()
            assert time.monotonic() - t0 < timeout, "the command never started its work"
            time.sleep(0.05)
        time.sleep(after_s)
        assert p.poll() is None, f"the command finished before {sig.name}: {p.communicate()}"
        if group:
            os.killpg(p.pid, sig)
        else:
            p.send_signal(sig)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def _check(r: subprocess.CompletedProcess, cmd: str, hint: str = HINT) -> None:
    assert r.returncode == 130, r.stderr
    assert "Traceback" not in r.stderr and "KeyboardInterrupt" not in r.stderr, r.stderr
    last = r.stderr.splitlines()[-1]
    assert last.startswith(f"dualscale {cmd}: ") and last.endswith(hint), r.stderr


def test_ctrl_c_in_fit(tmp_path):
    ds = small_dataset(tmp_path / "ds", size=48, leds=tuple(range(0, 127, 6)))
    out = tmp_path / "out"
    r = _interrupt(["fit", str(ds), "-o", str(out), "--preset", "paper", "--threads", "1", "--cv-pixels", "0"],
                   out / ".dualscale-output.json")
    _check(r, "fit")


def test_ctrl_c_in_synth(tmp_path):
    out = tmp_path / "s"
    r = _interrupt(["synth", "twill", "-o", str(out), "--size", "128", "--dataset", "--threads", "1"],
                   out / ".dualscale-output.json")
    _check(r, "synth")


def test_ctrl_c_in_propagate_train(tmp_path):
    from dualscale.cli import main

    src = tmp_path / "twill"
    assert main(["synth", "twill", "-o", str(src), "--size", "32", "--texel-um", "6", "--dataset", "--lights",
                 "mod16", "--no-previews", "--threads", "1"]) == 0
    model = tmp_path / "m.dsp"
    r = _interrupt(["propagate", "train", str(src), "-o", str(model), "--preset", "quick", "--iterations", "100000",
                    "--crop", "32", "--width", "8", "--threads", "1", "--checkpoint-every", "1"],
                   Path(str(model) + ".ckpt"))
    _check(r, "propagate train", "continue it with the same command and --resume (its checkpoint is OUTPUT.ckpt)")


def test_ctrl_c_in_digitize(tmp_path):
    from dualscale.cli import main

    src = tmp_path / "twill"
    assert main(["synth", "twill", "-o", str(src), "--size", "32", "--dataset", "--lights", "mod8",
                 "--no-previews", "--threads", "1"]) == 0
    run = tmp_path / "run"
    r = _interrupt(["digitize", str(src / "micro"), "-o", str(run), "--threads", "1"], run / "run.json", after_s=2.0)
    _check(r, "digitize")


def test_ctrl_c_while_the_commands_load(monkeypatch, capsys):
    from dualscale import cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    monkeypatch.delenv("DUALSCALE_DEBUG", raising=False)
    assert cli.main(["fit"]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "interrupted" in err and "Traceback" not in err
