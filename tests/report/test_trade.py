"""The run report's place on the propagation trade curve (issue 29 §4, dualscale.report.trade):
the propagation section names the run's preset with its own training time and iterations, shows
the twill benchmark's measured point for that preset (labelled as the benchmark's, with its
date and machine), and says so when the preset has no measured point; the packaged data are
checked on load."""

from __future__ import annotations

import copy
import json

import pytest

from dualscale.errors import FormatError
from dualscale.report import trade

from .runfolder import make_run
from .test_report import _section


def _set_preset(run, preset: str, iterations: int) -> None:
    rec = run / "stages" / "propagate.json"
    doc = json.loads(rec.read_text())
    doc["summary"].update(preset=preset, iterations=iterations)
    rec.write_text(json.dumps(doc))


def test_packaged_trade_data_load_and_give_every_preset_once():
    from dualscale.propagate.train import LEGACY_PRESETS, PRESETS

    doc = trade.load_trade()
    for name in ("quick", "fast", "balanced"):  # today's presets, warm-started as they train
        run, p = trade.measured_point(doc, name, warm_start=True)
        assert p["preset"] == name and p["warm_start"] and p["iterations"] == PRESETS[name].iterations
        assert p["batch"] == PRESETS[name].batch
        assert set(p["maps"]) == set(doc["maps"]) and run["date"] and run["machine"]
        old = trade.measured_point(doc, f"legacy-{name}")[1]  # the same run's presets before issue 29
        assert old["iterations"] == LEGACY_PRESETS[name].iterations and not old["warm_start"]
    assert trade.measured_point(doc, "fast") is None  # today's fast from random weights: not measured
    assert trade.measured_point(doc, "paper") is None


def test_report_says_where_its_preset_sits_on_the_curve(tmp_path, figures_not_drawn):
    from dualscale.report import write_run_report

    doc = trade.load_trade()
    run_meta, p = trade.measured_point(doc, "fast", warm_start=True)
    run = make_run(tmp_path / "R", flyouts=False)
    sec = _section(write_run_report(run), "propagation")
    assert "training preset fast" in sec and "warm start warmstart_w16.dsp" in sec
    assert "training of this run 58.9 s, 240 iterations" in sec  # the run's own record
    assert f"measured on the twill benchmark, {run_meta['date']}, {run_meta['machine']}; not this run's accuracy" in sec
    albedo_l1, albedo_ssim = p["maps"]["albedo"]
    assert f"{p['label']}: " in sec and f"for 240 iterations × batch 8 (load {p['load']:g})" in sec
    assert f"albedo L1 {albedo_l1:.3f}, SSIM {albedo_ssim:.2f}" in sec
    assert "not the benchmark's" not in sec

    _set_preset(run, "fast", 120)  # an overridden iteration count is pointed out
    sec = _section(write_run_report(run), "propagation")
    assert "this run trained 120 iterations, not the benchmark's 240" in sec


def test_report_says_when_its_preset_has_no_measured_point(tmp_path, figures_not_drawn):
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "R", flyouts=False)
    _set_preset(run, "paper", 5000)
    sec = _section(write_run_report(run), "propagation")
    assert "training preset paper" in sec and "training of this run 58.9 s, 5\u2009000 iterations" in sec
    assert "the preset paper (warm-started) has no measured point on the twill benchmark (measured: " in sec
    assert "measured on the twill benchmark," not in sec
    _set_preset(run, "fast", 240)  # a run from random weights has no point either: today's fast was measured warm
    rec = run / "stages" / "propagate.json"
    d = json.loads(rec.read_text())
    d["summary"]["warm_start"] = None
    rec.write_text(json.dumps(d))
    sec = _section(write_run_report(run), "propagation")
    assert "warm start none (random weights)" in sec
    assert "the preset fast (from random weights) has no measured point" in sec


def test_bad_trade_data_are_refused_with_the_field(tmp_path):
    good = trade.load_trade()
    dup = copy.deepcopy(good)
    dup["runs"][0]["points"].append(copy.deepcopy(dup["runs"][0]["points"][0]))
    short = copy.deepcopy(good)
    del short["runs"][0]["points"][0]["maps"]["normal"]
    for doc, what in ((dup, "a second point for preset '" + good["runs"][0]["points"][0]["preset"] + "'"), (short, "must give every map"),
                      ({"format": "other"}, "not a dualscale-propagate-trade document")):
        f = tmp_path / "t.json"
        f.write_text(json.dumps(doc))
        with pytest.raises(FormatError, match=what):
            trade.load_trade(f)
    with pytest.raises(FormatError, match="missing"):
        trade.load_trade(tmp_path / "absent.json")
