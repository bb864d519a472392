"""A stop request -- SIGTERM (``kill``, ``timeout``, Slurm at the end of a job's time) or SIGHUP
(the terminal went away) -- is handled like Ctrl-C (issue 24, fresh-user trial): exit 130 and
one line naming the signal with the hint to resume, never a traceback, never 143/129.  Real
processes, real signals, sent to the command's process only (as ``kill`` and ``timeout`` do)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.units.conftest import small_dataset
from tests.units.test_interrupts import _interrupt

HINT = "run the same command again to resume"


def _stop(argv: list[str], started: Path, sig: signal.Signals, after_s: float = 1.0,
          timeout: float = 120) -> subprocess.CompletedProcess:
    """``kill -SIG PID``: the signal to the process alone, as ``kill``/``timeout`` send it."""
    return _interrupt(argv, started, after_s, timeout, sig=sig, group=False)


def _check(r: subprocess.CompletedProcess, cmd: str, sig: signal.Signals) -> str:
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and "KeyboardInterrupt" not in r.stderr and "StopRequest" not in r.stderr
    last = r.stderr.splitlines()[-1]
    assert last.startswith(f"dualscale {cmd}: ") and last.endswith(HINT), r.stderr
    assert f"stopped by {sig.name}" in last, r.stderr
    return last


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_request_in_synth(tmp_path, sig):
    out = tmp_path / "s"
    r = _stop(["synth", "twill", "-o", str(out), "--size", "128", "--dataset", "--threads", "1"],
              out / ".dualscale-output.json", sig)
    last = _check(r, "synth", sig)
    assert last == f"dualscale synth: stopped by {sig.name}; {HINT}", r.stderr


def test_sigterm_in_fit_saves_the_checkpoint_and_names_the_signal(tmp_path):
    ds = small_dataset(tmp_path / "ds", size=48, leds=tuple(range(0, 127, 6)))
    out = tmp_path / "out"
    r = _stop(["fit", str(ds), "-o", str(out), "--preset", "paper", "--threads", "1", "--cv-pixels", "0"],
              out / ".dualscale-output.json", signal.SIGTERM, after_s=2.0)
    _check(r, "fit", signal.SIGTERM)


def test_sigterm_in_digitize_then_the_same_command_resumes(tmp_path):
    from dualscale.cli import main

    src = tmp_path / "twill"
    assert main(["synth", "twill", "-o", str(src), "--size", "32", "--dataset", "--lights", "mod8",
                 "--no-previews", "--threads", "1"]) == 0
    run = tmp_path / "run"
    argv = ["digitize", str(src / "micro"), "-o", str(run), "--threads", "1"]
    r = _stop(argv, run / "run.json", signal.SIGTERM, after_s=2.0)
    _check(r, "digitize", signal.SIGTERM)
    assert not (run / ".dualscale-lock").exists(), "the run folder's lock was left behind"


def test_the_handlers_are_restored_after_main(tmp_path):
    """``main`` runs in-process (tests, library callers): the previous handlers come back."""
    from dualscale.cli import main

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)}
    assert main(["synth", "twill", "-o", str(tmp_path / "s"), "--size", "16", "--no-previews"]) == 0
    assert {s: signal.getsignal(s) for s in before} == before


def test_sim_ends_cleanly_on_sighup(tmp_path):
    """``sim`` has always ended on SIGINT/SIGTERM with exit 0 and its link removed; SIGHUP too."""
    from dualscale.rig.launcher import SimulatedRig  # noqa: F401 - the simulator binary must exist

    link = tmp_path / "rig"
    p = subprocess.Popen([sys.executable, "-m", "dualscale.cli", "sim", "--target", "posix", "--link", str(link)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = p.stdout.readline().strip()
        if not first:
            err = p.communicate(timeout=30)[1]
            if "make -C firmware posix" in err:
                pytest.skip("the posix simulator is not built")
            raise AssertionError(err)
        assert link.is_symlink()
        p.send_signal(signal.SIGHUP)
        assert p.wait(20) == 0, p.stderr.read()
        assert not link.exists()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
