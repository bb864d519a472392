"""Fixtures of the photo workflow's tests (helpers in photoset.py)."""

from __future__ import annotations

import pytest
import torch

from photoset import SphereSet, lights_one_side, render_sphere


@pytest.fixture
def sphere_set(tmp_path) -> SphereSet:
    """A diffuse sphere under 12 lights on one side, 40 x 40 px, 8-bit sRGB, mask, ``.lp``."""
    return render_sphere(tmp_path / "ball", lights_one_side())


@pytest.fixture(autouse=True)
def one_thread():
    """The photo tests fit on one torch thread (the shared 2-core machines)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
