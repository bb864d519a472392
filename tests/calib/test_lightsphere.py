"""Light directions from a mirror sphere (calib/lightsphere.py), its virtual sphere
(sim/sphere.py) and the light files (formats/lightfile.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dualscale.calib.lightsphere import LightSphereError, pixel_to_light, recover_from_folder, recover_lights
from dualscale.formats.lightfile import LightRecord, read_lights, read_lights_json, write_lights_json, write_lp
from dualscale.sim.sphere import render_mirror_sphere, to_srgb8

ROOT = Path(__file__).resolve().parents[2]
CHROME = ROOT.parent / "shared" / "data" / "psm-12lights" / "chrome"


def rig_led_directions() -> np.ndarray:
    """The rig's nominal LED directions ``(127, 3)`` from protocol/rig.toml (ring layout, row by
    row, ``phi = phi0 + 360 k / count``), read directly so this test needs no other module."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    dome = tomllib.loads((ROOT / "protocol" / "rig.toml").read_text())["dome"]
    out = []
    for count, theta, phi0 in zip(dome["counts"], dome["theta_deg"], dome["phi0_deg"]):
        for k in range(count):
            t, p = math.radians(theta), math.radians(phi0 + 360.0 * k / count)
            out.append((math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)))
    return np.array(out)


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


def write_image(path: Path, img: np.ndarray) -> None:
    import OpenImageIO as oiio

    a = np.ascontiguousarray(np.repeat(img[..., None], 3, -1))
    buf = oiio.ImageBuf(a)
    assert buf.write(str(path)), buf.geterror()


# ------------------------------------------------------------------------------ virtual dome
@pytest.fixture(scope="module")
def dome_shots():
    dirs = rig_led_directions()
    assert dirs.shape == (127, 3) and (dirs[:, 2] > 0.1).all()  # all visible on the sphere
    return render_mirror_sphere(dirs, size=(240, 256), centre=(131.3, 117.8), radius=100.7,
                                half_angle_deg=1.5, peak=4.0, noise_sigma=0.004)


@pytest.mark.parametrize("quantise", [False, True], ids=["float", "srgb8"])
@pytest.mark.parametrize("use_mask", [True, False], ids=["mask", "auto"])
def test_virtual_dome_recovers_the_rig_leds(dome_shots, quantise, use_mask):
    imgs = to_srgb8(dome_shots.images) if quantise else dome_shots.images
    res = recover_lights(list(imgs), mask=dome_shots.coverage if use_mask else None)
    err = angles_deg(res.directions, dome_shots.directions)
    print(f"virtual dome ({'8-bit' if quantise else 'float'}, {'mask' if use_mask else 'auto'}): "
          f"mean {err.mean():.3f} deg, max {err.max():.3f} deg, sphere {res.sphere}")
    assert err.mean() < 0.5
    assert err.max() < 1.0
    assert abs(res.sphere.cx - 131.3) < 0.2 and abs(res.sphere.cy - 117.8) < 0.2 and abs(res.sphere.r - 100.7) < 0.2
    assert res.sphere.source == ("mask" if use_mask else "auto")
    assert np.allclose(np.linalg.norm(res.directions, axis=1), 1.0)
    assert (res.n_blobs == 1).all() and (res.confidence > 0.99).all()
    assert len(res.to_records()) == 127 and res.to_records()[5].file == "image 5"


def test_axes_image_rows_go_down():
    """A light up and to the right puts its highlight right of and *above* the centre."""
    d = np.array([[0.5, 0.5, math.sqrt(0.5)]])
    shots = render_mirror_sphere(d, size=(100, 100), radius=40)
    res = recover_lights([shots.images[0]], mask=shots.coverage)
    (x, y), (cx, cy) = res.highlights_px[0], shots.centre
    assert x > cx + 5 and y < cy - 5
    assert angles_deg(res.directions, d)[0] < 0.5
    assert np.allclose(pixel_to_light(res.sphere.cx, res.sphere.cy, res.sphere), [0, 0, 1])


def test_folder_of_exr_and_png_natural_order(tmp_path):
    dirs = rig_led_directions()[::10][:12]
    shots = render_mirror_sphere(dirs, size=(160, 180), radius=70, noise_sigma=0.003)
    for fmt in ("exr", "png"):
        folder = tmp_path / fmt
        folder.mkdir()
        for i, img in enumerate(shots.images):
            write_image(folder / f"ball.{i}.{fmt}", img.astype(np.float32) if fmt == "exr" else to_srgb8(img))
        write_image(folder / f"ball.mask.{fmt}", (shots.coverage * 255).round().astype(np.uint8)
                    if fmt == "png" else shots.coverage)
        res = recover_from_folder(folder)
        assert res.files == [f"ball.{i}.{fmt}" for i in range(12)]  # ball.10 after ball.9
        assert res.sphere.source == f"mask:ball.mask.{fmt}"
        assert angles_deg(res.directions, dirs).mean() < 0.5
        auto = recover_from_folder(folder, mask="auto")
        assert auto.sphere.source == "auto" and angles_deg(auto.directions, dirs).mean() < 0.5
        one = recover_from_folder(folder, pattern="ball.1*")
        assert one.files == [f"ball.{i}.{fmt}" for i in (1, 10, 11)]


def test_no_highlight_and_highlight_off_the_sphere_name_the_image():
    shots = render_mirror_sphere(np.array([[0.0, 0.0, 1.0]]), size=(100, 100), radius=35)
    dark = render_mirror_sphere(np.array([[0.0, 0.0, 1.0]]), size=(100, 100), radius=35, peak=0.0,
                                noise_sigma=0.003).images[0]  # the room on the sphere, no light
    with pytest.raises(LightSphereError, match=r"dark\.png: no highlight"):
        recover_lights([dark], mask=shots.coverage, names=["dark.png"])
    off = 0.05 * shots.coverage.copy()
    off[5:8, 5:8] = 1.0  # a bright spot in the corner, off the sphere
    with pytest.raises(LightSphereError, match=r"off\.png: the highlight at \(6\.0, 6\.0\) px is outside the sphere"):
        recover_lights([off], mask=shots.coverage, names=["off.png"])
    square = np.zeros((100, 100))
    square[20:80, 20:80] = 1
    with pytest.raises(LightSphereError, match="not a disc"):
        recover_lights([shots.images[0]], mask=square)
    with pytest.raises(LightSphereError, match="pass a mask"):
        recover_lights([np.zeros((50, 50)) + 0.01], mask=None)


# ------------------------------------------------------------------------------- light files
RECS = [LightRecord("a.png", (0.0, 0.0, 1.0)), LightRecord("b.png", (0.6, 0.0, 0.8), 2.5),
        LightRecord("c.png", (-0.36, 0.48, 0.8))]


def _same(a: list[LightRecord], b: list[LightRecord], intensity: bool = True) -> None:
    assert [r.file for r in a] == [r.file for r in b]
    assert np.allclose([r.direction for r in a], [r.direction for r in b], atol=1e-8)
    if intensity:
        assert [r.intensity for r in a] == [r.intensity for r in b]


def test_lp_and_json_round_trips(tmp_path):
    _same(read_lights(write_lp(tmp_path / "l.lp", RECS)), RECS, intensity=False)
    text = (tmp_path / "l.lp").read_text()
    assert text.splitlines()[0] == "3" and text.endswith("\n") and "\r" not in text
    src = {"method": "mirror-sphere", "sphere": {"centre_px": [1.5, 2.5], "radius_px": 10.0}}
    write_lights_json(tmp_path / "l.json", RECS, source=src)
    lf = read_lights_json(tmp_path / "l.json")
    _same(lf.records, RECS)
    assert lf.frame == "camera" and lf.source == src
    doc = json.loads((tmp_path / "l.json").read_text())
    assert doc["format"] == "dualscale-lights" and doc["version"] == 1 and doc["lights"][0]["intensity"] is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.json", "l.lp"]  # no temp files left


def test_lp_read_is_tolerant(tmp_path):
    p = tmp_path / "messy.lp"
    p.write_bytes("\ufeff# exported by some tool\r\n  3  \r\n\r\na.png\t0 0 1   # zenith\r\n"
                  "my b.png 0.6000004 0 0.8\r\n  c.png -0.36 0.48 0.8\r\n".encode())
    got = read_lights(p)
    assert [r.file for r in got] == ["a.png", "my b.png", "c.png"]
    assert abs(np.linalg.norm(got[1].direction) - 1) < 1e-12  # renormalised within 1e-3


@pytest.mark.parametrize("bad, message", [
    (LightRecord("x.png", (0.6, 0.0, -0.8)), "below the horizon"),
    (LightRecord("x.png", (1.0, 0.0, 0.0)), "below the horizon"),
    (LightRecord("x.png", (0.0, 0.0, 1.01)), "not unit"),
    (LightRecord("x.png", (float("nan"), 0.0, 1.0)), "not finite"),
    (LightRecord("a.png", (0.0, 0.0, 1.0)), "duplicate file name 'a.png'"),
    (LightRecord("x.png", (0.0, 0.0, 1.0), float("inf")), "intensity"),
])
@pytest.mark.parametrize("suffix", [".lp", ".json"])
def test_writes_refuse_and_leave_nothing(tmp_path, bad, message, suffix):
    path = tmp_path / f"lights{suffix}"
    writer = write_lp if suffix == ".lp" else write_lights_json
    with pytest.raises(ValueError, match=rf"lights{suffix}: light 3: .*{message}"):
        writer(path, RECS + [bad])
    assert list(tmp_path.iterdir()) == []
    writer(path, RECS)  # an existing file stays as it was when a later write is refused
    before = path.read_bytes()
    with pytest.raises(ValueError):
        writer(path, RECS + [bad])
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [path.name]


def test_lp_refuses_names_it_cannot_carry(tmp_path):
    with pytest.raises(ValueError, match="whitespace"):
        write_lp(tmp_path / "l.lp", [LightRecord("my file.png", (0, 0, 1))])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("body, message", [
    ("3\na.png 0 0 1\nb.png 0.6 0 0.8\n", r"bad\.lp:1: count mismatch: header says 3 images, the file lists 2"),
    ("1\na.png 0.6 0 -0.8\n", r"bad\.lp:2: .*below the horizon"),
    ("2\na.png 0 0 1\nb.png 0 0 1.5\n", r"bad\.lp:3: .*not unit"),
    ("1\na.png nan 0 1\n", r"bad\.lp:2: .*not finite"),
    ("2\na.png 0 0 1\n\n# x\na.png 0.6 0 0.8\n", r"bad\.lp:5: duplicate file name 'a\.png' \(first at .*bad\.lp:2\)"),
    ("a.png 0 0 1\n", r"bad\.lp:1: expected the number of images"),
    ("1\na.png 0 1\n", r"bad\.lp:2: expected 'filename x y z'"),
])
def test_lp_read_refusals_name_file_and_line(tmp_path, body, message):
    (tmp_path / "bad.lp").write_text(body)
    with pytest.raises(ValueError, match=message):
        read_lights(tmp_path / "bad.lp")


def test_json_read_refusals(tmp_path):
    p = tmp_path / "bad.json"
    good = {"format": "dualscale-lights", "version": 1, "frame": "camera",
            "lights": [{"file": "a.png", "direction": [0, 0, 1], "intensity": None}]}
    for change, message in [({"version": 2}, "unsupported version"), ({"frame": "sample"}, "unsupported frame"),
                            ({"format": "other"}, "not a 'dualscale-lights' file"),
                            ({"lights": [{"file": "a.png", "direction": [0, 0, -1]}]}, r"lights\[0\]: .*below the horizon")]:
        p.write_text(json.dumps({**good, **change}))
        with pytest.raises(ValueError, match=message):
            read_lights(p)
    with pytest.raises(ValueError, match="unknown light-file suffix"):
        read_lights(tmp_path / "x.txt")


# ------------------------------------------------------------------------------- real photos
@pytest.fixture(scope="module")
def chrome():
    if not CHROME.is_dir():
        pytest.skip("../shared/data/psm-12lights absent (a user's clone has no shared/)")
    return recover_from_folder(CHROME)


def test_real_chrome_sphere_gives_twelve_frontal_lights(chrome, tmp_path):
    d = chrome.directions
    assert chrome.files == [f"chrome.{i}.png" for i in range(12)]
    assert chrome.sphere.source == "mask:chrome.mask.png" and chrome.sphere.fit_rms_px < 0.5
    assert d.shape == (12, 3) and np.isfinite(d).all()
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0) and (d[:, 2] > 0).all()
    assert (chrome.elevation_deg > 30).all()  # roughly frontal lights
    assert d[:, 1].mean() > 0.2  # all from the upper side
    assert angles_deg(d[:, None], d[None]).max() > 25  # spread, not one light twelve times
    assert (chrome.n_blobs == 1).all() and (chrome.residual_deg < 0.5).all()
    assert (chrome.saturated_px > 20).all()  # clipped highlights: the centroid is the blob's
    for e, (f, v, el) in enumerate(zip(chrome.files, d, chrome.elevation_deg)):
        print(f"{f:14s} {v[0]:+.4f} {v[1]:+.4f} {v[2]:+.4f}  elevation {el:5.2f} deg")
    _same(read_lights(write_lp(tmp_path / "chrome.lp", chrome.to_records())), chrome.to_records())
    write_lights_json(tmp_path / "chrome.json", chrome.to_records(), source=chrome.source())
    assert read_lights_json(tmp_path / "chrome.json").source["sphere"]["from"] == "mask:chrome.mask.png"


def test_real_chrome_sphere_is_too_dark_to_find_without_its_mask(chrome):
    with pytest.raises(LightSphereError, match="pass a mask"):
        recover_from_folder(CHROME, mask="auto")
