"""The HTML reports: the run report of ``dualscale digitize`` on a small synthetic RUN folder
(tests/report/runfolder.py, written by the run-folder contract), the device-evaluation report on
synthetic results, the shared number formatting and plots, and a headless-browser check that the
page loads offline with no console error and no broken image."""

from __future__ import annotations

import functools
import html.parser
import http.server
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from dualscale.report import format as fmt

from tests.cdp import Browser

from .runfolder import make_run


# ---------------------------------------------------------------------------------------------
# helpers

class _Page(html.parser.HTMLParser):
    """Visible text (no <style>/<script>) and every <img src> of a page."""

    def __init__(self):
        super().__init__()
        self.text: list[str] = []
        self.imgs: list[str] = []
        self.scripts = 0
        self._skip = 0

    def handle_starttag(self, tag, attrs):
        if tag in ("style", "script"):
            self._skip += 1
            self.scripts += tag == "script"
        if tag == "img":
            self.imgs.append(dict(attrs).get("src", ""))

    def handle_endtag(self, tag):
        if tag in ("style", "script"):
            self._skip -= 1

    def handle_data(self, data):
        if not self._skip and data.strip():
            self.text.append(data.strip())


def _parse(path: Path) -> tuple[str, _Page]:
    p = _Page()
    p.feed(path.read_text(encoding="utf-8"))
    return " ".join(p.text), p


def _assert_readable(text: str) -> None:
    """No JSON dump, no Python repr, no float with a long tail of digits."""
    assert "{" not in text and "}" not in text, re.findall(r".{30}[{}].{30}", text)[:3]
    assert not re.search(r"\[\s*[-\d.'\"(]", text), re.findall(r".{30}\[\s*[-\d.'\"(].{30}", text)[:3]  # list repr
    for bad in ("True", "False", "None", "nan"):
        assert not re.search(rf"(?<![\w|]){re.escape(bad)}(?![\w|])", text), (bad, re.findall(rf".{{30}}{re.escape(bad)}.{{30}}", text)[:3])
    long_floats = [x for x in re.findall(r"\d+\.\d+", text) if len(x.replace(".", "").lstrip("0")) > 6]
    assert not long_floats, long_floats[:5]
    long_numbers = [n for n in re.findall(r"\d[\d.]*", text) if sum(c.isdigit() for c in n) >= 10]
    assert not long_numbers, long_numbers[:5]


def _checking_figures(problems: list):
    """A replacement for ``Assets.figure`` that checks each saved figure for overlapping labels
    and labels cut off at the figure's edge, appending ``(name, pairs)`` to ``problems``."""
    from dualscale.report import html as rhtml
    from dualscale.report import plots

    save = rhtml.Assets.figure

    def figure(self, fig, stem):
        bad = plots.overlapping_texts(fig)
        if bad:
            problems.append((stem, bad))
        return save(self, fig, stem)

    return figure


@pytest.fixture
def layout_checked(monkeypatch):
    """Every figure a report saves is checked (see :func:`_checking_figures`); returns the list
    of problems."""
    from dualscale.report import html as rhtml

    problems: list = []
    monkeypatch.setattr(rhtml.Assets, "figure", _checking_figures(problems))
    return problems


@pytest.fixture(scope="module")
def run_report(tmp_path_factory):
    """The full synthetic run, rendered once, every saved figure checked (the problems are
    returned third)."""
    from dualscale.report import html as rhtml
    from dualscale.report import write_run_report

    problems: list = []
    save = rhtml.Assets.figure
    run = make_run(tmp_path_factory.mktemp("report") / "RUN")
    rhtml.Assets.figure = _checking_figures(problems)
    try:
        page = write_run_report(run)
    finally:
        rhtml.Assets.figure = save
    return run, page, problems


def test_run_report_figures_have_no_overlapping_labels(run_report):
    assert run_report[2] == []


# ---------------------------------------------------------------------------------------------
# the run report

def test_run_report_content(run_report):
    run, page, _ = run_report
    assert page == run / "report" / "index.html"
    text, p = _parse(page)
    raw = page.read_text(encoding="utf-8")
    _assert_readable(text)
    # self-contained: no script, no external URL, every image in report/assets and present
    assert p.scripts == 0 and "http://" not in raw and "https://" not in raw and "//" not in "".join(p.imgs)
    assert len(p.imgs) >= 14
    for src in p.imgs:
        assert src.startswith("assets/"), src
        assert (page.parent / src).is_file() and (page.parent / src).stat().st_size > 1000, src
    assert not list(page.parent.glob(".*.tmp")), "temporary file left behind"
    # units and goals beside the values
    assert "✓" in text
    for unit in ("4.9 µm", "0.157 × 0.157 mm", "4.31%", "0.123%", "2 min 13 s", "1 min 1 s", "θ 21.2°"):
        assert unit in text, unit
    # every warning listed at the top and in its stage
    top = text.split("Inputs and calibration")[1]
    assert "3 warnings" in text.split("Inputs and calibration")[0] or "3 warnings" in top.split("Run")[0]
    for w in ("3 of 254 images have more than 1% saturated", "guidance image has no colour calibration"):
        assert text.count(w) >= 3, w  # top list, its section, its stage record
    # the sections
    for s in ("Component decision", "Evidence per decision", "Candidates", "Fit residual",
              "Held-out error (cross-validated over the lights)", "Fly-outs", "Propagated maps on the guidance", "Time per stage",
              "Stage records", "normalised_dn → relative_radiance", "val rmse isotropic: 0.0139"):
        assert s in text, s
    for name in ("albedo", "normal", "roughness", "anisotropy", "tangent azimuth", "index of refraction η",
                 "specular tint", "propagated albedo"):
        assert f"{name}." in text, name
    assert "η = 1 + 2·(stored value)" in text and "Clipped:" in text
    assert text.count("LED 7: θ") == 0 and "LED 88" in text


def test_run_report_heldout_section_is_cross_validated_and_labels_the_re_renders(run_report):
    """The held-out section: the cross-validated error of every light (fold, baseline), the
    maps fitted on every light, and the capture/render pairs labelled as re-renders of training
    lights, not as held-out predictions."""
    run, page, _ = run_report
    text, _ = _parse(page)
    section = text.split("Held-out error (cross-validated over the lights)")[1].split("Fly-outs")[0]
    assert "Measured by 8-fold cross-validation over 10 lights on 2000 sample pixels" in section
    assert "none is held out of them" in section and "made once, on all lights" in section
    for led in (3, 7, 12, 20, 31, 45, 60, 71, 88, 100):  # every light has its held-out error
        assert re.search(rf"(?<!\d){led} [\d.]+° [\d.]+° \d [\d.]+% [\d.]+%", section), led
    assert "3% 9%" in section  # LED 3: 0.03 held out, 0.09 baseline
    assert section.count("a training light (not held out)") == 3
    assert "not a prediction" in section and "held-out capture" not in section
    assert "held-out relative L1 (cross-validated) 4.31%" in text  # the headline cards
    assert "Lambertian baseline, same folds 10.3%" in text
    assert "254 of 254 (no light held out)" in text


def test_run_report_optional_stages_missing(tmp_path):
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    shutil.rmtree(run / "export")
    (run / "stages" / "export.json").unlink()
    text, p = _parse(write_run_report(run))
    _assert_readable(text)
    assert "Fly-out detection was skipped: the material has no fly-out fibres option (--no-flyouts)." in text
    assert "Propagation was skipped: no guidance image given." in text
    assert "The maps were not exported." in text
    assert re.search(r"export\s*: no record \(stage not run\)", text)
    assert all((run / "report" / s).is_file() for s in p.imgs)


def test_run_report_into_another_folder_and_rerun(tmp_path):
    """The pipeline renders into its work folder (then renames it to RUN/report); a rerun
    replaces the assets of the previous one."""
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    out = run / "work" / "report"
    page = write_run_report(run, out=out)
    assert page == out / "index.html" and not (run / "report").exists()
    stale = out / "assets" / "stale.png"
    stale.write_bytes(b"x")
    write_run_report(run, out=out)
    assert not stale.exists()
    _, p = _parse(page)
    assert p.imgs and all((page.parent / s).is_file() for s in p.imgs)


@pytest.mark.parametrize("missing", ["run.json", "stages/fit.json", "fit/residual.exr", "fit/maps/material.json",
                                     "fit/heldout/heldout.json", "fit/heldout/render_31.exr"])
def test_run_report_missing_required_artefact(tmp_path, missing):
    from dualscale.errors import FormatError
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    (run / missing).unlink()
    with pytest.raises(FormatError, match=re.escape(Path(missing).name)):
        write_run_report(run)
    assert not (run / "report" / "index.html").exists()


# ---------------------------------------------------------------------------------------------
# consistency (issue 24 Sec. 4): the title, the times, the capture stage, the file sizes

def _section(page: Path, sid: str) -> str:
    """The visible text of the page's ``<section id=sid>``."""
    raw = page.read_text(encoding="utf-8")
    body = raw.split(f'<section id="{sid}">', 1)[1].split("</section>", 1)[0]
    p = _Page()
    p.feed(body)
    return " ".join(p.text)


def test_run_report_title_uses_the_name(tmp_path, figures_not_drawn):
    """The title names the material by ``--name`` (it used the input folder's name), else by
    the name the export stage gave it."""
    from dualscale.report import write_run_report

    named = make_run(tmp_path / "A", flyouts=False, guidance=False, name="denim-01")
    text, _ = _parse(write_run_report(named))
    title = re.search(r"<title>(.*?)</title>", (named / "report" / "index.html").read_text(encoding="utf-8")).group(1)
    assert title == "dualscale run: denim-01" and "dualscale run: denim-01" in text
    plain = make_run(tmp_path / "B", flyouts=False, guidance=False)
    write_run_report(plain)
    assert "<title>dualscale run: twill_042</title>" in (plain / "report" / "index.html").read_text(encoding="utf-8")


def test_run_report_fit_time_is_the_records(run_report):
    """One figure for the fit's time: the fit stage's record (the time chart's), with the
    per-pixel fit and the cross-validation given as parts of it (the maps table said 2.7 s
    against 41.9 s in the chart)."""
    run, page, _ = run_report
    text, _ = _parse(page)
    maps = _section(page, "maps")
    timing = _section(page, "time")
    assert re.search(r"fit 2 min 13 s", timing), timing
    assert "fit stage time 2 min 13 s (of which the per-pixel fit 41.7 s, the cross-validation 1 min 1 s)" in maps
    assert not re.search(r"(?<!of which the per-pixel )fit time", maps)
    record = _section(page, "records")
    fit_record = record.split("fit", 1)[1].split("flyouts", 1)[0]
    assert "of which the per-pixel fit 41.7 s" in fit_record and "seconds" not in fit_record


def test_run_report_shows_the_capture_stage(tmp_path):
    """digitize --rig: the capture stage (stages/capture.json, before the stages run.json lists)
    is in the time chart, the table, the records and the total."""
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False, capture_seconds=23.9)
    page = write_run_report(run)
    text, _ = _parse(page)
    timing = _section(page, "time")
    assert "capture 23.9 s" in timing, timing
    total = 23.9 + 4.2 + 133.4 + 0.01 + 0.0 + 0.31
    assert f"total time (capture included) {fmt.duration(total)}" in text, total
    assert _section(page, "records").startswith("Stage records capture")


def test_run_report_export_gives_each_files_size(run_report):
    """Each file's own size (the table gave the format folder's total beside its main file:
    material.json 821 kB for a 776 B file)."""
    run, page, _ = run_report
    text, _ = _parse(page)
    section = _section(page, "export")
    micro = run / "export" / "micro"
    mj = (micro / "exr" / "material.json").stat().st_size
    assert mj < 1000
    assert f"export/micro/exr/material.json {mj} B" in section, section
    gl = (micro / "gltf" / "twill_micro.gltf").stat().st_size
    assert f"export/micro/gltf/twill_micro.gltf {gl} B" in section
    assert "export/micro/gltf/twill_micro_base_color.png 90 kB" in section
    total = sum(p.stat().st_size for p in (micro / "gltf").iterdir())
    assert f"3 files, {fmt.quantity(total / 1000, 'kB')} in all" in section


def test_run_report_propagated_anisotropy_scale_does_not_saturate(run_report):
    """The [0, 1] maps are drawn on 0 to 1: the propagated anisotropy (spread like the demo's,
    0.07-0.88) is not clipped (the robust 0.5-99.5 % scale clipped 1 % of it)."""
    run, page, _ = run_report
    section = _section(page, "propagation")
    cap = section.split("propagated anisotropy.", 1)[1].split("propagated tangent azimuth.", 1)[0]
    assert "colour scale 0 to 1." in cap and "Clipped" not in cap, cap


def test_unit_range_maps_are_drawn_zero_to_one():
    from dualscale.report import plots

    rng = np.random.default_rng(3)
    a = np.clip(rng.normal(0.83, 0.02, (64, 64, 1)), 0, 1)
    a[:2] = 0.07  # a low tail, as on the demo's propagated anisotropy
    for name in plots.UNIT_RANGE_MAPS:
        f, cap = plots.map_figure(name, a, 0.01)
        assert "colour scale 0 to 1." in cap and "Clipped" not in cap, (name, cap)
        plots._plt().close(f)


# ---------------------------------------------------------------------------------------------
# fly-outs (issue 24 Sec. 4): the red overlay, and what an under-resolved texel means

def _red_pixels(png: Path) -> int:
    import matplotlib.image as mpimg

    a = mpimg.imread(png)[..., :3]
    return int(((a[..., 0] > 0.6) & (a[..., 1] < 0.15) & (a[..., 2] < 0.15)).sum())


def test_run_report_flyout_figure_has_the_red_mask(run_report):
    """The caption promises a red overlay of the mask: the figure has red pixels, at least one
    per mask texel (it had none: the yellow polylines covered the mask they rasterise)."""
    run, page, _ = run_report
    from dualscale.formats.exr import read_exr

    mask = read_exr(run / "flyouts" / "flyout_mask.exr", ("Y",))[..., 0] > 0.5
    png = next((page.parent / "assets").glob("flyouts*.png"))
    assert _red_pixels(png) >= mask.sum() > 0
    assert "fly-out mask in red" in _section(page, "flyouts")


def test_flyout_figure_keeps_thin_fibres_red_on_large_maps():
    """A 1-texel fibre on a 2048-px map still shows red after the figure is reduced to its
    panel (block maximum, not mean or nearest sampling)."""
    import io

    from dualscale.report import plots

    mask = np.zeros((2048, 2048), bool)
    mask[1000, 100:1900] = True
    fig, cap = plots.flyout_figure(np.full((2048, 2048, 3), 0.4), [[[100, 1000], [1899, 1000]]], mask=mask)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plots._plt().close(fig)
    buf.seek(0)
    import matplotlib.image as mpimg

    a = mpimg.imread(buf)[..., :3]
    red = (a[..., 0] > 0.6) & (a[..., 1] < 0.15) & (a[..., 2] < 0.15)
    assert red.sum() > 200 and "red" in cap  # the line spans ~300 display pixels
    assert plots.max_pool(mask, 300).shape == plots.block_mean(np.zeros((2048, 2048, 3)), 300).shape[:2]


def test_run_report_says_when_the_texel_under_resolves_the_fibres(run_report):
    """At 4.9 um a 12 um fibre is 2.4 texels across: the section and the top list say the fibres
    are under-resolved, with the precision measured for that regime on the simulated rig and
    where it was measured."""
    run, page, _ = run_report
    text, _ = _parse(page)
    section = _section(page, "flyouts")
    assert "under-resolves the fly-out fibres" in section and "2.4 texels across" in section
    assert "fibres resolved by the texel no: under-resolved" in section
    assert "resolved when the fibre is at least 5 texels across" in section
    assert re.search(r"precision expected \(simulated rig\) 58% of the detected length within 2 px", section), section
    assert "bench/bench_flyouts.py --resolution" in section
    assert "under-resolves the fly-out fibres" in _section(page, "warnings")  # the top list


# ---------------------------------------------------------------------------------------------
# formatting and plots

def test_format_numbers_units_goals_durations():
    assert fmt.number(0.4299999999999) == "0.43"
    assert fmt.number(12345) == "12\u2009345" and fmt.number(1234567.0) == "1.23 × 10⁶"
    assert fmt.number(0.000123) == "1.23 × 10⁻⁴" and fmt.number(None) == "—" and fmt.number(float("nan")) == "—"
    assert str(fmt.check(0.43, "<", 0.5, "°")) == "0.43° (goal < 0.5°) ✓"
    assert str(fmt.check(0.93, ">=", 0.95)) == "0.93 (goal ≥ 0.95) ✗"
    assert [fmt.duration(s) for s in (0.42, 12.34, 133, 3725)] == ["0.42 s", "12.3 s", "2 min 13 s", "1 h 02 min"]
    assert fmt.length_mm(0.0049) == "4.9 µm" and fmt.length_mm(2.5) == "2.5 mm" and fmt.percent(0.0431) == "4.31%"
    assert fmt.value({"a": 0.123456789, "b": [1, 2], "c": None, "d": True}) == "a: 0.123; b: 1, 2; c: —; d: yes"
    assert fmt.value(list(range(20))) == "20 values, 0 to 19"
    assert fmt.timestamp("2026-12-01T14:03:27.123456+00:00") == "2026-12-01 14:03:27 UTC"


def test_plots_label_units_and_do_not_overlap():
    from dualscale.report import plots

    rng = np.random.default_rng(1)
    n = np.dstack([rng.normal(0, 0.2, (24, 24)), rng.normal(0, 0.2, (24, 24)), np.ones((24, 24))])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    figs = [plots.map_figure(k, v, 0.005) for k, v in (("albedo", rng.random((24, 24, 3))), ("normal", n),
                                                       ("roughness", rng.random((24, 24, 1))),
                                                       ("tangent", rng.random((24, 24, 1))),
                                                       ("ior", np.full((24, 24, 1), 0.25)))]
    figs += [plots.residual_figure(rng.random((24, 24, 1)) ** 6),
             plots.heldout_figure(rng.random((24, 24, 3)), rng.random((24, 24, 3)), title="LED 3", texel_mm=0.005),
             plots.time_bars(["calibrate", "fit", "propagate"], [1.5, 133.0, None]),
             plots.flyout_figure(rng.random((24, 24, 3)), [[[1, 2], [9, 9]]], mask=rng.random((24, 24)) > 0.9),
             plots.guidance_figure(rng.random((40, 40, 3)) * 3, [4, 4, 8, 8], texel_mm=0.05)]
    for f, cap in figs:
        assert plots.overlapping_texts(f) == [], (cap, plots.overlapping_texts(f))
        for ax in f.axes:
            if ax.name == "rectilinear" and ax.images and ax.get_label() != "<colorbar>":
                assert "[" in ax.get_xlabel() or "(" in ax.get_xlabel(), ax.get_xlabel()
        assert "{" not in cap
        plots._plt().close(f)
    # a clipped colour scale says so, and how much
    r = plots.robust_range(np.r_[np.zeros(999), 100.0])
    assert r.vmax < 100 and "0.1%" in plots.clip_note(r) and r.extend == "max"


def test_hemisphere_scale_covers_the_data():
    from dualscale.report import plots

    before = [3.0, 8.0, 25.0, 14.0]
    f, cap, norm = plots.hemisphere_figure([("before", [10, 40, 70, 20], [0, 90, 200, 300], before, 31.0),
                                            ("after", [10, 40, 70, 20], [0, 90, 200, 300], [1, 2, 3, 1.5], 1.0)],
                                           label="mean ΔE00", goal=3.0)
    assert norm.vmax >= 31.0 and norm.vmin <= 0 and "no point is capped" in cap
    assert plots.overlapping_texts(f) == []
    _, _, lognorm = plots.hemisphere_figure([("x", [10, 20, 30], [0, 1, 2], [0.01, 1, 500], None)], label="v")
    assert lognorm.vmax >= 500 and lognorm.vmin <= 0.01


def test_write_atomic_leaves_nothing_on_error(tmp_path):
    from dualscale.report.html import render, write_atomic

    target = write_atomic(tmp_path / "a.html", "old")

    class Boom(str):
        def encode(self, *a, **k):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_atomic(target, Boom("new"))
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["a.html"]
    # autoescape is on
    page = render("base.html", title="<script>x</script>", subtitle="", toc=[], footer="")
    assert "<script>x" not in page and "&lt;script&gt;" in page


# ---------------------------------------------------------------------------------------------
# the device-evaluation report

def _device_results(seed=0):
    rng = np.random.default_rng(seed)
    leds = [f"led{i:03d}" for i in range(0, 127, 16)]
    colour = {cam: {l: {"before": list(rng.gamma(4, b / 4, 24)), "after": list(rng.gamma(4, a / 4, 24))}
                    for l in leds + ["diffuse"]} for cam, b, a in (("micro", 8, 1.6), ("mid", 15, 3.3))}
    res = {"colour": colour,
           "sharpness": {"centres": [[x, y] for x in range(8, 40, 12) for y in range(8, 40, 12)],
                         "values": list(rng.uniform(0.5, 0.95, 9))},
           "polarization": {"leds": [{"led": int(l[3:]), "angles_deg": list(range(0, 180, 10)),
                                      "intensity": list(1 + 0.5 * np.cos(np.radians(2 * (np.arange(0, 180, 10) - 3)))),
                                      "error_deg": 3.0 + 0.01 * i} for i, l in enumerate(leds)]},
           "collimation": {l: float(rng.uniform(0.01, 0.04)) for l in leds},
           "summary": {"micro_mean_dE00": {"before": 7.934567891234, "after": 1.6412345678},
                       "mid_mean_dE00": {"before": 14.83456789, "after": 3.2712345},
                       "sharpness_mean": 0.7512345678,
                       "polarization_error_deg": {"mean_abs": 3.0012345, "max_abs": 3.0412345678,
                                                  "analyzer_misalignment": -3.00123456},
                       "collimation_std_max": 0.0398765432}}
    calib = {"rig": {"id": "virtual-dome-0", "layout": "dome127"}, "created": "2026-11-30T10:00:00Z",
             "ccm": {"micro": {"led": {"mean_delta_e2000": {
                 "before": {"fit": 7.481234, "held_out": 9.351234}, "least_squares": {"fit": 1.68, "held_out": 2.64},
                 "ciede2000": {"fit": 1.43, "held_out": 2.0712345}}}}}}
    return res, calib


def test_device_report_summary_and_hemisphere_scale(tmp_path, layout_checked):
    from dualscale.report.device import write_report

    res, calib = _device_results()
    page = write_report(tmp_path / "rep", res, calib)
    assert layout_checked == []
    assert page.name == "report.html"
    for name in ("colour_hemisphere", "colour_boxplots", "sharpness_map", "polarization", "collimation"):
        assert (page.parent / f"{name}.png").is_file() and (page.parent / f"{name}.svg").is_file()
    text, p = _parse(page)
    _assert_readable(text)
    summary = text.split("Summary", 2)[-1].split("Colour correction matrices")[0]
    assert "micro: mean ΔE00 after the CCM 1.64 (goal < 3) ✓" in summary
    assert "mid: mean ΔE00 after the CCM 3.27 (goal < 3) ✗" in summary
    assert "3.04° (goal < 12°) ✓" in summary and "0.0399 (goal < 0.15) ✓" in summary
    assert "2.07 (goal < 3) ✓" in text and "7.48 / 9.35" in text
    # the colour scale of the hemisphere reaches the largest per-light mean (no cap at ΔE 10)
    data_max = max(float(np.mean(d[s])) for cam in res["colour"].values() for d in cam.values() for s in d)
    m = re.search(r"One colour scale for all panels, (\S+) to (\S+) = the data's full range", text)
    assert m, text[:400]
    assert float(m.group(2)) >= round(data_max, 1) - 0.05 and data_max > 10
    assert all((page.parent / s).is_file() for s in p.imgs)


def test_device_report_without_optional_parts(tmp_path):
    from dualscale.report.device import write_report

    res, calib = _device_results()
    res = {"colour": res["colour"], "summary": {}}
    text, _ = _parse(write_report(tmp_path / "rep", res, {}))
    _assert_readable(text)
    assert "No dot-grid capture in this session" in text and "holds no colour correction matrix" in text


# ---------------------------------------------------------------------------------------------
# headless browser (Chrome DevTools Protocol)

class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest output clean
        pass


def test_report_loads_in_headless_browser(run_report, tmp_path):
    """The page served on 127.0.0.1 loads in headless Chromium with no console error, no failed
    or external request, every image decoded (naturalWidth > 0) and no horizontal overflow."""
    run, page, _ = run_report
    handler = functools.partial(_Quiet, directory=str(page.parent))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{server.server_address[1]}/"
    try:
        with Browser(tmp_path / "profile", window=(1280, 900), vendor=False) as cdp:
            cdp.send("Page.navigate", {"url": base + "index.html"})
            cdp.wait_event("Page.loadEventFired", 25)
            state = cdp.evaluate("""(() => ({
                images: Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, i.naturalWidth]),
                overflow: document.documentElement.scrollWidth - window.innerWidth,
                title: document.title}))()""")
            problems = cdp.problems(base)
    finally:
        server.shutdown()
        server.server_close()
    assert not problems["errors"], problems["errors"][:3]
    assert not problems["failed"], problems["failed"][:3]
    assert not problems["external"], problems["external"]
    assert state["title"].startswith("dualscale run")
    imgs = state["images"]
    assert len(imgs) >= 14
    broken = [src for src, complete, width in imgs if not complete or width == 0]
    assert not broken, broken
    assert state["overflow"] <= 0, f"page is {state['overflow']} px wider than the window"


def test_run_report_shows_the_runs_checks_near_the_top(tmp_path, figures_not_drawn):
    """Issue 24 trial: a run that failed its check (held-out 53 %) had a report saying only
    "held-out 53%"; the words goal/check/✗ appeared nowhere.  Now the checks (value, goal, ✓/✗)
    come right after the headline, computed from the fit stage's record."""
    from dualscale.report import write_run_report
    from dualscale.report.checks import CONSTANT_MARGIN, HELDOUT_L1_GOAL

    text, _ = _parse(write_run_report(make_run(tmp_path / "bad", flyouts=False, guidance=False, heldout_l1=0.53,
                                               constant_l1=0.6)))
    top = text.split("Component decision")[0]
    assert "The run's checks" in top and "The run failed its check" in top, top
    assert "✗" in top and "failed: fit held-out error, fit against the constant predictor" in top, top
    assert f"at most {100 * HELDOUT_L1_GOAL:.0f} %" in top and "53.0 %" in top
    assert f"below {CONSTANT_MARGIN:g}× the per-pixel constant predictor's 60.0 %" in top and "0.88×" in top, top
    # passing: both ✓, no failure words
    text, _ = _parse(write_run_report(make_run(tmp_path / "good", flyouts=False, guidance=False)))
    top = text.split("Component decision")[0]
    assert "The run's checks" in top and "✗" not in top and top.count("✓") >= 2 and "passed" in top, top
    assert "The run failed" not in text
    # a record without the constant predictor (a fit from before it): that check is not measured
    text, _ = _parse(write_run_report(make_run(tmp_path / "old", flyouts=False, guidance=False, constant_l1=None)))
    top = text.split("Component decision")[0]
    assert "not measured" in top and "✗" not in top, top
