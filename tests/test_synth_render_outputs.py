"""synth and render check every option before any work, and a synth rerun with other parameters is
another run (issue 24 trial: half-written outputs under final names; 32^2 maps beside a 64^2 dataset)."""

from __future__ import annotations

import pytest

from dualscale.cli import main


@pytest.mark.parametrize("extra, option", [(["--dataset", "--analyzers", "abc"], "--analyzers"),
                                           (["--seed", "-1"], "--seed"),
                                           (["--dataset", "--lights", "mod0"], "--lights")])
def test_synth_refuses_a_bad_option_before_writing_anything(tmp_path, capsys, extra, option):
    out = tmp_path / "S"
    assert main(["synth", "twill", "-o", str(out), "--size", "16", "--no-progress", *extra]) == 2
    assert option in capsys.readouterr().err
    assert not out.exists()


def test_render_refuses_duplicate_leds_and_bad_analyzers_before_writing_anything(tmp_path, capsys):
    assert main(["synth", "twill", "-o", str(tmp_path / "syn"), "--size", "8", "--no-previews", "--no-progress"]) == 0
    out = tmp_path / "R"
    for extra, says in ((["--led", "0", "0"], "--led"), (["--led", "0", "--analyzer", "0,abc"], "--analyzer")):
        capsys.readouterr()
        assert main(["render", str(tmp_path / "syn" / "maps"), "-o", str(out), "--no-progress", *extra]) == 2
        assert says in capsys.readouterr().err
        assert not out.exists()


def test_a_synth_rerun_with_other_parameters_is_another_run(tmp_path, capsys):
    out = str(tmp_path / "S")
    first = ["synth", "twill", "-o", out, "--size", "16", "--dataset", "--lights", "mod32", "--no-previews",
             "--no-progress"]
    assert main(first) == 0
    assert main(first) == 0  # the same run again: fine, as before
    capsys.readouterr()
    for other in (["--size", "8"], ["--size", "16", "--dataset", "--lights", "mod16"], ["--size", "16"]):
        assert main(["synth", "twill", "-o", out, *other, "--no-previews", "--no-progress"]) == 2
        assert "--overwrite" in capsys.readouterr().err
    assert main(["synth", "twill", "-o", out, "--size", "8", "--no-previews", "--no-progress", "--overwrite"]) == 0
    assert not (tmp_path / "S" / "micro").exists()
