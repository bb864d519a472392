"""``dualscale import IMAGES --lights LIGHTS -o DATASET --transfer ...``: the dataset it writes,
the name matching, and every refusal (message, exit code 2, nothing written)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.formats.dataset import read_dataset
from dualscale.formats.lightfile import LightRecord, write_lights_json
from photoset import lights_one_side, nothing_written, render_sphere, srgb8, write_png


def run(*args: str) -> int:
    return main(["import", *args])


@pytest.fixture
def small_set(tmp_path):
    """``sphere_set`` at 24 x 24 px: for the tests of name matching and replacement, which do not
    depend on the image size (every import still estimates the response, in time ~ pixels)."""
    return render_sphere(tmp_path / "ball", lights_one_side(), size=24)


def test_import_writes_a_v2_dataset_with_linear_radiance(sphere_set, tmp_path, capsys):
    out = tmp_path / "ds"
    assert run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer", "srgb",
               "--texel-mm", "0.1") == 0
    printed = capsys.readouterr().out
    assert "imported 12 images of 40x40 px" in printed and "ball.mask.png" in printed
    ds = read_dataset(out)
    assert ds.version == 2 and ds.transfer == "srgb" and ds.manifest["dome"]["polarizer"] == "none"
    assert len(ds.records) == 12
    cam = ds.manifest["cameras"]["photo"]
    assert cam["kind"] == "orthographic" and cam["field_mm"] == pytest.approx([4.0, 4.0])
    assert np.array_equal(ds.mask(), sphere_set.mask)
    scale = ds.records[0].intensity
    for k, rec in enumerate(ds.records):
        assert rec.light_kind == "led" and rec.light_id == k and rec.analyzer_deg is None
        assert rec.units == "relative_radiance" and rec.colour_space == "linear_rec709"
        # equal lights: their relative intensities, estimated from the photographs (issue 23), agree within 2 %
        assert rec.saturation == 1.0 and rec.intensity == pytest.approx(scale, rel=0.02)
        assert np.allclose(rec.direction, sphere_set.dirs[k], atol=1e-8)
        img = ds.load(k)  # the decoded pixels, as stored: linear, 1.0 = the top code value
        assert np.abs(img - sphere_set.linear[k]).max() < 0.01
    # the light scale makes the 99th-percentile Lambertian albedo 0.8 (max channel = red 0.6 x gain 2.5)
    assert scale == pytest.approx(0.6 * 2.5 / 0.8, rel=0.05)
    assert json.loads((out / "manifest.json").read_text())["extra"]["import"]["texel_mm_known"] is True


def test_import_matches_names_with_folder_prefixes_and_by_number(small_set, tmp_path, capsys):
    recs = [LightRecord(f"C:\\captures\\BALL.{k}.png", tuple(d)) for k, d in enumerate(small_set.dirs)]
    write_lights_json(tmp_path / "prefixed.json", recs)
    assert run(str(small_set.folder), "--lights", str(tmp_path / "prefixed.json"), "-o", str(tmp_path / "a"),
               "--transfer", "srgb") == 0
    lp = tmp_path / "chrome.lp"  # lights recovered from chrome.<k>.png, object shot as ball.<k>.png
    lp.write_text(small_set.lp.read_text().replace("ball.", "chrome."))
    assert run(str(small_set.folder), "--lights", str(lp), "-o", str(tmp_path / "b"), "--transfer", "srgb") == 0
    assert "by the numbers in the names" in capsys.readouterr().out
    a, b = read_dataset(tmp_path / "a"), read_dataset(tmp_path / "b")
    assert np.allclose([r.direction for r in a.records], [r.direction for r in b.records], atol=1e-8)
    assert np.array_equal(a.load(5), b.load(5))


def test_import_masks_clipped_pixels(tmp_path):
    s = render_sphere(tmp_path / "ball", np.array([[0.0, 0.2, 0.98], [0.5, 0.1, 0.86], [-0.4, 0.3, 0.87]]) /
                      np.linalg.norm([[0.0, 0.2, 0.98], [0.5, 0.1, 0.86], [-0.4, 0.3, 0.87]], axis=1, keepdims=True),
                      gain=6.0)
    assert run(str(s.folder), "--lights", str(s.lp), "-o", str(tmp_path / "ds"), "--transfer", "srgb") == 0
    ds = read_dataset(tmp_path / "ds")
    img = ds.load(0)
    clipped = (srgb8(s.linear[0]) == 255).any(-1)
    assert clipped.sum() > 10
    assert np.array_equal(~ds.valid(0, img), clipped | ~s.mask)


def test_import_replaces_an_earlier_dataset_only_when_complete(small_set, tmp_path):
    out = tmp_path / "ds"
    args = [str(small_set.folder), "--lights", str(small_set.lp), "-o", str(out)]
    assert run(*args, "--transfer", "srgb") == 0
    before = (out / "manifest.json").read_bytes()
    assert run(*args) == 2  # refused: the first dataset is untouched
    assert (out / "manifest.json").read_bytes() == before
    assert run(*args, "--transfer", "gamma:2.2") == 0
    assert read_dataset(out).transfer == "gamma:2.2"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


# ------------------------------------------------------------------------------------ refusals
def _refused(capsys, out, code, *words):
    err = capsys.readouterr().err
    assert code == 2, err
    for w in words:
        assert w in err, err
    assert nothing_written(out)


def test_refuses_integer_images_without_a_transfer(sphere_set, tmp_path, capsys):
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out)),
             "transfer", "--transfer auto|lights|srgb|linear|gamma:G")


def test_refuses_images_of_different_sizes(sphere_set, tmp_path, capsys):
    write_png(sphere_set.folder / "ball.7.png", np.zeros((40, 41, 3), np.uint8))
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer",
                              "srgb"), "different sizes", "ball.7.png (41x40)")


def test_refuses_a_light_below_the_horizon(sphere_set, tmp_path, capsys):
    lines = sphere_set.lp.read_text().splitlines()
    name, x, y, z = lines[4].split()
    lines[4] = f"{name} {x} {y} {-float(z):.9f}"
    bad = tmp_path / "below.lp"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(bad), "-o", str(out), "--transfer", "srgb"),
             f"{bad}:5", "horizon")


def test_refuses_a_mask_of_another_size(sphere_set, tmp_path, capsys):
    write_png(tmp_path / "small_mask.png", np.full((30, 40), 255, np.uint8))
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer",
                              "srgb", "--mask", str(tmp_path / "small_mask.png")), "small_mask.png", "40x30")


def test_refuses_missing_and_extra_images(sphere_set, tmp_path, capsys):
    (sphere_set.folder / "ball.3.png").unlink()
    shutil.copy(sphere_set.folder / "ball.4.png", sphere_set.folder / "stray.png")
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer",
                              "srgb"), "not in the folder: ball.3.png", "not in the light file: stray.png")


def test_refuses_an_unreadable_light_file(sphere_set, tmp_path, capsys):
    bad = tmp_path / "bad.lp"
    bad.write_text("13\n" + sphere_set.lp.read_text().split("\n", 1)[1])
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(bad), "-o", str(out), "--transfer", "srgb"),
             "count mismatch")


def test_refuses_an_unknown_transfer(sphere_set, tmp_path, capsys):
    out = tmp_path / "ds"
    _refused(capsys, out, run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer",
                              "rec709"), "unknown transfer function 'rec709'")


def test_refuses_an_output_folder_that_is_not_a_dataset(sphere_set, tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer", "srgb") == 2
    assert "not a dataset" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_light_scale_is_the_stated_one(sphere_set, tmp_path):
    assert run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(tmp_path / "ds"), "--transfer",
               "linear", "--scale", "1", "--intensities", "equal") == 0
    ds = read_dataset(tmp_path / "ds")
    assert all(r.intensity == 1.0 for r in ds.records)
    assert math.isclose(float(ds.load(2).max()), float(srgb8(sphere_set.linear[2]).max()) / 255, rel_tol=1e-6)


def test_overwrite_with_bad_input_loses_nothing(sphere_set, tmp_path, capsys):
    """`--overwrite` empties the folder only once the command succeeds: an import refused on a
    corrupt photograph leaves the earlier dataset as it was (a fresh user's trial, issue 23)."""
    import shutil

    out = tmp_path / "ds"
    assert run(str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer", "srgb") == 0
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    bad = tmp_path / "bad"
    shutil.copytree(sphere_set.folder, bad)
    first = sorted(p for p in bad.iterdir() if "mask" not in p.name)[0]
    first.write_bytes(first.read_bytes()[:40])
    capsys.readouterr()
    assert run(str(bad), "--lights", str(sphere_set.lp), "-o", str(out), "--transfer", "srgb", "--overwrite") == 2
    assert first.name in capsys.readouterr().err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert read_dataset(out).records and not list(tmp_path.glob(".ds.overwritten-*"))
