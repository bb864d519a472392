"""Shared tiny fixtures: a synthetic twill micro dataset (32x32, every 16th LED, P0/P90), and a
two-scale test bed (micro 96 px at 6 um inside a mid-range guidance of 160 px at 12 um)."""

from __future__ import annotations

import pytest
import torch

from dualscale.cli import main


@pytest.fixture(scope="session")
def twill(tmp_path_factory):
    root = tmp_path_factory.mktemp("prop") / "twill"
    assert main(["synth", "twill", "-o", str(root), "--size", "32", "--texel-um", "6", "--dataset",
                 "--lights", "mod16", "--no-previews"]) == 0
    return root


# the two-scale test bed: micro 96 x 6 um = 0.576 mm; guidance 160 x 12 um = 1.92 mm, micro centred
BED = {"micro": 96, "micro_um": 6.0, "mid": 160, "mid_um": 12.0}


@pytest.fixture(scope="session")
def bed(tmp_path_factory):
    root = tmp_path_factory.mktemp("bed") / "twill"
    assert main(["synth", "twill", "-o", str(root), "--size", str(BED["micro"]), "--texel-um", str(BED["micro_um"]),
                 "--dataset", "--lights", "mod16", "--mid", "--mid-size", str(BED["mid"]), "--mid-field-mm",
                 str(BED["mid"] * BED["mid_um"] / 1000), "--no-previews"]) == 0
    return root


def bed_truth() -> tuple[float, float, float, float]:
    """The micro field's box in the bed's guidance (the micro camera is centred on the origin)."""
    w = BED["micro"] * BED["micro_um"] / BED["mid_um"]
    return (BED["mid"] - w) / 2, (BED["mid"] - w) / 2, w, w


@pytest.fixture(scope="session")
def tiny_model(twill, tmp_path_factory):
    """A W=8 model trained for 3 iterations on 32 px crops (weights barely moved: a random net)."""
    from dualscale.propagate.data import load_source
    from dualscale.propagate.train import TrainOptions, preset_with, train

    out = tmp_path_factory.mktemp("model") / "m.dsp"
    train([load_source(twill)], preset_with("quick", iterations=3, batch=2, crop=32), out,
          TrainOptions(width=8, progress=False))
    return out


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)  # the 2 shared cores are busy: OpenMP spin-waiting with 2 threads is ~10x slower
