"""Radiometric self-calibration (issue 23): the camera response and the lights' relative
intensities recovered from synthetic photographs of the virtual rig (``dualscale.sim.photos``)
with known truth, and the import's checks and refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualscale.calib.response import code_window, estimate_response
from dualscale.sim.photos import PSM_LIGHTS, film_curve, inverse_of, render_photos, write_photos

RNG = np.random.default_rng(7)
E_TRUE = RNG.uniform(0.7, 1.3, len(PSM_LIGHTS))


def _srgb(x):
    import colour

    return np.asarray(colour.cctf_encoding(np.clip(x, 0, 1), function="sRGB"))


# (encode, the largest error with g(1) = 1): every response is held to 1 % of full scale at the
# best common scale (the gauge the photographs leave free: curve_distance's scale_free); with the
# convention g(1) = 1 the S-shaped film curve is 2-3 % off, because its last 2 % of codes, above
# the code window, span 17 % of the linear range and are extrapolated (docs/RADIOMETRY.md)
RESPONSES = {
    "linear": (lambda x: x, 0.01),
    "gamma1.2": (lambda x: x ** (1 / 1.2), 0.01),
    "gamma1.8": (lambda x: x ** (1 / 1.8), 0.01),
    "gamma2.2": (lambda x: x ** (1 / 2.2), 0.01),
    "srgb": (_srgb, 0.01),
    "film": (film_curve, 0.03),
}


def _estimate(shots, **kw):
    codes = shots.codes[:, shots.mask].astype(np.float64) / (2 ** shots.bits - 1)
    valid = (codes < 1.0).all(-1)
    return estimate_response(codes, shots.dirs, valid, bits=shots.bits, **kw)


def _curve_error(est, encode, bits=8, scale_free=False):
    """The largest error of the estimated inverse response over the code window (fractions of
    full scale), with g(1) = 1 or at the best common scale."""
    lo, hi = code_window(bits)
    c = np.linspace(lo, hi, 200)
    ge, gt = est.response.inverse(c), inverse_of(encode)(c)
    if scale_free:
        s = np.linspace(0.8, 1.25, 9001)[:, None]
        return float(np.min(np.max(np.abs(s * ge - gt), axis=1)))
    return float(np.max(np.abs(ge - gt)))


def test_curve_distance_scale_free():
    from dualscale.calib.response import curve_distance
    from dualscale.formats.response import Response

    a, b = Response("gamma", (1.5,)), Response("gamma", (2.0,))
    assert curve_distance(a, b, (0.03, 0.98), scale_free=True) < curve_distance(a, b, (0.03, 0.98))
    assert curve_distance(a, b, (0.03, 0.98), scale_free=True) > 0.05  # a different shape stays apart
    half = Response("curve", (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))  # the identity as a curve
    assert curve_distance(half, Response("linear", ()), scale_free=True) < 1e-6


@pytest.mark.parametrize("name", list(RESPONSES))
def test_response_and_intensities_recovered_sphere(name):
    encode, tol = RESPONSES[name]
    shots = render_photos("sphere", size=(72, 96), encode=encode, intensities=E_TRUE, spec=0.5, shininess=80)
    assert (shots.codes == 255).any(), "the highlights must clip, to test that clipped samples are left out"
    est = _estimate(shots, bootstrap=2)
    assert _curve_error(est, encode, scale_free=True) <= 0.01, (name, est.response.describe(), est.fits)
    assert _curve_error(est, encode) <= tol, (name, est.response.describe(), est.fits)
    e = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))
    assert np.max(np.abs(est.intensities / e - 1)) <= 0.02, (est.intensities, e)
    assert est.response.source == "auto" and est.response.evidence["fits"]


@pytest.mark.parametrize("name", ["gamma1.8", "srgb", "film"])
def test_relief_with_cast_shadows(name):
    encode, tol = RESPONSES[name]
    shots = render_photos("relief", size=(72, 96), encode=encode, intensities=E_TRUE)
    assert shots.shadow.mean() > 0.01, "the relief must cast shadows"
    est = _estimate(shots, bootstrap=0)
    assert _curve_error(est, encode, scale_free=True) <= 0.01, est.response.describe()
    assert _curve_error(est, encode) <= tol, est.response.describe()
    e = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))
    assert np.max(np.abs(est.intensities / e - 1)) <= 0.02


def test_wrong_response_is_less_consistent():
    """The criterion itself: the true family scores better than a wrong one."""
    shots = render_photos("sphere", size=(64, 80), encode=RESPONSES["gamma2.2"][0])
    est = _estimate(shots, bootstrap=0)
    assert est.fits["linear"]["score"] > 1.5 * est.fits["gamma"]["score"]
    assert abs(est.response.params[0] - 2.2) < 0.03 or est.response.family == "srgb"


def test_too_few_lit_pixels_refused():
    from dualscale.errors import CalibrationError

    shots = render_photos("sphere", size=(24, 24), exposure=0.02, encode=lambda x: x)
    with pytest.raises(CalibrationError, match="too few lit pixels"):
        _estimate(shots)


# -- through the command line ---------------------------------------------------------------------

def _cli(*args):
    from dualscale.cli import main

    return main(list(map(str, args)))


@pytest.fixture(scope="module")
def photos_g12(tmp_path_factory):
    root = tmp_path_factory.mktemp("photos")
    shots = render_photos("sphere", size=(64, 80), encode=RESPONSES["gamma1.2"][0], intensities=E_TRUE)
    folder, lp = write_photos(root / "obj", shots)
    return root, folder, lp, shots


def test_import_auto_records_the_estimate(photos_g12, capsys):
    root, folder, lp, shots = photos_g12
    assert _cli("import", folder, "--lights", lp, "-o", root / "auto", "--transfer", "auto", "--threads", "1") == 0
    out = capsys.readouterr().out
    assert "estimated from the photographs" in out
    man = json.loads((root / "auto" / "manifest.json").read_text())
    rad = man["extra"]["import"]["radiometry"]
    assert rad["response"]["source"] == "auto" and rad["response"]["family"] == "gamma"
    assert abs(rad["response"]["params"][0] - 1.2) < 0.02
    assert rad["response"]["uncertainty"]["gamma_std"] > 0
    assert man["transfer"].startswith("gamma:")
    e = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))
    got = np.array([im["light"]["intensity"] for im in man["images"]])
    got = got / np.exp(np.mean(np.log(got)))
    assert np.max(np.abs(got / e - 1)) < 0.02


def test_normals_match_a_fit_given_the_true_response(photos_g12):
    """Lambertian normals of the auto-decoded dataset within 0.5 deg of the truly decoded one's."""
    from dualscale.fit.lambertian import fit_lambertian
    from dualscale.formats.dataset import read_dataset

    root, folder, lp, shots = photos_g12
    true_lp = root / "true.json"
    from dualscale.formats.lightfile import LightRecord, write_lights_json

    write_lights_json(true_lp, [LightRecord(f"obj.{k}.png", tuple(d), float(E_TRUE[k]))
                                for k, d in enumerate(shots.dirs)])
    assert _cli("import", folder, "--lights", true_lp, "-o", root / "true", "--transfer", "gamma:1.2",
                "--threads", "1") == 0
    if not (root / "auto").is_dir():
        assert _cli("import", folder, "--lights", lp, "-o", root / "auto", "--transfer", "auto") == 0
    normals = []
    for name in ("auto", "true"):
        ds = read_dataset(root / name)
        imgs = np.stack([ds.load(i) / ds.records[i].intensity for i in range(len(ds.records))])
        clipped = np.stack([ds.clipped(i, ds.load(i)) for i in range(len(ds.records))])
        m = shots.mask
        fit = fit_lambertian(imgs[:, m], np.array([r.direction for r in ds.records]), ~clipped[:, m])
        normals.append(fit.normal)
    ang = np.degrees(np.arccos(np.clip((normals[0] * normals[1]).sum(-1), -1, 1)))
    assert float(ang.mean()) < 0.5, float(ang.mean())


def test_stated_transfer_contradicted_warns_and_strict_refuses(photos_g12, capsys):
    root, folder, lp, _ = photos_g12
    assert _cli("import", folder, "--lights", lp, "-o", root / "srgb", "--transfer", "srgb") == 0
    err = capsys.readouterr().err
    assert "contradict --transfer srgb" in err and "gamma 1.2" in err
    assert _cli("import", folder, "--lights", lp, "-o", root / "srgb2", "--transfer", "srgb", "--strict") == 2
    assert "contradict" in capsys.readouterr().err
    assert not (root / "srgb2" / "manifest.json").exists()
    # the true one is not contradicted
    assert _cli("import", folder, "--lights", lp, "-o", root / "g12", "--transfer", "gamma:1.2", "--strict") == 0
    assert "contradict" not in capsys.readouterr().err


# -- the matte reference sphere --------------------------------------------------------------------

@pytest.fixture(scope="module")
def chrome_and_matte(tmp_path_factory):
    from dualscale.sim.sphere import render_mirror_sphere, to_srgb8

    root = tmp_path_factory.mktemp("spheres")
    chrome = root / "chrome"
    chrome.mkdir()
    shots = render_mirror_sphere(PSM_LIGHTS, size=(120, 128), radius=50)
    import OpenImageIO as oiio

    for k, img in enumerate(to_srgb8(shots.images)):
        assert oiio.ImageBuf(np.ascontiguousarray(img[..., None])).write(str(chrome / f"chrome.{k}.png"))
    m8 = (shots.coverage > 0.5).astype(np.uint8) * 255
    assert oiio.ImageBuf(np.ascontiguousarray(m8[..., None])).write(str(chrome / "chrome.mask.png"))
    matte = render_photos("sphere", size=(80, 96), encode=lambda x: x ** (1 / 1.5), intensities=E_TRUE)
    write_photos(root / "matte", matte, "matte")
    return root, chrome, root / "matte", matte


def test_lights_sphere_with_a_matte_sphere(chrome_and_matte, capsys):
    from dualscale.formats.lightfile import read_lights_json

    root, chrome, matte_dir, matte = chrome_and_matte
    assert _cli("lights", "sphere", chrome, "-o", root / "lights", "--matte", matte_dir) == 0
    out = capsys.readouterr().out
    assert "from the matte reference sphere" in out
    lf = read_lights_json(root / "lights.json")
    rad = lf.source["radiometry"]
    assert rad["response"]["source"] == "target" and abs(rad["response"]["params"][0] - 1.5) < 0.03
    e = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))
    got = np.array([r.intensity for r in lf.records])
    assert np.max(np.abs(got / e - 1)) < 0.03, (got, e)
    # the object imported with the sphere's response and intensities (checked, not contradicted)
    assert _cli("import", matte_dir, "--lights", root / "lights.json", "-o", root / "ds", "--transfer", "lights",
                "--strict") == 0
    assert "contradict" not in capsys.readouterr().err


def test_matte_sphere_mask_not_a_circle_refused(chrome_and_matte, capsys, tmp_path):
    import shutil

    import OpenImageIO as oiio

    root, chrome, matte_dir, matte = chrome_and_matte
    bad = tmp_path / "matte"
    shutil.copytree(matte_dir, bad)
    m = (matte.mask * 255).astype(np.uint8)
    m[:, : m.shape[1] // 2] = 0  # half a disc
    assert oiio.ImageBuf(np.ascontiguousarray(m[..., None])).write(str(bad / "matte.mask.png"))
    assert _cli("lights", "sphere", chrome, "-o", tmp_path / "lights", "--matte", bad) == 2
    assert "not a disc" in capsys.readouterr().err
    assert not (tmp_path / "lights.json").exists()


def test_fit_and_exports_record_the_response(photos_g12, tmp_path, capsys):
    """The response the maps were fitted under is in the fit's summary, fit.json, the maps'
    material.json and the exports' provenance (glTF asset extras, MaterialX dualscale_meta)."""
    root, folder, lp, _ = photos_g12
    ds = root / "auto"
    if not ds.is_dir():
        assert _cli("import", folder, "--lights", lp, "-o", ds, "--transfer", "auto") == 0
    maps = tmp_path / "maps"
    assert _cli("fit", ds, "-o", maps, "--preset", "draft", "--cv-pixels", "0", "--threads", "1") == 0
    out = capsys.readouterr().out
    assert "camera response: gamma 1.2" in out and "estimated from the photographs" in out
    fit = json.loads((maps / "fit.json").read_text())
    assert fit["radiometry"]["source"] == "auto" and fit["radiometry"]["family"] == "gamma"
    meta = json.loads((maps / "material.json").read_text())["meta"]
    assert meta["radiometry"]["transfer"].startswith("gamma:1.2")
    exp = tmp_path / "export"
    assert _cli("export", maps, "-o", exp, "--format", "gltf,mtlx") == 0
    gltf = next(exp.rglob("*.gltf"))
    doc = json.loads(gltf.read_text())
    assert doc["asset"]["extras"]["dualscale"]["provenance"]["radiometry"]["source"] == "auto"
    mtlx = next(exp.rglob("*.mtlx")).read_text()
    assert "radiometry" in mtlx and "gamma:1.2" in mtlx


def test_a_truncated_chrome_photograph_is_refused_not_given_another_images_light(chrome_and_matte, tmp_path,
                                                                                  capsys):
    """A corrupt chrome photograph gave the previous image's direction (ImageBuf read lazily)."""
    import shutil

    root, chrome, _, _ = chrome_and_matte
    bad = tmp_path / "chrome"
    shutil.copytree(chrome, bad)
    data = (bad / "chrome.4.png").read_bytes()
    (bad / "chrome.4.png").write_bytes(data[: len(data) // 2])
    assert _cli("lights", "sphere", bad, "-o", tmp_path / "lights") == 2
    assert "chrome.4.png" in capsys.readouterr().err
    assert not (tmp_path / "lights.json").exists() and not (tmp_path / "lights.lp").exists()


def test_stated_srgb_on_a_stated_gamma_photograph_set_warns_through_the_fit(photos_g12, tmp_path, capsys):
    """The import's contradiction warning is repeated by the fit (and so by digitize's report)."""
    root, folder, lp, _ = photos_g12
    ds = tmp_path / "srgb"
    assert _cli("import", folder, "--lights", lp, "-o", ds, "--transfer", "srgb") == 0
    capsys.readouterr()
    assert _cli("fit", ds, "-o", tmp_path / "maps", "--preset", "draft", "--cv-pixels", "0", "--threads", "1") == 0
    err = capsys.readouterr().err
    assert "radiometry" in err and "contradict --transfer srgb" in err


def test_exr_photographs_are_linear_with_auto_and_refused_with_a_curve(tmp_path, capsys):
    """Float images carry no camera response: `auto` takes them as they are (with a note), a
    stated non-linear transfer is refused."""
    from dualscale.formats.exr import write_exr
    from dualscale.formats.lightfile import LightRecord, write_lp

    shots = render_photos("sphere", size=(24, 32))
    folder = tmp_path / "exr"
    folder.mkdir()
    for k in range(len(shots.dirs)):
        write_exr(folder / f"e.{k}.exr", shots.linear[k].astype(np.float32), ("R", "G", "B"))
    lp = tmp_path / "e.lp"
    write_lp(lp, [LightRecord(f"e.{k}.exr", tuple(d)) for k, d in enumerate(shots.dirs)])
    assert _cli("import", folder, "--lights", lp, "-o", tmp_path / "ds", "--transfer", "auto", "--mask", "none") == 0
    assert "linear already" in capsys.readouterr().out
    assert _cli("import", folder, "--lights", lp, "-o", tmp_path / "ds2", "--transfer", "gamma:2.2",
                "--mask", "none") == 2
    assert "linear already" in capsys.readouterr().err
