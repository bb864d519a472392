"""A small synthetic RUN folder written by the run-folder contract (32x32 maps), for the report tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

H = W = 32
TEXEL_MM = 0.0049


def _stage(root: Path, name: str, seconds: float, summary: dict, warnings=(), params=None, outputs=()):
    doc = {"format": "dualscale-stage", "version": 1, "stage": name,
           "inputs": {"captures": "9f2c" * 16}, "params": params or {},
           "versions": {"dualscale": "0.1.0", "torch": "2.13.0", "numpy": "2.1.0"},
           "seconds": seconds, "finished": "2026-12-01T14:03:27.123456+00:00",
           "warnings": list(warnings), "outputs": list(outputs), "summary": summary}
    (root / "stages").mkdir(parents=True, exist_ok=True)
    (root / "stages" / f"{name}.json").write_text(json.dumps(doc, indent=1))


def _maps(rng, h=H, w=W):
    import torch

    from dualscale.bsdf import MaterialMaps

    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    albedo = np.dstack([0.6 * xx + 0.1, 0.3 + 0.2 * yy, 0.25 + 0.05 * rng.random((h, w))])
    n = np.dstack([0.3 * np.sin(6 * xx), 0.2 * np.cos(5 * yy), np.ones((h, w))])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    rough = (0.3 + 0.4 * yy + 0.01 * rng.random((h, w)))[..., None]
    rough[0, 0] = 0.99  # one outlier: the colour scale must say it clips
    t = torch.from_numpy
    return MaterialMaps(albedo=t(albedo.astype(np.float32)), roughness=t(rough.astype(np.float32)),
                        normal=t(n.astype(np.float32)),
                        anisotropy=t((0.5 * xx)[..., None].astype(np.float32)),
                        tangent=t(((xx + yy) % 1.0)[..., None].astype(np.float32)),
                        ior=t(np.full((h, w, 1), 0.25, np.float32)),
                        specular_tint=t(np.full((h, w, 1), 0.2, np.float32)))


def make_run(root: Path, *, flyouts: bool = True, guidance: bool = True, seed: int = 0, name: str | None = None,
             capture_seconds: float | None = None, heldout_l1: float = 0.04312345678901,
             constant_l1: float | None = 0.6123) -> Path:
    """Write a complete RUN folder under ``root``; optional stages can be skipped.  ``name``: the
    ``--name`` option; ``capture_seconds``: a ``digitize --rig`` run, whose capture stage record
    (``stages/capture.json``) is written beside the stages ``run.json`` lists, as the pipeline does.
    ``heldout_l1``, ``constant_l1``: the fit's held-out relative L1 and the per-pixel constant
    predictor's, in the fit stage's summary (the run's checks)."""
    from dualscale.formats.exr import write_exr
    from dualscale.formats.maps import save_maps

    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    stages = ["calibrate", "fit", "flyouts", "propagate", "export", "report"]
    (root / "run.json").write_text(json.dumps({
        "format": "dualscale-run", "version": 1, "input": "/data/captures/twill_042",
        "options": {"preset": "standard", "guidance": "/data/guidance/twill.exr" if guidance else None,
                    "flyouts": flyouts, "shadow_ratio": 0.5, "name": name},
        "stages": stages}))
    if capture_seconds is not None:
        _stage(root, "capture", capture_seconds, {"micro": {"shots": 264, "frames": 792}})
    _stage(root, "calibrate", 4.2, {
        "calibration": "/lab/rig.calib.json", "units_in": "normalised_dn", "units_out": "relative_radiance",
        "colour_space_in": "camera_raw:Nikon 5100 (NPL)", "colour_space_out": "linear_rec709", "transfer": None,
        "images": 254, "clipped_share": 0.0012345678901234, "texel_mm": TEXEL_MM, "field_mm": [W * TEXEL_MM, H * TEXEL_MM]},
        warnings=["3 of 254 images have more than 1% saturated pixels in every bracket"])

    maps = _maps(rng)
    save_maps(root / "fit" / "maps", maps, meta={"texel_mm": TEXEL_MM})
    (root / "fit" / "maps" / "fit.json").write_text(json.dumps({"selection": {
        "method": "held-out validation", "margin": 0.02,
        "transmittance": {"chosen": False, "overridden": False,
                          "evidence": {"backlit_capture": True, "fraction_above_level": 0.0, "level": 0.02}},
        "anisotropy": {"chosen": True, "overridden": False,
                       "evidence": {"val_rmse_isotropic": 0.013912345678, "val_rmse_anisotropic": 0.00213456789,
                                    "relative_gain": 0.846666666666}},
        "validation": {"pixels": 512, "train_images": 190, "val_leds": list(range(0, 120, 5))},
        "components": {"opaque": True, "isotropic": False, "tinted": True, "normal_mapped": True, "ior": 1.5},
        "candidates": [
            {"components": {"opaque": True, "isotropic": True, "tinted": False}, "validation_error": 0.0139123456789},
            {"components": {"opaque": True, "isotropic": False, "tinted": True, "normal_mapped": True, "ior": 1.5},
             "validation_error": 0.00151234567891, "seconds": 2.412345678}]}}))
    write_exr(root / "fit" / "residual.exr", (0.02 + 0.05 * rng.random((H, W)) ** 6)[..., None], ["Y"])
    # the fit stage's heldout.json: the cross-validated error of every light (8 folds dealt
    # round-robin) and capture/re-render pairs of three of them (training lights, not held out)
    dirs = {7: [0.3, 0.2, 0.93], 31: [-0.5, 0.4, 0.77], 88: [0.1, -0.8, 0.59]}
    ids = [3, 7, 12, 20, 31, 45, 60, 71, 88, 100]
    folds = [ids[j::8] for j in range(8)]
    lights = []
    for i, led in enumerate(ids):
        d = np.array(dirs.get(led, [0.2 * np.cos(i), 0.2 * np.sin(i), 0.96]))
        lights.append({"led_id": led, "direction": list(d / np.linalg.norm(d)), "fold": i % 8,
                       "relative_l1": 0.03 + 0.004 * i, "baseline_relative_l1": 0.09 + 0.003 * i})
    renders = []
    for led, d in dirs.items():
        cap = np.asarray(maps.albedo) * (0.5 + 0.5 * rng.random((H, W, 1)))
        ren = cap * (1 + 0.05 * rng.standard_normal((H, W, 3)))
        write_exr(root / "fit" / "heldout" / f"capture_{led}.exr", cap)
        write_exr(root / "fit" / "heldout" / f"render_{led}.exr", ren)
        renders.append({"led_id": led, "direction": d, "capture": f"capture_{led}.exr", "render": f"render_{led}.exr",
                        "relative_l1": float(np.abs(ren - cap).mean() / cap.mean()), "held_out": False})
    method = "8-fold cross-validation over 10 lights on 2000 sample pixels"
    (root / "fit" / "heldout" / "heldout.json").write_text(json.dumps({
        "method": "cross-validation", "heldout_method": method, "relative_l1": 0.04312345678901,
        "baseline_relative_l1": 0.1031234567, "scheme": "8-fold", "folds": folds, "pixels": 2000,
        "components_chosen": "once, on all lights (the same components in every fold)",
        "lights": lights, "renders": renders}))
    _stage(root, "fit", 133.4, {"preset": "standard", "seconds": 41.7, "images": 254, "train_images": 254,
                                "leds": 127, "fitted_leds": 127, "heldout_relative_l1": heldout_l1,
                                "heldout_baseline_relative_l1": 0.1031234567, "heldout_method": method,
                                "heldout_constant_relative_l1": constant_l1,
                                "cv_seconds": 61.23456},
           params={"preset": "standard", "iterations": 120, "selection": {"margin": 0.02, "pixels": 512}},
           outputs=["fit/maps/albedo.exr", "fit/residual.exr"])

    if flyouts:
        mask = np.zeros((H, W, 1), np.float32)
        poly = [[[2, 3], [10, 9], [20, 12]], [[25, 28], [30, 20]]]
        for c, r in (p for line in poly for p in line):
            mask[r, c] = 1
        (root / "flyouts").mkdir(parents=True, exist_ok=True)
        from dualscale.fit.flyouts import resolvability

        res = resolvability(TEXEL_MM)  # 12 um fibres at 4.9 um: 2.4 texels across, under-resolved
        (root / "flyouts" / "flyouts.json").write_text(json.dumps({"count": 2, "polylines_px": poly,
                                                                   "resolvability": res}))
        write_exr(root / "flyouts" / "flyout_mask.exr", mask, ["Y"])
        _stage(root, "flyouts", 0.84, {"count": 2, "resolvability": res}, warnings=[res["warning"]])
    else:
        _stage(root, "flyouts", 0.01, {"skipped": "the material has no fly-out fibres option (--no-flyouts)"})

    if guidance:
        g = np.dstack([np.linspace(0.05, 0.6, 96)[None, :].repeat(96, 0)] * 3) * np.array([1.0, 0.8, 0.6])
        write_exr(root / "propagate" / "guidance.exr", g.astype(np.float32))
        pm = _maps(rng, 96, 96)
        # the propagated anisotropy spread as on the demo (0.07-0.88, most near 0.82): a robust
        # 0.5-99.5 % colour scale would clip both ends
        pa = np.clip(rng.normal(0.82, 0.03, (96, 96, 1)), 0, 0.88)
        pa[:3, :3] = rng.uniform(0.07, 0.3, (3, 3, 1))
        import torch

        pm.anisotropy = torch.from_numpy(pa.astype(np.float32))
        save_maps(root / "propagate" / "maps", pm, meta={"texel_mm": 0.05})
        _stage(root, "propagate", 61.0, {"guidance": "/data/guidance/twill.exr", "texel_mm": 0.05,
                                          "micro_box_px": [40, 30, 3.1, 3.1],
                                          "registration": {"method": "phase correlation", "scale": 0.098123456,
                                                           "residual_px": 0.4123456}, "train_seconds": 58.9,
                                          "preset": "fast", "iterations": 240, "crop": 128,
                                          "warm_start": "warmstart_w16.dsp"},
               warnings=["guidance image has no colour calibration; maps may be tinted"])
    else:
        _stage(root, "propagate", 0.0, {"skipped": "no guidance image given"})

    # the export stage's summary: per scale, the files of each format (relative to export/<scale>)
    micro = root / "export" / "micro"
    (micro / "gltf").mkdir(parents=True, exist_ok=True)
    (micro / "exr").mkdir(parents=True, exist_ok=True)
    (micro / "gltf" / "twill_micro.gltf").write_text(json.dumps({"asset": {"version": "2.0"}}))
    (micro / "gltf" / "twill_micro.bin").write_bytes(bytes(4000))
    (micro / "gltf" / "twill_micro_base_color.png").write_bytes(bytes(90_000))
    for n in ("albedo.exr", "normal.exr"):
        (micro / "exr" / n).write_bytes((root / "fit" / "maps" / n).read_bytes())
    (micro / "exr" / "material.json").write_text(json.dumps({"name": "twill_micro", "maps": ["albedo", "normal"]}))
    _stage(root, "export", 0.31, {"formats": ["gltf", "exr"], "exports": {"micro": {
        "name": "twill_micro", "repeat_mm": None, "tiled": False, "tile": None,
        "files": {"gltf": ["gltf/twill_micro.gltf", "gltf/twill_micro.bin", "gltf/twill_micro_base_color.png"],
                  "exr": ["exr/material.json", "exr/albedo.exr", "exr/normal.exr"]}}}},
           params={"formats": ["gltf", "exr"], "tile": False, "name": name or "twill_042"})
    return root


def add_uncertainty(run: Path, *, ground_truth: bool = False, record: bool = True, seed: int = 1) -> dict:
    """Write ``RUN/fit/maps/uncertainty/`` (synthetic sigma of every fitted map, the top-left
    4 x 4 texels undetermined, the tangent's left half too) and, when ``record``, fit.json's
    ``"uncertainty"``; ``ground_truth``: a ground-truth maps folder ``RUN/gt`` = the fit plus a
    Gaussian error of 1 sigma per texel, named in fit.json's ``"ground_truth"``.  Returns the
    sigma arrays."""
    import torch

    from dualscale.formats.maps import SIGMA_CHANNELS, load_maps, save_maps, save_uncertainty

    rng = np.random.default_rng(seed)
    maps_dir = run / "fit" / "maps"
    maps, meta = load_maps(maps_dir)
    scale = {"normal": 2.0, "tangent": 5.0, "ior": 0.05}
    sigma, und = {}, {}
    for name, _ in maps.items():
        if name not in SIGMA_CHANNELS:
            continue
        c = SIGMA_CHANNELS[name]
        s = scale.get(name, 0.01) * (0.5 + rng.random((H, W, c)))
        u = np.zeros((H, W, c), bool)
        u[:4, :4] = True
        if name == "tangent":
            u[:, : W // 2] = True
        sigma[name], und[name] = s, u
    save_uncertainty(maps_dir, sigma, und, {"noise": "residual", "preset": "standard"})
    doc = json.loads((maps_dir / "fit.json").read_text())
    if record:
        doc["uncertainty"] = {"noise": "the fit's residual (median |r|)", "seconds": 1.25, "maps": {}}
    if ground_truth:
        t = {}
        for name in sigma:
            a = np.asarray(getattr(maps, name), np.float64)
            if name == "normal":
                a = a + np.radians(sigma[name]) / np.sqrt(2) * rng.standard_normal(a.shape)
                a /= np.linalg.norm(a, axis=-1, keepdims=True)
            elif name == "tangent":
                a = (a + sigma[name] / 180.0 * rng.standard_normal(a.shape)) % 1.0
            elif name == "ior":
                a = a + sigma[name] / 2.0 * rng.standard_normal(a.shape)
            else:
                a = a + sigma[name] * rng.standard_normal(a.shape)
            t[name] = torch.from_numpy(a.astype(np.float32))
        gt = type(maps)(**{k: t.get(k, getattr(maps, k)) for k in ("albedo", "roughness", "normal", "anisotropy",
                                                                 "tangent", "ior", "specular_tint")})
        save_maps(run / "gt", gt, meta={"texel_mm": TEXEL_MM})
        doc["ground_truth"] = {"dir": str(run / "gt"), "errors": {}}
    (maps_dir / "fit.json").write_text(json.dumps(doc))
    return sigma
