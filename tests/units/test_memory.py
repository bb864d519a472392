"""Out of memory (issue 24, fresh-user trial): a ``synth`` that cannot fit is refused before any
work (exit 2, naming the option and the estimate) instead of being OOM-killed (137); a command
that runs out of memory anyway exits 4 (the environment) with one line, not 5 "internal error".
Real subprocesses under a real address-space limit (``ulimit -v``)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

from dualscale.cli import main

LIMIT = 6 * 2**30


def _limited(argv: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("DUALSCALE_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "dualscale.cli", *argv], capture_output=True, text=True, env=env,
                          timeout=120, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (LIMIT, LIMIT)))


def test_synth_too_big_for_the_memory_is_refused_before_any_work(tmp_path):
    out = tmp_path / "E"
    r = _limited(["synth", "twill", "-o", str(out), "--size", "8192", "--mid-size", "8192", "--dataset"])
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert r.stderr.startswith("dualscale synth: error: --size 8192: synth would need about 25.3 GiB"), r.stderr
    assert "ulimit -v" in r.stderr and "choose --size" in r.stderr
    assert not out.exists()
    r = _limited(["synth", "twill", "-o", str(out), "--size", "64", "--mid", "--mid-size", "4096"])
    assert r.returncode == 2 and "--mid-size 4096: synth would need" in r.stderr, r.stderr


def test_running_out_of_memory_is_the_environment_exit_4(tmp_path):
    assert main(["synth", "twill", "-o", str(tmp_path / "s"), "--size", "16", "--no-previews", "--no-progress"]) == 0
    r = _limited(["render", str(tmp_path / "s" / "maps"), "-o", str(tmp_path / "r"), "--camera", "mid", "--size",
                  "8192", "--diffuse"])
    assert r.returncode == 4, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr
    assert r.stderr.startswith("dualscale render: error: out of memory: ") and "GiB available" in r.stderr
