"""The virtual rig's calibration targets reflect as the calibration assumes (docs/CALIBRATION.md,
"The white sheet is Lambertian"): a matte Lambertian sheet, ``r_c`` = sheet raw colour x
``l_z / pi`` per unit LED irradiance, with no specular in P0 + P90."""

import math

import numpy as np
import pytest
import torch

from dualscale.calib import colourref as cr
from dualscale.calib.chart import ChartLayout
from dualscale.errors import InputError
from dualscale.geometry.dome import DomeGeometry
from dualscale.sim.render import Analyzer
from dualscale.sim.targets import SHEET_R, Defects, SynthConfig, rig_cameras, true_radiance

torch.set_num_threads(1)
NO_DEFECTS = Defects(led_gain_sigma=0.0, collimation_max=0.0)


@pytest.mark.parametrize("led", [0, 32, 64, 96])  # l_z 1.0, 0.81, 0.50, 0.31: one LED per ring
def test_white_sheet_is_lambertian_without_specular(led):
    dome = DomeGeometry.from_regmap()
    cfg = SynthConfig(micro_px=4)
    cam = rig_cameras(cfg)["micro"]
    tot = sum(true_radiance("white_sheet", cam, "led", led, cfg, NO_DEFECTS, dome, ChartLayout(),
                            analyzer=Analyzer(a, relative=True)) for a in (0.0, 90.0))
    sheet = cr.camera_raw([cr.flat_spectrum(*SHEET_R)], cfg.sens("micro"), cfg.illum("led"))[0]
    lz = float(dome.led_dirs[led, 2])
    # was 1.107 at l_z 0.31 (Burley's retro-reflection at roughness 0.9) and + 1.6-3.3 % (specular)
    np.testing.assert_allclose(tot.reshape(-1, 3).mean(0), sheet * lz / math.pi, rtol=1e-9)


def test_the_old_burley_sheet_stays_available_and_unknown_models_are_refused():
    dome = DomeGeometry.from_regmap()
    cfg = SynthConfig(micro_px=4, target_brdf="burley")
    cam = rig_cameras(cfg)["micro"]
    tot = sum(true_radiance("white_sheet", cam, "led", 96, cfg, NO_DEFECTS, dome, ChartLayout(),
                            analyzer=Analyzer(a, relative=True)) for a in (0.0, 90.0))
    sheet = cr.camera_raw([cr.flat_spectrum(*SHEET_R)], cfg.sens("micro"), cfg.illum("led"))[0]
    ratio = tot.reshape(-1, 3).mean(0) / (sheet * float(dome.led_dirs[96, 2]) / math.pi)
    assert np.all(ratio > 1.1), ratio
    with pytest.raises(InputError):
        SynthConfig(target_brdf="phong")
