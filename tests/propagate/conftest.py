"""Shared tiny fixtures: a synthetic twill micro dataset (32x32, every 16th LED, P0/P90)."""

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
