"""The viewer page in real headless Chromium (WebGL 2 through SwiftShader): it loads with no
console error, no failed and no non-localhost request; the swatch, cloth and sphere render; and
the viewer's image of the flat swatch under a directional light agrees with our renderer
(``dualscale.bsdf.evaluate``) of the same maps within the tolerances below (docs/VIEWER.md).

Tolerances and their reasons (the glTF/three.js model is not ours, seed Sec. 5):

* diffuse: three.js r187 uses Lambert x (1 - F_Schlick(v.h)); ours is Burley's
  (1 - F_l/2)(1 - F_v/2) plus the retro-reflection term -- a few % apart, most at grazing light;
* specular: Schlick's Fresnel from F0 = ((eta-1)/(eta+1))^2 x specular colour against our exact
  unpolarised dielectric Fresnel with the tint; three.js also adds multiple-scattering energy
  compensation; the roughness is floored at 0.045;
* textures: base colour and specular colour are 8-bit sRGB in the glTF;
* the anisotropy frame: three.js builds the anisotropy tangent from the mesh's tangent frame,
  not orthogonal to the normal-mapped normal; its anisotropic GGX then ignores the normal's
  tilt.  The viewer projects it onto the normal-mapped surface by default (our model's frame,
  ``dualscale.bsdf.mapping.tangent_frame``); three.js's own frame is measured too and is only
  held to the tolerance where the light is low (a near-normal light on a normal-mapped
  anisotropic twill gives a specular peak 10x too bright).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.cdp import Browser, open_viewer, require_browser
from .folders import export_folder, maps_folder, run_folder

ELEVATIONS = (15, 30, 45, 60, 75, 89)
AZIMUTHS = (30, 200)
TOL = 0.08          # sum |viewer - ours| / sum ours, per light, viewer in our model's anisotropy frame
TOL_THREE_FRAME = 0.20  # the same with three.js's own anisotropy frame, for elevations <= 45 deg


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    require_browser()
    with Browser(tmp_path_factory.mktemp("chromium")) as page:
        yield page


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return run_folder(tmp_path_factory.mktemp("view_browser") / "RUN")


def _serve(path):
    from dualscale.view import ViewerServer, locate

    return ViewerServer(locate(path))


def test_page_loads_without_errors(browser, run, tmp_path):
    """Every object, every map and the LED side-by-side load with no console error, no failed
    request and nothing fetched outside the local server (blob: URLs of the GLB's embedded
    textures are the page's own)."""
    with _serve(run) as v:
        info = open_viewer(browser, v.url + "?led=7")
        assert info["texture"] == [64, 64] and info["objects"] == ["swatch", "cloth", "sphere"]
        assert info["swatch_m"] == pytest.approx([0.00064, 0.00064], rel=1e-5)
        assert info["repeat_m"] == pytest.approx([0.00064, 0.00064], rel=1e-9)
        for want in ("base colour", "roughness", "normal: tilt", "anisotropy strength", "anisotropy direction",
                     "specular colour"):
            assert any(m.startswith(want) for m in info["maps"]), (want, info["maps"])
        for name in ("cloth", "sphere", "swatch"):
            browser.evaluate(f"window.dualscaleViewer.show('{name}'); window.dualscaleViewer.render(); 1")
        for i in range(len(info["maps"])):
            browser.evaluate(f"window.dualscaleViewer.showMap({i}); 1")
        assert info["led"]["led"] == 7
        imgs = browser.evaluate("""Array.from(document.querySelectorAll('#leds img')).map(
            i => [i.id, i.complete, i.naturalWidth])""")
        assert imgs == [["img-captured", True, 64], ["img-rendered", True, 64]]
        note = browser.evaluate("document.getElementById('led-info').textContent")
        assert "LED 7: θ 55.0°" in note and "differs from the capture by 9.1 %" in note
        problems = browser.problems(v.url)
    page_blobs = "blob:" + v.url.rstrip("/")
    external = [u for u in problems["external"] if not u.startswith(page_blobs)]
    assert not problems["errors"], problems["errors"][:3]
    assert not problems["failed"], problems["failed"][:3]
    assert not external, external


BAD_PARAMS = [  # (query, words the error must show, what is shown instead)
    ("?object=cube", ("?object=cube", "swatch, cloth, sphere"), "swatch"),
    ("?led=9999", ("?led=9999", "no such LED"), None),
    ("?export=nope", ("?export=nope", "micro"), None),
    ("?az=abc", ("?az=abc", "0 to 360"), None),
    ("?el=0", ("?el=0", "1 to 90"), None),
    ("?map=glitter", ("?map=glitter", "base colour"), None),
    ("?frame=yes", ("?frame=yes", "three or ours"), None),
    ("?objet=cloth", ("?objet", "not a parameter"), None),
]


def _url_error(browser) -> tuple[bool, str]:
    return tuple(browser.evaluate("""(() => { const b = document.getElementById('url-error');
        return [!b.hidden && b.getBoundingClientRect().height > 0, b.textContent]; })()"""))


@pytest.mark.parametrize("query,words,shown", BAD_PARAMS, ids=[q for q, _, _ in BAD_PARAMS])
def test_bad_url_parameter_is_a_visible_error(browser, run, query, words, shown):
    """A bad URL parameter is a visible error naming it and what it accepts, and the page still
    shows the material (issue 24 Sec. 4: ``?object=cube`` gave a blank 3D view captioned
    "undefined"; ``?led=9999``, ``?export=nope`` and ``?az=abc`` were ignored)."""
    with _serve(run) as v:
        info = open_viewer(browser, v.url + query)
        visible, text = _url_error(browser)
        size_note = browser.evaluate("document.getElementById('size-note').textContent")
    assert visible, text
    for w in words:
        assert w in text, (w, text)
    assert info["url_errors"] and info["texture"] == [64, 64]
    assert "undefined" not in size_note and size_note.startswith(shown or "swatch"), size_note


def test_good_url_parameters_raise_no_error(browser, run):
    with _serve(run) as v:
        info = open_viewer(browser, v.url + "?object=cloth&led=7&export=micro&az=30&el=20&e=2&map=rough&frame=three")
        visible, text = _url_error(browser)
        state = browser.evaluate("""[document.getElementById('light-az').value, document.getElementById('light-el').value,
            document.getElementById('size-note').textContent, document.getElementById('map-note').textContent]""")
    assert not visible and info["url_errors"] == [], text
    assert info["led"]["led"] == 7 and state[0] == "30" and state[1] == "20"
    assert state[2].startswith("cloth") and state[3].startswith("roughness")


def test_export_folder_gltf_without_capture(browser, tmp_path):
    """A .gltf export (JSON + .bin + PNG textures by relative URI) loads; the page says why there
    is no side-by-side."""
    out = export_folder(tmp_path / "OUT", maps_folder(tmp_path / "maps", "plain"), ("gltf",))
    with _serve(out) as v:
        info = open_viewer(browser, v.url)
        hidden, text = browser.evaluate("""[document.getElementById('led-panel').hidden,
            document.getElementById('led-absent').textContent]""")
        problems = browser.problems(v.url)
    assert info["texture"] == [64, 64] and any(m.startswith("normal") for m in info["maps"])
    assert hidden and text.startswith("No side-by-side: this is an export folder, not a digitize run")
    for suffix in ("gltf/swatch.gltf", "gltf/swatch.bin", "gltf/swatch_base_color.png"):
        assert v.url + "files/export/" + suffix in problems["requested"], suffix
    assert not problems["errors"], problems["errors"][:3]
    assert not problems["failed"], problems["failed"][:3]
    assert not problems["external"], problems["external"]


def test_swatch_renders(browser, run):
    """A screenshot of the 3D view is not blank: the swatch covers much of it, with texture."""
    with _serve(run) as v:
        open_viewer(browser, v.url)
        browser.evaluate("window.dualscaleViewer.show('swatch'); window.dualscaleViewer.render(); 1")
        r = browser.evaluate("(() => { const b = document.getElementById('gl').getBoundingClientRect(); "
                             "return {x: b.x, y: b.y, width: b.width, height: b.height}; })()")
        shot = browser.screenshot(r)[..., :3].astype(np.float64)
        shots = {}
        for name in ("cloth", "sphere"):
            browser.evaluate(f"window.dualscaleViewer.show('{name}'); window.dualscaleViewer.render(); 1")
            shots[name] = browser.screenshot(r)[..., :3].astype(np.float64)
    background = np.array([0x30, 0x32, 0x36], np.float64)
    for name, img in {"swatch": shot, **shots}.items():
        differs = np.abs(img - background).max(-1) > 12
        assert differs.mean() > 0.05, (name, differs.mean())
        assert img[differs].std() > 5, (name, img[differs].std())  # textured, not a flat fill


def _ours(maps, az: float, el: float) -> np.ndarray:
    import torch

    from dualscale.bsdf import evaluate

    a, e = math.radians(az), math.radians(el)
    d = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
    return evaluate(maps, torch.tensor([d], dtype=torch.float32), torch.tensor([0.0, 0.0, 1.0]))[0].numpy()


def _viewer(page, az: float, el: float, irradiance: float, size: int) -> np.ndarray:
    r = page.evaluate(f"window.dualscaleViewer.renderFlat({{az: {az}, el: {el}, irradiance: {irradiance}, "
                      f"width: {size}, height: {size}}})")
    return np.asarray(r["rgb"], np.float64).reshape(size, size, 3)


@pytest.mark.parametrize("material", ["ramp", "twill"])
def test_flat_swatch_agrees_with_our_renderer(browser, tmp_path, material):
    """Orthographic view straight down, one directional light of irradiance E at (az, el), no
    ambient, no tone mapping, read back linear: viewer = f * E with f from bsdf.evaluate (three.js
    punctual lights: radiance = BRDF x E x cos).  ``ramp``: an isotropic albedo gradient along x
    and y (catches a flipped or mirrored swatch); ``twill``: normal map, anisotropy, IOR and tint."""
    import torch

    from dualscale.bsdf import MaterialMaps
    from dualscale.formats.maps import load_maps, save_maps

    size, irradiance = 64, 2.5
    if material == "ramp":
        yy, xx = np.mgrid[0:size, 0:size] / (size - 1)
        albedo = np.dstack([0.1 + 0.8 * xx, 0.1 + 0.8 * (1 - yy), np.full_like(xx, 0.3)]).astype(np.float32)
        m = MaterialMaps(albedo=torch.from_numpy(albedo), roughness=torch.full((size, size, 1), 0.5))
        save_maps(tmp_path / "maps", m, {}, texel_mm=0.01)
    else:
        maps_folder(tmp_path / "maps", "twill", size)
    out = export_folder(tmp_path / "OUT", tmp_path / "maps")
    maps, _ = load_maps(tmp_path / "maps")
    rows = []
    with _serve(out) as v:
        open_viewer(browser, v.url)
        for frame in ("ours", "three"):
            browser.evaluate(f"window.dualscaleViewer.setShadingFrame({str(frame == 'ours').lower()}); 1")
            for el in ELEVATIONS:
                for az in AZIMUTHS:
                    ours = _ours(maps, az, el) * irradiance
                    seen = _viewer(browser, az, el, irradiance, size)
                    rel = float(np.abs(seen - ours).sum() / ours.sum())
                    bias = float(seen.sum() / ours.sum() - 1)
                    rows.append((frame, el, az, rel, bias))
    print(f"\n{material}: frame, elevation, azimuth, sum|viewer - ours| / sum ours, mean bias")
    for r in rows:
        print(f"  {r[0]:5s} {r[1]:3d} {r[2]:4d}  {r[3]:.3f}  {r[4]:+.3f}")
    bad = [r for r in rows if r[0] == "ours" and r[3] > TOL]
    bad += [r for r in rows if r[0] == "three" and r[1] <= 45 and r[3] > TOL_THREE_FRAME]
    assert not bad, bad
