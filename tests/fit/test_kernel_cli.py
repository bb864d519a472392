"""`dualscale fit --kernel`: the summary names the kernel and the thread count, fit.json records
the count, and contradictory kernel options are refused before anything is written."""

import json

import pytest

from dualscale.cli import main


@pytest.mark.parametrize("args,message", [
    (["--kernel", "eager", "--compile"], "--compile is --kernel compiled"),
    (["--preset", "standard-compiled", "--kernel", "fused"], "use --preset standard"),
    (["--preset", "paper", "--kernel", "compiled"], "LM optimiser only"),
])
def test_contradictory_kernel_options_are_refused(datasets, tmp_path, capsys, args, message):
    out = tmp_path / "fit"
    assert main(["fit", str(datasets("leather")), "-o", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_summary_and_record_name_kernel_and_threads(datasets, tmp_path, capsys):
    out = tmp_path / "fit"
    rc = main(["fit", str(datasets("leather")), "-o", str(out), "--preset", "draft", "--threads", "1",
               "--cv-pixels", "0", "--no-previews"])
    assert rc == 0
    assert "(kernel fused, 1 thread)" in capsys.readouterr().out
    rep = json.loads((out / "fit.json").read_text())
    assert rep["threads"] == 1 and rep["preset"]["kernel"] == "fused"
