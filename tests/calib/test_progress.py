"""Progress of the long calibration steps: counted through the library's `progress`
argument (never printed by the library), and the bar the command line draws from it."""

import pytest

from dualscale.progress import Tracker, iterate, tracker


def _recorder():
    calls = []

    def fn(done, total, what):
        calls.append((done, total, what))

    return calls, fn


def test_tracker_kinds():
    calls, fn = _recorder()
    assert list(iterate(fn, [10, 20, 30], "x")) == [10, 20, 30]
    assert [c[:2] for c in calls] == [(1, 3), (2, 3), (3, 3)]
    with tracker(False, 5, "quiet") as t:  # nothing to report to: still counts
        t.update(2)
    assert t.done == 2
    outer_calls, outer_fn = _recorder()
    with Tracker(outer_fn, 4, "outer") as outer:
        with tracker(outer, None, "inner") as inner:  # a nested step adds to the open tracker
            inner.update(what="a")
        outer.update(3)
    assert outer.done == 4 and outer_calls[-1][:2] == (4, 4) and outer_calls[0][2] == "a"


def test_synth_targets_counts_every_step(tmp_path):
    from dualscale.geometry.dome import DomeGeometry
    from dualscale.sim.targets import SynthConfig, lights, write_session

    calls, fn = _recorder()
    cfg = SynthConfig(led_step=64, micro_px=8, other_px=16, cameras=("micro", "mid"))
    write_session(tmp_path / "caps", cfg, parts=("white_sheet", "polarization"), progress=fn)
    n_lights = len(lights(cfg, DomeGeometry.from_regmap()))
    total = 2 * n_lights + (n_lights - 2)  # cameras x lights, then the sweep of each LED
    assert calls[-1][:2] == (total, total) and len(calls) == total


@pytest.mark.slow  # a calibration and an evaluation of the shared session: ~30 s on 2 cores
def test_calibrate_and_evaluate_count_each_merge_once(session_dir):
    """The bars of `calibrate` and `evaluate-device` end at their totals: every HDR merge is
    counted once, and the totals are known before the work starts."""
    from dualscale.calib.evaluate import merges_needed
    from dualscale.calib.pipeline import CALIBRATION_TARGETS, calibrate, session_with
    from dualscale.cli.calib import _evaluate
    from dualscale.formats.captures import read_captures

    cs = read_captures(session_dir[0])
    calls, fn = _recorder()
    calib = calibrate(cs, progress=fn)
    total = sum(g.target in CALIBRATION_TARGETS for g in cs.groups)
    assert total > 0 and calls[-1][:2] == (total, total) and len(calls) == total
    assert len({c[2] for c in calls}) == total  # each group's id, once
    calls, fn = _recorder()
    with tracker(fn, merges_needed(cs), "evaluate-device") as bar:
        _evaluate(session_with(cs, calib, progress=bar))
    assert calls[-1][:2] == (merges_needed(cs),) * 2 and len(calls) == merges_needed(cs)


def test_synth_targets_draws_its_bar_on_stderr_when_asked(tmp_path, capsys):
    from dualscale.cli import main

    args = ["synth-targets", "-o", str(tmp_path / "c"), "--led-step", "64", "--micro-px", "8", "--other-px", "16",
            "--parts", "white_sheet", "--threads", "1"]
    assert main(args + ["--progress"]) == 0
    cap = capsys.readouterr()
    assert "synth-targets:" in cap.err and "/16 [" in cap.err  # 4 cameras x (2 LEDs, diffuse, back light)
    assert cap.out.strip().endswith("captures.json")
    assert main(args + ["-o", str(tmp_path / "d"), "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
