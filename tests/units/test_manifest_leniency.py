"""Manifests the reader used to take (issue 24 §3, a fresh user's trial): two records naming
one file, a camera's width given as a string, an image that is a symbolic link out of the
dataset folder.  Each is refused with a FormatError naming what is wrong."""

from __future__ import annotations

import os

import pytest

from dualscale.errors import FormatError
from dualscale.formats.dataset import read_dataset

from .test_manifest_refusals import _edit, dataset  # noqa: F401  (the module's synthetic dataset)


def test_two_images_naming_one_file_refused_naming_both(dataset, tmp_path):  # noqa: F811
    names = {}

    def fn(m):
        names["a"], names["b"] = m["images"][0]["file"], m["images"][1]["file"]
        m["images"][1]["file"] = "./" + m["images"][0]["file"]  # the same file, spelt otherwise

    with pytest.raises(FormatError, match="name the same file") as e:
        read_dataset(_edit(dataset, tmp_path, fn))
    assert "images 0 (" in str(e.value) and " and 1 (" in str(e.value) and names["a"] in str(e.value)


@pytest.mark.parametrize("field, value", [("width", "64"), ("height", "16"), ("width", 16.5), ("width", True)])
def test_a_camera_size_that_is_not_a_number_refused_naming_the_field(dataset, tmp_path, capsys, field, value):  # noqa: F811
    def fn(m):
        next(iter(m["cameras"].values()))[field] = value

    ds = _edit(dataset, tmp_path, fn)
    with pytest.raises(FormatError, match=rf"camera '\w+': {field} must be a whole number, got {value!r}"):
        read_dataset(ds)
    from dualscale.cli import main

    assert main(["fit", str(ds), "-o", str(tmp_path / "o")]) == 2
    assert f"{field} must be a whole number" in capsys.readouterr().err


def test_an_image_record_with_a_string_size_or_exposure_refused(dataset, tmp_path):  # noqa: F811
    def size(m):
        m["images"][0]["width"] = "16"

    with pytest.raises(FormatError, match=r"width must be a whole number, got '16'"):
        read_dataset(_edit(dataset, tmp_path / "a", size))

    def exposure(m):
        m["images"][0]["exposure_s"] = "1"

    with pytest.raises(Exception, match=r"exposure_s must be a finite number > 0, got '1'"):
        read_dataset(_edit(dataset, tmp_path / "b", exposure))


def test_an_image_linked_out_of_the_dataset_refused(dataset, tmp_path):  # noqa: F811
    ds = _edit(dataset, tmp_path, lambda m: None)
    read_dataset(ds)  # as written: fine
    import json

    first = json.loads((ds / "manifest.json").read_text())["images"][0]["file"]
    outside = tmp_path / "elsewhere.exr"
    os.replace(ds / first, outside)
    os.symlink(outside, ds / first)
    with pytest.raises(FormatError, match="outside the dataset folder"):
        read_dataset(ds)
    os.remove(ds / first)
    os.symlink("/etc/passwd", ds / first)
    with pytest.raises(FormatError, match="outside the dataset folder"):
        read_dataset(ds)
    # a link that stays inside the folder is an ordinary file of it
    os.remove(ds / first)
    os.replace(outside, ds / "images" / "moved.exr")
    os.symlink("moved.exr", ds / first)
    read_dataset(ds)
