"""Fixtures of the photo workflow's tests (helpers in photoset.py)."""

from __future__ import annotations

import pytest

from photoset import SphereSet, lights_one_side, render_sphere


@pytest.fixture
def sphere_set(tmp_path) -> SphereSet:
    """A diffuse sphere under 12 lights on one side, 40 x 40 px, 8-bit sRGB, mask, ``.lp``."""
    return render_sphere(tmp_path / "ball", lights_one_side())
