"""Dataset manifests the reader refuses (issue 24 §3): images outside the dataset folder, images
of a camera the manifest does not define, cameras with impossible sizes -- each naming the file
and the field, exit 2 on the command line, before any pixel is read."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from dualscale.errors import FormatError
from dualscale.formats.dataset import read_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from dualscale.cli import main

    root = tmp_path_factory.mktemp("ds")
    assert main(["synth", "twill", "-o", str(root / "syn"), "--dataset", "--size", "16", "--threads", "1"]) == 0
    ds = root / "syn" / "dataset"
    if not (ds / "manifest.json").is_file():
        ds = next(p.parent for p in (root / "syn").rglob("manifest.json"))
    return ds


def _edit(src, tmp_path, fn):
    dst = tmp_path / "ds"
    shutil.copytree(src, dst)
    m = json.loads((dst / "manifest.json").read_text())
    fn(m)
    (dst / "manifest.json").write_text(json.dumps(m))
    return dst


@pytest.mark.parametrize("bad", ["../../etc/passwd", "/etc/passwd", "images/../../x.exr", "C:\\\\x\\\\y.exr"])
def test_image_outside_the_dataset_refused(dataset, tmp_path, bad):
    def fn(m):
        m["images"][0]["file"] = bad

    with pytest.raises(FormatError, match="not inside the dataset folder"):
        read_dataset(_edit(dataset, tmp_path, fn))


def test_image_of_an_undefined_camera_refused(dataset, tmp_path):
    def fn(m):
        m["images"][0]["camera"] = "nope"

    with pytest.raises(FormatError, match="camera 'nope'"):
        read_dataset(_edit(dataset, tmp_path, fn))


def test_camera_with_negative_width_refused_naming_the_field(dataset, tmp_path, capsys):
    def fn(m):
        next(iter(m["cameras"].values()))["width"] = -5

    ds = _edit(dataset, tmp_path, fn)
    with pytest.raises(FormatError, match=r"width must be a positive finite number, got -5"):
        read_dataset(ds)
    from dualscale.cli import main

    assert main(["fit", str(ds), "-o", str(tmp_path / "maps"), "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert "manifest.json" in err and "width" in err
    assert not (tmp_path / "maps" / "fit.json").exists()


def test_render_with_an_analyser_on_the_mid_camera_is_refused_up_front(tmp_path, capsys):
    """`render --analyzer 0,90 --camera mid` failed with "duplicate image" and left an image
    (issue 24 §3): the mid camera has no analyser; refused before anything is written."""
    from dualscale.cli import main

    assert main(["synth", "leather", "-o", str(tmp_path / "s"), "--size", "8", "--no-previews"]) == 0
    out = tmp_path / "r"
    assert main(["render", str(tmp_path / "s" / "maps"), "-o", str(out), "--led", "0", "12", "--analyzer", "0,90",
                 "--camera", "mid", "--size", "16"]) == 2
    assert "has no analyser" in capsys.readouterr().err
    assert not out.exists() or not any(out.rglob("*.exr"))


def test_the_same_pixels_give_the_same_exr_bytes(tmp_path):
    """No write time in our EXR files (issue 24 §8: calibrate wrote the time into every EXR, so
    recomputing an unchanged calibration changed the fit's input key)."""
    import time

    from dualscale.formats.exr import write_exr

    img = np.linspace(0, 1, 48, dtype=np.float32).reshape(4, 4, 3)
    write_exr(tmp_path / "a.exr", img, ("R", "G", "B"))
    time.sleep(1.1)
    write_exr(tmp_path / "b.exr", img, ("R", "G", "B"))
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()


def test_the_calibration_key_ignores_the_time_it_was_written(tmp_path):
    """Recomputing an unchanged calibration changes only its ``created`` time: the calibrate
    stage's input key stays, so the run is not redone (issue 24 §8)."""
    from dualscale.pipeline import _calibration_key

    a, b, c = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "c.json"
    a.write_text(json.dumps({"format": "x", "created": "2026-12-01T10:00:00+00:00", "dark": {"micro": [1, 2]}}))
    b.write_text(json.dumps({"created": "2026-12-02T11:00:00+00:00", "dark": {"micro": [1, 2]}, "format": "x"}))
    c.write_text(json.dumps({"format": "x", "created": "2026-12-01T10:00:00+00:00", "dark": {"micro": [1, 3]}}))
    assert _calibration_key(a) == _calibration_key(b) != _calibration_key(c)
