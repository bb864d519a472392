"""The simulated sensor's noise is drawn per shot identity (issue 24 §8): a shot taken again --
as a capture resumed after a kill takes it -- has the same noise whatever was exposed before,
and different shots have different noise."""

from __future__ import annotations

import numpy as np

from dualscale.geometry.cameras import Camera
from dualscale.sim.targets import rig_exposer


def _exposer():
    cam = Camera("micro", "orthographic", 16, 12, (0.16, 0.12))
    return rig_exposer(cam)


def test_same_shot_same_noise_whatever_came_before():
    raw = np.full((12, 16, 3), 0.4)
    a = _exposer()
    first = a(raw, 0.01, shot=("sample", ((1, 3, 100),), 0, 0.01))
    b = _exposer()
    b(raw, 0.02, shot=("sample", ((1, 4, 100),), 0, 0.02))  # another shot first, as before a resume
    b(raw, 0.01)
    again = b(raw, 0.01, shot=("sample", ((1, 3, 100),), 0, 0.01))
    np.testing.assert_array_equal(first, again)


def test_different_shots_have_different_noise():
    raw = np.full((12, 16, 3), 0.4)
    e = _exposer()
    x = e(raw, 0.01, shot=("sample", ((1, 3, 100),), 0, 0.01))
    y = e(raw, 0.01, shot=("sample", ((1, 3, 100),), 9000, 0.01))  # the analyser turned
    assert not np.array_equal(x, y)
    assert np.std(x - y) > 0  # noise, not an offset
