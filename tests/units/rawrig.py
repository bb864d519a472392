"""A raw capture of a synthetic material on the virtual rig, consistent with the synthetic
calibration session (``dualscale.sim.targets``): the same camera spectral response to the same
LED spectrum, per-LED gains and collimation ramps, vignetting, dark signal, shot and read noise,
12-bit quantisation and saturation, and an exposure metered per LED (its brightest pixel at
``headroom`` of full scale) and then shortened by a factor cycling through ``spread`` (as a rig
that brackets, or meters on another criterion, would), so exposures differ from LED to LED."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch


def calibration_session(root: Path, led_step: int = 8, rig_id: str = "virtual-dome-0") -> Path:
    """Write a synthetic calibration session (micro + mid cameras, white sheet and chart) and
    calibrate it; returns the calibration file."""
    from dualscale.calib.pipeline import calibrate
    from dualscale.formats.calibration import write_calibration
    from dualscale.formats.captures import read_captures
    from dualscale.sim.targets import Defects, SynthConfig, write_session

    cfg = SynthConfig(led_step=led_step, cameras=("micro", "mid"), rig_id=rig_id)
    write_session(root / "captures", cfg, Defects(), parts=("white_sheet", "chart"))
    return write_calibration(root / "rig.calib.json", calibrate(read_captures(root / "captures")))


SPREAD = (1.0, 0.3, 0.6, 0.15)


def raw_dataset(out: Path, material: str = "leather", size: int = 16, led_step: int = 8, headroom: float = 0.9,
                texel_um: float = 9.0, seed: int = 0, rig_id: str = "virtual-dome-0",
                spread: tuple[float, ...] = SPREAD) -> Path:
    """A ``dn_normalized`` / ``camera_raw`` micro dataset of ``material`` under every
    ``led_step``-th LED (P0 and P90) and back light 0, with two dark frames; ground-truth maps
    in ``out/maps``, the dataset in ``out/micro``."""
    from dualscale.formats.dataset import DatasetWriter
    from dualscale.geometry.cameras import micro_camera
    from dualscale.geometry.dome import DomeGeometry
    from dualscale.sim.materials import generate
    from dualscale.sim.materials.io import save_material
    from dualscale.sim.render import Analyzer, LightState, render
    from dualscale.sim.sensor import spectral_matrix
    from dualscale.sim.targets import (SENSOR, Defects, Exposer, SynthConfig, collimation_ramp,
                                       led_gains, rig_cameras)

    cfg, defects = SynthConfig(led_step=led_step, micro_px=size), Defects()
    dome = DomeGeometry.from_regmap()
    mat = generate(material, size, texel_um / 1000.0, seed)
    save_material(out / "maps", mat, previews=False)
    cam = micro_camera(size, texel_um)
    grid = rig_cameras(cfg)["micro"]  # the calibration's micro camera: same pixel grid, its ramps
    m = torch.from_numpy(spectral_matrix(cfg.sens("micro"), cfg.illum("led")))
    gains = led_gains(dome.n_leds, defects)
    ex = Exposer(cam, cfg, defects, seed + 1)
    space = f"camera_raw:{cfg.sens('micro')}"
    with DatasetWriter(out / "micro", units="dn_normalized", colour_space=space,
                       dome={"source": dome.source, "polarizer": dome.polarizer, "radius_mm": dome.radius_mm},
                       rig={"id": rig_id, "layout": dome.signature()}, extra={"material": mat.meta}) as w:
        for t in (0.01, 0.2):
            w.add(ex(np.zeros((size, size, 3)), t), cam, "off", None, None, 1.0, exposure_s=t)
        for k, lid in enumerate(range(0, dome.n_leds, led_step)):
            raws = []
            for a in (0.0, 90.0):
                rgb = render(mat.maps, cam, LightState.led(lid), dome, Analyzer(a, True)).to(torch.float64)
                raw = (rgb @ m.T).numpy() * gains[lid] * collimation_ramp(grid, lid, defects)[..., None]
                raws.append(raw)
            peak = max(float(r.max()) for r in raws)
            t = float(np.clip(headroom * SENSOR.full_well_e / (peak * SENSOR.gain_e), 1e-4, 10.0))
            t *= spread[k % len(spread)]
            for a, raw in zip((0.0, 90.0), raws):
                w.add(ex(raw, t), cam, "led", lid, [float(x) for x in dome.led_dirs[lid]], 1.0, a, True, t,
                      saturation=1.0)
        back = render(mat.maps, cam, LightState.backlight(0), dome, Analyzer(0.0, True)).to(torch.float64)
        w.add(ex((back @ m.T).numpy(), 0.05), cam, "backlight", 0, None, 1.0, 0.0, True, 0.05, saturation=1.0)
    return out
