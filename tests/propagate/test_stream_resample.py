"""The propagate stage out of core (issue 25): a micro capture over the in-memory threshold is a
DiskSource that resample_source reads two lights at a time; the resampled source, and so the
stage's model and propagated maps, are bit for bit those of the in-memory capture."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from dualscale.cli import main
from dualscale.propagate.data import DiskSource, Source, load_source
from dualscale.propagate.resample import resample_source


def _same(a: Source, b: Source) -> None:
    assert isinstance(a, Source) and isinstance(b, Source)
    assert a.name == b.name and a.light_names == b.light_names and a.texel_mm == b.texel_mm
    assert a.pairs.dtype == b.pairs.dtype == torch.float16 and torch.equal(a.pairs, b.pairs)
    assert list(a.maps) == list(b.maps) and all(torch.equal(a.maps[k], b.maps[k]) for k in a.maps)


# shrinking (area average), a fractional shrink, enlarging (bilinear: OpenCV's result depends on
# the channel grouping, which two lights per call keep)
@pytest.mark.parametrize("scale", [0.5, 0.37, 1.44])
@pytest.mark.parametrize("odd", [False, True])
def test_streamed_resampling_equals_in_memory(twill, scale, odd, monkeypatch):
    mem = load_source(twill, in_memory_bytes=float("inf"))
    monkeypatch.setenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", "0")
    disk = load_source(twill)
    assert isinstance(mem, Source) and isinstance(disk, DiskSource) and disk.maps is None  # maps read too
    if odd == (mem.n_lights % 2 == 0):  # both parities: the last call holds one light or two
        mem = replace(mem, pairs=mem.pairs[:-1], light_names=mem.light_names[:-1])
        disk = replace(disk, lights=disk.lights[:-1], light_names=disk.light_names[:-1])
    assert mem.n_lights % 2 == int(odd)
    a, b = resample_source(mem, scale), resample_source(disk, scale)
    assert a.size == b.size == tuple(max(1, round(32 * scale)) for _ in range(2))
    _same(a, b)


def test_streamed_resampling_with_held_maps(twill, monkeypatch):
    """Images from disk, maps held in memory (a threshold the maps alone fit in)."""
    monkeypatch.setattr("dualscale.propagate.data.MAPS_SHARE", 1.0)
    mem = load_source(twill, in_memory_bytes=float("inf"))
    disk = load_source(twill, in_memory_bytes=100_000)  # 32 px: ~155 kB in all, maps 45 kB
    assert isinstance(disk, DiskSource) and disk.maps is not None
    _same(resample_source(mem, 0.37), resample_source(disk, 0.37))


@pytest.fixture(scope="module")
def digitized(tmp_path_factory):
    """``digitize --quality draft --until propagate`` on a tiny twill (32 px of 9 um, every 4th LED:
    33 lights, an odd count; a 96 px guidance of 6.25 um, so the micro data are enlarged)."""
    root = tmp_path_factory.mktemp("digit")
    sample = root / "sample"
    assert main(["synth", "twill", "-o", str(sample), "--size", "32", "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--mid", "--mid-size", "96", "--mid-field-mm", "0.6", "--no-previews", "--no-progress"]) == 0
    run = root / "run"
    assert _digitize(sample, run) == 0
    return sample, run


def _digitize(sample, run) -> int:
    return main(["digitize", str(sample / "micro"), "-o", str(run), "--guidance", str(sample / "mid"),
                 "--quality", "draft", "--threads", "1", "--no-progress", "--until", "propagate"])


@pytest.mark.slow  # a whole digitize run (28 s); the streamed resampling's equality is tested above, fast
def test_digitize_propagate_stage_from_disk_gives_the_same_maps(digitized, tmp_path, monkeypatch):
    from dualscale.formats.maps import load_maps

    sample, one = digitized
    two = tmp_path / "run"
    shutil.copytree(one, two)
    shutil.rmtree(two / "propagate")
    (two / "stages" / "propagate.json").unlink()  # the fit is reused, the propagate stage redone
    monkeypatch.setenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", "0")
    assert isinstance(load_source(sample / "micro", one / "fit" / "maps"), DiskSource)
    assert _digitize(sample, two) == 0
    ra, rb = (json.loads((r / "stages" / "propagate.json").read_text())["summary"] for r in (one, two))
    assert rb["resumed_from"] == ra["resumed_from"] == 0  # both trained from scratch
    for k in ("micro_box_px", "training_size_px", "in_field_l1", "gain", "maps", "crop", "iterations"):
        assert ra[k] == rb[k], k
    a, _ = load_maps(one / "propagate" / "maps")
    b, _ = load_maps(two / "propagate" / "maps")
    for (k, v), (_, u) in zip(a.items(), b.items(), strict=True):
        assert torch.equal(v, u), k
    assert np.isfinite(a.albedo.numpy()).all()
