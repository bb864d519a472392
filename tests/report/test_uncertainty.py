"""The run report's uncertainty section (issue 26): per map a sigma image (undetermined texels in
a flat colour named in a legend, a colour bar in the sigma's unit) and a histogram with the
median; beside the ground-truth error with the 1.96-sigma coverage when the fit was scored
against one; absent for a fit without ``uncertainty/``."""

from __future__ import annotations

import re

import numpy as np
import pytest

from .runfolder import add_uncertainty, make_run
from .test_report import _assert_readable, _checking_figures, _parse, _section


@pytest.fixture(scope="module")
def gt_report(tmp_path_factory):
    """The run with ground truth, rendered once, every saved figure checked for overlapping labels."""
    from dualscale.report import html as rhtml
    from dualscale.report import write_run_report

    run = make_run(tmp_path_factory.mktemp("unc") / "RUN", flyouts=False, guidance=False)
    sigma = add_uncertainty(run, ground_truth=True)
    problems: list = []
    save = rhtml.Assets.figure
    rhtml.Assets.figure = _checking_figures(problems)
    try:
        page = write_run_report(run)
    finally:
        rhtml.Assets.figure = save
    return run, page, sigma, problems


def test_uncertainty_section_with_ground_truth(gt_report):
    run, page, sigma, problems = gt_report
    text, p = _parse(page)
    _assert_readable(text)
    sec = _section(page, "uncertainty")
    assert "Uncertainty of the maps (1σ per texel)" in sec
    assert "noise scale the fit's residual (median |r|)" in sec and "time 1.25 s" in sec
    assert "magenta" in sec and "undetermined" in sec
    for name in ("albedo", "normal", "roughness", "tangent azimuth", "index of refraction η"):
        assert f"σ of {name}." in sec, name
    assert "degrees (RMS angle to the true normal)" in sec and "eta (index of refraction)" in sec
    # the table: medians per channel, the undetermined share (16 of 1024 texels; the tangent's half)
    assert "1.56%" in sec and "50%" in sec
    med = float(np.median(sigma["roughness"][4:, :].ravel().tolist() + sigma["roughness"][:4, 4:].ravel().tolist()))
    assert f"{med:.3g}" in sec or f"{med:.2g}" in sec
    # ground truth: error maps beside sigma and the coverage (the error is 1 sigma Gaussian: ~95 %)
    assert "|error| ≤ 1.96σ, the normal's ≤ 1.73σ (ground truth; 95 % expected)" in sec and "Coverage:" in sec
    cov = [float(x) for x in re.findall(r"Coverage: ([\d.]+)%", sec)]
    assert len(cov) == len(sigma) and all(85 < c < 99.5 for c in cov), cov
    imgs = [s for s in p.imgs if "sigma_" in s]
    assert len(imgs) == len(sigma) and all((page.parent / s).is_file() for s in imgs)
    # the undetermined texels are drawn in the flat colour, the rest on the colour map
    import matplotlib.image as mpimg

    a = mpimg.imread(page.parent / next(s for s in imgs if s.endswith("sigma_albedo.png")))[..., :3]
    magenta = (a[..., 0] > 0.95) & (a[..., 1] < 0.05) & (a[..., 2] > 0.95)
    assert magenta.sum() > 50
    assert [x for x in problems if x[0].startswith("sigma_")] == []  # no overlapping label
    assert 'href="#uncertainty"' in page.read_text(encoding="utf-8")  # in the table of contents


@pytest.mark.slow  # a whole report page (21 s on 2 cores): the case with ground truth covers the section
def test_uncertainty_section_without_ground_truth_or_record(tmp_path):
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    add_uncertainty(run, record=False)
    page = write_run_report(run)
    sec = _section(page, "uncertainty")
    assert "noise scale not recorded" in sec and "time not recorded" in sec
    assert "Coverage" not in sec and "ground truth" not in sec


def test_no_uncertainty_section_without_it(tmp_path, figures_not_drawn):
    """(The page's words only: its figures are not drawn, see figures_not_drawn.)"""
    from dualscale.report import write_run_report

    run = make_run(tmp_path / "RUN", flyouts=False, guidance=False)
    page = write_run_report(run)
    raw = page.read_text(encoding="utf-8")
    assert 'id="uncertainty"' not in raw and "#uncertainty" not in raw and "σ of" not in raw


def test_sigma_colours_are_the_viewers():
    from dualscale.report import plots

    s = np.array([[0.0, 0.5, 1.0, np.nan]])
    u = np.array([[False, False, False, True]])
    rgb = plots.sigma_colours(s, u, 1.0)
    assert tuple(rgb[0, 3]) == plots.UNDETERMINED_RGB
    assert rgb[0, 0].sum() < rgb[0, 2].sum()  # viridis: dark at 0, bright at the top
    top, und = plots.sigma_display(np.dstack([s, 2 * s]), np.dstack([u, u]))
    assert und.tolist() == [[False, False, False, True]] and top[0, 2] == 2.0


def test_a_heavy_tailed_sigma_gets_a_log_histogram():
    """A sigma that spans decades (a noise-free fit's ~1e-8 with a fly-out fibre's 1e-3, a fresh
    user's trial: ~980 of 1024 texels in the first linear bin) is histogrammed on a log axis and
    the caption says so; an ordinary one keeps the linear axis."""
    from dualscale.report.plots import sigma_figure

    rng = np.random.default_rng(0)
    heavy = np.exp(rng.uniform(np.log(1e-8), np.log(1e-6), (32, 32, 1)))
    heavy[:2] = 1e-3  # the fibre
    und = np.zeros((32, 32, 1), bool)
    def hist(fig):
        return next(a for a in fig.axes if a.get_title() == "σ over the determined texels")

    fig, cap = sigma_figure("roughness", heavy, und)
    assert hist(fig).get_xscale() == "log" and "log axis" in cap
    fig, cap = sigma_figure("roughness", rng.uniform(0.001, 0.003, (32, 32, 1)), und)
    assert hist(fig).get_xscale() == "linear" and "log axis" not in cap
