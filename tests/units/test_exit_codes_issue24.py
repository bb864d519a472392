"""Issue 24 §2: one exit code per kind of error.  A corrupt image is bad input (exit 2, naming the
file); sizes, ports and thread counts no library can honour are refused (or clamped) up front,
one line, nothing left behind."""

from __future__ import annotations

import pytest

from dualscale.cli import main
from dualscale.errors import FormatError


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_a_corrupt_exr_is_a_format_error_naming_the_file(tmp_path):
    import numpy as np

    from dualscale.formats.exr import read_exr, write_exr

    good = tmp_path / "good.exr"
    write_exr(good, np.ones((8, 8, 3), np.float32))
    for name, data in (("truncated.exr", good.read_bytes()[:120]), ("noise.exr", bytes(range(256)) * 4)):
        bad = tmp_path / name
        bad.write_bytes(data)
        with pytest.raises(FormatError, match=name):
            read_exr(bad)


def test_corrupt_maps_exit_2_not_4(tmp_path, capsys):
    maps = tmp_path / "syn"
    assert main(["synth", "twill", "-o", str(maps), "--size", "8", "--no-previews", "--no-progress",
                 "--threads", "1"]) == 0
    albedo = maps / "maps" / "albedo.exr"
    albedo.write_bytes(albedo.read_bytes()[:200])
    capsys.readouterr()
    assert main(["export", str(maps / "maps"), "-o", str(tmp_path / "out"), "--format", "exr"]) == 2
    assert "albedo.exr" in _one_line(capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, words", [
    (["--size", "1000000"], "--size 1000000"),
    (["--size", "16", "--mid", "--mid-field-mm", "inf"], "--mid-field-mm inf"),
    (["--size", "16", "--mid", "--mid-size", "0"], "--mid-size 0"),
    (["--size", "16", "--texel-um", "nan"], "--texel-um nan"),
])
def test_synth_refuses_impossible_sizes_up_front(args, words, tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["synth", "twill", "-o", str(out), "--no-progress", "--threads", "1", *args]) == 2
    assert words in _one_line(capsys)
    assert not out.exists()


def test_view_refuses_a_port_out_of_range(tmp_path, capsys):
    assert main(["view", str(tmp_path), "--port", "99999"]) == 2
    assert "--port" in _one_line(capsys)


def test_threads_beyond_the_cores_are_clamped_with_a_notice(tmp_path, capsys):
    import os

    from dualscale import threads

    out = tmp_path / "s"
    assert main(["synth", "twill", "-o", str(out), "--size", "8", "--no-previews", "--no-progress",
                 "--threads", "10000"]) == 0
    err = capsys.readouterr().err
    assert f"--threads 10000 is more than this machine's {os.cpu_count()}" in err and "warning" in err, err
    assert threads.effective_threads() == os.cpu_count()
