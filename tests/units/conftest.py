"""Fixtures for the units boundary: small datasets in every units/colour space the format
knows, and the calibration of the virtual rig."""

from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)


def small_dataset(root: Path, size: int = 6, leds: tuple[int, ...] = (0, 8, 40), **writer) -> Path:
    """A tiny dataset written through the format's writer (random pixels, real LED directions,
    P0 and P90); ``writer`` goes to :class:`DatasetWriter` (units, colour_space, mask, ...)."""
    import numpy as np

    from dualscale.formats.dataset import DatasetWriter
    from dualscale.geometry.cameras import micro_camera
    from dualscale.geometry.dome import DomeGeometry

    cam = micro_camera(size, 9.0)
    dome = DomeGeometry.from_regmap()
    g = np.random.default_rng(0)
    with DatasetWriter(root, dome={"source": dome.source, "polarizer": dome.polarizer}, **writer) as w:
        for led in leds:
            for a in (0.0, 90.0):
                w.add(g.uniform(0.01, 0.2, (size, size, 3)), cam, "led", led,
                      [float(x) for x in dome.led_dirs[led]], 1.0, a, True, 1.0)
    return root


@pytest.fixture
def dataset(tmp_path):
    return small_dataset(tmp_path / "ds")


@pytest.fixture(scope="session")
def rig_calibration(tmp_path_factory):
    """A real calibration of the virtual rig (synthetic captures of the white sheet and the
    ColorChecker, micro + mid cameras, every 32nd LED: 4 LEDs), calibrated by the pipeline."""
    from tests.units.rawrig import calibration_session

    return calibration_session(tmp_path_factory.mktemp("rig"), led_step=32)
