"""The viewer's uncertainty switch (issue 26): ``scene.json`` names the export's sigma, the
server serves it (JSON + false-colour PNG in the report's colour map), and the page's ``show``
select puts a map's sigma on the swatch with its legend; without ``uncertainty/`` the switch is
hidden and disabled (headless Chromium, as tests/view/test_browser.py)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest

from tests.cdp import Browser, open_viewer, require_browser
from .folders import SIZE, add_uncertainty, run_folder


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("view_sigma")
    with_sigma = run_folder(base / "RUN")
    add_uncertainty(with_sigma / "fit" / "maps")
    return with_sigma, run_folder(base / "PLAIN")


def _serve(path):
    from dualscale.view import ViewerServer, locate

    return ViewerServer(locate(path))


def _get(url: str):
    try:
        with urllib.request.urlopen(url) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def test_server_serves_the_sigma(runs):
    from dualscale.formats.maps import SIGMA_UNITS
    from dualscale.report import plots

    run, plain = runs
    with _serve(run) as v:
        scene = json.loads(_get(v.url + "scene.json")[1])
        assert scene["exports"][0]["sigma"] == "api/sigma/micro.json"
        status, body = _get(v.url + "api/sigma/micro.json")
        info = json.loads(body)
        assert status == 200 and [m["name"] for m in info["maps"]] == ["albedo", "normal", "roughness"]
        normal = info["maps"][1]
        assert normal["units"] == SIGMA_UNITS["normal"] and normal["unit"] == "°"
        assert normal["undetermined_fraction"] == pytest.approx(0.25)
        assert info["undetermined"] == {"colour": plots.UNDETERMINED_HEX, "name": plots.UNDETERMINED_NAME}
        status, png = _get(v.url + normal["url"])
        assert status == 200 and png[:8] == b"\x89PNG\r\n\x1a\n"
        assert _get(v.url + "api/sigma/micro/ior.png")[0] == 404
        assert _get(v.url + "api/sigma/nope.json")[0] == 404
    with _serve(plain) as v:
        scene = json.loads(_get(v.url + "scene.json")[1])
        assert scene["exports"][0]["sigma"] is None
        assert _get(v.url + "api/sigma/micro.json")[0] == 404


def test_a_damaged_uncertainty_is_a_server_error_with_one_warning(tmp_path, capsys):
    """A truncated sigma EXR (a fresh user's trial): the sigma routes answer 500 naming the
    file, not 400 as if the request were bad; the terminal gets one warning; the rest is served."""
    run = run_folder(tmp_path / "RUN")
    add_uncertainty(run / "fit" / "maps")
    victim = run / "fit" / "maps" / "uncertainty" / "normal.exr"
    victim.write_bytes(victim.read_bytes()[:200])
    with _serve(run) as v:
        assert _get(v.url + "scene.json")[0] == 200
        for url in ("api/sigma/micro.json", "api/sigma/micro/albedo.png", "api/sigma/micro.json"):
            status, body = _get(v.url + url)
            assert status == 500 and "normal.exr" in json.loads(body)["error"], (url, status)
    assert capsys.readouterr().err.count("warning: the uncertainty of 'micro' is not readable") == 1


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    require_browser()
    with Browser(tmp_path_factory.mktemp("chromium")) as page:
        yield page


def test_show_sigma_on_the_swatch(browser, runs):
    """The show select lists the sigma maps; choosing one covers the swatch with the false colour
    (undetermined rows in magenta, at the top as in the maps), with its legend and units; back
    to material restores it.  No console error, nothing external."""
    run, _ = runs
    with _serve(run) as v:
        info = open_viewer(browser, v.url)
        assert info["sigma"] == ["albedo", "normal", "roughness"] and info["showing"] == "material"
        state = browser.evaluate("""[document.getElementById('show-label').hidden,
            document.getElementById('show-select').disabled,
            Array.from(document.getElementById('show-select').options, (o) => o.textContent),
            document.getElementById('sigma-legend').hidden]""")
        assert state == [False, False, ["material", "σ albedo", "σ normal", "σ roughness"], True]
        flat = "window.dualscaleViewer.renderFlat({az: 0, el: 90, irradiance: 1, width: %d, height: %d})" % (SIZE, SIZE)
        before = np.asarray(browser.evaluate(flat)["rgb"]).reshape(SIZE, SIZE, 3)
        assert browser.evaluate("window.dualscaleViewer.showSigma('normal')", timeout=30) == "normal"
        img = np.asarray(browser.evaluate(flat)["rgb"]).reshape(SIZE, SIZE, 3)
        legend = browser.evaluate("""[document.getElementById('sigma-legend').hidden,
            document.getElementById('sigma-range').textContent, document.getElementById('sigma-text').textContent,
            getComputedStyle(document.getElementById('sigma-und-swatch')).backgroundColor]""")
        problems = browser.problems(v.url)
        page_blobs = "blob:" + v.url.rstrip("/")  # the GLB's embedded textures are the page's own
        assert browser.evaluate("window.dualscaleViewer.showSigma('material')") == "material"
        after = np.asarray(browser.evaluate(flat)["rgb"]).reshape(SIZE, SIZE, 3)
    magenta = (img[..., 0] > 0.9) & (img[..., 1] < 0.1) & (img[..., 2] > 0.9)
    top, rest = magenta[2: SIZE // 4 - 2, 2:-2], magenta[SIZE // 4 + 2: -2, 2:-2]
    assert top.mean() > 0.95 and rest.mean() < 0.01, (top.mean(), rest.mean())
    lum = img[SIZE // 2, 2:-2].sum(-1)
    assert lum[-1] > lum[0] + 0.3  # sigma rises left to right: viridis dark to bright
    assert legend[0] is False and legend[1].startswith("0 °") and "degrees (RMS angle to the true normal)" in legend[2]
    assert "25.0 % of texels" in legend[2] and "magenta" in legend[2] and legend[3] == "rgb(255, 0, 255)"
    assert not problems["errors"], problems["errors"][:3]
    assert not problems["failed"], problems["failed"][:3]
    assert not [u for u in problems["external"] if not u.startswith(page_blobs)], problems["external"]
    assert v.url + "api/sigma/micro/normal.png" in problems["requested"]
    assert np.abs(after - before).max() < 1e-6 and np.abs(img - before).max() > 0.1


def test_no_sigma_switch_without_uncertainty(browser, runs):
    _, plain = runs
    with _serve(plain) as v:
        info = open_viewer(browser, v.url)
        state = browser.evaluate("""[document.getElementById('show-label').hidden,
            document.getElementById('show-select').disabled]""")
        problems = browser.problems(v.url)
    assert info["sigma"] == [] and state == [True, True]
    assert not problems["errors"], problems["errors"][:3]
