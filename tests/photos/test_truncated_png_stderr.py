"""A truncated PNG (issue 24 §3): the command's one-line error, and nothing else on stderr --
libpng's own ``libpng error: IDAT: ...`` (OpenImageIO lets libpng print it) is caught and
folded into that error (formats/photo.py ``library_stderr``)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "dualscale.cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def _one_line(res, path):
    lines = res.stderr.splitlines()
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1, res.stderr
    assert str(path) in lines[0] and "truncated or corrupt" in lines[0] and "libpng error" not in lines[0]


def test_import_and_propagate_run_of_a_truncated_png_print_one_line(sphere_set, tmp_path):
    bad = sphere_set.folder / "ball.3.png"
    _truncate(bad)
    _one_line(_cli("import", sphere_set.folder, "--lights", sphere_set.lp, "-o", tmp_path / "imp",
                   "--transfer", "srgb", cwd=tmp_path), bad)
    model = tmp_path / "m.dsp"
    model.write_bytes(b"not read: the guidance is read first")
    _one_line(_cli("propagate", "run", model, bad, "--transfer", "srgb", "-o", tmp_path / "maps",
                   cwd=tmp_path), bad)


def test_the_caught_text_is_kept_in_the_error_and_a_good_read_prints_nothing(sphere_set, tmp_path, capfd):
    from dualscale.errors import FormatError
    from dualscale.formats.photo import read_codes, read_mask

    assert read_codes(sphere_set.folder / "ball.0.png").bits == 8
    bad = sphere_set.folder / "ball.3.png"
    _truncate(bad)
    for read in (read_codes, read_mask):
        with pytest.raises(FormatError, match="IDAT"):
            read(bad)
    assert capfd.readouterr().err == ""
