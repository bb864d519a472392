"""`dualscale propagate export --int8` and `propagate run --precision int8` (issue 15 §2): the
int8 model is made and used only when asked for, and refused clearly when it is absent."""

import json
import shutil

import numpy as np

from dualscale.cli import main
from dualscale.formats.exr import write_exr


def _guidance(tmp_path):
    img = (0.2 + 0.3 * np.random.default_rng(1).random((72, 88, 3))).astype(np.float32)
    write_exr(tmp_path / "g.exr", img)
    return tmp_path / "g.exr"


def test_int8_export_and_run(tiny_model, tmp_path, capsys):
    shutil.copy(tiny_model, tmp_path / "m.dsp")
    g = _guidance(tmp_path)
    run = ["propagate", "run", str(tmp_path / "m.dsp"), str(g), "--exposure", "1", "--tile", "48", "--overlap", "16",
           "--precision", "int8", "--no-progress"]
    assert main([*run, "-o", str(tmp_path / "refused")]) == 2  # no int8 export yet
    assert "propagate export MODEL --int8" in capsys.readouterr().err
    assert not (tmp_path / "refused").exists()
    assert main(["propagate", "export", str(tmp_path / "m.dsp"), "--int8", "--no-check"]) == 0
    assert (tmp_path / "m.int8.onnx").is_file()
    assert main([*run, "-o", str(tmp_path / "o")]) == 0
    assert "int8" in capsys.readouterr().out
    assert json.loads((tmp_path / "o" / "material.json").read_text())["meta"]["propagate"]["precision"] == "int8"
