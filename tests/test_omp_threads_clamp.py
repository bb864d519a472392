"""``OMP_NUM_THREADS`` above the machine's cores (issue 24 §3, a fresh user's trial): lowered to
them with a notice, as ``--threads`` is, not taken as it is."""

from __future__ import annotations

import os
import warnings

from dualscale import threads


def test_an_excessive_omp_num_threads_is_lowered_with_a_notice(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "10000")
    cores = threads.machine_cores()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert threads.resolve(None) == cores
    assert [str(w.message) for w in caught] == [f"OMP_NUM_THREADS=10000 is more than this machine's {cores} "
                                                f"core{'s' if cores > 1 else ''}: using {cores}"]
    assert os.environ["OMP_NUM_THREADS"] == str(cores)  # what later processes inherit; no second notice
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert threads.default_threads() == cores
    assert not caught


def test_a_fitting_omp_num_threads_is_taken_without_a_notice(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert threads.default_threads() == 1


def test_the_command_line_prints_the_notice_once(monkeypatch, tmp_path, capsys):
    from dualscale.cli import main

    monkeypatch.setattr(threads, "_chosen", threads._chosen)  # the process's choice, restored after
    monkeypatch.setenv("OMP_NUM_THREADS", "10000")
    out = tmp_path / "s"
    assert main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress"]) == 0
    err = capsys.readouterr().err
    line = f"OMP_NUM_THREADS=10000 is more than this machine's {threads.machine_cores()}"
    assert err.count(line) == 1 and f"dualscale synth: warning: {line}" in err, err
