"""Training crops read from disk (issue 25 Sec. 4): a source over the in-memory threshold is a
DiskSource whose crops, and therefore training, are bit for bit those of the in-memory Source."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualscale.propagate.data import DiskSource, Source, load_source, sample_batch
from dualscale.propagate.train import TrainOptions, input_reference, preset_with, train


@pytest.fixture(scope="module")
def leather(tmp_path_factory):
    """16 px, every LED (so the diffuse image is synthesised) and a back light."""
    from dualscale.cli import main

    root = tmp_path_factory.mktemp("disk") / "l"
    assert main(["synth", "leather", "-o", str(root), "--size", "16", "--dataset", "--no-previews"]) == 0
    return root


def _both(root, limit=0):
    mem, disk = load_source(root, in_memory_bytes=float("inf")), load_source(root, in_memory_bytes=limit)
    assert isinstance(mem, Source) and isinstance(disk, DiskSource)
    assert (disk.maps is None) == (limit == 0)  # 0: the maps too are read per crop
    return mem, disk


def test_threshold_picks_the_path(twill, monkeypatch):
    assert isinstance(load_source(twill), Source)  # 32 px: far under the default
    monkeypatch.setenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", "0")
    assert isinstance(load_source(twill), DiskSource)
    monkeypatch.setenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", "1")  # 1 MiB: the 32 px source (~0.2 MB) fits
    assert isinstance(load_source(twill), Source)


@pytest.mark.parametrize("which,limit", [("twill", 0), ("leather", 0), ("twill", 100_000)])
def test_disk_crops_equal_memory_crops(which, limit, twill, leather, monkeypatch):
    monkeypatch.setattr("dualscale.propagate.data.MAPS_SHARE", 1.0)  # 32 px twill: maps 45 kB, all 155 kB
    mem, disk = _both(twill if which == "twill" else leather, limit)  # 100 kB: images from disk, maps held
    assert disk.light_names == mem.light_names and disk.map_names == mem.map_names
    assert disk.size == mem.size and disk.texel_mm == mem.texel_mm
    if which == "leather":
        assert mem.light_names[-1] == "diffuse"  # the synthesised diffuse, held in memory by both
    for seed in range(3):
        xm, ym = sample_batch([mem], 12, 8, torch.Generator().manual_seed(seed))
        xd, yd = sample_batch([disk], 12, 8, torch.Generator().manual_seed(seed))
        assert torch.equal(xm, xd)
        assert ym.keys() == yd.keys() and all(torch.equal(ym[k], yd[k]) for k in ym)
    # every light and mode at one position, not just the ones a seed draws
    for li in range(mem.n_lights):
        for mode in range(3):
            assert torch.equal(mem.crop_image(li, mode, 3, 5, 8), disk.crop_image(li, mode, 3, 5, 8)), (li, mode)
    assert torch.equal(mem.diffuse_image(), disk.diffuse_image())
    ref_m, ref_d = input_reference([mem]), input_reference([disk])
    if "diffuse" in mem.light_names:
        assert ref_m == ref_d
    else:  # mean of every image: float64 accumulation on disk, float32 in memory
        assert np.allclose(ref_m, ref_d, rtol=1e-5, atol=0)


def test_disk_training_equals_memory_training(twill, tmp_path):
    mem, disk = _both(twill)
    pre = preset_with("quick", iterations=3, batch=2, crop=16)
    opts = TrainOptions(width=8, progress=False, amp=False)
    a = train([mem], pre, tmp_path / "mem.dsp", opts)
    b = train([disk], pre, tmp_path / "disk.dsp", opts)
    assert [h["loss"] for h in a.history] == [h["loss"] for h in b.history]
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k


def test_disk_source_refuses_bad_maps(twill, tmp_path):
    import shutil

    from dualscale.errors import GeometryError
    from dualscale.formats.exr import read_exr, write_exr
    from dualscale.formats.maps import channel_names

    root = tmp_path / "bad"
    shutil.copytree(twill, root)
    f = root / "maps" / "normal.exr"
    n = read_exr(f, channel_names("normal"))
    n[4, 7] = [0.0, 0.0, -1.0]
    write_exr(f, n, channel_names("normal"))
    with pytest.raises(GeometryError, match="below the sample plane"):
        load_source(root, in_memory_bytes=0)
