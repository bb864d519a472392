"""``lights sphere -o``: existing files are refused (issue 24 trial), ``--overwrite`` replaces only light
files, and an unwritable target is named, not its temporary file."""

from __future__ import annotations

import json

from dualscale.cli import main
from dualscale.formats.lightfile import read_lights
from photoset import lights_one_side
from test_lights_cli import mirror_folder


def test_lights_sphere_never_replaces_a_file_that_is_not_a_light_file(tmp_path, capsys):
    chrome = tmp_path / "chrome"
    chrome.mkdir()  # refused before any photo is read
    manifest = tmp_path / "ds" / "manifest.json"
    manifest.parent.mkdir()
    manifest.write_text(json.dumps({"format": "dualscale-dataset"}))
    for extra in ([], ["--overwrite"]):
        assert main(["lights", "sphere", str(chrome), "-o", str(manifest), *extra]) == 2
        assert "not a light file" in capsys.readouterr().err
        assert json.loads(manifest.read_text()) == {"format": "dualscale-dataset"}
    assert not (tmp_path / "ds" / "manifest.lp").exists()


def test_lights_sphere_refuses_its_own_files_without_overwrite(tmp_path, capsys):
    mirror_folder(tmp_path / "chrome", lights_one_side(4, seed=3))
    out = str(tmp_path / "l")
    assert main(["lights", "sphere", str(tmp_path / "chrome"), "-o", out]) == 0
    before = (tmp_path / "l.lp").read_bytes()
    (tmp_path / "l.lp").write_text("1\nx.png 0 0 1\n")
    assert main(["lights", "sphere", str(tmp_path / "chrome"), "-o", out]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["lights", "sphere", str(tmp_path / "chrome"), "-o", out, "--overwrite"]) == 0
    assert (tmp_path / "l.lp").read_bytes() == before and len(read_lights(tmp_path / "l.json")) == 4


def test_an_unwritable_target_is_named_not_its_temporary_file(capsys):
    chrome_free = "/proc/dualscale-test-L"  # /proc takes no new files, even for root
    from dualscale.formats.atomic import write_text

    try:
        write_text(f"{chrome_free}.lp", "x")
    except OSError as e:
        assert e.filename == f"{chrome_free}.lp" and ".tmp-" not in str(e)
    else:
        raise AssertionError("/proc took a file")
