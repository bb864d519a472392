from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def sample(tmp_path_factory) -> Path:
    """A tiny synthetic twill: 32 x 32 texels of 9 um, every 4th LED, P0/P90, plus a 96 px
    mid-range guidance image of a 0.6 mm field (the micro field spans 46 guidance pixels)."""
    from dualscale.cli import main

    root = tmp_path_factory.mktemp("digitize") / "sample"
    assert main(["synth", "twill", "-o", str(root), "--size", "32", "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--mid", "--mid-size", "96", "--mid-field-mm", "0.6", "--no-previews", "--no-progress"]) == 0
    return root
