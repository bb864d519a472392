import json

import numpy as np
import pytest
import torch

from dualscale.cli import main
from dualscale.formats.exr import read_exr, write_exr
from dualscale.propagate.export import export_model, onnx_paths
from dualscale.propagate.infer import OnnxModel, _decode, _encode, run_tiled, tile_positions, window_1d
from dualscale.propagate.model import load_model


@pytest.fixture(scope="module")
def exported(tiny_model):
    return export_model(tiny_model)


def test_onnx_parity(exported):
    assert max(exported["parity_fp32"].values()) < 1e-4
    assert max(exported["parity_fp16"].values()) < 1e-2  # fp16 reported, looser


def test_onnx_metadata(exported, tiny_model):
    om = OnnxModel.open(exported["fp32"])
    _, doc = load_model(tiny_model)
    assert om.maps == doc["config"]["maps"] and om.input_reference == pytest.approx(doc["input_reference"])
    assert OnnxModel.open(exported["fp16"]).half


@pytest.mark.parametrize("n,tile,overlap", [(100, 32, 8), (32, 32, 8), (20, 32, 8), (1000, 512, 64), (515, 128, 0)])
def test_windows_cover_everything(n, tile, overlap):
    t = min(tile, -(-n // 16) * 16)
    pos = tile_positions(n, t, t - overlap)
    assert pos[0] == 0 and pos[-1] + t >= n
    acc = np.zeros(max(n, t))
    for k, p in enumerate(pos):
        acc[p:p + t] += window_1d(t, overlap, k == 0, k == len(pos) - 1)
    assert acc[:n].min() > 0.05


def test_tangent_blends_axially():
    maps = ["tangent"]
    y = np.array([0.02, 0.98], np.float32).reshape(2, 1, 1, 1)
    enc = _encode(maps, y)
    out = _decode(maps, enc.mean(0)[:, :, :])["tangent"]
    assert min(float(out.ravel()[0]), 1 - float(out.ravel()[0])) < 1e-4


def _guidance(tmp_path, h=96, w=80, c=3):
    rng = np.random.default_rng(0)
    img = (0.3 + 0.2 * rng.random((h, w, c))).astype(np.float32)
    write_exr(tmp_path / "g.exr", img)
    return tmp_path / "g.exr", img


def test_tiled_matches_whole_image_and_no_seams(exported, tmp_path):
    """Blended tiles agree with one whole-image pass; naive tiling does not, at its borders."""
    path, img = _guidance(tmp_path)
    om = OnnxModel.open(exported["fp32"])
    run_tiled(om, path, tmp_path / "whole", tile=96, overlap=0, exposure=1.0, progress=False)
    run_tiled(om, path, tmp_path / "blend", tile=48, overlap=16, exposure=1.0, progress=False)
    run_tiled(om, path, tmp_path / "naive", tile=48, overlap=0, exposure=1.0, progress=False)
    ref = read_exr(tmp_path / "whole" / "albedo.exr")
    d_blend = np.abs(read_exr(tmp_path / "blend" / "albedo.exr") - ref).mean(-1)
    d_naive = np.abs(read_exr(tmp_path / "naive" / "albedo.exr") - ref).mean(-1)
    band = np.zeros(80, bool)
    for p in tile_positions(80, 48, 48)[1:] + tile_positions(80, 48, 32)[1:]:
        band[p - 4:p + 4] = True
    assert d_naive[:, band].mean() > 2 * d_blend[:, band].mean()
    assert d_blend[:, band].mean() < 1.5 * d_blend[:, ~band].mean() + 1e-3
    n = read_exr(tmp_path / "blend" / "normal.exr")
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-4)
    meta = json.loads((tmp_path / "blend" / "material.json").read_text())
    assert meta["height"] == 96 and meta["width"] == 80


def test_small_and_odd_sizes(exported, tmp_path):
    path, _ = _guidance(tmp_path, 21, 37)
    s = run_tiled(OnnxModel.open(exported["fp16"]), path, tmp_path / "o", tile=64, overlap=16, progress=False)
    assert read_exr(tmp_path / "o" / "roughness.exr").shape == (21, 37, 1) and s["precision"] == "fp16"


def test_wrong_channel_count(exported, tmp_path):
    write_exr(tmp_path / "grey.exr", np.ones((32, 32), np.float32))
    with pytest.raises(ValueError, match="RGB"):
        run_tiled(OnnxModel.open(exported["fp32"]), tmp_path / "grey.exr", tmp_path / "o", progress=False)


def test_cli_train_export_run(twill, tmp_path, capsys):
    model = tmp_path / "m.dsp"
    assert main(["propagate", "train", str(twill), "-o", str(model), "--preset", "quick", "--iterations", "2",
                 "--batch", "2", "--crop", "32", "--width", "8", "--no-progress"]) == 0
    assert main(["propagate", "export", str(model)]) == 0
    assert all(p.is_file() for p in onnx_paths(model))
    path, _ = _guidance(tmp_path)
    assert main(["propagate", "run", str(model), str(path), "-o", str(tmp_path / "maps"), "--tile", "64",
                 "--overlap", "16",
                 "--no-progress"]) == 0
    from dualscale.formats.maps import load_maps

    maps, _ = load_maps(tmp_path / "maps")
    assert maps.shape == (96, 80) and maps.tangent is not None
    capsys.readouterr()
    # bad inputs: clear errors, exit 2
    write_exr(tmp_path / "two.exr", np.ones((32, 32, 2), np.float32))
    assert main(["propagate", "run", str(model), str(tmp_path / "two.exr"), "-o", str(tmp_path / "x")]) == 2
    assert "RGB" in capsys.readouterr().err
    doc = torch.load(model, weights_only=True)
    doc["version"] = 99
    torch.save(doc, tmp_path / "future.dsp")
    assert main(["propagate", "run", str(tmp_path / "future.dsp"), str(path), "-o", str(tmp_path / "x")]) == 2
    assert "incompatible" in capsys.readouterr().err
    (tmp_path / "nomaps").mkdir()
    import shutil

    shutil.copytree(twill / "micro", tmp_path / "nomaps" / "micro")
    assert main(["propagate", "train", str(tmp_path / "nomaps"), "-o", str(tmp_path / "n.dsp")]) == 2
    assert "no fitted maps" in capsys.readouterr().err


def test_run_on_mid_dataset_folder(exported, tmp_path):
    """`run` accepts the mid-range dataset folder that `dualscale synth --mid` writes."""
    assert main(["synth", "leather", "-o", str(tmp_path / "s"), "--size", "16", "--mid", "--mid-size", "48",
                 "--no-previews"]) == 0
    assert main(["propagate", "run", exported["fp32"], str(tmp_path / "s" / "mid"), "-o", str(tmp_path / "m"),
                 "--tile", "32", "--overlap", "8", "--no-progress"]) == 0
    assert read_exr(tmp_path / "m" / "albedo.exr").shape == (48, 48, 3)


def test_auto_exposure_matches_training_reference(exported, tmp_path):
    """`exposure='auto'` makes the result independent of the guidance's absolute exposure."""
    path, img = _guidance(tmp_path)
    write_exr(tmp_path / "bright.exr", 3 * img)
    om = OnnxModel.open(exported["fp32"])
    a = run_tiled(om, path, tmp_path / "a", tile=48, overlap=16, progress=False)
    b = run_tiled(om, tmp_path / "bright.exr", tmp_path / "b", tile=48, overlap=16, progress=False)
    assert a["gain"] == pytest.approx(3 * b["gain"], rel=1e-5)
    luma = float((img @ np.array([0.2126, 0.7152, 0.0722])).mean())
    assert a["gain"] * luma == pytest.approx(float(np.dot(om.input_reference, [0.2126, 0.7152, 0.0722])), rel=1e-5)
    assert np.allclose(read_exr(tmp_path / "a" / "albedo.exr"), read_exr(tmp_path / "b" / "albedo.exr"), atol=1e-5)
