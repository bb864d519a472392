"""``dualscale lights sphere DIR -o LIGHTS``: both light files, the table, the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.formats.lightfile import read_lights, read_lights_json
from dualscale.sim.sphere import render_mirror_sphere, to_srgb8
from photoset import angle_deg, lights_one_side, write_png


def mirror_folder(folder, dirs, size=(120, 140)):
    folder.mkdir(parents=True)
    shots = render_mirror_sphere(dirs, size=size, centre=(71.3, 58.6), radius=48.2, half_angle_deg=1.5, peak=4.0)
    for k, img in enumerate(shots.images):
        write_png(folder / f"chrome.{k}.png", to_srgb8(img))
    write_png(folder / "chrome.mask.png", (255 * (shots.coverage > 0.5)).astype(np.uint8))
    return shots


@pytest.mark.parametrize("suffix", ["", ".json", ".lp"])
def test_lights_sphere_writes_both_files_and_the_table(tmp_path, capsys, suffix):
    dirs = lights_one_side(12, seed=3)
    mirror_folder(tmp_path / "chrome", dirs)
    assert main(["lights", "sphere", str(tmp_path / "chrome"), "-o", str(tmp_path / f"out/lights{suffix}")]) == 0
    js, lp = tmp_path / "out/lights.json", tmp_path / "out/lights.lp"
    a, b = read_lights_json(js), read_lights(lp)
    assert [r.file for r in b] == [f"chrome.{k}.png" for k in range(12)] == [r.file for r in a.records]
    got = np.array([r.direction for r in b])
    err = angle_deg(got, dirs)
    assert err.mean() < 0.5 and err.max() < 1.0, err  # 8-bit, masked sphere of radius 48 px
    assert np.allclose(got, np.array([r.direction for r in a.records]), atol=1e-8)
    assert a.source["method"] == "mirror-sphere" and a.source["sphere"]["from"] == "mask:chrome.mask.png"
    lines = lp.read_text().splitlines()
    assert lines[0] == "12" and len(lines) == 13
    out = capsys.readouterr().out
    assert "elev deg" in out and "resid deg" in out and "chrome.11.png" in out
    row = next(ln for ln in out.splitlines() if ln.startswith("chrome.0.png"))
    assert float(row.split()[4]) == pytest.approx(np.degrees(np.arcsin(got[0, 2])), abs=0.01)


def test_lights_sphere_auto_finds_the_sphere_without_a_mask(tmp_path):
    dirs = lights_one_side(12, seed=4)
    mirror_folder(tmp_path / "chrome", dirs)
    (tmp_path / "chrome" / "chrome.mask.png").unlink()
    assert main(["lights", "sphere", str(tmp_path / "chrome"), "-o", str(tmp_path / "l"), "--mask", "auto"]) == 0
    got = np.array([r.direction for r in read_lights(tmp_path / "l.lp")])
    assert angle_deg(got, dirs).mean() < 0.5


def test_lights_sphere_refuses_a_folder_without_a_highlight(tmp_path, capsys):
    d = tmp_path / "chrome"
    mirror_folder(d, lights_one_side(3))
    write_png(d / "chrome.1.png", np.zeros((120, 140), np.uint8))  # a black frame: no highlight
    assert main(["lights", "sphere", str(d), "-o", str(tmp_path / "l")]) == 2
    err = capsys.readouterr().err
    assert "chrome.1.png" in err and "highlight" in err
    assert not (tmp_path / "l.json").exists() and not (tmp_path / "l.lp").exists()


def test_lights_sphere_refuses_a_missing_folder(tmp_path, capsys):
    assert main(["lights", "sphere", str(tmp_path / "nope"), "-o", str(tmp_path / "l")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
