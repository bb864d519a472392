"""The pipeline entry point run_propagation on the two-scale test bed: outputs, summary, texel
size, registration, resume, and refusals before anything is written."""

import json

import numpy as np
import pytest

from dualscale.errors import InputError
from dualscale.formats.exr import read_exr, write_exr
from dualscale.formats.maps import load_maps
from dualscale.propagate.stage import run_propagation

from .conftest import BED, bed_truth

FAST = {"preset": "quick", "iterations": 4, "batch": 2, "threads": 1, "progress": False}


@pytest.fixture(scope="module")
def staged(bed, tmp_path_factory):
    out = tmp_path_factory.mktemp("stage") / "propagate"
    return out, run_propagation(bed / "micro", bed / "maps", bed / "mid", out, **FAST)


def test_outputs_and_summary(staged):
    out, s = staged
    for f in ("guidance.exr", "model.dsp", "model.onnx", "model.fp16.onnx", "propagate.json", "maps/material.json"):
        assert (out / f).is_file(), f
    assert s == json.loads((out / "propagate.json").read_text())
    for key in ("guidance", "texel_mm", "micro_box_px", "registration", "train_seconds", "run_seconds", "preset",
                "warnings"):
        assert key in s, key
    assert s["texel_mm"] == pytest.approx(BED["mid_um"] / 1000) and s["preset"] == "quick"
    # the micro data were resampled to the guidance texel: 96 px of 6 um -> 48 px of 12 um
    assert s["training_size_px"] == [48, 48] and s["crop"] == 32
    truth = bed_truth()
    assert np.hypot(s["micro_box_px"][0] - truth[0], s["micro_box_px"][1] - truth[1]) < 1.0
    assert s["registration"]["method"] == "ncc+ecc" and s["registration"]["prior_px"] == pytest.approx(truth)
    assert set(s["in_field_l1"]) == set(s["maps"])
    maps, meta = load_maps(out / "maps")
    assert maps.shape == (BED["mid"], BED["mid"]) and meta["texel_mm"] == pytest.approx(s["texel_mm"])
    assert meta["field_mm"] == pytest.approx([BED["mid"] * BED["mid_um"] / 1000] * 2)
    g = read_exr(out / "guidance.exr")
    assert g.shape == (BED["mid"], BED["mid"], 3) and np.isfinite(g).all()


def test_rerun_reuses_the_trained_model(bed, staged):
    out, first = staged
    mtime = (out / "model.dsp").stat().st_mtime_ns
    again = run_propagation(bed / "micro", bed / "maps", bed / "mid", out, **FAST)
    assert again["resumed_from"] == FAST["iterations"] and (out / "model.dsp").stat().st_mtime_ns == mtime
    assert again["micro_box_px"] == first["micro_box_px"]
    a, _ = load_maps(out / "maps")
    assert np.isfinite(a.albedo.numpy()).all()


def test_resumes_from_a_checkpoint(bed, staged, tmp_path):
    """A run stopped after its last checkpoint (model file not yet written) finishes from it."""
    import shutil

    out = tmp_path / "p"
    shutil.copytree(staged[0], out)
    (out / "model.dsp").unlink()
    s = run_propagation(bed / "micro", bed / "maps", bed / "mid", out, **FAST)
    assert s["resumed_from"] == FAST["iterations"] and (out / "model.dsp").is_file()


def test_refusals_write_nothing(bed, tmp_path):
    g = read_exr(next((bed / "mid" / "images").glob("*.exr")))
    g[5, 7] = np.nan
    write_exr(tmp_path / "nan.exr", g)
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"nan\.exr: 1 pixel\(s\) are NaN or Inf \(first at row 5, col 7\)"):
        run_propagation(bed / "micro", bed / "maps", tmp_path / "nan.exr", out, texel_mm_guidance=0.012, **FAST)
    assert not out.exists()
    # a guidance so coarse that the micro field is under 32 px
    with pytest.raises(InputError, match="needs at least 32 px"):
        run_propagation(bed / "micro", bed / "maps", bed / "mid", out, texel_mm_guidance=0.02, **FAST)
    assert not out.exists()


def test_unknown_guidance_texel_assumes_the_rig_with_a_warning(bed, tmp_path):
    """A bare image: the rig's mid camera (100 mm over its width) is assumed, and said."""
    from dualscale.propagate.stage import _guidance_texel
    from dualscale.propagate.guidance import read_guidance

    g = read_exr(next((bed / "mid" / "images").glob("*.exr")))
    write_exr(tmp_path / "g.exr", g)
    warnings = []
    assert _guidance_texel(read_guidance(tmp_path / "g.exr"), warnings) == pytest.approx(100 / BED["mid"])
    assert "unknown" in warnings[0] and "100 mm" in warnings[0]


@pytest.mark.parametrize("side,crop", [(38, 32), (48, 32), (64, 48), (100, 80), (144, 128), (512, 128)])
def test_training_crop_moves_around_the_field(side, crop):
    """The crop leaves room to move (16 px) when the field is small: a crop of the whole 64 px field
    was memorised (docs/PROPAGATION.md: normal L1 0.200 against 0.036 with 48 px crops)."""
    from dualscale.propagate.stage import training_crop

    assert training_crop(side, 128) == crop
