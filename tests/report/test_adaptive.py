"""The run report's "Adaptive capture" section (issue 27 §2): a real ``digitize --rig sim
--adaptive`` run through the POSIX firmware simulator, its report checked against the
``"adaptive"`` record of ``RUN/capture/micro/capture.json``; and the section's absence without
that record."""

from __future__ import annotations

import json
import re

import pytest

from dualscale.report import format as fmt
from dualscale.rig.launcher import sim_binary

from .runfolder import make_run
from .test_report import _assert_readable, _checking_figures, _parse, _section

MICRO = "sim:micro?material=leather&size=12&texel_um=9&readout_ms=1"


@pytest.fixture(scope="module")
def adaptive_run(tmp_path_factory):
    """One adaptive capture (16 candidates, 6 initial LEDs, 2 a round, 24 shots) digitized to its
    report in one ``digitize`` call, every saved figure checked for overlapping labels."""
    if not sim_binary().exists():
        pytest.skip("POSIX simulator not built (make -C firmware posix)")
    from dualscale.cli import main
    from dualscale.report import html as rhtml

    from tests.units.rawrig import calibration_session

    tmp = tmp_path_factory.mktemp("adaptive")
    cal = calibration_session(tmp / "cal", led_step=8)
    run = tmp / "RUN"
    problems: list = []
    save = rhtml.Assets.figure
    rhtml.Assets.figure = _checking_figures(problems)
    try:
        assert main(["digitize", "--rig", "sim", "--sim-speed", "0", "--rig-id", "virtual-dome-0", "--lights", "MOD8",
                     "--camera", MICRO, "-o", str(run), "--calibration", str(cal), "--quality", "draft",
                     "--threads", "1", "--no-progress", "--export", "exr", "--adaptive", "--initial-leds", "6",
                     "--batch-leds", "2", "--budget", "24"]) == 0
    finally:
        rhtml.Assets.figure = save
    record = json.loads((run / "capture" / "micro" / "capture.json").read_text())["adaptive"]
    return run, run / "report" / "index.html", record, problems


@pytest.mark.slow  # a rig capture, four fits and a whole report: 60 s on 2 cores (load 2.8)
def test_adaptive_section_shows_the_rounds(adaptive_run):
    run, page, rec, problems = adaptive_run
    text, p = _parse(page)
    _assert_readable(text)
    raw = page.read_text(encoding="utf-8")
    assert 'href="#adaptive"' in raw  # in the table of contents
    sec = _section(page, "adaptive")
    assert "Adaptive capture" in sec
    fitted = [r for r in rec["rounds"] if "fit" in r]
    assert len(fitted) >= 2 and rec["rounds"][-1]["leds"] == [] and "fit" not in rec["rounds"][-1]
    # the table: one row per fitted round, its LEDs, shots, device time and medians from capture.json
    table = raw.split('<section id="adaptive">', 1)[1].split("</section>", 1)[0].split("<table>", 1)[1]
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", r) for r in table.split("</table>", 1)[0].split("<tr>")[2:]]
    assert len(rows) == len(fitted)
    for row, r in zip(rows, fitted):
        f = r["fit"]
        assert row[0] == str(r["round"])
        assert row[1].split(" + ")[0] == ", ".join(str(x) for x in r["leds"])
        assert row[2] == str(f["shots"]) and row[3] == fmt.quantity(f["floor_s"], "s")
        for cell, n in zip(row[4:], ("normal", "roughness", "albedo")):
            assert cell == (fmt.number(f["sigma"][n]) if n in f["sigma"] else "not fitted"), (n, cell)
    assert f"Stopped ({rec['stop']}): {rec['reason']}." in sec
    assert f"shots taken {rec['shots']}" in sec and fmt.quantity(rec["floor_s"], "s") in sec
    # the figures: written, with captions that say what is shown
    imgs = [s for s in p.imgs if "adaptive_" in s]
    assert sorted(imgs) == ["assets/adaptive_dome.png", "assets/adaptive_sigma.png"]
    assert all((page.parent / s).stat().st_size > 10_000 for s in imgs)
    n_taken = sum(len(r["leds"]) for r in fitted)
    assert f"after each of the {len(fitted)} rounds" in sec and "log axis" in sec
    assert "the 127 LEDs" in sec and "the 16 candidates" in sec and f"the {n_taken} LEDs taken" in sec
    # the dome: the chosen LEDs are drawn in the round colours (plasma), not only grey
    import matplotlib.image as mpimg

    a = mpimg.imread(page.parent / "assets/adaptive_dome.png")[..., :3]
    assert ((a[..., 0] > 0.8) & (a[..., 2] < 0.3)).sum() > 30  # the last rounds' yellow/orange
    assert [x for x in problems if x[0].startswith("adaptive_")] == []  # no overlapping label


def test_no_adaptive_section_without_the_record(tmp_path, figures_not_drawn):
    """Absent for a run without a rig capture and for a fixed plan's capture.json (no
    ``"adaptive"``); an unreadable capture.json is a report warning, and the page is written.
    (The page's words only: its figures are not drawn, see figures_not_drawn.)"""
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    for doc in (None, json.dumps({"format": "dualscale-capture", "plan": {"shots": []}}), "{not json"):
        if doc is not None:
            (run / "capture" / "micro").mkdir(parents=True, exist_ok=True)
            (run / "capture" / "micro" / "capture.json").write_text(doc)
        raw = write_run_report(run).read_text(encoding="utf-8")
        assert 'id="adaptive"' not in raw and "#adaptive" not in raw and "Adaptive capture" not in raw
        assert ("capture/micro/capture.json is not readable" in raw) == (doc == "{not json")


def test_adaptive_section_words(tmp_path, figures_not_drawn):
    """The section from a record of the shape ``AdaptiveCapture.run`` writes (module doc of
    dualscale.adaptive.loop), in ``make test`` without the rig: the header rows, a row per fitted
    round (a map the round did not fit says so), the stop rule under the table, the two figures
    in the table of contents' section.  (Words only: figures_not_drawn.)"""
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False, capture_seconds=12.0)
    fit = {"components": {"opaque": True}, "sample_pixels": 144, "warm": False}
    rec = {"options": {"initial": 6, "batch": 2, "criterion": "D", "targets": {"normal": 0.2}, "budget_shots": None,
                       "budget_s": 300.0},
           "stop": "targets", "reason": "every map at or under its target",
           "rounds": [{"round": 0, "leds": [0, 48], "why": "2 LEDs spread over the dome",
                       "fit": dict(fit, round=0, shots=6, floor_s=20.5, sigma={"normal": 0.41, "albedo": 0.0021})},
                      {"round": 1, "leds": [16], "why": "best D-gain per second", "picks": [[16, 1.2]],
                       "fit": dict(fit, round=1, shots=8, floor_s=27.25,
                                   sigma={"normal": 0.19, "albedo": 0.0012, "roughness": 0.0051})},
                      {"round": 2, "leds": [], "stop": "targets", "reason": "every map at or under its target"}],
           "shots": 8, "floor_s": 27.25}
    plan = {"shots": [{"kind": "led", "index": i, "analyzer_cdeg": a} for a in (0, 9000) for i in range(0, 127, 16)]
            + [{"kind": "backlight", "index": 0, "analyzer_cdeg": 0}]}
    (run / "capture" / "micro").mkdir(parents=True)
    (run / "capture" / "micro" / "capture.json").write_text(json.dumps({"plan": plan, "adaptive": rec}))
    page = write_run_report(run)
    text, p = _parse(page)
    _assert_readable(text)
    assert 'href="#adaptive"' in page.read_text(encoding="utf-8")
    sec = _section(page, "adaptive")
    assert "rounds 2 candidates (the plan's LEDs) 8 shots taken 8 device time (physical floor) 27.2 s" in sec
    assert "budget 5 min " in sec and "targets (median σ) normal 0.2" in sec
    assert "0 0, 48 + back light 6 20.5 s 0.41 not fitted 0.0021" in sec
    assert "1 16 8 27.2 s 0.19 0.0051 0.0012" in sec
    assert "Stopped (targets): every map at or under its target." in sec
    assert "after each of the 2 rounds" in sec and "A gap: the map was not fitted in that round (roughness" in sec
    assert "the 8 candidates" in sec and "the 3 LEDs taken" in sec
    assert sorted(s for s in p.imgs if "adaptive_" in s) == ["assets/adaptive_dome.png", "assets/adaptive_sigma.png"]
    assert "whole candidate plan" not in sec  # a record without the prediction: nothing invented
    # with the whole plan's prediction (the last decision's full_plan) and the relative target
    rec["options"]["full_target"] = 0.05
    rec["rounds"][1]["full_plan"] = {"sigma": {"normal": 0.1, "albedo": 0.001}, "sigma_now": {"normal": 0.19, "albedo": 0.0012},
                                     "cost_s": 95.5, "shots": 18}
    (run / "capture" / "micro" / "capture.json").write_text(json.dumps({"plan": plan, "adaptive": rec}))
    sec = _section(write_run_report(run), "adaptive")
    assert "targets (median σ) normal 0.2, every other map within 5 % of the whole plan's predicted σ" in sec
    assert ("the whole candidate plan (predicted) 18 shots, about 95.5 s of device time; at the last decision the worst map, "
            "normal, had 1.9 times its predicted σ") in sec, sec
    assert "Dashed: each map's median 1σ that the whole candidate plan would give" in sec
