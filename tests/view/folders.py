"""Small export and run folders for the viewer tests, written by the real writers:
maps from the synthetic materials (``dualscale.sim.materials``), the export by
``dualscale.export.material.export_material`` (glb), and a run with a calibrated dataset of a
few LEDs rendered by our model with a known perturbation (so captured != rendered)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

SIZE = 64
TEXEL_MM = 0.01
# a few LEDs of a dome: (id, theta deg, phi deg)
LEDS = [(0, 0.0, 0.0), (3, 30.0, 20.0), (7, 55.0, 140.0), (11, 70.0, 260.0)]
CAPTURE_GAIN = 1.1  # the "captured" images are our render x this gain (+ a little noise)


def maps_folder(root: Path, material: str = "twill", size: int = SIZE) -> Path:
    from dualscale.formats.maps import save_maps
    from dualscale.sim.materials import generate

    m = generate(material, size=size, texel_mm=TEXEL_MM)
    save_maps(root, m.maps, {"material": material}, texel_mm=TEXEL_MM)
    return root


def export_folder(out: Path, maps: Path, formats=("glb",)) -> Path:
    from dualscale.export.material import export_material

    export_material(maps, out, formats, name="swatch")
    return out


def led_dir(theta: float, phi: float) -> list[float]:
    t, p = np.radians(theta), np.radians(phi)
    return [float(np.sin(t) * np.cos(p)), float(np.sin(t) * np.sin(p)), float(np.cos(t))]


def run_folder(run: Path, material: str = "twill", exports: tuple[str, ...] = ("glb",)) -> Path:
    """RUN/run.json, RUN/fit/maps, RUN/calibrate/dataset (P0 and P90 images of :data:`LEDS`),
    RUN/export/micro (when ``exports``)."""
    import torch

    from dualscale.bsdf import evaluate
    from dualscale.formats.dataset import DatasetWriter
    from dualscale.formats.maps import load_maps
    from dualscale.formats.run import write_run
    from dualscale.geometry.cameras import micro_camera

    run.mkdir(parents=True)
    maps_dir = maps_folder(run / "fit" / "maps", material)
    maps, _ = load_maps(maps_dir)
    cam = micro_camera(SIZE, pixel_um=TEXEL_MM * 1000)
    rng = np.random.default_rng(0)
    with DatasetWriter(run / "calibrate" / "dataset", dome={"polarizer": "s"}) as w:
        for led, theta, phi in LEDS:
            d = led_dir(theta, phi)
            for analyzer, (ws, wd) in ((0.0, (1.0, 0.5)), (90.0, (0.0, 0.5))):
                f = evaluate(maps, torch.tensor([d]), torch.tensor([0.0, 0.0, 1.0]), w_s=ws, w_p=0.0,
                             diffuse_weight=wd)[0].numpy()
                img = CAPTURE_GAIN * f * (1 + 0.01 * rng.standard_normal(f.shape))
                w.add(np.clip(img, 0, None).astype(np.float32), cam, "led", led, d, analyzer_deg=analyzer,
                      analyzer_relative=True)
    write_run(run, {"input": str(run / "calibrate" / "dataset"), "options": {}, "stages": ["calibrate", "fit",
                                                                                            "export"]})
    if exports:
        export_folder(run / "export" / "micro", maps_dir, exports)
    return run


def write_export_json(out: Path, formats: dict) -> None:
    """A hand-written export.json (for refusals)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "export.json").write_text(json.dumps({"format": "dualscale-export", "version": 1, "name": "x",
                                                 "formats": formats, "repeat_mm": None, "tiled": False,
                                                 "source": "maps"}))


def add_uncertainty(maps_dir: Path, maps=("albedo", "roughness", "normal")) -> dict:
    """A synthetic ``uncertainty/`` beside ``maps_dir`` (:func:`dualscale.formats.maps.save_uncertainty`):
    sigma rising left to right, the top quarter of the rows undetermined.  Returns the sigma."""
    from dualscale.formats.maps import SIGMA_CHANNELS, save_uncertainty

    xx = np.linspace(0.01, 0.1, SIZE)[None, :, None]
    sigma, und = {}, {}
    for name in maps:
        c = SIGMA_CHANNELS[name]
        sigma[name] = np.broadcast_to(xx * (20.0 if name == "normal" else 1.0), (SIZE, SIZE, c)).copy()
        u = np.zeros((SIZE, SIZE, c), bool)
        u[: SIZE // 4] = True
        und[name] = u
    save_uncertainty(maps_dir, sigma, und, {"noise": "synthetic"})
    return sigma
