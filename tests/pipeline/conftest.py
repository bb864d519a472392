from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def sample(tmp_path_factory) -> Path:
    """A tiny synthetic twill: 16 x 16 texels of 9 um, every 4th LED, P0/P90, plus a 96 px
    mid-range guidance image of a 2 mm field (so the micro field spans a few guidance pixels)."""
    from dualscale.cli import main

    root = tmp_path_factory.mktemp("digitize") / "sample"
    assert main(["synth", "twill", "-o", str(root), "--size", "16", "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--mid", "--mid-size", "96", "--mid-field-mm", "2", "--no-previews", "--no-progress"]) == 0
    return root
