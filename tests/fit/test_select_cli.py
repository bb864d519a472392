"""Component selection, the CLI and the on-disk output."""

import json

import pytest
import torch

from dualscale.cli import main
from dualscale.geometry.cameras import micro_camera
from dualscale.sim.render import Analyzer, LightState, render
from dualscale.fit.io import read_fit_attributes
from dualscale.fit.observations import load_observations
from dualscale.fit.select import select_components
from dualscale.formats.maps import load_maps


def _with_backlight(root):
    """Observations plus the back-lit P0 image the renderer gives (black for opaque maps), as
    the rig captures it for every material."""
    obs = load_observations(root)
    if obs.backlight is None:
        maps, _ = load_maps(root / "maps")
        img = render(maps, micro_camera(obs.shape[0], 9.0), LightState.backlight(0), analyzer=Analyzer(0.0, True))
        obs.backlight, obs.back_wd = img, 0.5
    return obs


@pytest.mark.parametrize("material,trans,aniso", [("twill", False, True), ("leather", False, False),
                                                  ("sheer", True, True), ("brick", False, False)])
def test_component_choice(datasets, material, trans, aniso):
    comps, rep = select_components(_with_backlight(datasets(material)))
    assert (not comps.opaque) == trans, rep["transmittance"]
    assert (not comps.isotropic) == aniso, rep["anisotropy"]
    assert rep["transmittance"]["evidence"]["backlit_capture"]
    assert "val_rmse_isotropic" in rep["anisotropy"]["evidence"]
    assert "val_rmse_tinted" in rep["tint"]["evidence"]
    json.dumps(rep)


def test_override_is_recorded(datasets):
    comps, rep = select_components(_with_backlight(datasets("leather")), {"anisotropy": True, "tint": False})
    assert not comps.isotropic and not comps.tinted
    assert rep["anisotropy"] == {"chosen": True, "overridden": True}
    assert rep["tint"]["overridden"]
    with pytest.raises(ValueError, match="unknown component"):
        select_components(_with_backlight(datasets("leather")), {"sheen": True})


def test_cli_fit_writes_exr_with_metadata(datasets, tmp_path, capsys):
    out = tmp_path / "maps"
    rc = main(["fit", str(datasets("twill")), "-o", str(out), "--preset", "draft", "--no-previews",
               "--gt", str(datasets("twill") / "maps")])
    assert rc == 0
    attrs = read_fit_attributes(out / "albedo.exr")
    assert attrs["preset"] == "draft" and attrs["iterations"] == "11"
    assert attrs["components"]["isotropic"] is False and attrs["components"]["opaque"] is True
    assert attrs["selection"]["anisotropy"]["chosen"] is True
    assert "train_l1" in attrs["final_losses"] and "heldout_ssim" not in attrs["final_losses"]  # no light held out
    assert all(torch.isfinite(torch.tensor(v)) for v in attrs["final_losses"].values())
    report = json.loads((out / "fit.json").read_text())
    assert report["ground_truth"]["errors"]["normal_mean_deg"] < 5
    assert report["cross_validation"]["scheme"] == "8-fold" and len(report["cross_validation"]["ours"]) == 127
    assert report["lights"]["images"] == 254
    maps, meta = load_maps(out)  # readable as a dualscale-maps directory
    assert maps.anisotropy is not None and maps.normal is not None
    assert not (out / "checkpoint.pt").exists()
    assert "vs ground truth" in capsys.readouterr().out
    assert meta["texel_mm"] == pytest.approx(0.009) and meta["field_mm"] == pytest.approx([0.144, 0.144])


def test_fit_takes_no_ground_truth_it_was_not_given(datasets, tmp_path):
    """A material.json beside the dataset (here the synth ground truth, and a first fit's
    output put there) is never taken as ground truth: evaluation needs an explicit --gt."""
    ds = datasets("twill")
    args = ["fit", str(ds), "--preset", "draft", "--no-previews", "--cv-pixels", "0"]
    assert main(args + ["-o", str(ds / "fit1")]) == 0
    assert main(args + ["-o", str(tmp_path / "fit2")]) == 0
    assert "ground_truth" not in json.loads((tmp_path / "fit2" / "fit.json").read_text())


def test_cli_fit_override_and_resume(datasets, tmp_path):
    out = tmp_path / "maps"
    args = ["fit", str(datasets("leather")), "-o", str(out), "--preset", "draft", "--no-previews",
            "--anisotropy", "off", "--tint", "on", "--transmittance", "off"]
    assert main(args + ["--stop-after", "4", "--checkpoint-every", "2"]) == 130  # Interrupted: resumable
    assert (out / "checkpoint.pt").is_file()
    assert main(args) == 0
    rep = json.loads((out / "fit.json").read_text())
    assert rep["resumed_from_iteration"] == 4
    assert rep["selection"]["tint"] == {"chosen": True, "overridden": True}


def test_cli_fit_ior_prior_override(datasets, tmp_path, capsys):
    out = tmp_path / "maps"
    rc = main(["fit", str(datasets("leather")), "-o", str(out), "--preset", "draft", "--no-previews",
               "--anisotropy", "off", "--tint", "off", "--transmittance", "off", "--ior-prior", "0"])
    assert rc == 0
    rep = json.loads((out / "fit.json").read_text())
    assert rep["preset"]["name"] == "draft" and rep["preset"]["ior_prior_sd"] == 0.0
    assert main(["fit", str(datasets("leather")), "-o", str(tmp_path / "o"), "--preset", "paper",
                 "--ior-prior", "0.05"]) == 2
    assert "LM optimiser only" in capsys.readouterr().err
    assert not (tmp_path / "o" / "checkpoint.pt").exists()


def test_cli_errors_are_clear(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "missing"), "-o", str(tmp_path / "o")]) == 2
    assert "dataset not found" in capsys.readouterr().err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "manifest.json").write_text('{"format": "other"}')
    assert main(["fit", str(tmp_path / "bad"), "-o", str(tmp_path / "o")]) == 2
    assert "not a dualscale-photometric" in capsys.readouterr().err
